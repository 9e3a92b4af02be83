"""Camera -> global point covariance: the one kernel.

A camera point ``p_c`` (upper camera frame, mm) with independent per-axis
standard uncertainties ``sigma_c`` (mm) is carried into the global frame by
a registration ``p_g = A @ p_c + t`` with ``A = scale * R`` (paper Formulas
(5)-(9)). First-order propagation (GUM 5.1.2, JCGM 100 eq. (10) in matrix
form) gives

    Sigma_g = A diag(sigma_c^2) A^T                                  (camera)
            + J C_reg J^T,   J = [-[p_g - g_bar]_x, I_3]            (registration)

where ``C_reg`` is the (6, 6) covariance of the registration's small
rotation and translation (dtheta in rad, dt in mm) about the control
centroid ``g_bar`` (global mm), and ``[y]_x`` the cross-product matrix.
The registration term is correlated between points of one stereo pair
(they share ``C_reg``); callers that combine points keep ``J`` to form the
cross-covariances ``J_a C_reg J_b^T``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["camera_covariance", "global_point_covariance", "global_sigma", "registration_jacobian", "skew"]


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrices ``[v]_x`` (..., 3, 3) of vectors v (..., 3): ``[v]_x @ w == v x w``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def camera_covariance(A: np.ndarray, sigma_xyz: np.ndarray) -> np.ndarray:
    """``A diag(sigma^2) A^T``: the camera term of a global point's covariance (mm^2).

    A: (3, 3) linear part of the registration (``scale * R``, global <- camera).
    sigma_xyz: (3,) or (N, 3) per-axis standard uncertainties in the camera
    frame (mm). Returns (3, 3) or (N, 3, 3).
    """
    A = np.asarray(A, dtype=np.float64)
    s2 = np.asarray(sigma_xyz, dtype=np.float64) ** 2
    return (A * s2[..., None, :]) @ A.T


def registration_jacobian(p_global: np.ndarray, g_bar: np.ndarray) -> np.ndarray:
    """``J = [-[p_g - g_bar]_x, I_3]`` (..., 3, 6) for global points (..., 3) mm: how
    a point moves with the registration's (dtheta (rad), dt (mm)) about the control
    centroid ``g_bar`` (mm)."""
    y = np.asarray(p_global, dtype=np.float64) - np.asarray(g_bar, dtype=np.float64)
    J = np.zeros(y.shape + (6,))
    J[..., :3] = -skew(y)
    J[..., 3:] = np.eye(3)
    return J


def global_point_covariance(
    A: np.ndarray,
    sigma_xyz: np.ndarray,
    J: np.ndarray | None = None,
    C_reg: np.ndarray | None = None,
) -> np.ndarray:
    """The (3, 3) (or (N, 3, 3)) covariance (mm^2) of camera points carried into the
    global frame: the camera term, plus ``J C_reg J^T`` when the registration's
    (6, 6) covariance ``C_reg`` and the points' (3, 6) / (N, 3, 6) Jacobians ``J``
    (:func:`registration_jacobian`) are given."""
    cov = camera_covariance(A, sigma_xyz)
    if C_reg is not None and J is not None:
        J = np.asarray(J, dtype=np.float64)
        cov = cov + J @ np.asarray(C_reg, dtype=np.float64) @ np.swapaxes(J, -1, -2)
    return cov


def global_sigma(A: np.ndarray, sigma_xyz: np.ndarray) -> np.ndarray:
    """Per-axis standard uncertainties (N, 3) in the global frame (mm): the square
    roots of the diagonal of :func:`camera_covariance` (registration not included)."""
    cov = camera_covariance(A, np.asarray(sigma_xyz, dtype=np.float64).reshape(-1, 3))
    return np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)).reshape(-1, 3)
