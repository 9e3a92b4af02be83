"""The compiled stereo kernels (crossfield.camera.stereo_kernels) against OpenCV, scipy and the
NumPy formulas they replaced (issue 25, item 4: same results to rounding, ~1e-12 mm).

A strong-distortion rig (rational k4..k6 and thin-prism s1..s4 terms non-zero) is used where the
lens model is the subject, so that every term of the compiled projection and of the Newton
undistortion is exercised.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares

import crossfield.camera.stereo_model as stereo_model
from crossfield.imaging.eccentricity import View, project
from crossfield.plugins.triangulate_epipolar import EpipolarTriangulator

from test_triangulate import make_calibration, observe, random_points, stereo

#: k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4: every term of OpenCV's model but the tilt
STRONG = (-0.21, 0.12, 1.5e-3, -9e-4, -0.03, 0.05, -0.02, 0.01, 2e-3, -1e-3, 1.5e-3, -5e-4)


def _cv2_project(geometry, X):
    """cv2.projectPoints of upper-frame X into both cameras: (N, 4) px."""
    out = []
    for cam in (geometry.upper, geometry.lower):
        rvec = cv2.Rodrigues(cam.R)[0]
        uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t, cam.K, cam.dist)
        out.append(uv.reshape(-1, 2))
    return np.hstack(out)


@pytest.fixture(scope="module")
def strong():
    calibration = make_calibration(dist_upper=STRONG, dist_lower=tuple(0.9 * c for c in STRONG))
    rng = np.random.default_rng(7)
    X = np.column_stack([rng.uniform(-60, 60, 40), rng.uniform(-20, 50, 40), rng.uniform(350, 450, 40)])
    return stereo_model.stereo_geometry(calibration), X


def test_projection_equals_opencv_with_every_lens_term(strong):
    geometry, X = strong
    uv, J = stereo_model.project_pair(geometry, X)
    assert np.max(np.abs(uv - _cv2_project(geometry, X))) < 1e-9  # px
    h = 1e-4  # mm: central differences of the cv2 projection
    numeric = np.stack(
        [(_cv2_project(geometry, X + h * e) - _cv2_project(geometry, X - h * e)) / (2 * h) for e in np.eye(3)],
        axis=-1,
    )
    assert np.max(np.abs(J - numeric)) < 1e-5 * np.max(np.abs(J))


def test_view_projection_equals_cv2_projectpoints(strong):
    geometry, X = strong
    cam = geometry.lower
    view = View(cam.K, cam.dist, cam.R, cam.t)
    Xv = X @ cam.R.T + cam.t
    reference, _ = cv2.projectPoints(Xv.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.max(np.abs(project(view, Xv) - reference.reshape(-1, 2))) < 1e-9


def test_newton_undistortion_equals_opencv(strong):
    geometry, X = strong
    uv = _cv2_project(geometry, X)
    for cam, points in ((geometry.upper, uv[:, :2]), (geometry.lower, uv[:, 2:])):
        reference = cv2.undistortPoints(points.reshape(-1, 1, 2), cam.K, cam.dist,
                                        criteria=stereo_model.UNDISTORT_CRITERIA).reshape(-1, 2)
        ours = stereo_model.undistort(points, cam)
        assert np.max(np.abs(ours - reference)) < 1e-12
        Xc = X @ cam.R.T + cam.t  # and both are the true rays
        assert np.max(np.abs(ours - Xc[:, :2] / Xc[:, 2:])) < 1e-12


def _numpy_linear(xn_u, xn_l, geometry):
    """The NumPy formulation before issue 25 (H&Z 12.2, inhomogeneous, normal equations by LAPACK)."""
    n = len(xn_u)
    P2 = np.hstack([geometry.lower.R, geometry.lower.t[:, None] / geometry.baseline_mm])
    A = np.zeros((n, 4, 4))
    A[:, 0, 0], A[:, 0, 2], A[:, 1, 1], A[:, 1, 2] = -1.0, xn_u[:, 0], -1.0, xn_u[:, 1]
    A[:, 2, :] = xn_l[:, 0:1] * P2[2] - P2[0]
    A[:, 3, :] = xn_l[:, 1:2] * P2[2] - P2[1]
    M = A[:, :, :3]
    X = np.linalg.solve(np.swapaxes(M, 1, 2) @ M, -np.swapaxes(M, 1, 2) @ A[:, :, 3:4])[:, :, 0]
    return X * geometry.baseline_mm


def test_linear_triangulation_equals_the_numpy_formulation_and_opencv(strong):
    geometry, X = strong
    uv = _cv2_project(geometry, X)
    xn_u = stereo_model.undistort(uv[:, :2], geometry.upper)
    xn_l = stereo_model.undistort(uv[:, 2:], geometry.lower)
    ours = stereo_model.linear_triangulation(xn_u, xn_l, geometry)
    assert np.max(np.abs(ours - _numpy_linear(xn_u, xn_l, geometry))) < 1e-9  # mm
    P_l = np.hstack([geometry.lower.R, geometry.lower.t[:, None]])
    Xh = cv2.triangulatePoints(np.eye(3, 4), P_l, xn_u.T, xn_l.T)
    assert np.max(np.abs(ours - (Xh[:3] / Xh[3]).T)) < 1e-6  # noise-free: both the true point
    assert np.max(np.abs(ours - X)) < 1e-6


def test_refinement_and_covariance_equal_scipy_least_squares():
    """Gauss-Newton point = scipy's least-squares minimiser of the weighted reprojection error
    through cv2.projectPoints; cov = (J^T W J)^-1 with J from cv2's projection."""
    calibration = make_calibration()
    geometry = stereo_model.stereo_geometry(calibration)
    rng = np.random.default_rng(3)
    X = random_points(rng, calibration, 12)
    uv_u, uv_l = observe(calibration, X, rng, 0.05)
    sigma = rng.uniform(0.02, 0.08, (12, 4))
    points = EpipolarTriangulator().triangulate(
        stereo(uv_u, uv_l, sigma[:, :2], sigma[:, 2:]), calibration
    )
    assert len(points) == 12
    obs = np.hstack([uv_u, uv_l])[points.upper_index]
    s = sigma[points.upper_index]
    for k in range(len(points)):
        def residual(x, k=k):
            return (_cv2_project(geometry, x[None])[0] - obs[k]) / s[k]

        fit = least_squares(residual, points.xyz[k] + 0.01, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert np.max(np.abs(fit.x - points.xyz[k])) < 1e-7  # mm
        cov = np.linalg.inv(fit.jac.T @ fit.jac)
        assert np.allclose(points.cov_xyz[k], cov, rtol=1e-4, atol=0)


def test_triangulation_equals_the_numpy_path_to_rounding():
    """The whole plugin against the NumPy refinement and covariance it replaced (issue 25)."""
    calibration = make_calibration()
    geometry = stereo_model.stereo_geometry(calibration)
    rng = np.random.default_rng(11)
    X = random_points(rng, calibration, 20)
    uv_u, uv_l = observe(calibration, X, rng, 0.02)
    order = rng.permutation(20)
    points = EpipolarTriangulator().triangulate(stereo(uv_u, uv_l[order], 0.02, 0.02), calibration)
    assert len(points) == 20 and not points.rejected
    # the NumPy path: linear start, Gauss-Newton with LAPACK solves, cov = inv(J^T W J)
    uv = np.hstack([uv_u, uv_l])
    Xk = _numpy_linear(stereo_model.undistort(uv_u, geometry.upper), stereo_model.undistort(uv_l, geometry.lower),
                       geometry)
    w = np.full((20, 4), 1.0 / 0.02**2)
    for _ in range(10):
        pred, J = _cv2_project(geometry, Xk), stereo_model.project_pair(geometry, Xk)[1]
        JtW = np.swapaxes(J, 1, 2) * w[:, None, :]
        step = -np.linalg.solve(JtW @ J, JtW @ (pred - uv)[:, :, None])[:, :, 0]
        Xk = Xk + step
    J = stereo_model.project_pair(geometry, Xk)[1]
    cov = np.linalg.inv((np.swapaxes(J, 1, 2) * w[:, None, :]) @ J)
    upper = points.upper_index
    assert np.array_equal(order[points.lower_index], upper)  # the shuffled lower set matched back
    assert np.max(np.abs(points.xyz - Xk[upper])) < 1e-9  # mm (measured: ~5e-13)
    assert np.max(np.abs(points.cov_xyz - cov[upper])) < 1e-9 * np.max(np.abs(cov))


# ---- matching glue (issue 25 item 4, round 4): the compiled gathers against the NumPy they replaced ----


def test_unique_matches_equal_the_numpy_counts_and_nonzero():
    rng = np.random.default_rng(11)
    for n, m, density in [(0, 0, 0.5), (0, 4, 0.5), (5, 0, 0.5), (1, 1, 1.0)] + [
        (int(rng.integers(1, 30)), int(rng.integers(1, 30)), float(rng.uniform(0.0, 0.3))) for _ in range(300)
    ]:
        candidate = rng.random((n, m)) < density
        n_upper, n_lower, upper, lower = stereo_model.unique_matches(candidate)
        want_upper, want_lower = candidate.sum(axis=1), candidate.sum(axis=0)
        accepted = candidate & (want_upper == 1)[:, None] & (want_lower == 1)[None, :]
        want_i, want_j = np.nonzero(accepted)
        np.testing.assert_array_equal(n_upper, want_upper)
        np.testing.assert_array_equal(n_lower, want_lower)
        np.testing.assert_array_equal(upper, want_i)
        np.testing.assert_array_equal(lower, want_j)
        assert upper.dtype == lower.dtype == np.int64


def test_paired_observations_equal_the_numpy_gather_bit_for_bit():
    rng = np.random.default_rng(12)
    n, m = 17, 13
    uv_u, uv_l = rng.uniform(0, 2000, (n, 2)), rng.uniform(0, 2000, (m, 2))
    sigma_u, sigma_l = rng.uniform(0.005, 0.3, (n, 2)), rng.uniform(0.005, 0.3, (m, 2))
    X_pairs = rng.normal(0, 300, (n, m, 3))
    i, j = np.array([0, 3, 4, 16]), np.array([12, 0, 5, 2])
    X, uv, w = stereo_model.paired_observations(i, j, uv_u, uv_l, sigma_u, sigma_l, X_pairs)
    assert np.array_equal(X, X_pairs[i, j])
    assert np.array_equal(uv, np.concatenate((uv_u[i], uv_l[j]), axis=1))
    assert np.array_equal(w, 1.0 / np.concatenate((sigma_u[i], sigma_l[j]), axis=1) ** 2)
    empty = stereo_model.paired_observations(i[:0], j[:0], uv_u, uv_l, sigma_u, sigma_l, X_pairs)
    assert [a.shape for a in empty] == [(0, 3), (0, 4), (0, 4)]


@pytest.mark.parametrize("bad", [np.nan, 0.0, -0.01, np.inf])
def test_centroid_sigmas_replace_only_the_invalid_ones(bad):
    sigma = np.full((6, 2), 0.02)
    assert stereo_model.centroid_sigmas(sigma, 0.05) is sigma  # all valid: the array itself, no copy
    sigma[4, 1] = bad
    out = stereo_model.centroid_sigmas(sigma, 0.05)
    expected = np.full((6, 2), 0.02)
    expected[4, 1] = 0.05
    assert np.array_equal(out, expected)
    assert stereo_model.centroid_sigmas(np.zeros((0, 2)), 0.05).shape == (0, 2)
