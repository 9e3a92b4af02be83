"""The stereo camera model: OpenCV's lens model with its analytic Jacobian, and triangulation.

One kernel for every stereo projection and triangulation in crossfield: the
``epipolar`` triangulation plugin, the Cramér-Rao bound and the Monte Carlo
routes of :mod:`crossfield.precision.stereo` use these functions, so the bound
describes the estimator the pipeline runs.

* :func:`stereo_geometry` precomputes a :class:`StereoGeometry` from a
  ``StereoCalibration`` (both cameras, the fundamental matrix, H&Z 9.6);
* :func:`project_pair` projects upper-frame points into both cameras with
  distortion (rational + thin-prism model) and gives d(uv)/dX;
* :func:`undistort` maps distorted pixels to normalised image coordinates;
* :func:`epipolar_candidates`: each lower point's distance to each upper point's
  epipolar line, its limit from both centroids' sigmas (H&Z 9.2, 4.2.6), and the pairs
  within it triangulated and checked against the working range;
* :func:`unique_matches`: the candidate pairs whose two centroids have no other
  candidate, and :func:`paired_observations`: their points, observations and weights;
* :func:`linear_triangulation`: the linear method (Hartley & Zisserman 12.2,
  inhomogeneous form) in normalised coordinates;
* :func:`refine_points`: Gauss-Newton on the weighted reprojection error in both
  distorted images, the maximum-likelihood point for Gaussian centroid errors
  (H&Z 12.3, with OpenCV's lens model);
* :func:`point_covariance`: first-order covariance of the refined points (H&Z 5.2.2),
  plus that of offsets taken off the observations.

The arithmetic is compiled (numba, :mod:`crossfield.camera.stereo_kernels`): ~20
targets per frame are too few for NumPy's per-call overhead.

Units and frames: pixels in the images (OpenCV convention), mm in the upper
camera frame; a camera's pose is ``p_cam = R @ p_upper + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossfield.camera import stereo_kernels
from crossfield.errors import ConfigError
from crossfield.types import StereoCalibration

__all__ = [
    "STEP_TOLERANCE_MM",
    "UNDISTORT_CRITERIA",
    "UNDISTORT_TOLERANCE",
    "CameraModel",
    "StereoGeometry",
    "camera_model",
    "centroid_sigmas",
    "epipolar_candidates",
    "linear_triangulation",
    "paired_observations",
    "point_covariance",
    "project_pair",
    "refine_points",
    "stereo_geometry",
    "undistort",
    "unique_matches",
]

#: Termination of cv2.undistortPoints' fixed-point iteration (its default is only 5 iterations).
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-14)
#: Newton's undistortion stops when its step is below this (normalised image coordinates).
UNDISTORT_TOLERANCE = 1e-15
#: Gauss-Newton stops when no point moves by more than this (mm).
STEP_TOLERANCE_MM = 1e-10


# --------------------------------------------------------------------------------------------------
# Per-calibration precomputation
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraModel:
    """One camera as seen from the upper frame: ``p_cam = R @ p_upper + t`` (mm).

    K: (3, 3) camera matrix (px); dist: (k,) OpenCV distortion coefficients as
    calibrated (for cv2 calls); coeffs: the 12 coefficients k1 k2 p1 p2 k3 k4 k5 k6
    s1 s2 s3 s4, zero-padded; R: (3, 3); t: (3,) mm.
    """

    K: np.ndarray  # (3, 3) pixels
    dist: np.ndarray  # (k,) OpenCV order, as calibrated (for cv2 calls)
    coeffs: tuple[float, ...]  # k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4, zero-padded
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) mm
    coeff_array: np.ndarray  # (12,) the coefficients as an array (for the compiled kernels)


@dataclass(frozen=True)
class StereoGeometry:
    """A stereo rig precomputed for projection and triangulation (upper camera frame, mm).

    upper, lower: the two cameras (the upper one at the origin, R = I, t = 0);
    F: (3, 3) fundamental matrix on undistorted pixels, ``q_lower^T F q_upper = 0``
    (H&Z 9.6); baseline_mm: |t_lower_upper|; R (2, 3, 3), t (2, 3) mm, K (2, 3, 3) px,
    coeffs (2, 12): both cameras stacked (0 = upper, 1 = lower) for the compiled kernels
    (:mod:`crossfield.camera.stereo_kernels`).
    """

    upper: CameraModel
    lower: CameraModel
    F: np.ndarray  # (3, 3) fundamental matrix on undistorted pixels, q_lower^T F q_upper = 0
    baseline_mm: float  # |t|, used to scale the DLT (H&Z 4.4 normalisation)
    # Both cameras stacked (index 0 = upper, 1 = lower) for the compiled kernels:
    R: np.ndarray  # (2, 3, 3)
    t: np.ndarray  # (2, 3) mm
    K: np.ndarray  # (2, 3, 3) px
    coeffs: np.ndarray  # (2, 12) k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 per camera


def camera_model(intrinsics, R: np.ndarray, t: np.ndarray, source: str, name: str) -> CameraModel:
    """The :class:`CameraModel` of one camera's intrinsics (``CameraIntrinsics``) at pose R (3, 3), t (3,) mm.

    A tilted-sensor model (tauX, tauY non-zero) is a ConfigError naming ``source`` and ``name``.
    """
    dist = np.asarray(intrinsics.dist_coeffs, dtype=np.float64).ravel()
    padded = np.zeros(14)
    padded[: dist.size] = dist
    if np.any(padded[12:14] != 0.0):
        raise ConfigError(
            f"{source or 'calibration'}: the {name} camera uses OpenCV's tilted-sensor model "
            f"(tauX, tauY), which the stereo model does not support"
        )
    return CameraModel(
        K=np.asarray(intrinsics.camera_matrix, dtype=np.float64),
        dist=dist,
        coeffs=tuple(float(c) for c in padded[:12]),
        R=np.asarray(R, dtype=np.float64),
        t=np.asarray(t, dtype=np.float64),
        coeff_array=padded[:12].copy(),
    )


def stereo_geometry(calibration: StereoCalibration) -> StereoGeometry:
    """Precompute the rig of ``calibration`` (a zero baseline is a ConfigError naming its source)."""
    R = np.asarray(calibration.R_lower_upper, dtype=np.float64)
    t = np.asarray(calibration.t_lower_upper, dtype=np.float64)
    baseline = float(np.linalg.norm(t))
    if not baseline > 0:
        raise ConfigError(f"{calibration.source or 'calibration'}: zero stereo baseline (t_lower_upper = 0)")
    upper = camera_model(calibration.upper, np.eye(3), np.zeros(3), calibration.source, "upper")
    lower = camera_model(calibration.lower, R, t, calibration.source, "lower")
    # Essential matrix E = [t]x R, fundamental F = K'^-T E K^-1 (H&Z 9.6). E is scaled by 1/|t|.
    t_cross = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = t_cross @ R / baseline
    F = np.linalg.inv(lower.K).T @ E @ np.linalg.inv(upper.K)
    return StereoGeometry(
        upper, lower, F, baseline,
        R=np.stack([upper.R, lower.R]),
        t=np.stack([upper.t, lower.t]),
        K=np.ascontiguousarray(np.stack([upper.K, lower.K])),
        coeffs=np.array([upper.coeffs, lower.coeffs]),
    )


# --------------------------------------------------------------------------------------------------
# Projection with OpenCV's lens model, and its Jacobian
# --------------------------------------------------------------------------------------------------


def project_pair(geometry: StereoGeometry, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project upper-frame points into both cameras with lens distortion.

    X: (N, 3) mm, upper camera frame. Returns uv (N, 4) pixels
    ``[u_upper, v_upper, u_lower, v_lower]`` (as ``cv2.projectPoints`` gives
    them) and J (N, 4, 3) = d(uv)/dX in px/mm. Lens model: OpenCV's rational
    + thin-prism distortion (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4), compiled
    (:func:`crossfield.camera.stereo_kernels.project_into`).
    """
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3)
    uv, J = np.empty((len(X), 4)), np.empty((len(X), 4, 3))
    stereo_kernels.project_into(X, geometry.R, geometry.t, geometry.K, geometry.coeffs, uv, J)
    return uv, J


def undistort(uv: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Distorted pixels (N, 2) of ``camera`` -> normalised undistorted image coordinates (N, 2).

    The inverse of OpenCV's lens model by Newton's method (compiled:
    :func:`crossfield.camera.stereo_kernels.undistort_points`, to a step below
    :data:`UNDISTORT_TOLERANCE`); the same points as ``cv2.undistortPoints`` with
    :data:`UNDISTORT_CRITERIA` (to ~1e-15, tests/triangulate/test_stereo_kernels.py) at a
    fraction of its cost. ``cv2.undistortPoints`` itself where Newton does not converge
    and for a camera matrix with skew (which OpenCV's undistortion ignores).
    """
    if len(uv) == 0:
        return np.zeros((0, 2))
    points = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 2)
    K = camera.K
    if K[0, 1] == 0.0:
        xn, converged = stereo_kernels.undistort_points(
            points, K[0, 0], K[1, 1], K[0, 2], K[1, 2], camera.coeff_array, 20, UNDISTORT_TOLERANCE
        )
        if converged:
            return xn
    return cv2.undistortPoints(points.reshape(-1, 1, 2), K, camera.dist, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)


def epipolar_candidates(
    xn_upper: np.ndarray,
    xn_lower: np.ndarray,
    sigma_upper: np.ndarray,
    sigma_lower: np.ndarray,
    geometry: StereoGeometry,
    *,
    max_epipolar_px: float,
    epipolar_k: float,
    calibration_px: float,
    z_min_mm: float,
    z_max_mm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The candidate pairs of epipolar matching: each pair's distance to the epipolar line, its
    limit, its linear triangulation and whether it triangulates into the working range.

    xn_upper (N, 2), xn_lower (M, 2): normalised undistorted coordinates; sigma_upper (N, 2),
    sigma_lower (M, 2): the centroids' standard uncertainties (px). On undistorted pixels
    ``q = K [x, y, 1]`` the lines are ``l = F q_upper`` (H&Z 9.2) and the distance of
    lower point j to line i is ``|q_lower[j]^T l_i| / |l_i[:2]|``, with variance
    ``sigma_line^2 = (grad_u^T S_u grad_u + grad_l^T S_l grad_l) / |l_i[:2]|^2`` to first order (as in
    the Sampson error, H&Z 4.2.6, 11.4.3). The limit is ``max_epipolar_px`` when > 0, else
    ``epipolar_k * sqrt(sigma_line^2 + calibration_px^2)``. A pair within its limit is
    triangulated (:func:`linear_triangulation`, the same arithmetic) and is a candidate when
    ``z_min_mm <= z_upper <= z_max_mm`` and it lies in front of the lower camera.

    Returns distance (N, M) px, limit (N, M) px, X (N, M, 3) mm (upper frame; nan off the line)
    and candidate (N, M) bool. |F q| > 0 for any finite image point of a rig with a baseline.
    """
    return stereo_kernels.epipolar_candidates(
        np.ascontiguousarray(xn_upper, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(xn_lower, dtype=np.float64).reshape(-1, 2),
        geometry.upper.K, geometry.lower.K, geometry.F,
        np.ascontiguousarray(sigma_upper, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(sigma_lower, dtype=np.float64).reshape(-1, 2),
        geometry.lower.R, geometry.lower.t, geometry.baseline_mm,
        float(max_epipolar_px), float(epipolar_k), float(calibration_px), float(z_min_mm), float(z_max_mm),
    )


def centroid_sigmas(sigma_uv: np.ndarray, default_px: float) -> np.ndarray:
    """(N, 2) px: the centroids' ``sigma_uv``, ``default_px`` where one is not a positive finite number.

    The array itself when every sigma is valid (the common case: one compiled pass, no copy).
    """
    sigma = np.asarray(sigma_uv, dtype=np.float64)
    if stereo_kernels.all_positive_finite(sigma):
        return sigma
    valid = (sigma > 0) & (sigma < np.inf)  # False for nan
    return np.where(valid, sigma, default_px)


def unique_matches(candidate: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The one-to-one matches of epipolar matching (docs/triangulation.md, step 2).

    candidate: (N, M) bool, :func:`epipolar_candidates`' table. Returns each upper centroid's
    count of candidates (N,), each lower centroid's (M,), and the accepted pairs, those whose
    two centroids each have exactly one candidate, as index arrays upper (K,), lower (K,)
    int64, sorted by the upper index (compiled: :func:`crossfield.camera.stereo_kernels.unique_matches`).
    """
    return stereo_kernels.unique_matches(np.ascontiguousarray(candidate, dtype=np.bool_))


def paired_observations(
    upper_index: np.ndarray,
    lower_index: np.ndarray,
    uv_upper: np.ndarray,
    uv_lower: np.ndarray,
    sigma_upper: np.ndarray,
    sigma_lower: np.ndarray,
    X_pairs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The matched pairs' inputs to :func:`refine_points`.

    upper_index, lower_index (K,): the pairs (:func:`unique_matches`); uv_upper (N, 2), uv_lower
    (M, 2) px: the centroids (distorted pixels); sigma_upper (N, 2), sigma_lower (M, 2) px;
    X_pairs (N, M, 3) mm: :func:`epipolar_candidates`' linear points. Returns the pairs' linear
    points (K, 3) mm, observations ``[u_upper, v_upper, u_lower, v_lower]`` (K, 4) px and weights
    ``1 / sigma^2`` (K, 4) px^-2 (compiled: :func:`crossfield.camera.stereo_kernels.paired_observations`).
    """
    return stereo_kernels.paired_observations(
        np.ascontiguousarray(upper_index, dtype=np.int64),
        np.ascontiguousarray(lower_index, dtype=np.int64),
        np.ascontiguousarray(uv_upper, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(uv_lower, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(sigma_upper, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(sigma_lower, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(X_pairs, dtype=np.float64),
    )


def linear_triangulation(xn_upper: np.ndarray, xn_lower: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """Linear triangulation (Hartley & Zisserman 12.2, inhomogeneous form).

    xn_upper, xn_lower: (N, 2) normalised undistorted coordinates of paired
    points. With camera matrices ``[I | 0]`` and ``[R | t/|t|]`` (translation
    scaled to unit length, H&Z 4.4) each pair gives four equations
    ``x P^3 - P^1 = 0``, ``y P^3 - P^2 = 0``; with ``X = (X, Y, Z, 1)`` they
    are solved in the least-squares sense (normal equations, compiled:
    :func:`crossfield.camera.stereo_kernels.linear_points`). Returns (N, 3) mm, upper frame
    (non-finite or huge for rays that do not converge, i.e. points at infinity).
    """
    t_unit = geometry.lower.t / geometry.baseline_mm
    return stereo_kernels.linear_points(
        np.ascontiguousarray(xn_upper, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(xn_lower, dtype=np.float64).reshape(-1, 2),
        geometry.lower.R, t_unit, geometry.baseline_mm,
    )


def refine_points(
    X: np.ndarray,
    uv_obs: np.ndarray,
    weights: np.ndarray,
    geometry: StereoGeometry,
    *,
    max_iterations: int = 10,
    refine: bool = True,
):
    """Gauss-Newton on sum(w * r^2) over both images (H&Z 12.3's cost; H&Z A6.1 iteration).

    X: (K, 3) mm initial points (upper frame); uv_obs: (K, 4) px observed
    ``[u_upper, v_upper, u_lower, v_lower]`` (distorted pixels); weights: (K, 4) px^-2.
    Returns the refined X (K, 3) mm, the residuals (K, 4) px and the Jacobian (K, 4, 3) px/mm
    at X, and the normal matrix J^T W J (K, 3, 3) at X when the iteration converged (else None).
    ``refine=False``: X unchanged, its residuals and Jacobian. Compiled
    (:func:`crossfield.camera.stereo_kernels.refine`): converged when no point moves by more than
    :data:`STEP_TOLERANCE_MM`; the residual is then linearised over the last step (exact to
    ~1e-15 px) and J and J^T W J are those of the last projection, one projection saved.
    """
    X, residual, J, normal, converged = stereo_kernels.refine(
        np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3),
        np.ascontiguousarray(uv_obs, dtype=np.float64).reshape(-1, 4),
        np.ascontiguousarray(weights, dtype=np.float64).reshape(-1, 4),
        geometry.R, geometry.t, geometry.K, geometry.coeffs, max_iterations, STEP_TOLERANCE_MM, refine,
    )
    return X, residual, J, (normal if converged else None)


def point_covariance(
    information: np.ndarray, J: np.ndarray, weights: np.ndarray, offset_cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """First-order covariance of ML-triangulated points: ``cov(X) = (J^T W J)^-1`` (H&Z 5.2.2).

    information: (K, 3, 3) J^T W J (px^-2 px^2/mm^2 = mm^-2); J: (K, 4, 3) px/mm; weights:
    (K, 4) px^-2. ``offset_cov`` (K, 4, 4) px^2: the covariance of offsets taken off the
    observations [u_upper, v_upper, u_lower, v_lower], added as ``G C G^T`` with
    ``G = (J^T W J)^-1 J^T W`` (3 x 4). Returns cov (K, 3, 3) mm^2 and sigma (K, 3) mm,
    the square roots of its diagonal.
    """
    information = np.ascontiguousarray(information, dtype=np.float64).reshape(-1, 3, 3)
    with_offsets = offset_cov is not None
    offsets = np.ascontiguousarray(offset_cov, dtype=np.float64) if with_offsets else np.zeros((0, 4, 4))
    return stereo_kernels.point_covariances(
        information,
        np.ascontiguousarray(J, dtype=np.float64).reshape(-1, 4, 3),
        np.ascontiguousarray(weights, dtype=np.float64).reshape(-1, 4),
        offsets, with_offsets,
    )
