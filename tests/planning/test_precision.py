"""The Cramér-Rao calculator (crossfield.precision) against analytic cases and Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crossfield.precision import (
    NoiseModel, camera_point_covariance, centroid_crb, chain_bound, edge_limited_bound, fitzpatrick_covariance,
    fitzpatrick_tre, point_jacobian, project_stereo, registration_covariance, registration_crb, triangulate_batch,
)
from crossfield.precision.centroid import blurred_disc
from crossfield.rigid import kabsch
from crossfield.simulator.scenarios import build_scene
from crossfield.types import CameraIntrinsics, StereoCalibration


# ---- centroid -----------------------------------------------------------------------------------


def test_large_disc_is_edge_limited():
    # R >> blur, constant noise: the 1-D edge-limited bound (sigma_n / A) sqrt(2 s_eff / (sqrt(pi) R)).
    for radius, blur in ((60.0, 1.5), (40.0, 0.8)):
        bound = centroid_crb(radius, blur, 1000.0, 100.0, NoiseModel(0.0, 5.0))
        expected = edge_limited_bound(radius, blur, 1000.0, 5.0)
        assert bound.sigma_u_px == pytest.approx(expected, rel=0.01)
        assert bound.sigma_v_px == pytest.approx(expected, rel=0.01)


def test_bound_scales_as_the_noise_and_falls_with_contrast():
    a = centroid_crb(8.0, 1.0, 1000.0, 100.0, NoiseModel(0.0, 4.0)).sigma_u_px
    b = centroid_crb(8.0, 1.0, 1000.0, 100.0, NoiseModel(0.0, 8.0)).sigma_u_px
    c = centroid_crb(8.0, 1.0, 2000.0, 100.0, NoiseModel(0.0, 4.0)).sigma_u_px
    assert b == pytest.approx(2 * a, rel=1e-9)  # read noise only: sigma proportional to noise / contrast
    assert c == pytest.approx(a / 2, rel=1e-9)
    shot = centroid_crb(8.0, 1.0, 1000.0, 100.0, NoiseModel(0.35, 4.0)).sigma_u_px
    assert shot > a  # photon noise adds


def test_blurred_disc_gradient_is_the_derivative_of_the_model():
    h = 1e-4
    P0, du, dv, _ = blurred_disc(5.0, 1.2, (0.3, -0.2), supersample=8)
    Pp, *_ = blurred_disc(5.0, 1.2, (0.3 + h, -0.2), supersample=8)
    Pm, *_ = blurred_disc(5.0, 1.2, (0.3 - h, -0.2), supersample=8)
    np.testing.assert_allclose((Pp - Pm) / (2 * h), du, atol=2e-3 * np.abs(du).max())
    assert P0.sum() == pytest.approx(math.pi * 25.0, rel=1e-3)  # the disc's area (blur keeps it)


def test_centroid_bound_is_attained_by_maximum_likelihood_monte_carlo():
    """ML fits (Gauss-Newton on the exact model, weighted by the true variances) of noisy
    images: their RMS centre error equals the bound within the sampling error."""
    R, s, A, b = 4.0, 1.0, 2500.0, 120.0
    noise = NoiseModel(0.35, 2.5)
    c0 = (0.2, -0.1)
    bound = centroid_crb(R, s, A, b, noise, centre_px=c0, supersample=8)
    P, _, _, _ = blurred_disc(R, s, c0, supersample=8)
    mu = b + A * P
    sd = np.sqrt(noise.variance(mu))
    rng = np.random.default_rng(3)
    errors = []
    for _ in range(300):
        data = mu + sd * rng.standard_normal(mu.shape)
        theta = np.array([c0[0], c0[1], A, b])
        for _ in range(3):
            Pk, du, dv, _ = blurred_disc(R, s, (theta[0], theta[1]), supersample=8)
            model = theta[3] + theta[2] * Pk
            J = np.stack([theta[2] * du, theta[2] * dv, Pk, np.ones_like(Pk)]).reshape(4, -1).T / sd.reshape(-1, 1)
            r = ((data - model) / sd).ravel()
            theta = theta + np.linalg.lstsq(J, r, rcond=None)[0]
        errors.append(theta[:2] - c0)
    rms = np.sqrt(np.mean(np.array(errors) ** 2, axis=0))
    # 300 samples: the RMS is uncertain by ~4 %.
    assert rms[0] == pytest.approx(bound.sigma_u_px, rel=0.13)
    assert rms[1] == pytest.approx(bound.sigma_v_px, rel=0.13)


def test_bad_centroid_inputs_are_refused():
    with pytest.raises(ValueError, match="blur_sigma_px"):
        centroid_crb(5.0, 0.0, 1000.0, 100.0)
    with pytest.raises(ValueError, match="radius_px"):
        centroid_crb(-1.0, 1.0, 1000.0, 100.0)
    with pytest.raises(ValueError, match="zero variance"):
        centroid_crb(5.0, 1.0, 1000.0, 100.0, NoiseModel(0.0, 0.0))


# ---- camera points ------------------------------------------------------------------------------


def _parallel_rig(f_px: float = 2000.0, baseline: float = 60.0) -> StereoCalibration:
    K = np.array([[f_px, 0, 800.0], [0, f_px, 600.0], [0, 0, 1]])
    intr = CameraIntrinsics(K, np.zeros(5), (1600, 1200))
    # Lower camera centre at (0, b, 0) in the upper frame, parallel axes: p_lower = p_upper - C.
    return StereoCalibration(intr, intr, np.eye(3), np.array([0.0, -baseline, 0.0]), source="test")


def test_parallel_stereo_depth_formula():
    f, b, sigma = 2000.0, 60.0, 0.02
    cal = _parallel_rig(f, b)
    X = np.array([[0.0, 30.0, 300.0], [40.0, -20.0, 500.0], [-70.0, 50.0, 800.0]])
    _, J = project_stereo(cal, X)
    cov = camera_point_covariance(J, sigma)
    sigma_d = math.sqrt(2) * sigma  # disparity: difference of two centroids
    for k, z in enumerate(X[:, 2]):
        assert math.sqrt(cov[k, 2, 2]) == pytest.approx(z**2 * sigma_d / (f * b), rel=1e-6)


def test_triangulation_monte_carlo_matches_the_bound_with_distortion():
    scene = build_scene("station")
    X = np.array([t.centre_camera for t in scene.targets])
    uv, J = project_stereo(scene.calibration, X)
    sigma = np.array([0.01, 0.012, 0.009, 0.011])
    cov = camera_point_covariance(J, sigma)
    rng = np.random.default_rng(1)
    noisy = uv + sigma * rng.standard_normal((20000,) + uv.shape)
    Xb = triangulate_batch(scene.calibration, noisy, sigma)
    np.testing.assert_allclose(Xb.mean(axis=0), X, atol=3 * np.sqrt(cov.diagonal(axis1=1, axis2=2).max()) / 100)
    mc = np.einsum("bni,bnj->nij", Xb - X, Xb - X) / len(Xb)
    np.testing.assert_allclose(np.sqrt(mc.diagonal(axis1=1, axis2=2)), np.sqrt(cov.diagonal(axis1=1, axis2=2)),
                               rtol=0.03)


def test_batched_triangulation_is_the_plugins_result():
    from crossfield.plugins.triangulate_epipolar import EpipolarTriangulator
    from crossfield.types import CentroidSet, StereoCentroids

    scene = build_scene("station")
    X = np.array([t.centre_camera for t in scene.targets])
    uv, _ = project_stereo(scene.calibration, X)
    uv = uv + 0.05 * np.random.default_rng(2).standard_normal(uv.shape)
    sig = np.full((len(X), 2), 0.05)
    n = len(X)

    def side(name: str, q: np.ndarray) -> CentroidSet:
        return CentroidSet(name, 0, q, sig, np.full(n, 1500.0), np.ones(n), np.full(n, 3000.0))

    cs = StereoCentroids(0, side("upper", uv[:, :2]), side("lower", uv[:, 2:]))
    points = EpipolarTriangulator().triangulate(cs, scene.calibration)
    order = np.argsort(points.upper_index)
    np.testing.assert_allclose(triangulate_batch(scene.calibration, uv, 0.05), points.xyz[order], atol=1e-9)


# ---- registration -------------------------------------------------------------------------------


def _circle(n: int, rho: float) -> np.ndarray:
    a = 2 * np.pi * np.arange(n) / n
    return np.stack([rho * np.cos(a), rho * np.sin(a), np.zeros(n)], axis=1)


def test_fitzpatrick_tre_on_a_ring_of_fiducials():
    # N fiducials on a circle of radius rho: principal axes x, y (f^2 = rho^2 / 2) and z (f^2 = rho^2);
    # a target on the axis at height h: TRE^2 = FLE^2 / N (1 + 4 h^2 / (3 rho^2)).
    n, rho, fle = 6, 50.0, 0.1
    h = np.array([0.0, 25.0, 100.0, 300.0])
    r = np.stack([np.zeros(4), np.zeros(4), h], axis=1) + 7.0  # anywhere: the formula is about the centroid
    tre = fitzpatrick_tre(_circle(n, rho) + 7.0, fle, r)
    np.testing.assert_allclose(tre, np.sqrt(fle**2 / n * (1 + 4 * h**2 / (3 * rho**2))), rtol=1e-12)


def test_fitzpatrick_tre_is_the_trace_of_its_covariance_and_of_a_direct_monte_carlo():
    """Textbook configuration: four non-coplanar fiducials, isotropic FLE, equal weights; a direct
    Monte Carlo of the rigid registration (rigid.kabsch) gives the same TRE."""
    G = np.array([[0.0, 0.0, 0.0], [80.0, 0.0, 10.0], [10.0, 60.0, -5.0], [30.0, 20.0, 40.0]])
    targets = np.array([[30.0, 20.0, 10.0], [200.0, -50.0, 0.0], [0.0, 0.0, 300.0]])
    fle = 0.05
    cov, g_bar = fitzpatrick_covariance(G, fle)
    J = point_jacobian(targets, g_bar)
    trace = np.trace(J @ cov @ np.swapaxes(J, 1, 2), axis1=1, axis2=2)
    tre = fitzpatrick_tre(G, fle, targets)
    np.testing.assert_allclose(np.sqrt(trace), tre, rtol=1e-10)
    rng = np.random.default_rng(4)
    noisy = G + fle / np.sqrt(3) * rng.standard_normal((40000,) + G.shape)
    R, t, _, _ = kabsch(noisy, np.broadcast_to(G, noisy.shape))  # fit the noisy set onto the true one
    mapped = np.einsum("bij,nj->bni", R, targets) + t[:, None, :]
    mc = np.sqrt(np.mean(np.sum((mapped - targets) ** 2, axis=-1), axis=0))
    np.testing.assert_allclose(mc, tre, rtol=0.02)


def test_registration_covariances_reduce_to_fitzpatrick_for_isotropic_errors():
    G = np.random.default_rng(5).uniform(-60, 60, (7, 3))
    s = 0.02
    S = np.broadcast_to(s**2 * np.eye(3), (7, 3, 3))
    fitz, g0 = fitzpatrick_covariance(G, math.sqrt(3) * s)
    crb, g1 = registration_crb(G, S)
    ls, g2 = registration_covariance(G, S)
    np.testing.assert_allclose(crb, fitz, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(ls, fitz, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(g0, g1)
    np.testing.assert_allclose(g0, g2)


def test_weighted_registration_covariance_matches_monte_carlo_with_anisotropic_errors():
    rng = np.random.default_rng(6)
    G = rng.uniform(-60, 60, (6, 3))
    S = np.array([np.diag(rng.uniform(0.01, 0.05, 3) ** 2) for _ in range(6)])
    w = 1.0 / np.trace(S, axis1=1, axis2=2)
    cov, g_bar = registration_covariance(G, S, w)
    target = np.array([250.0, -40.0, 90.0])
    J = point_jacobian(target, g_bar)
    predicted = J @ cov @ J.T
    noise = rng.standard_normal((40000, 6, 3)) * np.sqrt(np.diagonal(S, axis1=1, axis2=2))
    R, t, _, _ = kabsch(G + noise, np.broadcast_to(G, noise.shape), w)
    err = np.einsum("bij,j->bi", R, target) + t - target
    np.testing.assert_allclose(np.cov(err.T), predicted, rtol=0.05, atol=0.05 * np.abs(predicted).max())
    # The ML bound is never larger than the weighted least-squares covariance.
    crb, g_c = registration_crb(G, S)
    Jc = point_jacobian(target, g_c)
    assert np.all(np.linalg.eigvalsh(predicted - Jc @ crb @ Jc.T) > -1e-12)


def test_chain_bound_on_the_station():
    scene = build_scene("station")
    X = np.array([t.centre_camera for t in scene.targets])
    controls = np.array([k for k, t in enumerate(scene.targets) if t.id.startswith("C")])
    sig = np.full((len(X), 4), 0.003)
    bound = chain_bound(scene.calibration, X, sig, controls, 0.01, scene.R_global_camera, scene.t_global_camera)
    # Depth is the weak axis of a short-baseline rig: sigma_z ~ z^2 sqrt(2) sigma / (f b).
    f = scene.calibration.upper.camera_matrix[1, 1]
    expected_z = X[:, 2] ** 2 * math.sqrt(2) * 0.003 / (f * 50.0)
    np.testing.assert_allclose(bound.camera_sigma_mm[:, 2], expected_z, rtol=0.08)
    assert np.all(bound.camera_sigma_mm[:, 2] > 4 * bound.camera_sigma_mm[:, :2].max(axis=1))
    # The registration translation is at least the CMM sigma / sqrt(N) per axis.
    assert np.all(bound.registration_sigma[3:] >= 0.01 / math.sqrt(len(controls)))
    # A point far from the controls is worse than one at their centroid.
    assert bound.global_rms_mm.min() > 0


# ---- perspective eccentricity -------------------------------------------------------------------


def test_a_circle_facing_the_camera_on_its_axis_has_no_eccentricity():
    from crossfield.imaging.eccentricity import View, centre_offsets

    K = np.array([[3000.0, 0, 800], [0, 3000.0, 600], [0, 0, 1]])
    pinhole = (View(K, np.zeros(5), np.eye(3), np.zeros(3)),)

    def offset(centre, normal, r):
        return centre_offsets(np.array([centre]), np.array([normal]), np.array([r]), pinhole)

    np.testing.assert_allclose(offset([0.0, 0.0, 400.0], [0.0, 0.0, -1.0], 2.5), 0.0, atol=1e-12)
    # Tilted or off-axis: the ellipse centre moves; the offset grows as r^2 (small-target limit).
    tilt = [0.0, np.sin(0.4), -np.cos(0.4)]
    small = offset([30.0, 20.0, 400.0], tilt, 1.0)
    large = offset([30.0, 20.0, 400.0], tilt, 2.0)
    assert np.linalg.norm(small) > 1e-4
    np.testing.assert_allclose(large, 4 * small, rtol=0.01)


def test_eccentricity_matches_the_simulators_blob_centres():
    """The planner's perspective bias (centre_offsets of stereo_views, the triangulation's kernel)."""
    from crossfield.imaging.eccentricity import centre_offsets, stereo_views

    scene = build_scene("table3")
    X = np.array([t.centre_camera for t in scene.targets])
    N = np.array([t.normal_camera for t in scene.targets])
    uv, _ = project_stereo(scene.calibration, X)
    blob = {c: scene.true_blob_centres(c) for c in ("upper", "lower")}
    true = np.array([np.r_[blob["upper"][t.id], blob["lower"][t.id]] for t in scene.targets]) - uv
    model = centre_offsets(X, N, np.full(len(X), 2.5), stereo_views(scene.calibration))
    assert np.sqrt(np.mean(true**2)) > 0.01  # the effect is real: ~0.02 px
    # The conic model explains it to ~0.0014 px RMS (the rest: rendering discretisation).
    assert np.sqrt(np.mean((model - true) ** 2)) < 0.15 * np.sqrt(np.mean(true**2))
