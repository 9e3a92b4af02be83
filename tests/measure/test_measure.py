"""Measure implementation "plan" on a synthetic station (no simulator images)."""

from __future__ import annotations


import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.chain.correspondence import match_control_points
from crossfield.errors import MeasurementError
from crossfield.geometry import perpendicular_basis
from crossfield.plan import parse_plan
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.stages import Measurer
from crossfield.types import CameraPoints, GroundTruth, Line3D, ProbedPoint, ReferenceData, Registration
from crossfield.plugins.register_svd import SvdRegistrar

R_GC = Rotation.from_rotvec([0.55, -0.42, 2.35]).as_matrix()  # camera -> global
T_GC = np.array([842.6, -415.3, 318.9])
CMM_SIGMA = 0.01
CAMERA_SIGMA = np.array([0.01, 0.01, 0.04])  # mm, x y z of the camera frame (depth worst)


def to_global(p):
    return np.asarray(p) @ R_GC.T + T_GC


class Station:
    """8 controls, targets P1 P2 in view; R1 and the axis L3 ~300 mm away (camera frame first)."""

    def __init__(self, fit: str = "cylinder", seed: int = 0):
        rng = np.random.default_rng(seed)
        self.controls_c = np.column_stack(
            [rng.uniform(-80, 80, 8), rng.uniform(-20, 70, 8), rng.uniform(382, 418, 8)]
        )
        self.targets_c = {"P1": np.array([-12.0, 30.0, 395.0]), "P2": np.array([35.0, 5.0, 405.0])}
        self.strays_c = np.array([[60.0, 60.0, 390.0], [-70.0, -10.0, 410.0]])
        axis_dir_c = np.array([0.25, -0.30, 0.92]) / np.linalg.norm([0.25, -0.30, 0.92])
        radial = np.array([1.0, 0.8, 0.0])
        radial -= (radial @ axis_dir_c) * axis_dir_c
        radial /= np.linalg.norm(radial)
        self.axis = Line3D(to_global(np.array([0.0, 25.0, 400.0]) - 308.0 * radial), R_GC @ axis_dir_c)
        self.points_g = {f"C{k + 1}": to_global(p) for k, p in enumerate(self.controls_c)}
        self.points_g.update({tid: to_global(p) for tid, p in self.targets_c.items()})
        self.points_g["R1"] = to_global(np.array([-90.0, 310.0, 420.0]))
        self.fit = fit
        e1, e2 = perpendicular_basis(self.axis.direction)
        if fit == "cylinder":
            self.line_probes = [
                self.axis.point + h * self.axis.direction + 18.0 * (np.cos(a) * e1 + np.sin(a) * e2)
                for h in (-25.0, 0.0, 25.0)
                for a in np.radians([20.0, 80.0, 140.0, 200.0])
            ]
        else:
            self.line_probes = [self.axis.point + h * self.axis.direction for h in (-40, -20, 0, 20, 40)]
        self.truth = GroundTruth(self.points_g, {"L3": self.axis}, R_GC, T_GC)
        p1, p2, r1 = self.points_g["P1"], self.points_g["P2"], self.points_g["R1"]
        self.plan = parse_plan(
            f"""
[plan]
name = "test station"
{''.join(f'[[control]]{chr(10)}id = "C{k + 1}"{chr(10)}' for k in range(8))}
[[target]]
id = "P1"
nominal = [{p1[0] + 0.3}, {p1[1] - 0.2}, {p1[2] + 0.1}]
search_radius = 3.0
[[target]]
id = "P2"
nominal = {list(map(float, p2))}
search_radius = 3.0
[[reference_point]]
id = "R1"
[[reference_line]]
id = "L3"
probes = {len(self.line_probes)}
fit = "{fit}"
[[characteristic]]
name = "P1-L3"
kind = "point_line"
a = "P1"
b = "L3"
nominal = {round(self.axis.distance(p1), 2)}
tolerance = 0.1
[[characteristic]]
name = "P1-R1"
kind = "point_point"
a = "P1"
b = "R1"
nominal = {round(float(np.linalg.norm(p1 - r1)), 2)}
tolerance = 0.1
[[characteristic]]
name = "P1-P2"
kind = "point_point"
a = "P1"
b = "P2"
nominal = {float(np.linalg.norm(p1 - p2)) + 0.5}
tolerance = 0.1
[[characteristic]]
name = "P2-depth"
kind = "depth"
a = "P2"
nominal = {float(p2[2])}
tolerance = 0.2
[[characteristic]]
name = "C3-L3"
kind = "point_line"
a = "C3"
b = "L3"
nominal = {round(self.axis.distance(self.points_g['C3']), 2)}
tolerance = 0.1
""",
            "<test plan>",
        )

    def reference(self, rng=None, drop: tuple[str, ...] = ()) -> ReferenceData:
        noise = (lambda: rng.normal(0, CMM_SIGMA, 3)) if rng is not None else (lambda: np.zeros(3))
        probes = []
        for label in self.plan.probing_order():
            if label in drop:
                continue
            if label.startswith("L3."):
                xyz = self.line_probes[int(label.split(".")[1]) - 1]
            else:
                xyz = self.points_g[label]
            probes.append(ProbedPoint(label, xyz + noise(), CMM_SIGMA))
        return ReferenceData(tuple(probes), source="test")

    def camera_points(self, sequence=0, rng=None, targets=("P1", "P2"), extra=()) -> CameraPoints:
        xyz = np.vstack([self.controls_c, [self.targets_c[t] for t in targets], self.strays_c, *extra])
        if rng is not None:
            xyz = xyz + rng.normal(0, 1, xyz.shape) * CAMERA_SIGMA
            xyz = xyz[rng.permutation(len(xyz))]
        n = len(xyz)
        sigma = np.tile(CAMERA_SIGMA, (n, 1))
        return CameraPoints(sequence, xyz, sigma, np.arange(n), np.arange(n), np.zeros(n))


def register(points: CameraPoints, reference: ReferenceData, plan) -> Registration:
    by_label = reference.by_label()
    ids = [c for c in plan.control_ids if c in by_label]
    G = np.array([by_label[c].xyz for c in ids])
    corr = match_control_points(points.xyz, G, ids)
    Q = np.array([by_label[c].xyz for c in corr.control_ids])
    return Registration(points.sequence, SvdRegistrar().fit(points.xyz[corr.camera_index], Q), corr)


def measurer(**options) -> Measurer:
    return implementations(make_plugin_manager(), "measure")["plan"].create(options)


def by_name(measurement):
    return {c.name: c for c in measurement.characteristics}


@pytest.mark.parametrize("fit", ["cylinder", "line"])
def test_noise_free_station_measures_the_truth(fit):
    station = Station(fit)
    reference = station.reference()
    points = station.camera_points()
    registration = register(points, reference, station.plan)
    m = measurer().measure(station.plan, reference, points, registration, station.truth)
    assert m.missing_targets == ()
    for tid in ("P1", "P2"):
        np.testing.assert_allclose(m.target_points[tid], station.points_g[tid], atol=1e-9)
    results = by_name(m)
    assert set(results) == {"P1-L3", "P1-R1", "P1-P2", "P2-depth", "C3-L3"}
    p1, p2 = station.points_g["P1"], station.points_g["P2"]
    expected = {
        "P1-L3": station.axis.distance(p1),
        "P1-R1": np.linalg.norm(p1 - station.points_g["R1"]),
        "P1-P2": np.linalg.norm(p1 - p2),
        "P2-depth": p2[2],
        "C3-L3": station.axis.distance(station.points_g["C3"]),
    }
    for name, value in expected.items():
        r = results[name]
        assert r.measured_mm == pytest.approx(value, abs=1e-7), name
        assert r.actual_mm == pytest.approx(value, abs=1e-9)
        assert abs(r.error_mm) < 1e-7
        assert r.deviation_mm == pytest.approx(r.measured_mm - r.nominal_mm)
        assert r.passed == (abs(r.deviation_mm) <= r.tolerance_mm)
    assert not results["P1-P2"].passed  # nominal set 0.5 mm off
    assert results["P2-depth"].passed
    assert results["P1-L3"].elements == ("P1", "L3") and results["P2-depth"].elements == ("P2",)


def test_controls_use_cmm_coordinates():
    station = Station()
    rng = np.random.default_rng(1)
    reference = station.reference(rng)
    points = station.camera_points(rng=rng)
    m = measurer().measure(station.plan, reference, points, register(points, reference, station.plan), None)
    c3 = reference.by_label()["C3"].xyz
    line = measurer().reference_line(station.plan, reference, "L3").line
    assert by_name(m)["C3-L3"].measured_mm == pytest.approx(line.distance(c3), abs=1e-12)
    assert by_name(m)["C3-L3"].actual_mm is None  # no ground truth given


def test_missing_and_ambiguous_targets():
    station = Station()
    reference = station.reference()
    # P1 not seen; a second point 1 mm from P2 makes P2 ambiguous.
    points = station.camera_points(targets=("P2",), extra=([station.targets_c["P2"] + [1.0, 0, 0]],))
    registration = register(points, reference, station.plan)
    m = measurer().measure(station.plan, reference, points, registration, station.truth)
    assert m.missing_targets == ("P1", "P2")
    assert dict(m.target_points) == {}
    assert set(by_name(m)) == {"C3-L3"}  # only the characteristic that needs no target


def test_a_control_point_is_never_taken_for_a_target():
    station = Station()
    reference = station.reference()
    points = station.camera_points(targets=("P2",))
    # Move P1's nominal onto control C5, whose camera point the registration uses.
    c5 = station.points_g["C5"]
    nominal_line = next(line for line in station.plan.text.splitlines() if line.startswith("nominal = ["))
    text = station.plan.text.replace(nominal_line, f"nominal = {list(map(float, c5))}", 1)
    plan = parse_plan(text, "<moved>")
    m = measurer().measure(plan, reference, points, register(points, reference, plan), None)
    assert "P1" in m.missing_targets


def test_line_fits_are_cached_per_reference():
    station = Station()
    reference = station.reference(np.random.default_rng(2))
    impl = measurer()
    first = impl.reference_line(station.plan, reference, "L3")
    assert impl.reference_line(station.plan, reference, "L3") is first
    other = station.reference(np.random.default_rng(3))
    assert impl.reference_line(station.plan, other, "L3") is not first


def test_undetermined_reference_line_is_an_error():
    station = Station()
    reference = station.reference(drop=("L3.1", "L3.2", "L3.3", "L3.4", "L3.5", "L3.6", "L3.7", "L3.8"))
    points = station.camera_points()
    with pytest.raises(MeasurementError, match="L3: 4 of 12 probes"):
        measurer().measure(station.plan, reference, points, register(points, reference, station.plan), None)


def test_uncertainty_agrees_with_monte_carlo():
    """Per-frame uncertainty of each characteristic vs the scatter of its error over
    simulated sessions (CMM noise, camera noise, registration), line fit for speed."""
    station = Station("line")
    rng = np.random.default_rng(4)
    impl = measurer()
    errors: dict[str, list[float]] = {}
    sigmas: dict[str, list[float]] = {}
    for k in range(150):
        reference = station.reference(rng)
        points = station.camera_points(k, rng)
        registration = register(points, reference, station.plan)
        m = impl.measure(station.plan, reference, points, registration, station.truth)
        for r in m.characteristics:
            errors.setdefault(r.name, []).append(r.error_mm)
            sigmas.setdefault(r.name, []).append(r.uncertainty_mm)
    for name in errors:
        ratio = np.std(errors[name]) / np.mean(sigmas[name])
        assert 0.75 < ratio < 1.3, (name, ratio)
        assert abs(np.mean(errors[name])) < 4 * np.mean(sigmas[name]) / np.sqrt(len(errors[name])) + 1e-3


def test_registration_uncertainty_option():
    station = Station("line")
    rng = np.random.default_rng(5)
    reference = station.reference(rng)
    points = station.camera_points(rng=rng)
    registration = register(points, reference, station.plan)
    with_reg = by_name(measurer().measure(station.plan, reference, points, registration, None))
    without = by_name(
        measurer(registration_uncertainty=False).measure(station.plan, reference, points, registration, None)
    )
    assert with_reg["P1-R1"].uncertainty_mm > without["P1-R1"].uncertainty_mm
    assert with_reg["C3-L3"].uncertainty_mm == pytest.approx(without["C3-L3"].uncertainty_mm)  # CMM only
    assert with_reg["P1-R1"].measured_mm == without["P1-R1"].measured_mm
