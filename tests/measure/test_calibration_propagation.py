"""The calibration's parameters (std_R, std_T, std_M, std_D of the calibration file) propagated into
the characteristics as a session-systematic source (crossfield.uncertainty.calibration, issue 22 item 4).

Reference: the synthetic station's points projected exactly with the simulator's rig, triangulated
again from the same pixels with the rotation between the cameras turned by a known angle (scipy's
least squares on the reprojection error), registered with the real SVD registrar and measured.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares

from crossfield.calibration.covariance import camera_param_names
from crossfield.chain.aggregate import SessionAccumulator
from crossfield.session import FrameResult
from crossfield.simulator.scenarios import station_calibration
from crossfield.types import CameraPoints, ProbedPoint, ReferenceData, StereoCalibration
from crossfield.uncertainty.calibration import (
    CalibrationCovariance,
    calibration_contributions,
    calibration_covariance,
    point_displacements,
    session_propagation,
)

from test_measure import Station, by_name, measurer, register

CAL = station_calibration()
N_DIST = 5
NAMES = camera_param_names(N_DIST)
RX = NAMES.index("rig.rx")


def _project(X: np.ndarray, cal: StereoCalibration, rvec: np.ndarray) -> np.ndarray:
    """(4,) px: X (upper frame, mm) in the upper and the lower image."""
    u1, _ = cv2.projectPoints(X[None], np.zeros(3), np.zeros(3), cal.upper.camera_matrix, cal.upper.dist_coeffs)
    u2, _ = cv2.projectPoints(X[None], rvec, cal.t_lower_upper, cal.lower.camera_matrix, cal.lower.dist_coeffs)
    return np.concatenate([u1.ravel(), u2.ravel()])


def _retriangulate(xyz: np.ndarray, d_rvec: np.ndarray) -> np.ndarray:
    """The points seen in exact pixels of the true rig, triangulated with the rig's rotation vector
    off by ``d_rvec`` (rad): least squares on the four image coordinates (reference solver)."""
    rvec = cv2.Rodrigues(np.asarray(CAL.R_lower_upper))[0].ravel()
    out = []
    for X in xyz:
        pixels = _project(X, CAL, rvec)
        fit = least_squares(lambda P: _project(P, CAL, rvec + d_rvec) - pixels, X, xtol=1e-15, ftol=1e-15)
        out.append(fit.x)
    return np.array(out)


def _exact_session(station: Station):
    plan = station.plan
    probes = []
    for label in plan.probing_order():
        xyz = station.line_probes[int(label.split(".")[1]) - 1] if label.startswith("L3.") else station.points_g[label]
        probes.append(ProbedPoint(label, np.asarray(xyz), 0.001))
    reference = ReferenceData(tuple(probes), source="test")
    xyz = np.vstack([station.controls_c, [station.targets_c[t] for t in ("P1", "P2")], station.strays_c])
    n = len(xyz)
    points = CameraPoints(0, xyz, np.full((n, 3), 0.001), np.arange(n), np.arange(n), np.zeros(n))
    return plan, reference, points


def test_point_displacements_match_a_retriangulation_with_the_rotation_turned():
    station = Station()
    xyz = station.controls_c[:4]
    delta = 2e-5  # rad about the upper camera's x axis: the disparity direction
    columns = np.zeros((len(NAMES), 1))
    columns[RX, 0] = delta
    predicted = point_displacements(xyz, CAL, N_DIST, columns)[:, :, 0]
    actual = _retriangulate(xyz, np.array([delta, 0.0, 0.0])) - xyz
    # about Z^2 delta / B = 0.06 mm along the line of sight
    assert np.all(np.linalg.norm(actual, axis=1) > 0.03)
    assert np.allclose(predicted, actual, rtol=0, atol=2e-3 * np.abs(actual).max())


def test_std_R_propagated_through_registration_and_measurement_equals_the_finite_difference():
    station = Station()
    plan, reference, points = _exact_session(station)
    m = measurer()
    delta = 2e-5
    cov = np.zeros((len(NAMES), len(NAMES)))
    cov[RX, RX] = delta**2
    got = calibration_contributions(
        plan, reference, points, register(points, reference, plan), CAL, CalibrationCovariance(cov, N_DIST, "t"), m
    )
    # the reference: triangulate again with the rotation off by +delta, register (SVD), measure
    moved = CameraPoints(0, _retriangulate(points.xyz, np.array([delta, 0, 0])), points.sigma_xyz,
                         points.upper_index, points.lower_index, points.residual_px)
    base = by_name(m.measure(plan, reference, points, register(points, reference, plan), None))
    turned = by_name(m.measure(plan, reference, moved, register(moved, reference, plan), None))
    assert set(got) == set(base)
    for name, u in got.items():
        expected = abs(turned[name].measured_mm - base[name].measured_mm)
        assert u == pytest.approx(expected, rel=0.02, abs=2e-6), name
    assert max(got.values()) > 1e-3  # a real contribution (mm), not a test of zeros


def _calibration_file(tmp_path, std: dict[str, np.ndarray], cov_params: np.ndarray | None = None):
    path = tmp_path / "stereo.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", CAL.upper.camera_matrix)
    fs.write("M2", CAL.lower.camera_matrix)
    fs.write("T", CAL.t_lower_upper.reshape(3, 1))
    for key, value in std.items():
        fs.write(key, np.asarray(value, dtype=np.float64).reshape(1, -1))
    if cov_params is not None:
        fs.write("cov_params", cov_params)
        fs.write("cov_param_names", " ".join(NAMES))
    fs.release()
    return path


def _std_keys(r=(3e-5, 1e-5, 1e-5), t=(0.01, 0.004, 0.02)):
    return {"std_M1": [0.3, 0.3, 0.5, 0.5], "std_D1": [1e-4] * 5, "std_M2": [0.3, 0.3, 0.5, 0.5],
            "std_D2": [1e-4] * 5, "std_R": list(r), "std_T": list(t)}


def test_covariance_from_the_std_keys_with_the_correlations_of_cov_params(tmp_path):
    keys = _std_keys()
    std = np.concatenate([np.asarray(keys[k], float) for k in keys])
    assert calibration_covariance(str(_calibration_file(tmp_path, {"std_T": keys["std_T"]}))) is None
    diagonal = calibration_covariance(str(_calibration_file(tmp_path, keys)))
    assert np.allclose(diagonal.covariance, np.diag(std**2)) and diagonal.n_dist == 5
    # cov_params: the Jacobian's (half the honest std here), with a correlation of rx and Tz
    s_jac = 0.5 * std
    corr = np.eye(len(std))
    tz = NAMES.index("rig.Tz")
    corr[RX, tz] = corr[tz, RX] = 0.6
    stated = calibration_covariance(str(_calibration_file(tmp_path, keys, corr * np.outer(s_jac, s_jac))))
    assert np.allclose(stated.std, std)  # the honest std_* keys, not cov_params' diagonal
    assert stated.covariance[RX, tz] == pytest.approx(0.6 * std[RX] * std[tz])
    assert "cov_params" in stated.source


def test_session_budget_takes_the_propagated_term_not_divided_by_the_frames(tmp_path):
    station = Station()
    plan, reference, points = _exact_session(station)
    cal = StereoCalibration(CAL.upper, CAL.lower, CAL.R_lower_upper, CAL.t_lower_upper,
                            source=str(_calibration_file(tmp_path, _std_keys())))
    m = measurer()
    expected = calibration_contributions(
        plan, reference, points, register(points, reference, plan), cal, calibration_covariance(cal.source), m
    )
    rng = np.random.default_rng(3)
    terms = {}
    for frames in (1, 6):
        acc = SessionAccumulator(plan, calibration_source=cal.source,
                                 calibration_propagation=session_propagation(plan, reference, cal, m))
        for k in range(frames):
            noisy = CameraPoints(k, points.xyz + rng.normal(0, 0.001, points.xyz.shape), points.sigma_xyz,
                                 points.upper_index, points.lower_index, points.residual_px)
            registration = register(noisy, reference, plan)
            acc.add(FrameResult(k, k, points=noisy, registration=registration,
                                measurement=m.measure(plan, reference, noisy, registration, station.truth)))
        aggregate = acc.result()
        assert "propagated" in aggregate.calibration_uncertainty_source
        terms[frames] = {c.name: next(t.u_mm for t in c.budget if t.source == "calibration")
                         for c in aggregate.characteristics}
    for name, u in expected.items():
        # one draw of the calibration for the session: 6 frames keep the term of one
        assert terms[1][name] == pytest.approx(u, rel=0.05) and terms[6][name] == pytest.approx(terms[1][name], rel=0.05)
    assert max(expected.values()) > 1e-3
    # without std keys: the relative scale term, as before
    plain = SessionAccumulator(plan, calibration_propagation=session_propagation(plan, reference, CAL, m))
    assert plain._calibration_propagation is None and math.isfinite(plain.result().calibration_scale_u)
