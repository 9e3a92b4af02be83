"""triangulate "epipolar" against ground truth, OpenCV and analytic configurations.

Synthetic rig: two scA1600-14gm-like cameras (1626 x 1236 px, fx ~ 3636 px),
lower camera 50 mm below the upper one (t_lower_upper ~ (0, -50, 0) mm), a
few mrad from parallel, mild distortion; targets at z ~ 350..450 mm.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import crossfield.camera.stereo_model as stereo_model
import crossfield.plugins.triangulate_epipolar as epipolar
from crossfield.errors import ConfigError
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.types import CameraIntrinsics, CentroidSet, StereoCalibration, StereoCentroids

SIZE = (1626, 1236)


def make_calibration(
    dist_upper=(-0.05, 0.02, 1e-4, -2e-4, 0.0),
    dist_lower=(-0.048, 0.018, -1e-4, 1e-4, 0.0),
    rvec=(2e-3, -3e-3, 1e-3),
    t=(0.3, -50.0, 0.2),
) -> StereoCalibration:
    K_upper = np.array([[3636.0, 0.0, 812.5], [0.0, 3636.0, 617.5], [0.0, 0.0, 1.0]])
    K_lower = np.array([[3630.0, 0.0, 815.2], [0.0, 3633.0, 620.4], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array(rvec, dtype=np.float64))[0]
    return StereoCalibration(
        CameraIntrinsics(K_upper, np.array(dist_upper), SIZE),
        CameraIntrinsics(K_lower, np.array(dist_lower), SIZE),
        R,
        np.array(t, dtype=np.float64),
        source="synthetic",
    )


def project(calibration: StereoCalibration, X: np.ndarray, camera: str) -> np.ndarray:
    """Reference projection with cv2.projectPoints (N, 2) px."""
    cam = calibration.camera(camera)
    if camera == "upper":
        rvec, tvec = np.zeros(3), np.zeros(3)
    else:
        rvec, tvec = cv2.Rodrigues(np.asarray(calibration.R_lower_upper))[0], calibration.t_lower_upper
    uv, _ = cv2.projectPoints(np.asarray(X, dtype=np.float64), rvec, np.asarray(tvec), cam.camera_matrix,
                              cam.dist_coeffs)
    return uv.reshape(-1, 2)


def random_points(rng: np.random.Generator, calibration: StereoCalibration, n: int, margin: float = 20.0):
    """n points in the working volume (upper frame, mm) visible in both images."""
    points = []
    while len(points) < n:
        X = np.column_stack([rng.uniform(-85, 85, 64), rng.uniform(-20, 70, 64), rng.uniform(350, 450, 64)])
        ok = np.ones(len(X), dtype=bool)
        for camera in ("upper", "lower"):
            uv = project(calibration, X, camera)
            ok &= np.all((uv > margin) & (uv < np.array(SIZE) - 1 - margin), axis=1)
        points.extend(X[ok])
    return np.array(points[:n])


def centroid_set(camera: str, uv: np.ndarray, sigma, sequence: int = 7) -> CentroidSet:
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = len(uv)
    return CentroidSet(
        camera=camera,
        sequence=sequence,
        uv=uv,
        sigma_uv=np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n, 2)),
        area_px=np.full(n, 80.0),
        roundness=np.full(n, 0.98),
        peak=np.full(n, 3000.0),
    )


def observe(calibration, X, rng=None, noise_px=0.0, sigma_px=0.02):
    """Upper/lower centroid positions (N, 2) of X, with optional Gaussian noise."""
    uv_u = project(calibration, X, "upper")
    uv_l = project(calibration, X, "lower")
    if noise_px:
        uv_u = uv_u + rng.normal(0.0, noise_px, uv_u.shape)
        uv_l = uv_l + rng.normal(0.0, noise_px, uv_l.shape)
    return uv_u, uv_l


def stereo(uv_u, uv_l, sigma_u=0.02, sigma_l=0.02, sequence=7) -> StereoCentroids:
    return StereoCentroids(sequence, centroid_set("upper", uv_u, sigma_u, sequence),
                           centroid_set("lower", uv_l, sigma_l, sequence))


@pytest.fixture(scope="module")
def calibration():
    return make_calibration()


def triangulator(**options):
    pm = make_plugin_manager(builtins=False, extra=[epipolar])
    return get_implementation(pm, "triangulate", "epipolar").create(options)


# ---------------------------------------------------------------------------------------------------
# The lens model used for refinement and error propagation
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "dist",
    [
        (-0.05, 0.02, 1e-4, -2e-4, 0.0),
        (-0.05, 0.02, 1e-4, -2e-4, 0.01, 0.002, -0.001, 0.003),  # rational
        (-0.05, 0.02, 1e-4, -2e-4, 0.01, 0.002, -0.001, 0.003, 1e-4, -2e-4, 3e-4, 1e-4),  # thin prism
    ],
)
def test_projection_and_jacobian_match_opencv(dist):
    calibration = make_calibration(dist_upper=dist, dist_lower=dist)
    geometry = stereo_model.stereo_geometry(calibration)
    X = random_points(np.random.default_rng(3), calibration, 30)
    uv, J = stereo_model.project_pair(geometry, X)
    np.testing.assert_allclose(uv[:, :2], project(calibration, X, "upper"), atol=1e-9)
    np.testing.assert_allclose(uv[:, 2:], project(calibration, X, "lower"), atol=1e-9)
    h = 1e-4  # mm; central differences
    plus = [stereo_model.project_pair(geometry, X + h * e)[0] for e in np.eye(3)]
    minus = [stereo_model.project_pair(geometry, X - h * e)[0] for e in np.eye(3)]
    numeric = np.stack([(p - m) / (2 * h) for p, m in zip(plus, minus)], axis=2)
    np.testing.assert_allclose(J, numeric, rtol=0, atol=1e-6)


# ---------------------------------------------------------------------------------------------------
# Accuracy
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("refine", [True, False])
def test_noise_free_points_are_recovered_exactly_despite_shuffling(calibration, refine):
    rng = np.random.default_rng(11)
    X = random_points(rng, calibration, 20)
    uv_u, uv_l = observe(calibration, X)
    order_u, order_l = rng.permutation(20), rng.permutation(20)
    points = triangulator(refine=refine).triangulate(stereo(uv_u[order_u], uv_l[order_l]), calibration)

    assert len(points) == 20 and points.rejected == ()
    assert points.sequence == 7 and points.method == "epipolar"
    # The pairing follows the shuffles: upper[i] shows X[order_u[i]], lower[j] shows X[order_l[j]].
    np.testing.assert_array_equal(order_u[points.upper_index], order_l[points.lower_index])
    truth = X[order_u[points.upper_index]]
    assert np.max(np.abs(points.xyz - truth)) < 1e-6
    assert np.max(points.residual_px) < 1e-6
    assert np.all(np.diff(points.upper_index) > 0)


def test_agrees_with_cv2_triangulatePoints(calibration):
    """Reference implementation: cv2.triangulatePoints on undistorted pixels (linear DLT)."""
    rng = np.random.default_rng(5)
    X = random_points(rng, calibration, 200)
    P_upper = calibration.upper.camera_matrix @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_lower = calibration.lower.camera_matrix @ np.hstack(
        [calibration.R_lower_upper, calibration.t_lower_upper[:, None]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-15)

    def opencv(uv_u, uv_l):
        und_u = cv2.undistortPoints(uv_u.reshape(-1, 1, 2), calibration.upper.camera_matrix,
                                    calibration.upper.dist_coeffs, P=calibration.upper.camera_matrix,
                                    criteria=criteria).reshape(-1, 2)
        und_l = cv2.undistortPoints(uv_l.reshape(-1, 1, 2), calibration.lower.camera_matrix,
                                    calibration.lower.dist_coeffs, P=calibration.lower.camera_matrix,
                                    criteria=criteria).reshape(-1, 2)
        Xh = cv2.triangulatePoints(P_upper, P_lower, und_u.T, und_l.T)
        return (Xh[:3] / Xh[3]).T

    tri = triangulator(max_epipolar_px=1.0, z_min_mm=300, z_max_mm=500)
    errors_ours, errors_cv = [], []
    for noise in (0.0, 0.02):
        for chunk in np.split(X, 10):
            uv_u, uv_l = observe(calibration, chunk, rng, noise)
            points = tri.triangulate(stereo(uv_u, uv_l), calibration)
            assert len(points) == len(chunk)
            np.testing.assert_array_equal(points.upper_index, points.lower_index)
            reference = opencv(uv_u, uv_l)
            if noise == 0.0:
                assert np.max(np.abs(points.xyz - reference)) < 1e-6
            else:
                # Linear and optimal estimates differ by a fraction of the uncertainty.
                assert np.all(np.abs(points.xyz - reference) < 3 * points.sigma_xyz)
                errors_ours.append(points.xyz - chunk)
                errors_cv.append(reference - chunk)
    rms_ours = np.sqrt(np.mean(np.concatenate(errors_ours) ** 2))
    rms_cv = np.sqrt(np.mean(np.concatenate(errors_cv) ** 2))
    assert rms_ours <= 1.02 * rms_cv


def test_noisy_errors_are_consistent_with_propagated_sigma(calibration):
    """0.02 px centroid noise: errors / sigma_xyz have RMS ~ 1 per axis, no wrong pairs."""
    rng = np.random.default_rng(2024)
    tri = triangulator()
    normalised, residuals, errors = [], [], []
    for _ in range(150):
        X = random_points(rng, calibration, 20)
        uv_u, uv_l = observe(calibration, X, rng, noise_px=0.02)
        order = rng.permutation(20)
        points = tri.triangulate(stereo(uv_u, uv_l[order], 0.02, 0.02), calibration)
        np.testing.assert_array_equal(order[points.lower_index], points.upper_index)
        truth = X[points.upper_index]
        normalised.append((points.xyz - truth) / points.sigma_xyz)
        errors.append(points.xyz - truth)
        residuals.append(points.residual_px)
    normalised = np.concatenate(normalised)
    assert len(normalised) > 0.97 * 150 * 20  # only rare chance ambiguities may be rejected
    rms = np.sqrt(np.mean(normalised**2, axis=0))
    assert np.all((rms > 0.93) & (rms < 1.07)), rms
    assert np.all(np.abs(np.mean(normalised, axis=0)) < 0.06)  # no bias
    # Depth (z) is the weak direction: ~ z^2 / (f b) * sigma_disparity ~ 0.03 mm at 400 mm.
    rms_mm = np.sqrt(np.mean(np.concatenate(errors) ** 2, axis=0))
    assert rms_mm[2] < 0.05 and np.all(rms_mm[:2] < 0.01), rms_mm
    # Two observations of 2 coordinates, 3 unknowns: E[sum (r/sigma)^2] = 1, so the RMS of
    # residual_px = sqrt(|r_upper|^2 + |r_lower|^2) / sqrt(2) is sigma / sqrt(2).
    rms_residual = np.sqrt(np.mean(np.concatenate(residuals) ** 2))
    assert abs(rms_residual - 0.02 / np.sqrt(2)) < 0.1 * 0.02 / np.sqrt(2)


def test_unequal_sigmas_weight_the_solution(calibration):
    """Per-point, per-axis sigmas: weighted solution and propagated sigma still agree with Monte Carlo."""
    rng = np.random.default_rng(8)
    X = random_points(rng, calibration, 1)
    sigma_u = np.array([[0.01, 0.05]])
    sigma_l = np.array([[0.04, 0.015]])
    tri = triangulator(max_epipolar_px=2.0)
    uv_u0, uv_l0 = observe(calibration, X)
    estimates, sigmas = [], None
    for _ in range(3000):
        uv_u = uv_u0 + rng.normal(0.0, 1.0, (1, 2)) * sigma_u
        uv_l = uv_l0 + rng.normal(0.0, 1.0, (1, 2)) * sigma_l
        points = tri.triangulate(stereo(uv_u, uv_l, sigma_u, sigma_l), calibration)
        estimates.append(points.xyz[0])
        sigmas = points.sigma_xyz[0]
    spread = np.std(np.array(estimates), axis=0)
    np.testing.assert_allclose(spread, sigmas, rtol=0.06)
    assert np.all(np.abs(np.mean(estimates, axis=0) - X[0]) < 4 * sigmas / np.sqrt(3000))


# ---------------------------------------------------------------------------------------------------
# Matching: dropped, stray and ambiguous centroids
# ---------------------------------------------------------------------------------------------------


def test_dropped_and_stray_centroids_are_rejected_not_paired(calibration):
    rng = np.random.default_rng(21)
    X = random_points(rng, calibration, 20)
    uv_u, uv_l = observe(calibration, X, rng, noise_px=0.02)
    keep_u = np.setdiff1d(np.arange(20), [3, 9])  # seen by the lower camera only
    keep_l = np.setdiff1d(np.arange(20), [0, 5, 17])  # seen by the upper camera only
    strays_u = rng.uniform([0, 0], SIZE, (3, 2))
    strays_l = rng.uniform([0, 0], SIZE, (3, 2))
    ids_u = np.concatenate([keep_u, [-1, -1, -1]])  # -1 = stray
    ids_l = np.concatenate([keep_l, [-1, -1, -1]])
    order_u, order_l = rng.permutation(len(ids_u)), rng.permutation(len(ids_l))
    all_u = np.vstack([uv_u[keep_u], strays_u])[order_u]
    all_l = np.vstack([uv_l[keep_l], strays_l])[order_l]
    ids_u, ids_l = ids_u[order_u], ids_l[order_l]

    points = triangulator().triangulate(stereo(all_u, all_l), calibration)

    matched_ids = ids_u[points.upper_index]
    np.testing.assert_array_equal(matched_ids, ids_l[points.lower_index])
    assert np.all(matched_ids >= 0)
    assert sorted(matched_ids) == sorted(set(keep_u) & set(keep_l))  # all 15 common points
    assert np.max(np.abs(points.xyz - X[matched_ids])) < 0.1
    rejected = set(points.rejected)
    for i, ident in enumerate(ids_u):
        if ident < 0 or ident in (0, 5, 17):
            assert any(r.startswith(f"upper[{i}]: no match") for r in rejected), (i, ident)
    for j, ident in enumerate(ids_l):
        if ident < 0 or ident in (3, 9):
            assert any(r.startswith(f"lower[{j}]: no match") for r in rejected), (j, ident)
    assert len(rejected) == len(all_u) + len(all_l) - 2 * len(points)


def epipolar_neighbour(calibration, X1: np.ndarray, offset_mm: float) -> np.ndarray:
    """A point in the epipolar plane of X1, shifted by offset_mm along the baseline."""
    centre_lower = -calibration.R_lower_upper.T @ calibration.t_lower_upper  # (0, ~50, 0) mm
    return X1 + offset_mm * centre_lower / np.linalg.norm(centre_lower)


def test_two_points_on_one_epipolar_line_are_ambiguous_then_pruned_by_depth(calibration):
    X1 = np.array([10.0, 10.0, 400.0])
    X2 = epipolar_neighbour(calibration, X1, 20.0)  # cross pairings triangulate to ~286 and ~667 mm
    X = np.vstack([X1, X2])
    uv_u, uv_l = observe(calibration, X)
    sc = stereo(uv_u, uv_l[::-1])  # lower order swapped

    wide = triangulator(z_min_mm=100, z_max_mm=2000).triangulate(sc, calibration)
    assert len(wide) == 0
    assert sorted(wide.rejected) == [
        "lower[0]: ambiguous (2 candidates: upper[0], upper[1])",
        "lower[1]: ambiguous (2 candidates: upper[0], upper[1])",
        "upper[0]: ambiguous (2 candidates: lower[0], lower[1])",
        "upper[1]: ambiguous (2 candidates: lower[0], lower[1])",
    ]

    narrow = triangulator(z_min_mm=350, z_max_mm=450).triangulate(sc, calibration)
    np.testing.assert_array_equal(narrow.upper_index, [0, 1])
    np.testing.assert_array_equal(narrow.lower_index, [1, 0])
    assert np.max(np.abs(narrow.xyz - X)) < 1e-6 and narrow.rejected == ()


def test_a_candidate_claimed_by_two_centroids_is_ambiguous(calibration):
    X1 = np.array([-20.0, 15.0, 410.0])
    X2 = epipolar_neighbour(calibration, X1, 15.0)
    uv_u, uv_l = observe(calibration, np.vstack([X1, X2]))
    points = triangulator(z_min_mm=100, z_max_mm=2000).triangulate(stereo(uv_u, uv_l[:1]), calibration)
    assert len(points) == 0
    assert sorted(points.rejected) == [
        "lower[0]: ambiguous (2 candidates: upper[0], upper[1])",
        "upper[0]: ambiguous (its candidate lower[0] is also a candidate of upper[1])",
        "upper[1]: ambiguous (its candidate lower[0] is also a candidate of upper[0])",
    ]


def test_ambiguity_does_not_disturb_other_points(calibration):
    rng = np.random.default_rng(4)
    X1 = np.array([10.0, 10.0, 400.0])
    X = np.vstack([X1, epipolar_neighbour(calibration, X1, 20.0), random_points(rng, calibration, 12)])
    uv_u, uv_l = observe(calibration, X)
    points = triangulator().triangulate(stereo(uv_u, uv_l), calibration)
    np.testing.assert_array_equal(points.upper_index, np.arange(2, 14))
    np.testing.assert_array_equal(points.lower_index, np.arange(2, 14))
    assert len(points.rejected) == 4 and all("ambiguous" in r for r in points.rejected)


def test_pairs_outside_the_working_range_are_not_matched(calibration):
    X = np.array([[0.0, 20.0, 400.0], [5.0, 30.0, 900.0]])
    uv_u, uv_l = observe(calibration, X)
    points = triangulator(z_min_mm=300, z_max_mm=600).triangulate(stereo(uv_u, uv_l), calibration)
    np.testing.assert_array_equal(points.upper_index, [0])
    expected = "upper[1]: no match (lower[1] is on its epipolar line but triangulates to z = 900.0 mm"
    assert any(r.startswith(expected) for r in points.rejected), points.rejected
    # A pairing that puts the point behind the cameras is never a candidate, whatever the range:
    # the lower camera's image of -X lies on the upper image's epipolar line but on the wrong side.
    upper_view = project(calibration, X[:1], "upper")
    lower_view = project(calibration, -X[:1], "lower")
    behind = triangulator(z_min_mm=0, z_max_mm=1e9).triangulate(stereo(upper_view, lower_view), calibration)
    assert len(behind) == 0
    expected = "upper[0]: no match (lower[0] is on its epipolar line but triangulates to z = -400.0 mm"
    assert behind.rejected[0].startswith(expected), behind.rejected


def test_fixed_epipolar_limit_and_no_match_reason(calibration):
    X = np.array([[0.0, 20.0, 400.0]])
    uv_u, uv_l = observe(calibration, X)
    shifted = uv_l + np.array([[0.8, 0.0]])  # 0.8 px off the (near-vertical) epipolar line
    assert len(triangulator(max_epipolar_px=1.0).triangulate(stereo(uv_u, shifted), calibration)) == 1
    points = triangulator(max_epipolar_px=0.5).triangulate(stereo(uv_u, shifted), calibration)
    assert len(points) == 0
    (reason,) = [r for r in points.rejected if r.startswith("upper[0]")]
    distance = float(reason.split(" at ")[1].split(" px")[0])
    assert reason.endswith("limit 0.50 px)") and abs(distance - 0.80) < 0.02


def test_derived_limit_follows_centroid_sigma(calibration):
    X = np.array([[0.0, 20.0, 400.0]])
    uv_u, uv_l = observe(calibration, X)
    shifted = uv_l + np.array([[0.8, 0.0]])
    tri = triangulator(epipolar_k=5.0, calibration_px=0.0)
    # limit = 5 * sqrt(s_u^2 + s_l^2) (lines near vertical): 0.71 px for 0.1 px, 1.41 px for 0.2 px.
    assert len(tri.triangulate(stereo(uv_u, shifted, 0.1, 0.1), calibration)) == 0
    assert len(tri.triangulate(stereo(uv_u, shifted, 0.2, 0.2), calibration)) == 1


def test_empty_and_one_sided_inputs(calibration):
    uv_u, _ = observe(calibration, np.array([[0.0, 20.0, 400.0]]))
    tri = triangulator()
    none = tri.triangulate(stereo(np.zeros((0, 2)), np.zeros((0, 2))), calibration)
    assert len(none) == 0 and none.xyz.shape == (0, 3) and none.rejected == ()
    one_sided = tri.triangulate(stereo(uv_u, np.zeros((0, 2))), calibration)
    assert one_sided.rejected == ("upper[0]: no match (no lower centroids)",)


# ---------------------------------------------------------------------------------------------------
# Calibration handling and options
# ---------------------------------------------------------------------------------------------------


def test_per_calibration_cache_follows_the_calibration_object():
    rng = np.random.default_rng(9)
    first = make_calibration()
    second = make_calibration(rvec=(-4e-3, 2e-3, 0.0), t=(-0.5, -48.0, 0.4))
    tri = triangulator()
    for calibration in (first, second, first):
        X = random_points(rng, calibration, 10)
        points = tri.triangulate(stereo(*observe(calibration, X)), calibration)
        assert len(points) == 10 and np.max(np.abs(points.xyz - X)) < 1e-6
    geometry = tri._cached_geometry
    tri.triangulate(stereo(*observe(first, X)), first)
    assert tri._cached_geometry is geometry  # same object: precomputation reused


def test_tilted_sensor_model_is_refused():
    tilted = make_calibration(dist_upper=(-0.05, 0.02, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1e-3, 0))
    with pytest.raises(ConfigError, match="tilted-sensor"):
        triangulator().triangulate(stereo(np.zeros((0, 2)), np.zeros((0, 2))), tilted)


@pytest.mark.parametrize(
    "options, key",
    [
        ({"z_min_mm": 500, "z_max_mm": 400}, "z_max_mm"),
        ({"epipolar_k": 0}, "epipolar_k"),
        ({"max_epipolar_px": -1}, "max_epipolar_px"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"refine": "yes"}, "refine"),
        ({"threshold": 1.0}, "threshold"),
    ],
)
def test_bad_options_name_the_key(options, key):
    with pytest.raises(ConfigError, match=key):
        triangulator(**options)
