"""Reference-element fits (crossfield.geometry) against analytic cases."""

from __future__ import annotations

from dataclasses import FrozenInstanceError, replace
from unittest import mock

import numpy as np
import pytest

from crossfield.geometry import (
    distance_point_line,
    distance_point_point,
    fit_cylinder_axis,
    fit_line,
    perpendicular_basis,
    point_line_distance,
)
from crossfield.types import Line3D

AXIS_DIR = np.array([0.25, -0.30, 0.92]) / np.linalg.norm([0.25, -0.30, 0.92])
AXIS_POINT = np.array([612.0, -355.0, 140.0])


def cylinder_probes(heights=(-25.0, 0.0, 25.0), angles_deg=(20.0, 80.0, 140.0, 200.0), radius=17.0):
    e1, e2 = perpendicular_basis(AXIS_DIR)
    return np.array(
        [
            AXIS_POINT + h * AXIS_DIR + radius * (np.cos(a) * e1 + np.sin(a) * e2)
            for h in heights
            for a in np.radians(angles_deg)
        ]
    )


def test_perpendicular_basis_is_right_handed_orthonormal():
    for d in (AXIS_DIR, np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), np.array([-0.3, 0.9, 0.1])):
        e1, e2 = perpendicular_basis(d)
        d = d / np.linalg.norm(d)
        B = np.column_stack([e1, e2, d])
        np.testing.assert_allclose(B.T @ B, np.eye(3), atol=1e-12)
        assert np.linalg.det(B) == pytest.approx(1.0)



def test_perpendicular_basis_of_many_directions_is_each_rows_basis():
    rng = np.random.default_rng(3)
    D = np.vstack([rng.normal(size=(200, 3)), np.eye(3), -np.eye(3)])
    E1, E2 = perpendicular_basis(D)
    assert E1.shape == E2.shape == D.shape
    for d, e1, e2 in zip(D, E1, E2):
        single = perpendicular_basis(d)
        np.testing.assert_allclose(e1, single[0], atol=1e-15)
        np.testing.assert_allclose(e2, single[1], atol=1e-15)
        B = np.column_stack([e1, e2, d / np.linalg.norm(d)])
        np.testing.assert_allclose(B.T @ B, np.eye(3), atol=1e-12)
        assert np.linalg.det(B) == pytest.approx(1.0)

def test_distances():
    assert distance_point_point([1, 2, 3], [4, 6, 3]) == pytest.approx(5.0)
    line = Line3D(np.array([0.0, 0, 5]), np.array([0.0, 0, 2]))
    assert distance_point_line(np.array([3.0, 4.0, -7.0]), line) == pytest.approx(5.0)


def test_line_fit_exact_points():
    points = AXIS_POINT + np.outer(np.linspace(-40, 60, 6), AXIS_DIR)
    fit = fit_line(points)
    assert abs(fit.line.direction @ AXIS_DIR) == pytest.approx(1.0, abs=1e-14)
    assert fit.line.distance(AXIS_POINT) < 1e-12
    np.testing.assert_allclose(fit.line.point, points.mean(axis=0), atol=1e-12)
    assert fit.rms_mm < 1e-12 and fit.kind == "line" and fit.radius_mm is None


def test_line_fit_is_orthogonal_regression():
    """Direction = principal eigenvector of the scatter matrix (independent computation),
    and it beats ordinary least squares in the orthogonal sum of squares."""
    rng = np.random.default_rng(1)
    points = AXIS_POINT + np.outer(rng.uniform(-50, 50, 30), AXIS_DIR) + rng.normal(0, 0.5, (30, 3))
    fit = fit_line(points)
    scatter = np.cov(points.T)
    _, vectors = np.linalg.eigh(scatter)
    assert abs(fit.line.direction @ vectors[:, -1]) == pytest.approx(1.0, abs=1e-12)
    other = Line3D(fit.line.point, fit.line.direction + np.array([0.01, 0.0, 0.0]))
    assert np.sum(fit.residuals_mm**2) < sum(other.distance(p) ** 2 for p in points)
    np.testing.assert_allclose(fit.residuals_mm, [fit.line.distance(p) for p in points], atol=1e-12)


def test_line_fit_uncertainty_matches_monte_carlo():
    rng = np.random.default_rng(2)
    s = np.linspace(-30, 30, 8)
    clean = AXIS_POINT + np.outer(s, AXIS_DIR)
    e1, _ = perpendicular_basis(AXIS_DIR)
    far = AXIS_POINT + 300.0 * e1 + 20.0 * AXIS_DIR  # 300 mm from the axis, as in the paper
    errors, sigmas = [], []
    for _ in range(400):
        fit = fit_line(clean + rng.normal(0, 0.01, clean.shape), sigma_mm=0.01)
        d, sigma, _ = point_line_distance(far, fit)
        errors.append(d - 300.0)
        sigmas.append(sigma)
    assert np.std(errors) == pytest.approx(np.mean(sigmas), rel=0.15)


@pytest.mark.parametrize(
    "heights, angles",
    [((-25.0, 0.0, 25.0), (20.0, 80.0, 140.0, 200.0)), ((-25.0, 0.0, 25.0), (0.0, 120.0, 240.0)),
     ((-40.0, -10.0, 15.0, 30.0), (0.0, 90.0, 180.0, 270.0))],
)
def test_cylinder_fit_exact_points(heights, angles):
    points = cylinder_probes(heights, angles)
    fit = fit_cylinder_axis(points)
    assert fit.kind == "cylinder"
    assert abs(fit.line.direction @ AXIS_DIR) == pytest.approx(1.0, abs=1e-12)
    assert fit.line.distance(AXIS_POINT) < 1e-8
    assert fit.radius_mm == pytest.approx(17.0, abs=1e-8)
    assert np.abs(fit.residuals_mm).max() < 1e-8
    # The axis point is the foot of the probes' centroid.
    foot_offset = points.mean(axis=0) - fit.line.point
    assert abs(foot_offset @ fit.line.direction) < 1e-8


def test_cylinder_fit_noise_and_uncertainty():
    rng = np.random.default_rng(3)
    clean = cylinder_probes()
    e1, _ = perpendicular_basis(AXIS_DIR)
    far = AXIS_POINT + 300.0 * e1 + 10.0 * AXIS_DIR
    errors, sigmas = [], []
    for _ in range(40):
        fit = fit_cylinder_axis(clean + rng.normal(0, 0.01, clean.shape), sigma_mm=0.01)
        d, sigma, _ = point_line_distance(far, fit)
        errors.append(d - 300.0)
        sigmas.append(sigma)
        assert fit.radius_mm == pytest.approx(17.0, abs=0.03)
    errors = np.array(errors)
    assert np.abs(errors).max() < 5 * np.mean(sigmas)
    assert 0.5 < np.std(errors) / np.mean(sigmas) < 1.6  # 40 samples: loose band


def test_cylinder_direction_hint_and_principal_axis_start():
    """A short, wide probe pattern (the axis is not the longest spread) still fits."""
    points = cylinder_probes(heights=(-4.0, 0.0, 4.0), angles_deg=(0, 50, 110, 170, 230, 290), radius=40.0)
    fit = fit_cylinder_axis(points)
    assert abs(fit.line.direction @ AXIS_DIR) == pytest.approx(1.0, abs=1e-10)
    fit = fit_cylinder_axis(points, direction_hint=AXIS_DIR + 0.05)
    assert fit.radius_mm == pytest.approx(40.0, abs=1e-8)


@pytest.mark.parametrize(
    "heights, angles",
    [((-25.0, 25.0), (0.0, 90.0, 180.0, 270.0)),  # corners of a square prism: a family of cylinders
     ((0.0,), (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0))],  # one ring: plane-like fits
)
def test_cylinder_fit_refuses_probe_patterns_that_do_not_determine_the_axis(heights, angles):
    rng = np.random.default_rng(4)
    points = cylinder_probes(heights, angles) + rng.normal(0, 0.01, (len(heights) * len(angles), 3))
    with pytest.raises(ValueError, match="cylinder"):
        fit_cylinder_axis(points, sigma_mm=0.01)


def test_fit_input_errors():
    with pytest.raises(ValueError, match="at least 5"):
        fit_cylinder_axis(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="at least 2"):
        fit_line(np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_line(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="coincide"):
        fit_line(np.ones((4, 3)))


def test_point_line_distance_propagates_point_covariance():
    fit = fit_line(AXIS_POINT + np.outer(np.linspace(-50, 50, 11), AXIS_DIR))  # exact: zero line covariance
    e1, e2 = perpendicular_basis(AXIS_DIR)
    p = AXIS_POINT + 100.0 * e1
    cov = 0.04 * np.outer(e1, e1) + 9.0 * np.outer(e2, e2) + 9.0 * np.outer(AXIS_DIR, AXIS_DIR)
    d, sigma, gradient = point_line_distance(p, fit, cov)
    assert d == pytest.approx(100.0)
    np.testing.assert_allclose(gradient, e1, atol=1e-12)
    assert sigma == pytest.approx(0.2, rel=1e-6)  # only the radial variance counts


# --------------------------------------------------------------------------
# The plan's reference elements: one fit for the measurement and the viewer
# --------------------------------------------------------------------------

REFERENCE_PLAN = """
[[control]]
id = "C1"
[[control]]
id = "C2"
[[control]]
id = "C3"
[[reference_line]]
id = "L3"
probes = 12
fit = "cylinder"
[[reference_line]]
id = "L4"
probes = 6
fit = "line"
"""

LINE_POINT = np.array([-120.0, 240.0, 30.0])
LINE_DIR = np.array([0.8, 0.6, 0.0])


def reference_data(rng, extra=(), sigma=0.01):
    """ProbedPoints: 12 noisy probes of the cylinder (radius 17 mm about AXIS_POINT,
    AXIS_DIR), 6 of the line, plus ``extra`` (label, xyz) points."""
    from crossfield.types import ProbedPoint, ReferenceData

    cylinder = cylinder_probes() + rng.normal(0, sigma, (12, 3))
    line = LINE_POINT + np.outer(np.linspace(-50, 50, 6), LINE_DIR) + rng.normal(0, sigma, (6, 3))
    points = [ProbedPoint(f"L3.{k + 1}", xyz, sigma) for k, xyz in enumerate(cylinder)]
    points += [ProbedPoint(f"L4.{k + 1}", xyz, sigma) for k, xyz in enumerate(line)]
    points += [ProbedPoint(label, np.asarray(xyz, dtype=np.float64), sigma) for label, xyz in extra]
    return ReferenceData(points=tuple(points))


def test_reference_element_fit_selects_the_elements_probes_and_finds_the_axis():
    from crossfield.geometry import element_probes, fit_reference_element
    from crossfield.plan import parse_plan

    plan = parse_plan(REFERENCE_PLAN, "plan.toml")
    # Points that are not probes of L3 although their labels start alike.
    reference = reference_data(np.random.default_rng(5), extra=[("L3", [0, 0, 0]), ("L30.1", [9e3, 0, 0])])
    cyl_spec, line_spec = plan.reference_lines
    assert [p.label for p in element_probes("L3", reference.points)] == [f"L3.{k}" for k in range(1, 13)]
    fit = fit_reference_element(cyl_spec, reference.points)
    assert fit.kind == "cylinder" and fit.radius_mm == pytest.approx(17.0, abs=0.01)
    assert abs(fit.line.direction @ AXIS_DIR) == pytest.approx(1.0, abs=1e-5)
    assert fit.line.distance(AXIS_POINT) < 0.01  # the true axis, within the 0.01 mm probe noise
    line = fit_reference_element(line_spec, reference.points)
    assert line.kind == "line" and abs(line.line.direction @ LINE_DIR) == pytest.approx(1.0, abs=1e-6)
    assert line.line.distance(LINE_POINT) < 0.01


def test_reference_element_fit_errors_name_the_element():
    from crossfield.geometry import fit_reference_element
    from crossfield.plan import parse_plan
    from crossfield.types import ReferenceData

    plan = parse_plan(REFERENCE_PLAN, "plan.toml")
    few = ReferenceData(points=reference_data(np.random.default_rng(6)).points[:4])
    message = r"reference line L3: 4 of 12 probes imported, a cylinder fit needs at least 5"
    with pytest.raises(ValueError, match=message):
        fit_reference_element(plan.reference_lines[0], few.points)
    with pytest.raises(ValueError, match=r"reference line L4: 0 of 6 probes imported"):
        fit_reference_element(plan.reference_lines[1], few.points)


def test_reference_element_fits_are_cached_per_process_and_immutable():
    """The same probes are fitted once per process (issue 25: the measurement and the
    session's CMM evidence fitted them twice a session, ~25 ms a cylinder fit); the
    shared result cannot be changed by a caller; other probes or sigma are refitted."""
    from crossfield.geometry import element_probes, fit_reference_element
    from crossfield.plan import parse_plan
    from crossfield.types import ProbedPoint

    plan = parse_plan(REFERENCE_PLAN, "plan.toml")
    cyl_spec, line_spec = plan.reference_lines
    points = reference_data(np.random.default_rng(7)).points
    same = tuple(ProbedPoint(p.label, np.array(p.xyz), p.sigma_mm) for p in points)  # equal, not the same
    first = fit_reference_element(cyl_spec, points)
    with mock.patch("crossfield.geometry.fit_cylinder_axis", wraps=fit_cylinder_axis) as fits:
        again = fit_reference_element(cyl_spec, same)
        assert fits.call_count == 0  # before: 1, a fit per call
        assert again is first
        moved = tuple(replace(p, xyz=p.xyz + [0.0, 0.0, 1e-9]) if p.label == "L3.5" else p for p in points)
        fit_reference_element(cyl_spec, moved)
        fit_reference_element(cyl_spec, tuple(replace(p, sigma_mm=0.02) for p in points))
        assert fits.call_count == 2
    xyz = np.array([p.xyz for p in element_probes("L3", points)])
    direct = fit_cylinder_axis(xyz, sigma_mm=0.01)
    assert np.array_equal(first.residuals_mm, direct.residuals_mm) and first.sigma_mm == direct.sigma_mm
    assert np.array_equal(first.covariance, direct.covariance) and first.radius_mm == direct.radius_mm
    for array in (first.residuals_mm, first.covariance, *first.basis, first.line.point, first.line.direction):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0.0
    with pytest.raises(FrozenInstanceError):
        first.sigma_mm = 1.0  # type: ignore[misc]
    coincident = tuple(replace(p, xyz=np.array(LINE_POINT)) if p.label.startswith("L4.") else p for p in points)
    for _ in range(2):  # a failed fit is not cached: it raises every time, naming the line
        with pytest.raises(ValueError, match="reference line L4: line fit: all points coincide"):
            fit_reference_element(line_spec, coincident)


@pytest.mark.parametrize("bad_probe", [None, ("L3.13", [np.nan, 0.0, 0.0])])
def test_viewer_draws_the_axis_that_is_measured(bad_probe):
    """The Rerun viewer's axes are the measure plugin's reference fits, bit for bit; a
    line the measurement refuses (here a non-finite probe) is not drawn."""
    from crossfield.errors import MeasurementError
    from crossfield.plan import parse_plan
    from crossfield.plugins.measure_plan import PlanMeasurer
    from crossfield.viz.rerun_log import fit_reference_axes

    plan = parse_plan(REFERENCE_PLAN, "plan.toml")
    reference = reference_data(np.random.default_rng(7), extra=[bad_probe] if bad_probe else [])
    shown = fit_reference_axes(plan, reference)
    measurer = PlanMeasurer()
    for spec in plan.reference_lines:
        if bad_probe and spec.id == "L3":
            with pytest.raises(MeasurementError, match="reference line L3"):
                measurer.reference_line(plan, reference, "L3")
            assert "L3" not in shown
            continue
        measured = measurer.reference_line(plan, reference, spec.id)
        np.testing.assert_array_equal(shown[spec.id].line.point, measured.line.point)
        np.testing.assert_array_equal(shown[spec.id].line.direction, measured.line.direction)
        assert shown[spec.id].radius_mm == measured.radius_mm
        np.testing.assert_array_equal(shown[spec.id].covariance, measured.covariance)


def test_cylinder_jacobian_is_the_derivative_of_the_residuals() -> None:
    """The analytic (N, 5) Jacobian the cylinder fit hands to Levenberg-Marquardt against
    scipy's finite differences, at tilted axes including a turn past 90 degrees."""
    from scipy.optimize._numdiff import approx_derivative

    from crossfield.geometry import _cylinder_jacobian, _cylinder_residuals

    rng = np.random.default_rng(5)
    P = cylinder_probes() + rng.normal(0.0, 0.05, (12, 3))
    d0 = np.array([0.0, 0.0, 1.0])
    e1, e2 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    origin = np.array([0.3, -0.2, 1.0])
    for params in ([0.0, 0.0, 0.0, 0.0, 17.0], [0.5, -0.4, 0.05, -0.03, 16.0], [1.0, 2.0, 1.2, 1.5, 20.0]):
        params = np.asarray(params)
        numeric = approx_derivative(_cylinder_residuals, params, method="3-point", args=(P, origin, d0, e1, e2))
        analytic = _cylinder_jacobian(params, P, origin, d0, e1, e2)
        np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-7)
