"""The budget's eccentricity term (crossfield.uncertainty.eccentricity.eccentricity_sigma_mm).

u^2 per axis = E|e|^2 / 2, e = X_e - C the shift of the triangulated centre of a tilted
circle (imaging.eccentricity.ellipse_centre_point, H&Z result 2.13), over normals uniform
on the cap of half-angle max_tilt about the line of sight. Checked (1) against a Monte Carlo
of that distribution through the kernel, (2) against the simulator's rendered blob centres
of the camera-limited scene (its tilts fill the bound), triangulated.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.camera.stereo_model import linear_triangulation, refine_points, stereo_geometry, undistort
from crossfield.imaging.eccentricity import ellipse_centre_point
from crossfield.uncertainty.eccentricity import eccentricity_sigma_mm, off_axis_rad
from crossfield.simulator.scenarios import build_scene


def cap_normals(rng, C, max_tilt_deg, n):
    """n unit normals uniform on the cap within max_tilt of C's line of sight (towards the camera)."""
    sight = -C / np.linalg.norm(C)
    axis = np.cross(sight, rng.normal(size=(n, 3)))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    tau = np.arccos(1.0 - rng.uniform(0.0, 1.0, n) * (1.0 - np.cos(np.radians(max_tilt_deg))))
    return Rotation.from_rotvec(tau[:, None] * axis).apply(sight)


@pytest.mark.parametrize("max_tilt_deg", [10.0, 25.0, 45.0])
@pytest.mark.parametrize("C", [(0.0, 0.0, 400.0), (60.0, -40.0, 380.0), (-90.0, 70.0, 350.0)])
def test_term_is_the_rms_shift_over_the_stated_tilt_distribution(C, max_tilt_deg):
    C = np.asarray(C)
    rng = np.random.default_rng(7)
    n = 40000
    normals = cap_normals(rng, C, max_tilt_deg, n)
    e = ellipse_centre_point(np.repeat(C[None], n, axis=0), normals, np.full(n, 2.5)) - C
    rms_per_axis = np.sqrt(np.mean(np.sum(e**2, axis=1)) / 2.0)  # in-plane: two axes
    u = eccentricity_sigma_mm(float(np.linalg.norm(C)), 2.5, max_tilt_deg, off_axis_rad(C))
    assert u == pytest.approx(rms_per_axis, rel=0.01)
    # the off-axis angle matters: a facing target off the axis is eccentric too
    if np.hypot(C[0], C[1]) > 50:
        assert u > 1.05 * eccentricity_sigma_mm(float(np.linalg.norm(C)), 2.5, max_tilt_deg)


def test_term_scales_and_vanishes_as_stated():
    assert eccentricity_sigma_mm(400.0, 0.0, 20.0) == 0.0
    assert eccentricity_sigma_mm(400.0, 2.5, 0.0) == 0.0
    # r^2 / Z and, for small bounds, tau_max / 2 (E sin^2 tau ~ tau^2 / 2 on the cap)
    assert eccentricity_sigma_mm(400.0, 5.0, 20.0) == pytest.approx(4 * eccentricity_sigma_mm(400.0, 2.5, 20.0))
    assert eccentricity_sigma_mm(200.0, 2.5, 20.0) == pytest.approx(2 * eccentricity_sigma_mm(400.0, 2.5, 20.0))
    small = np.radians(1.0)
    assert eccentricity_sigma_mm(400.0, 2.5, 1.0) == pytest.approx(2.5**2 / 400.0 * small / 2.0, rel=1e-3)


def test_term_matches_the_simulators_true_shifts():
    """camera-limited (tilts uniform in [0.4, 1] x 25 deg, near the cap's distribution):
    the rendered blob centres, triangulated, minus the true centres; the component across
    the line of sight (the lens-curvature and rendering parts go into depth, via the
    disparity) per axis, RMS over the scene's 14 targets, against the stated u."""
    scene = build_scene("camera-limited")
    geometry = stereo_geometry(scene.calibration)
    upper, lower = scene.true_blob_centres("upper"), scene.true_blob_centres("lower")
    targets = [t for t in scene.targets if t.id in upper and t.id in lower]
    uv = np.array([np.r_[upper[t.id], lower[t.id]] for t in targets])
    X0 = linear_triangulation(undistort(uv[:, :2], geometry.upper), undistort(uv[:, 2:], geometry.lower), geometry)
    X = refine_points(X0, uv, np.ones_like(uv), geometry)[0]
    C = np.array([t.centre_camera for t in targets])
    e = X - C
    # the disparity error goes along the line from the baseline's midpoint
    lower_centre = -scene.calibration.R_lower_upper.T @ scene.calibration.t_lower_upper
    sight = C - lower_centre / 2.0
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    across = e - np.sum(e * sight, axis=1, keepdims=True) * sight
    true_rms = np.sqrt(np.mean(np.sum(across**2, axis=1)) / 2.0)
    u = np.array([eccentricity_sigma_mm(float(np.linalg.norm(c)), t.radius_mm, 25.0, off_axis_rad(c))
                  for c, t in zip(C, targets)])
    model_rms = np.sqrt(np.mean(u**2))
    # 14 targets: the RMS of their shifts scatters by ~10 %; across the line of sight the
    # shift is cos(theta) of |e| (~0.95 here)
    assert 0.7 * model_rms < true_rms < 1.1 * model_rms
    # per target, with its own tilt, the shift is the pinhole X_e - C (um-level agreement)
    normals = np.array([t.normal_camera for t in targets])
    e_pinhole = ellipse_centre_point(C, normals, np.array([t.radius_mm for t in targets])) - C
    across_pinhole = e_pinhole - np.sum(e_pinhole * sight, axis=1, keepdims=True) * sight
    np.testing.assert_allclose(np.linalg.norm(across, axis=1), np.linalg.norm(across_pinhole, axis=1),
                               atol=0.3e-3)  # lens curvature, 1/16 px edges: ~1e-3 px
