"""Precision of the rigid registration (camera frame -> global CMM frame).

Parametrisation (as ``plugins/measure_plan.py``): the estimated transform
differs from the true one by a small rotation ``dtheta`` (rad) about the
control centroid ``g_bar`` and a translation ``dt`` (mm), so a point p (global
frame) moves by ``dtheta x (p - g_bar) + dt = J(p) xi`` with
``J(p) = [-[p - g_bar]x, I]`` (3 x 6) and ``xi = (dtheta, dt)``.

Control k contributes the residual ``J(g_k) xi + e_k``, e_k with covariance
``S_k = R Sigma_cam,k R^T + Sigma_cmm,k`` (its camera point rotated into the
global frame plus its CMM point). Then:

* ML (Gauss-Markov) bound: ``cov(xi) >= (sum_k J_k^T S_k^-1 J_k)^-1`` (the
  Cramér-Rao bound of the registration; :func:`registration_crb`);
* least squares with scalar weights w_k (Kabsch / Arun, the paper's Formulas
  (5)-(9) with weights) about the weighted centroid: the sandwich
  ``(J^T W J)^-1 (J^T W S W J) (J^T W J)^-1`` (:func:`registration_covariance`);
* isotropic, identical fiducial errors (FLE^2 = E|e_k|^2) and equal weights:
  Fitzpatrick, West & Maurer (1998), ``cov(dt) = FLE^2 / (3N) I``,
  ``cov(dtheta) = FLE^2 / 3 (sum_k |y_k|^2 I - y_k y_k^T)^-1``, whose trace
  at a target r is their eq. (46)
  ``TRE^2(r) = FLE^2 / N (1 + 1/3 sum_j d_j^2 / f_j^2)``, d_j the distance of r
  from principal axis j of the fiducials and f_j the RMS distance of the
  fiducials from that axis (:func:`fitzpatrick_tre`, :func:`fitzpatrick_covariance`).

Lengths in mm, angles in rad; arrays (N, 3) unless stated.
"""

from __future__ import annotations

import numpy as np

from crossfield.covariance import registration_jacobian

#: d(point error)/d(xi) (..., 3, 6) of points (..., 3) mm: the one kernel of crossfield.covariance.
point_jacobian = registration_jacobian


def registration_crb(controls_global: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cramér-Rao (ML) covariance (6, 6) of xi and the centroid g_bar (3,) it refers to.

    controls_global: (N, 3) mm; S: (N, 3, 3) mm^2 total error covariance of each
    control (camera point rotated to global + CMM). g_bar is the plain centroid
    (the bound does not depend on the reference point; only its parametrisation does).
    """
    G = np.asarray(controls_global, dtype=np.float64)
    g_bar = G.mean(axis=0)
    J = point_jacobian(G, g_bar)  # (N, 3, 6)
    information = np.einsum("nai,nab,nbj->ij", J, np.linalg.inv(S), J)
    return np.linalg.inv(information), g_bar


def registration_covariance(
    controls_global: np.ndarray, S: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (6, 6) of xi for the scalar-weighted least-squares fit, and g_bar (3,).

    weights: (N,) (normalised here), None = equal. g_bar is the weighted
    centroid the fit turns about. Sandwich form (module docstring).
    """
    G = np.asarray(controls_global, dtype=np.float64)
    n = len(G)
    w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    g_bar = w @ G
    J = point_jacobian(G, g_bar)
    A = np.einsum("n,nai,naj->ij", w, J, J)
    B = np.einsum("n,nai,nab,nbj->ij", w * w, J, S, J)
    A_inv = np.linalg.inv(A)
    return A_inv @ B @ A_inv, g_bar


def fitzpatrick_covariance(fiducials: np.ndarray, fle_rms_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Fitzpatrick-West-Maurer covariance (6, 6) of xi = (dtheta, dt) for isotropic,
    identical fiducial errors with E|e|^2 = fle_rms_mm^2 (module docstring); and g_bar (3,)."""
    G = np.asarray(fiducials, dtype=np.float64)
    g_bar = G.mean(axis=0)
    y = G - g_bar
    s2 = fle_rms_mm**2 / 3.0  # per coordinate
    M = np.sum(y * y) * np.eye(3) - y.T @ y
    cov = np.zeros((6, 6))
    cov[:3, :3] = s2 * np.linalg.inv(M)
    cov[3:, 3:] = s2 / len(G) * np.eye(3)
    return cov, g_bar


def fitzpatrick_tre(fiducials: np.ndarray, fle_rms_mm: float, targets: np.ndarray) -> np.ndarray:
    """Expected RMS target registration error (M,) mm at targets (M, 3) mm:
    ``TRE^2 = FLE^2 / N (1 + 1/3 sum_j d_j^2 / f_j^2)`` (Fitzpatrick, West & Maurer 1998, eq. 46)."""
    G = np.asarray(fiducials, dtype=np.float64)
    r = np.atleast_2d(np.asarray(targets, dtype=np.float64))
    g_bar = G.mean(axis=0)
    y = G - g_bar
    _, axes = np.linalg.eigh(y.T @ y)  # principal axes (columns)
    yk = y @ axes  # fiducial coordinates along the principal axes
    rk = (r - g_bar) @ axes
    ratio = 0.0
    for j in range(3):
        others = [k for k in range(3) if k != j]
        f2 = np.mean(np.sum(yk[:, others] ** 2, axis=1))  # mean squared distance from axis j
        d2 = np.sum(rk[:, others] ** 2, axis=1)
        ratio = ratio + d2 / f2
    return np.sqrt(fle_rms_mm**2 / len(G) * (1.0 + ratio / 3.0))


def global_point_covariance(
    R_global_camera: np.ndarray,
    camera_cov: np.ndarray,
    points_global: np.ndarray,
    registration_cov: np.ndarray,
    g_bar: np.ndarray,
) -> np.ndarray:
    """Covariance (M, 3, 3) mm^2 of camera-measured points mapped to the global frame:
    ``R Sigma_cam R^T + J(p) C_xi J(p)^T`` (independent camera and registration errors)."""
    R = np.asarray(R_global_camera, dtype=np.float64)
    J = point_jacobian(points_global, g_bar)
    return R @ camera_cov @ R.T + J @ registration_cov @ np.swapaxes(J, -1, -2)
