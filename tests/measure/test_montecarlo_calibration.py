"""The Monte Carlo check draws the calibration from the file's stated parameters (std_* keys), as the
linear budget propagates them (crossfield.uncertainty.montecarlo, issue 22): with every other input
at zero, the sample's standard deviation of each characteristic equals the linear calibration term
(crossfield.uncertainty.calibration.calibration_contributions: central differences through the
measurer), within the sample's own uncertainty."""

from __future__ import annotations

import numpy as np
import pytest
from test_calibration_propagation import CAL, _calibration_file, _std_keys
from test_measure import Station, measurer, register

from crossfield.types import CameraPoints, ProbedPoint, ReferenceData, StereoCalibration
from crossfield.uncertainty.calibration import (
    calibration_contributions,
    calibration_covariance,
    point_displacements,
    sqrt_columns,
)
from crossfield.uncertainty.montecarlo import MonteCarloFrame, MonteCarloProblem, draw_chunk


def test_calibration_is_drawn_from_the_stated_parameters_as_the_linear_term_propagates(tmp_path):
    station = Station()
    plan = station.plan
    probes = []
    for label in plan.probing_order():
        xyz = station.line_probes[int(label.split(".")[1]) - 1] if label.startswith("L3.") else station.points_g[label]
        probes.append(ProbedPoint(label, np.asarray(xyz), 1e-9))  # the CMM exact: only the calibration
    reference = ReferenceData(tuple(probes), source="test")
    xyz = np.vstack([station.controls_c, [station.targets_c[t] for t in ("P1", "P2")], station.strays_c])
    n = len(xyz)
    points = CameraPoints(0, xyz, np.full((n, 3), 1e-12), np.arange(n), np.arange(n), np.zeros(n))
    registration = register(points, reference, plan)
    cal = StereoCalibration(CAL.upper, CAL.lower, CAL.R_lower_upper, CAL.t_lower_upper,
                            source=str(_calibration_file(tmp_path, _std_keys())))
    stated = calibration_covariance(cal.source)
    linear = calibration_contributions(plan, reference, points, registration, cal, stated, measurer())
    labels = [""] * n
    for cid, i in zip(registration.correspondence.control_ids, registration.correspondence.camera_index):
        labels[int(i)] = cid
    frame = MonteCarloFrame(points, registration.correspondence, np.zeros(n), tuple(labels),
                            point_displacements(xyz, cal, stated.n_dist, sqrt_columns(stated.covariance)))
    names = tuple(linear)
    kinds = tuple(next(c.kind for c in plan.characteristics if c.name == name) for name in names)
    problem = MonteCarloProblem(plan, reference, (frame,), 1.0, 1.0, 0.0, names, kinds, np.zeros(len(names)),
                                plan.temperature, ("svd", {}), ("plan", {}))
    draws = draw_chunk(problem, np.random.SeedSequence(0), 150)
    for j, name in enumerate(names):
        # the sample sd of 150 normal draws: 5.8 % standard uncertainty; 2.6 of them
        assert np.std(draws[:, j], ddof=1) == pytest.approx(linear[name], rel=0.15, abs=1e-6), name
    assert max(linear.values()) > 1e-3  # a real contribution (mm)
