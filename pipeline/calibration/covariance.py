"""Covariance of a stereo calibration, and the 3-D uncertainty it predicts.

The stereo solution minimises the reprojection error over both cameras and
every view (Zhang 2000, eq. 10, for two cameras tied by R, T; OpenCV's
``stereoCalibrate``). Its parameters, in this order:

* upper camera: fx fy cx cy (px), distortion (OpenCV order, 5 or 8 terms);
* lower camera: the same;
* the rig: rotation vector r (rad, ``R = Rodrigues(r)``), T (mm);
* per view: the board pose in the upper camera, rotation vector and t (mm).

With J the Jacobian of the residuals (``cv2.projectPoints`` gives the
derivatives of one camera, ``cv2.composeRT`` the chain rule through
``R_lower = R R_i``, ``t_lower = R t_i + T``), the covariance is
``sigma^2 (J^T J)^-1`` with ``sigma^2 = SSR / (m - p)`` (Hartley & Zisserman
5.2.3; the Gauss-Newton covariance of a least-squares estimate). The block
of the camera and rig parameters is their covariance with the board poses
marginalised, what mrcal's ``projection_uncertainty`` propagates.

The predicted 3-D uncertainty of a point X (upper frame, mm) is that of its
triangulation from fixed pixels when the parameters err: by the implicit
function theorem on ``min_X |u - pi(X; theta)|^2``,
``dX/dtheta = -(J_X^T J_X)^-1 J_X^T J_theta`` and
``Sigma_X = G Sigma_theta G^T``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

INTRINSIC_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy")
DIST_NAMES: tuple[str, ...] = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def camera_param_names(n_dist: int) -> tuple[str, ...]:
    """Names of the camera and rig parameters, in covariance order (see the module docstring)."""
    names = []
    for cam in ("upper", "lower"):
        names += [f"{cam}.{n}" for n in INTRINSIC_NAMES + DIST_NAMES[:n_dist]]
    names += ["rig.rx", "rig.ry", "rig.rz", "rig.Tx", "rig.Ty", "rig.Tz"]
    return tuple(names)


def project_with_jacobians(
    object_points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, D: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project (N, 3) points (mm) with pose (rvec, tvec) and intrinsics (K px, D).

    Returns uv (N, 2) px, J_pose (2N, 6) = d(uv)/d(rvec, tvec) and J_cam
    (2N, 4 + len(D)) = d(uv)/d(fx, fy, cx, cy, D); rows interleave u, v.
    """
    uv, J = cv2.projectPoints(
        np.ascontiguousarray(object_points, np.float64).reshape(-1, 1, 3),
        np.asarray(rvec, np.float64).reshape(3, 1),
        np.asarray(tvec, np.float64).reshape(3, 1),
        np.asarray(K, np.float64),
        np.asarray(D, np.float64).ravel(),
    )
    return uv.reshape(-1, 2), J[:, :6], J[:, 6 : 10 + len(np.ravel(D))]


@dataclass(frozen=True)
class StereoObservations:
    """What the stereo solution was fitted to: per view the common points of both cameras.

    object_points[i] (N_i, 3) mm; upper[i], lower[i] (N_i, 2) px.
    """

    object_points: tuple[np.ndarray, ...]
    upper: tuple[np.ndarray, ...]
    lower: tuple[np.ndarray, ...]


def stereo_jacobian(
    obs: StereoObservations,
    K1: np.ndarray,
    D1: np.ndarray,
    K2: np.ndarray,
    D2: np.ndarray,
    rvec: np.ndarray,
    T: np.ndarray,
    rvecs: Sequence[np.ndarray],
    tvecs: Sequence[np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (m,) px (observed - projected) and Jacobian (m, p) of the stereo problem at a solution.

    Parameter order as in the module docstring; p = 2 (4 + n_dist) + 6 + 6 V.
    """
    n1, n2 = 4 + D1.size, 4 + D2.size
    n_cam = n1 + n2 + 6
    n_views = len(obs.object_points)
    rows_total = 2 * sum(2 * len(p) for p in obs.object_points)
    J = np.zeros((rows_total, n_cam + 6 * n_views))
    res = np.zeros(rows_total)
    row = 0
    for i, (X, u1, u2) in enumerate(zip(obs.object_points, obs.upper, obs.lower)):
        pose = slice(n_cam + 6 * i, n_cam + 6 * i + 6)
        m = 2 * len(X)
        uv, J_pose, J_cam = project_with_jacobians(X, rvecs[i], tvecs[i], K1, D1)
        res[row : row + m] = (u1 - uv).ravel()
        J[row : row + m, :n1] = J_cam
        J[row : row + m, pose] = J_pose
        row += m
        # Lower camera: (R_l, t_l) = (R R_i, R t_i + T), cv2.composeRT(r_i, t_i, r, T).
        r_l, t_l, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            np.asarray(rvecs[i], np.float64).reshape(3, 1),
            np.asarray(tvecs[i], np.float64).reshape(3, 1),
            np.asarray(rvec, np.float64).reshape(3, 1),
            np.asarray(T, np.float64).reshape(3, 1),
        )
        uv, J_pose, J_cam = project_with_jacobians(X, r_l, t_l, K2, D2)
        Jr, Jt = J_pose[:, :3], J_pose[:, 3:]
        res[row : row + m] = (u2 - uv).ravel()
        J[row : row + m, n1 : n1 + n2] = J_cam
        J[row : row + m, n1 + n2 : n1 + n2 + 3] = Jr @ dr3dr2 + Jt @ dt3dr2
        J[row : row + m, n1 + n2 + 3 : n_cam] = Jr @ dr3dt2 + Jt @ dt3dt2
        J[row : row + m, pose] = np.hstack([Jr @ dr3dr1 + Jt @ dt3dr1, Jr @ dr3dt1 + Jt @ dt3dt1])
        row += m
    return res, J


def covariance_from_jacobian(res: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, float]:
    """Gauss-Newton covariance sigma^2 (J^T J)^-1 and sigma (px), sigma^2 = SSR / (m - p)."""
    m, p = J.shape
    if m <= p:
        raise ValueError(f"{m} residuals cannot determine {p} parameters")
    sigma2 = float(res @ res) / (m - p)
    # Column scaling keeps J^T J well conditioned (focal lengths ~1e3 px next to k3 ~ 1).
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    # (J^T J)^-1 = V S^-2 V^T from the SVD J = U S V^T: positive semi-definite by construction even
    # where J^T J is ill-conditioned (the rational model's k4..k6 against k1..k3).
    _, sv, Vt = np.linalg.svd(J / scale, full_matrices=False)
    if sv[-1] <= sv[0] * 1e-14:
        raise ValueError("the parameters are not determined by the views (singular Jacobian)")
    cov = (Vt.T / sv**2) @ Vt / np.outer(scale, scale)
    return sigma2 * cov, float(np.sqrt(sigma2))


def triangulation_sensitivity(
    points_upper: np.ndarray,
    K1: np.ndarray,
    D1: np.ndarray,
    K2: np.ndarray,
    D2: np.ndarray,
    rvec: np.ndarray,
    T: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """For (N, 3) upper-frame points (mm): G (N, 3, p_cam) = dX/dtheta_cam and H (N, 3, 4) = dX/d(pixels).

    theta_cam is the camera + rig block (``camera_param_names``); pixels are
    (u_upper, v_upper, u_lower, v_lower). Implicit-function derivative of
    the least-squares triangulation (module docstring).
    """
    n1, n2 = 4 + D1.size, 4 + D2.size
    p = n1 + n2 + 6
    zero = np.zeros(3)
    G = np.zeros((len(points_upper), 3, p))
    H = np.zeros((len(points_upper), 3, 4))
    R = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    for k, X in enumerate(np.asarray(points_upper, np.float64)):
        J_theta = np.zeros((4, p))
        # Upper camera, pose identity: d(uv)/dX = d(uv)/dt.
        _, Jp1, Jc1 = project_with_jacobians(X[None], zero, zero, K1, D1)
        # Lower camera seeing X through (r, T): d(uv)/dX = d(uv)/dt @ R.
        _, Jp2, Jc2 = project_with_jacobians(X[None], rvec, T, K2, D2)
        J_X = np.vstack([Jp1[:, 3:], Jp2[:, 3:] @ R])
        J_theta[:2, :n1] = Jc1
        J_theta[2:, n1 : n1 + n2] = Jc2
        J_theta[2:, n1 + n2 :] = Jp2
        A = np.linalg.solve(J_X.T @ J_X, J_X.T)  # (3, 4) least-squares inverse
        G[k] = -A @ J_theta
        H[k] = A
    return G, H
