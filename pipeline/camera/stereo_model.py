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
* :func:`linear_triangulation`: the linear method (Hartley & Zisserman 12.2,
  inhomogeneous form) in normalised coordinates;
* :func:`refine_points`: Gauss-Newton on the weighted reprojection error in both
  distorted images, the maximum-likelihood point for Gaussian centroid errors
  (H&Z 12.3, with OpenCV's lens model).

Units and frames: pixels in the images (OpenCV convention), mm in the upper
camera frame; a camera's pose is ``p_cam = R @ p_upper + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossfield.errors import ConfigError
from crossfield.types import StereoCalibration

__all__ = [
    "STEP_TOLERANCE_MM",
    "UNDISTORT_CRITERIA",
    "CameraModel",
    "StereoGeometry",
    "camera_model",
    "linear_triangulation",
    "project_pair",
    "refine_points",
    "stereo_geometry",
    "undistort",
]

#: Termination of cv2.undistortPoints' fixed-point iteration (its default is only 5 iterations).
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-14)
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


@dataclass(frozen=True)
class StereoGeometry:
    """A stereo rig precomputed for projection and triangulation (upper camera frame, mm).

    upper, lower: the two cameras (the upper one at the origin, R = I, t = 0);
    F: (3, 3) fundamental matrix on undistorted pixels, ``q_lower^T F q_upper = 0``
    (H&Z 9.6); baseline_mm: |t_lower_upper|; R (2, 3, 3), t (2, 1, 3) mm, K (2, 3, 3) px,
    coeffs (12, 2, 1): both cameras stacked (0 = upper, 1 = lower) for one vectorised
    projection; rational / prism: whether any k4 k5 k6 / s1..s4 is non-zero.
    """

    upper: CameraModel
    lower: CameraModel
    F: np.ndarray  # (3, 3) fundamental matrix on undistorted pixels, q_lower^T F q_upper = 0
    baseline_mm: float  # |t|, used to scale the DLT (H&Z 4.4 normalisation)
    # Both cameras stacked (index 0 = upper, 1 = lower) for one vectorised projection:
    R: np.ndarray  # (2, 3, 3)
    t: np.ndarray  # (2, 1, 3) mm
    K: np.ndarray  # (2, 3, 3) px
    coeffs: np.ndarray  # (12, 2, 1) k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 per camera
    rational: bool  # any of k4 k5 k6 non-zero (else those terms are skipped)
    prism: bool  # any of s1..s4 non-zero


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
        t=np.stack([upper.t, lower.t])[:, None, :],
        K=np.stack([upper.K, lower.K]),
        coeffs=np.array([upper.coeffs, lower.coeffs]).T[:, :, None],
        rational=any(c != 0.0 for cam in (upper, lower) for c in cam.coeffs[5:8]),
        prism=any(c != 0.0 for cam in (upper, lower) for c in cam.coeffs[8:12]),
    )


# --------------------------------------------------------------------------------------------------
# Projection with OpenCV's lens model, and its Jacobian
# --------------------------------------------------------------------------------------------------


def project_pair(geometry: StereoGeometry, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project upper-frame points into both cameras with lens distortion.

    X: (N, 3) mm, upper camera frame. Returns uv (N, 4) pixels
    ``[u_upper, v_upper, u_lower, v_lower]`` (as ``cv2.projectPoints`` gives
    them) and J (N, 4, 3) = d(uv)/dX in px/mm. Lens model: OpenCV's rational
    + thin-prism distortion (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4); both
    cameras are computed at once (leading axis 2) to keep the per-frame cost low.
    """
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = geometry.coeffs  # each (2, 1)
    n = len(X)
    Xc = np.matmul(X, np.swapaxes(geometry.R, 1, 2)) + geometry.t  # (2, N, 3)
    inv_z = 1.0 / Xc[:, :, 2]
    x = Xc[:, :, 0] * inv_z
    y = Xc[:, :, 1] * inv_z
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_num = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    if geometry.rational:
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = num / den
        d_radial = (d_num * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / (den * den)  # d/d(r2)
    else:
        radial, d_radial = num, d_num
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    if geometry.prism:
        xd = xd + s1 * r2 + s2 * r2 * r2
        yd = yd + s3 * r2 + s4 * r2 * r2
    K = geometry.K
    fx, skew, cx = K[:, 0, 0:1], K[:, 0, 1:2], K[:, 0, 2:3]
    fy, cy = K[:, 1, 1:2], K[:, 1, 2:3]
    uv = np.empty((n, 2, 2))  # (N, camera, axis)
    uv[:, :, 0] = (fx * xd + skew * yd + cx).T
    uv[:, :, 1] = (fy * yd + cy).T
    # d(xd, yd)/d(x, y)
    a = 2.0 * d_radial
    cross = a * xy + 2.0 * p1 * x + 2.0 * p2 * y
    dxd_dx = radial + a * xx + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = cross
    dyd_dx = cross
    dyd_dy = radial + a * yy + 6.0 * p1 * y + 2.0 * p2 * x
    if geometry.prism:
        prism_x = 2.0 * (s1 + 2.0 * s2 * r2)
        prism_y = 2.0 * (s3 + 2.0 * s4 * r2)
        dxd_dx = dxd_dx + prism_x * x
        dxd_dy = dxd_dy + prism_x * y
        dyd_dx = dyd_dx + prism_y * x
        dyd_dy = dyd_dy + prism_y * y
    # d(u, v)/d(x, y) = K[:2, :2] @ d(xd, yd)/d(x, y), then d(x, y)/d(Xc) = [[1, 0, -x], [0, 1, -y]] / z
    du_dx = (fx * dxd_dx + skew * dyd_dx) * inv_z
    du_dy = (fx * dxd_dy + skew * dyd_dy) * inv_z
    dv_dx = fy * dyd_dx * inv_z
    dv_dy = fy * dyd_dy * inv_z
    J_c = np.empty((2, n, 2, 3))
    J_c[:, :, 0, 0] = du_dx
    J_c[:, :, 0, 1] = du_dy
    J_c[:, :, 0, 2] = -(du_dx * x + du_dy * y)
    J_c[:, :, 1, 0] = dv_dx
    J_c[:, :, 1, 1] = dv_dy
    J_c[:, :, 1, 2] = -(dv_dx * x + dv_dy * y)
    J = np.matmul(J_c, geometry.R[:, None, :, :])  # d(Xc)/dX = R, (2, N, 2, 3)
    return uv.reshape(n, 4), np.swapaxes(J, 0, 1).reshape(n, 4, 3)


def undistort(uv: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Distorted pixels (N, 2) of ``camera`` -> normalised undistorted image coordinates (N, 2)
    (``cv2.undistortPoints`` with :data:`UNDISTORT_CRITERIA`)."""
    if len(uv) == 0:
        return np.zeros((0, 2))
    points = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.undistortPoints(points, camera.K, camera.dist, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)


def linear_triangulation(xn_upper: np.ndarray, xn_lower: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """Linear triangulation (Hartley & Zisserman 12.2, inhomogeneous form).

    xn_upper, xn_lower: (N, 2) normalised undistorted coordinates of paired
    points. With camera matrices ``[I | 0]`` and ``[R | t/|t|]`` (translation
    scaled to unit length, H&Z 4.4) each pair gives four equations
    ``x P^3 - P^1 = 0``, ``y P^3 - P^2 = 0``; with ``X = (X, Y, Z, 1)`` they
    are solved in the least-squares sense. Returns (N, 3) mm, upper frame
    (non-finite or huge for rays that do not converge, i.e. points at infinity).
    """
    n = len(xn_upper)
    P2 = np.hstack([geometry.lower.R, geometry.lower.t[:, None] / geometry.baseline_mm])
    A = np.zeros((n, 4, 4))
    A[:, 0, 0] = -1.0
    A[:, 0, 2] = xn_upper[:, 0]
    A[:, 1, 1] = -1.0
    A[:, 1, 2] = xn_upper[:, 1]
    A[:, 2, :] = xn_lower[:, 0:1] * P2[2] - P2[0]
    A[:, 3, :] = xn_lower[:, 1:2] * P2[2] - P2[1]
    M = A[:, :, :3]
    MtM = np.matmul(np.swapaxes(M, 1, 2), M)
    rhs = -np.matmul(np.swapaxes(M, 1, 2), A[:, :, 3:4])
    try:
        X = np.linalg.solve(MtM, rhs)[:, :, 0]
    except np.linalg.LinAlgError:  # an exactly degenerate pair (parallel rays)
        X = np.matmul(np.linalg.pinv(MtM), rhs)[:, :, 0]
    return X * geometry.baseline_mm


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
    ``refine=False``: X unchanged, its residuals and Jacobian.
    """
    uv, J = project_pair(geometry, X)
    residual = uv - uv_obs
    if not refine or len(X) == 0:
        return X, residual, J, None
    for _ in range(max_iterations):
        JtW = np.swapaxes(J, 1, 2) * weights[:, None, :]  # (K, 3, 4)
        normal = np.matmul(JtW, J)
        gradient = np.matmul(JtW, residual[:, :, None])
        try:
            step = -np.linalg.solve(normal, gradient)[:, :, 0]
        except np.linalg.LinAlgError:
            step = -np.matmul(np.linalg.pinv(normal), gradient)[:, :, 0]
        X = X + step
        if np.max(np.abs(step)) < STEP_TOLERANCE_MM:
            # Converged: the last step is below 1e-10 mm, so the linearised residual is exact to
            # ~1e-15 px and J (hence J^T W J) is unchanged to that order; skip one more projection.
            residual = residual + np.matmul(J, step[:, :, None])[:, :, 0]
            return X, residual, J, normal
        uv, J = project_pair(geometry, X)
        residual = uv - uv_obs
    return X, residual, J, None
