"""Perspective eccentricity of circular targets: the 3-D circle from its two image conics.

One job: the centre of a tilted circle's image ellipse is not the image of
the circle's centre. Given the triangulated centre of each target and the
ellipse (edge conic) fitted to it in both views, this module estimates the
circle (unit normal and radius), returns the offset of each view's ellipse
centre from the projected circle centre (to be taken off the measured
centroids before triangulating), and the covariance of those offsets
(``docs/triangulation.md``, "Eccentricity").

The ellipse centre, exactly (pinhole): a circle with centre C, unit normal n
and radius r (view frame, mm) spans X = C + x e1 + y e2, x^2 + y^2 = r^2,
i.e. the plane conic diag(1, 1, -r^2) mapped by H = [e1 e2 C]. The image
conic is Q = H^-T diag(1, 1, -r^2) H^-1 (Hartley & Zisserman 2.2.3, result
2.13), and its centre is the pole of the line at infinity,
c ~ Q^-1 (0, 0, 1)^T = H diag(r^2, r^2, -1) H^T (0, 0, 1)^T, which gives

    c ~ C_z C - r^2 (z - n_z n),   i.e.   X_e = C - (r^2 / C_z) (z - n_z n)

(z the optical axis): the ellipse centre is the image of the 3-D point X_e,
not of C; the offset vanishes for a circle facing the camera (n = z) and
grows with r^2 / C_z and the tilt. Lens distortion is applied to X_e like
any point, and its curvature over the blob moves the blob's centroid by a
further ~0.003 px near the image corners (:func:`centre_offsets`).

The circle from two conics: per target, the normal n = rot(w) n0 (a
rotation by w, perpendicular to the line of sight n0 = -C / |C|) and
log r are found by Gauss-Newton on the two views' shape matrices, the
observed ones (pixels, mapped to normalised coordinates through the local
Jacobian M of the lens: S_n = M^T S_px M) against those of Q at its centre
(S = A / (c^T A c - s) for Q = [[A, q], [q^T, s]], c = -A^-1 q), each
whitened by the covariance of the fitted conic. A single view leaves a
two-fold ambiguity of the tilt (+-theta about the major axis); the fit
starts from both signs in both views and keeps the best. Its covariance
(J^T J)^-1 goes into the covariance of the offsets to first order.

Speed: the correction is compiled (numba, scalar 3 x 3 algebra per target, the GIL
released): the circle fit (:func:`fit_circles`: the observed shapes and their whitening
:func:`_observed_rows`, the starts and the Gauss-Newton loop over every start of every target
:func:`_fit_rows` / :func:`_gauss_newton`, the final Jacobian and normals), the centre offsets
(:func:`_centre_offsets_rows`, the lens through :func:`crossfield.camera.stereo_kernels.project_point`)
and their covariance (:func:`_offset_covariance_rows`). What NumPy computes with LAPACK (the
inverse and Cholesky factor of the conics' covariance, eigh of the observed shapes, pinv of
J^T J) and with its own SIMD arccos, log and exp stays in NumPy between the kernels. The
kernels do the NumPy formulation's floating-point operations in the same order (its small
matmuls as the fused multiply-add chains OpenBLAS computes them, :func:`crossfield.blas_order.fma`; its row sums
left to right), so the results are the NumPy path's bit for bit (:func:`_fit_circles_numpy`,
:func:`_offset_covariance_numpy`, kept for lenses that need ``cv2.projectPoints``, the
tilted-sensor model); tests/triangulate/test_eccentricity_kernels.py. Against the NumPy
*formulas* (:func:`predicted_shape`, :func:`ellipse_centre_point`, ``cv2.projectPoints``) the
points move by < 1e-9 mm and the offsets by < 1e-9 px; tests/centroid/test_eccentricity.py.

Units: mm in the camera frames, pixels in the images, normalised image
coordinates where stated; views are given as ``p_view = R @ p_upper + t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from crossfield.blas_order import fma
from crossfield.camera import stereo_kernels

__all__ = [
    "CircleFit",
    "View",
    "centre_offsets",
    "ellipse_centre_point",
    "fit_circles",
    "offset_covariance",
    "predicted_shape",
    "project",
    "stereo_views",
]


@dataclass(frozen=True)
class View:
    """One camera: intrinsics K (3, 3) px, OpenCV distortion, and pose
    ``p_view = R @ p_upper + t`` (R (3, 3), t (3,) mm)."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class CircleFit:
    """Circles of N targets (upper camera frame).

    normal: (N, 3) unit normals (towards the cameras); radius_mm: (N,);
    cov: (N, 3, 3) covariance of (w1, w2, log r) (rad, rad, 1); cost: (N,)
    whitened sum of squares (6 residuals, 3 parameters); params: (N, 3).
    """

    normal: np.ndarray
    radius_mm: np.ndarray
    cov: np.ndarray
    cost: np.ndarray
    params: np.ndarray


def stereo_views(calibration) -> tuple[View, View]:
    """The (upper, lower) :class:`View` of a ``StereoCalibration``: the upper camera at the
    origin, the lower at ``p_lower = R_lower_upper @ p_upper + t_lower_upper`` (mm)."""
    return tuple(
        View(np.asarray(c.camera_matrix, dtype=np.float64), np.asarray(c.dist_coeffs, dtype=np.float64).ravel(),
             np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))
        for c, R, t in ((calibration.upper, np.eye(3), np.zeros(3)),
                        (calibration.lower, calibration.R_lower_upper, calibration.t_lower_upper))
    )


def ellipse_centre_point(C: np.ndarray, n: np.ndarray, r: np.ndarray) -> np.ndarray:
    """X_e (N, 3) mm, view frame: the point whose image is the centre of the image
    ellipse of the circle (C (N, 3), unit normal n (N, 3), radius r (N,)) (module docstring)."""
    z = np.array([0.0, 0.0, 1.0])
    return C - (r * r / C[:, 2])[:, None] * (z - n[:, 2:3] * n)


def project(view: View, X_view: np.ndarray) -> np.ndarray:
    """(N, 3) view-frame points (mm) -> (N, 2) distorted pixels: ``cv2.projectPoints``' model
    (rvec = tvec = 0), compiled (:func:`crossfield.camera.stereo_kernels.project_view`: the same
    pixels to ~1e-13, without the Jacobian cv2 always computes); cv2 itself for the tilted-sensor
    model (more than 12 coefficients, tauX or tauY non-zero)."""
    if len(X_view) == 0:
        return np.zeros((0, 2))
    X_view = np.ascontiguousarray(X_view, dtype=np.float64).reshape(-1, 3)
    dist = np.asarray(view.dist, dtype=np.float64).ravel()
    if dist.size <= 12 or not np.any(dist[12:]):
        coeffs = np.zeros(12)
        coeffs[: min(dist.size, 12)] = dist[:12]
        K = view.K
        return stereo_kernels.project_view(X_view, K[0, 0], K[1, 1], K[0, 2], K[1, 2], coeffs)
    uv, _ = cv2.projectPoints(X_view.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), view.K, view.dist)
    return uv.reshape(-1, 2)


def _lens_jacobian(view: View, X_view: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(N, 2, 2) d(uv px) / d(normalised x, y) at the image of X_view."""
    x = X_view[:, :2] / X_view[:, 2:3]
    n = len(x)
    # x +- h in x, then in y, projected in one cv2.projectPoints call (the projection is per point)
    probes = np.concatenate([x + (h, 0.0), x - (h, 0.0), x + (0.0, h), x - (0.0, h)])
    uv = project(view, np.column_stack([probes, np.ones(4 * n)])).reshape(4, n, 2)
    return np.stack([(uv[0] - uv[1]) / (2 * h), (uv[2] - uv[3]) / (2 * h)], axis=-1)


def _sym(s: np.ndarray) -> np.ndarray:
    """(N, 3) (s_uu, s_uv, s_vv) -> (N, 2, 2)."""
    return np.stack([np.stack([s[:, 0], s[:, 1]], -1), np.stack([s[:, 1], s[:, 2]], -1)], -2)


def _vec(S: np.ndarray) -> np.ndarray:
    return np.stack([S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]], -1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross without its per-call overhead)."""
    return np.column_stack((
        a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
        a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
        a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
    ))


def _basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`crossfield.geometry.perpendicular_basis` of (N, 3) rows with :func:`_cross`:
    the same operations in the same order (np.cross computes a1 b2 - a2 b1 too), without
    np.cross's per-call overhead, which dominated the per-frame fit."""
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    helper = np.eye(3)[np.argmin(np.abs(d), axis=-1)]
    e1 = _cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, _cross(d, e1)


def _normals(n0, b1, b2, w):
    """Rodrigues: n0 rotated by the rotation vector w1 b1 + w2 b2 (perpendicular to n0)."""
    axis = w[:, :1] * b1 + w[:, 1:2] * b2
    angle = np.linalg.norm(axis, axis=1, keepdims=True)
    unit = axis / np.maximum(angle, 1e-300)
    return np.cos(angle) * n0 + np.sin(angle) * _cross(unit, n0)


def predicted_shape(C: np.ndarray, n: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(N, 3) shape (s_uu, s_uv, s_vv) in normalised coordinates of the image ellipse of
    circles (C, n, r) in the view frame: S = A / (c^T A c - s) of Q = H^-T diag(1, 1, -r^2) H^-1."""
    e1, e2 = _basis(n)
    H = np.stack([e1, e2, C], axis=-1)  # columns
    G = np.linalg.inv(H)
    D = np.zeros((len(C), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = -r * r
    Q = np.swapaxes(G, 1, 2) @ D @ G
    A = Q[:, :2, :2]
    q = Q[:, :2, 2]
    c = -np.linalg.solve(A, q[:, :, None])[:, :, 0]
    k = np.einsum("ni,nij,nj->n", c, A, c) - Q[:, 2, 2]
    return _vec(A / k[:, None, None])


def _observed(views, X, ellipses, covs):
    """Observed shapes in normalised coordinates and their whitening (Cholesky of the inverse cov)."""
    out = []
    for view, S_px, cov in zip(views, ellipses, covs):
        Xv = X @ view.R.T + view.t
        M = _lens_jacobian(view, Xv)
        S_n = _vec(np.swapaxes(M, 1, 2) @ _sym(S_px) @ M)
        # the linear map vec(S_px) -> vec(S_n), columns = images of the basis conics
        T = np.stack([_vec(np.swapaxes(M, 1, 2) @ _sym(np.tile(e, (len(X), 1))) @ M)
                      for e in np.eye(3)], axis=-1)
        if cov is None:
            scale = np.abs(S_n).max(axis=1) * 1e-3
            Wc = np.eye(3)[None] / scale[:, None, None]
        else:
            cov_n = T @ cov @ np.swapaxes(T, 1, 2)
            cov_n = cov_n + np.eye(3) * 1e-12 * np.abs(np.diagonal(cov_n, axis1=1, axis2=2)).max(axis=1)[:, None, None]
            Wc = np.linalg.cholesky(np.linalg.inv(cov_n))  # inv = L L^T -> whitened residual L^T r
            Wc = np.swapaxes(Wc, 1, 2)
        out.append((Xv, S_n, Wc))
    return out


# ---- the circle fit's compiled Gauss-Newton loop --------------------------------------------------
# The per-target arithmetic of _normals and predicted_shape (above), row by row on scalars,
# compiled (numba, the GIL released): the NumPy version's ~40 small-array calls per iteration
# cost ~0.6 ms of overhead per frame-iteration for ~100 rows of 3x3 algebra.


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _inverse_frame(x, y, z, cx, cy, cz):
    """H^-1 row by row (a 9-tuple), H = [e1 e2 C] (columns): e1, e2 the perpendicular basis of the
    normal (x, y, z) (as :func:`_basis`, helper the axis of its smallest component) and C
    (cx, cy, cz) mm the centre (view frame); the part of :func:`_shape_row` without the radius."""
    norm = math.sqrt(x * x + y * y + z * z)
    dx, dy, dz = x / norm, y / norm, z / norm
    if abs(dx) <= abs(dy) and abs(dx) <= abs(dz):  # helper: the axis of the smallest component
        e1x, e1y, e1z = 0.0, dz, -dy
    elif abs(dy) <= abs(dz):
        e1x, e1y, e1z = -dz, 0.0, dx
    else:
        e1x, e1y, e1z = dy, -dx, 0.0
    norm = math.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x, e1y, e1z = e1x / norm, e1y / norm, e1z / norm
    e2x, e2y, e2z = dy * e1z - dz * e1y, dz * e1x - dx * e1z, dx * e1y - dy * e1x
    # G = H^-1: the adjugate over the determinant
    g00, g01, g02 = e2y * cz - cy * e2z, e2z * cx - cz * e2x, e2x * cy - cx * e2y
    g10, g11, g12 = cy * e1z - e1y * cz, cz * e1x - e1z * cx, cx * e1y - e1x * cy
    g20, g21, g22 = e1y * e2z - e2y * e1z, e1z * e2x - e2z * e1x, e1x * e2y - e2x * e1y
    det = e1x * g00 + e1y * g01 + e1z * g02
    return (g00 / det, g01 / det, g02 / det, g10 / det, g11 / det, g12 / det,
            g20 / det, g21 / det, g22 / det)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _shape_from_frame(G, r2):
    """(s_uu, s_uv, s_vv) normalised of the circle of radius^2 r2 mm^2 in the frame G (a 9-tuple,
    :func:`_inverse_frame`): Q = G^T diag(1, 1, -r^2) G; A = Q[:2, :2], q = Q[:2, 2];
    S = A / (c^T A c - s), c = -A^-1 q."""
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = G[0], G[1], G[2], G[3], G[4], G[5], G[6], G[7], G[8]
    q00 = g00 * g00 + g10 * g10 - r2 * g20 * g20
    q01 = g00 * g01 + g10 * g11 - r2 * g20 * g21
    q11 = g01 * g01 + g11 * g11 - r2 * g21 * g21
    q02 = g00 * g02 + g10 * g12 - r2 * g20 * g22
    q12 = g01 * g02 + g11 * g12 - r2 * g21 * g22
    q22 = g02 * g02 + g12 * g12 - r2 * g22 * g22
    det_a = q00 * q11 - q01 * q01
    c0 = -(q11 * q02 - q01 * q12) / det_a
    c1 = -(q00 * q12 - q01 * q02) / det_a
    k = c0 * c0 * q00 + 2.0 * c0 * c1 * q01 + c1 * c1 * q11 - q22
    return q00 / k, q01 / k, q11 / k


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shape_row(x, y, z, cx, cy, cz, r2):
    """:func:`predicted_shape` of one circle on scalars: normal (x, y, z), centre (cx, cy, cz)
    mm (view frame), radius^2 r2 mm^2; returns (s_uu, s_uv, s_vv) normalised."""
    return _shape_from_frame(_inverse_frame(x, y, z, cx, cy, cz), r2)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _row_frames(p0, p1, n0, b1, b2, Xv, R):
    """(G_upper, G_lower): :func:`_inverse_frame` in both views of the circle with the tilt (p0, p1) rad
    (the normal n0 rotated by the rotation vector p0 b1 + p1 b2, Rodrigues) and the centres Xv
    (2, 3) mm (views R (2, 3, 3)); the part of the residuals that does not depend on log r."""
    a0 = p0 * b1[0] + p1 * b2[0]
    a1 = p0 * b1[1] + p1 * b2[1]
    a2 = p0 * b1[2] + p1 * b2[2]
    angle = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    scale = 1.0 / max(angle, 1e-300)
    u0, u1, u2 = a0 * scale, a1 * scale, a2 * scale
    ca, sa = math.cos(angle), math.sin(angle)
    m0 = ca * n0[0] + sa * (u1 * n0[2] - u2 * n0[1])
    m1 = ca * n0[1] + sa * (u2 * n0[0] - u0 * n0[2])
    m2 = ca * n0[2] + sa * (u0 * n0[1] - u1 * n0[0])
    return _view_frame(m0, m1, m2, Xv, R, 0), _view_frame(m0, m1, m2, Xv, R, 1)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _view_frame(m0, m1, m2, Xv, R, v):
    """:func:`_inverse_frame` of the upper-frame normal (m0, m1, m2) in view v (R (2, 3, 3), Xv (2, 3) mm)."""
    x = R[v, 0, 0] * m0 + R[v, 0, 1] * m1 + R[v, 0, 2] * m2  # the normal in the view's frame
    y = R[v, 1, 0] * m0 + R[v, 1, 1] * m1 + R[v, 1, 2] * m2
    z = R[v, 2, 0] * m0 + R[v, 2, 1] * m1 + R[v, 2, 2] * m2
    return _inverse_frame(x, y, z, Xv[v, 0], Xv[v, 1], Xv[v, 2])


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _frame_residuals(G, r2, S_obs, W, out):
    """The 6 whitened residuals W (S_obs - S) into out from the views' frames G (two 9-tuples,
    :func:`_row_frames`) and radius^2 r2 mm^2."""
    _view_residuals(G[0], r2, S_obs, W, out, 0)
    _view_residuals(G[1], r2, S_obs, W, out, 1)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _view_residuals(G, r2, S_obs, W, out, v):
    """View v's 3 whitened residuals W_v (S_obs_v - S) into out[3 v: 3 v + 3]."""
    s0, s1, s2 = _shape_from_frame(G, r2)
    d0, d1, d2 = S_obs[v, 0] - s0, S_obs[v, 1] - s1, S_obs[v, 2] - s2
    for i in range(3):
        out[3 * v + i] = W[v, i, 0] * d0 + W[v, i, 1] * d1 + W[v, i, 2] * d2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_residuals(p0, p1, p2, n0, b1, b2, Xv, R, S_obs, W, out):
    """The 6 whitened shape residuals of one row (``residuals`` of :func:`fit_circles`) into ``out``.

    p0, p1, p2: the tilt (w1, w2) rad and log r; n0, b1, b2 (3,): the line of sight and its
    perpendicular basis (upper frame); Xv (2, 3): the centre in each view's frame (mm);
    R (2, 3, 3) the views' rotations; S_obs (2, 3) the observed normalised shapes; W (2, 3, 3)
    their whitening. Residual = W (S_obs - S(C, R n, r)), S as :func:`predicted_shape`.
    """
    _frame_residuals(_row_frames(p0, p1, n0, b1, b2, Xv, R), math.exp(p2) ** 2, S_obs, W, out)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_jacobian(p, n0, b1, b2, Xv, R, S_obs, W, h, res, J, probe):
    """Residuals res (6,) at p (3,) and their forward-difference Jacobian J (6, 3), steps h (3,)
    (probe (6,): work space). The log r probe reuses the frames at p: the
    same values as recomputing them (:func:`_row_residuals` at p + h_2 e_2)."""
    G = _row_frames(p[0], p[1], n0, b1, b2, Xv, R)
    r2 = math.exp(p[2]) ** 2
    _frame_residuals(G, r2, S_obs, W, res)
    for j in range(3):
        if j == 0:
            _frame_residuals(_row_frames(p[0] + h[0], p[1], n0, b1, b2, Xv, R), r2, S_obs, W, probe)
        elif j == 1:
            _frame_residuals(_row_frames(p[0], p[1] + h[1], n0, b1, b2, Xv, R), r2, S_obs, W, probe)
        else:
            _frame_residuals(G, math.exp(p[2] + h[2]) ** 2, S_obs, W, probe)
        for i in range(6):
            J[i, j] = (probe[i] - res[i]) / h[j]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gauss_newton(p, n0, b1, b2, Xv, R, S_obs, W, h, iterations):
    """The circle fit's Gauss-Newton loop over the K rows (every start of every target) in place
    on p (K, 3): step = -(J^T J + 1e-9 I)^-1 J^T r, clipped to +-0.2, all rows together
    until the largest step is below 1e-7 (or ``iterations``). Returns the (K,) costs sum(r^2)
    at the end. Per-target inputs of the N targets, row k = start k // N of target k % N:
    n0, b1, b2 (N, 3); Xv (N, 2, 3); S_obs (N, 2, 3); W (N, 2, 3, 3)."""
    k_rows = len(p)
    n_targets = len(n0)
    res = np.empty(6)
    probe = np.empty(6)
    J = np.empty((6, 3))
    a = np.empty((3, 3))
    g = np.empty(3)
    step = np.empty((k_rows, 3))
    for _ in range(iterations):
        largest = 0.0
        for k in range(k_rows):
            target = k % n_targets
            _row_jacobian(p[k], n0[target], b1[target], b2[target], Xv[target], R, S_obs[target], W[target],
                          h, res, J, probe)
            # normal equations (J^T J + 1e-9 I) s = -J^T r, solved by Cramer's rule (3 x 3)
            a[:] = 0.0
            g[:] = 0.0
            for i in range(3):
                for j in range(3):
                    for m in range(6):
                        a[i, j] += J[m, i] * J[m, j]
                for m in range(6):
                    g[i] -= J[m, i] * res[m]
                a[i, i] += 1e-9
            c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
            c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
            c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
            det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
            s0 = (g[0] * c00 + g[1] * (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2])
                  + g[2] * (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1])) / det
            s1 = (g[0] * c01 + g[1] * (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0])
                  + g[2] * (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2])) / det
            s2 = (g[0] * c02 + g[1] * (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1])
                  + g[2] * (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0])) / det
            for i, si in enumerate((s0, s1, s2)):
                step[k, i] = min(max(si, -0.2), 0.2)
                largest = max(largest, abs(step[k, i]))
        p += step
        if largest < 1e-7:
            break
    cost = np.empty(k_rows)
    for k in range(k_rows):
        target = k % n_targets
        _row_residuals(p[k, 0], p[k, 1], p[k, 2], n0[target], b1[target], b2[target], Xv[target], R,
                       S_obs[target], W[target], res)
        cost[k] = np.sum(res * res)
    return cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobians(p, n0, b1, b2, Xv, R, S_obs, W, h):
    """(K, 6, 3) forward-difference Jacobians of the residuals at the rows p (K, 3)."""
    out = np.empty((len(p), 6, 3))
    res = np.empty(6)
    probe = np.empty(6)
    for k in range(len(p)):
        _row_jacobian(p[k], n0[k], b1[k], b2[k], Xv[k], R, S_obs[k], W[k], h, res, out[k], probe)
    return out


# ---- the rest of the circle fit, compiled ---------------------------------------------------------
# The per-target NumPy glue of _fit_circles_numpy (_observed's lens Jacobian and shape maps, the
# starts, the row gathers, the final Jacobian and normals) as scalar row loops: for the ~10 targets
# of a frame its ~250 small-array calls were ~1 ms of overhead per pair. The same floating-point
# operations in the same order: NumPy's small stacked matmuls (OpenBLAS' dgemm kernels on this
# machine) sum each product as a chain of fused multiply-adds in k order,
# fma(a_k, b_k, ... fma(a_1, b_1, a_0 b_0)), which :func:`crossfield.blas_order.fma` reproduces; NumPy's row sums and
# norms add left to right. What NumPy computes with LAPACK (inv, cholesky, eigh, pinv) or with its
# own SIMD arccos / log / exp stays in NumPy, between the kernels.


#: forward-difference steps of (w1, w2, log r) in the circle fit's Jacobian
_FIT_STEP = np.array([1e-6, 1e-6, 1e-7])

#: the single-entry cache of :func:`_lens_arrays`: (views, arrays)
_LENS_CACHE: list = [None, None]


def _lens_arrays(views):
    """The kernels' layout of two views: R (2, 3, 3), t (2, 3) mm, intrinsics (2, 4) fx fy cx cy
    px and coeffs (2, 12) (:func:`project`'s compiled model); None when a view needs
    ``cv2.projectPoints`` (tilted sensor) or when there are not two views (:func:`centre_offsets`
    takes any number). Cached for the last views passed (by identity: the arrays of a View are
    not expected to change in place)."""
    if len(views) != 2:
        return None
    cached_views, arrays = _LENS_CACHE
    if cached_views is not None and cached_views[0] is views[0] and cached_views[1] is views[1]:
        return arrays
    coeffs = np.zeros((2, 12))
    for v, view in enumerate(views):
        dist = np.asarray(view.dist, dtype=np.float64).ravel()
        if dist.size > 12 and np.any(dist[12:]):
            arrays = None
            break
        coeffs[v, : min(dist.size, 12)] = dist[:12]
    else:
        arrays = (np.ascontiguousarray([view.R for view in views], dtype=np.float64),
                  np.ascontiguousarray([view.t for view in views], dtype=np.float64),
                  np.array([[view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2]] for view in views],
                           dtype=np.float64),
                  coeffs)
    _LENS_CACHE[:] = [tuple(views), arrays]
    return arrays


def _cov_or_empty(cov) -> np.ndarray:
    """An ellipse covariance (N, 3, 3) as a contiguous float64 array; (0, 3, 3) for None."""
    if cov is None:
        return np.zeros((0, 3, 3))
    return np.ascontiguousarray(cov, dtype=np.float64)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _max3(a, b, c):
    """max(a, b, c), nan if any is nan (as NumPy's max)."""
    if a != a or b != b or c != c:
        return math.nan
    return max(a, max(b, c))


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sandwich(M, s00, s01, s11):
    """vec(M^T S M) = (uu, uv, vv) of the symmetric 2 x 2 S = [[s00, s01], [s01, s11]] and M (2, 2):
    (M^T S) then (.) M, each entry an fma chain as NumPy's stacked matmul computes it."""
    # P = M^T S: P[r, c] = M[0, r] S[0, c] + M[1, r] S[1, c]
    p00 = fma(M[1, 0], s01, M[0, 0] * s00)
    p01 = fma(M[1, 0], s11, M[0, 0] * s01)
    p10 = fma(M[1, 1], s01, M[0, 1] * s00)
    p11 = fma(M[1, 1], s11, M[0, 1] * s01)
    # (P M)[r, c] = P[r, 0] M[0, c] + P[r, 1] M[1, c]; the (0, 0), (0, 1), (1, 1) entries
    return (fma(p01, M[1, 0], p00 * M[0, 0]), fma(p01, M[1, 1], p00 * M[0, 1]),
            fma(p11, M[1, 1], p10 * M[0, 1]))


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lens_jacobian_row(xv0, xv1, xv2, fx, fy, cx, cy, k, h, M):
    """:func:`_lens_jacobian` of one view-frame point (mm) into M (2, 2): d(uv px) / d(x, y)
    normalised, central differences +-h (the probes projected at z = 1, as :func:`project`)."""
    x, y = xv0 / xv2, xv1 / xv2
    u0, v0 = stereo_kernels.project_point(x + h, y + 0.0, 1.0, fx, fy, cx, cy, k)
    u1, v1 = stereo_kernels.project_point(x - h, y - 0.0, 1.0, fx, fy, cx, cy, k)
    u2, v2 = stereo_kernels.project_point(x + 0.0, y + h, 1.0, fx, fy, cx, cy, k)
    u3, v3 = stereo_kernels.project_point(x - 0.0, y - h, 1.0, fx, fy, cx, cy, k)
    M[0, 0], M[1, 0] = (u0 - u1) / (2 * h), (v0 - v1) / (2 * h)
    M[0, 1], M[1, 1] = (u2 - u3) / (2 * h), (v2 - v3) / (2 * h)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _observed_rows(Xv, S_u, S_l, cov_u, cov_l, has_cov, intr, coeffs, h):
    """:func:`_observed` of both views up to LAPACK: per target the observed shape in normalised
    coordinates S_n = vec(M^T S_px M) (M: the lens Jacobian at the centre, :func:`_lens_jacobian_row`)
    and, for a view with ellipse covariances, cov_n = T cov T^T + 1e-12 max|diag| I (T: the linear
    map vec(S_px) -> vec(S_n), columns the images of the basis conics); for a view without, the
    whitening diag(1 / (1e-3 max|S_n|)).

    Xv (N, 2, 3) mm: the centres in the views' frames; S_u, S_l (N, 3) px^-2 the conics' shapes;
    cov_u, cov_l (N, 3, 3) px^-4 (any shape where has_cov (2,) is False); intr (2, 4), coeffs
    (2, 12) the lenses. Returns S_n (N, 2, 3), S_sym (2, N, 2, 2) (S_n as matrices, for eigh),
    cov_n (2, N, 3, 3) and W (N, 2, 3, 3) (filled for the views without covariances).
    """
    n = Xv.shape[0]
    S_n = np.empty((n, 2, 3))
    S_sym = np.empty((2, n, 2, 2))
    cov_n = np.zeros((2, n, 3, 3))
    W = np.zeros((n, 2, 3, 3))
    M = np.empty((2, 2))
    T = np.empty((3, 3))
    TC = np.empty((3, 3))
    for v in range(2):
        S_px = S_u if v == 0 else S_l
        cov = cov_u if v == 0 else cov_l
        fx, fy, cx, cy = intr[v, 0], intr[v, 1], intr[v, 2], intr[v, 3]
        k = coeffs[v]
        for i in range(n):
            _lens_jacobian_row(Xv[i, v, 0], Xv[i, v, 1], Xv[i, v, 2], fx, fy, cx, cy, k, h, M)
            a, b, c = _sandwich(M, S_px[i, 0], S_px[i, 1], S_px[i, 2])
            S_n[i, v, 0], S_n[i, v, 1], S_n[i, v, 2] = a, b, c
            S_sym[v, i, 0, 0], S_sym[v, i, 0, 1], S_sym[v, i, 1, 0], S_sym[v, i, 1, 1] = a, b, b, c
            if not has_cov[v]:
                scale = _max3(abs(a), abs(b), abs(c)) * 1e-3
                for r in range(3):
                    for q in range(3):
                        W[i, v, r, q] = (1.0 if r == q else 0.0) / scale
                continue
            for j in range(3):  # T[:, j] = vec(M^T sym(e_j) M)
                T[0, j], T[1, j], T[2, j] = _sandwich(M, 1.0 if j == 0 else 0.0, 1.0 if j == 1 else 0.0,
                                                      1.0 if j == 2 else 0.0)
            for r in range(3):  # TC = T cov, then cov_n = TC T^T (fma chains in k)
                for q in range(3):
                    TC[r, q] = fma(T[r, 2], cov[i, 2, q], fma(T[r, 1], cov[i, 1, q], T[r, 0] * cov[i, 0, q]))
            for r in range(3):
                for q in range(3):
                    cov_n[v, i, r, q] = fma(TC[r, 2], T[q, 2], fma(TC[r, 1], T[q, 1], TC[r, 0] * T[q, 0]))
            top = _max3(abs(cov_n[v, i, 0, 0]), abs(cov_n[v, i, 1, 1]), abs(cov_n[v, i, 2, 2]))
            for r in range(3):
                for q in range(3):
                    cov_n[v, i, r, q] = cov_n[v, i, r, q] + ((1.0 if r == q else 0.0) * 1e-12) * top
    return S_n, S_sym, cov_n, W


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _start_shapes(evals, Xv):
    """From the eigenvalues (2, N, 2) of the observed normalised shapes (ascending): the axis
    ratio clip(b / a, 0, 1) (2, N) (its arccos is the start's tilt) and a C_z (2, N) mm (its log
    the start's log r), a = 1 / sqrt|lambda_0| (major), b = 1 / sqrt|lambda_1| normalised."""
    n = evals.shape[1]
    ratio = np.empty((2, n))
    scale = np.empty((2, n))
    for v in range(2):
        for i in range(n):
            a_n = 1.0 / math.sqrt(abs(evals[v, i, 0]))
            b_n = 1.0 / math.sqrt(abs(evals[v, i, 1]))
            q = b_n / a_n
            if q < 0.0:  # np.clip: nan stays nan
                q = 0.0
            elif q > 1.0:
                q = 1.0
            ratio[v, i] = q
            scale[v, i] = a_n * Xv[i, v, 2]
    return ratio, scale


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _unit_sight(X, i, n0):
    """n0 (3,) = -X[i] / |X[i]|: the line of sight towards the camera (|.| summed left to right)."""
    norm = math.sqrt(X[i, 0] * X[i, 0] + X[i, 1] * X[i, 1] + X[i, 2] * X[i, 2])
    for a in range(3):
        n0[a] = -X[i, a] / norm


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _basis_row(n0, b1, b2):
    """:func:`_basis` of one row: b1, b2 (3,) the perpendicular basis of n0 (3,), normalised
    again; the helper axis is the first of the smallest |component| (np.argmin, nan first)."""
    norm = math.sqrt(n0[0] * n0[0] + n0[1] * n0[1] + n0[2] * n0[2])
    d0, d1, d2 = n0[0] / norm, n0[1] / norm, n0[2] / norm
    best, low = 0, abs(d0)
    if low == low:
        for a, value in ((1, abs(d1)), (2, abs(d2))):
            if value != value:
                best = a
                break
            if value < low:
                best, low = a, value
    h0, h1, h2 = (1.0 if best == 0 else 0.0), (1.0 if best == 1 else 0.0), (1.0 if best == 2 else 0.0)
    e0, e1, e2 = d1 * h2 - d2 * h1, d2 * h0 - d0 * h2, d0 * h1 - d1 * h0  # d x helper
    norm = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 / norm, e1 / norm, e2 / norm
    b1[0], b1[1], b1[2] = e0, e1, e2
    b2[0], b2[1], b2[2] = d1 * e2 - d2 * e1, d2 * e0 - d0 * e2, d0 * e1 - d1 * e0  # d x e1


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _normal_row(n0, b1, b2, w0, w1, out):
    """:func:`_normals` of one row into out (3,): n0 rotated by the rotation vector w0 b1 + w1 b2
    (Rodrigues, n = cos|a| n0 + sin|a| (a / |a|) x n0)."""
    a0, a1, a2 = w0 * b1[0] + w1 * b2[0], w0 * b1[1] + w1 * b2[1], w0 * b1[2] + w1 * b2[2]
    angle = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    floor = angle if (angle != angle or angle > 1e-300) else 1e-300  # np.maximum(angle, 1e-300)
    u0, u1, u2 = a0 / floor, a1 / floor, a2 / floor
    ca, sa = math.cos(angle), math.sin(angle)
    out[0] = ca * n0[0] + sa * (u1 * n0[2] - u2 * n0[1])
    out[1] = ca * n0[1] + sa * (u2 * n0[0] - u0 * n0[2])
    out[2] = ca * n0[2] + sa * (u0 * n0[1] - u1 * n0[0])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fit_rows(X, R, Xv, S_n, W, evecs, theta, r0, h, iterations):
    """The circle fit after LAPACK's eigh: the four starts per target (both views' major axes,
    both signs of the tilt theta (2, N), log r0 (2, N)), the Gauss-Newton loop over all of them
    (:func:`_gauss_newton`), the best start per target (the first of the lowest costs, nan first,
    as np.argmin), its residual Jacobian's normal matrix J^T J (N, 3, 3) and the normal (N, 3).

    X (N, 3) mm upper frame; R (2, 3, 3); Xv (N, 2, 3) mm; S_n (N, 2, 3); W (N, 2, 3, 3);
    evecs (2, N, 2, 2) (columns; column 0 the major axis' image direction). Returns params
    (N, 3) (w1, w2 rad, log r), costs (N,), J^T J (N, 3, 3) and normals (N, 3) upper frame.
    """
    n = X.shape[0]
    n0 = np.empty((n, 3))
    b1 = np.empty((n, 3))
    b2 = np.empty((n, 3))
    for i in range(n):
        _unit_sight(X, i, n0[i])
        _basis_row(n0[i], b1[i], b2[i])
    m = np.empty(3)
    p = np.empty((4 * n, 3))  # row (2 v + s) N + i: view v, sign s (+, -), target i
    for v in range(2):
        for i in range(n):
            e0, e1 = evecs[v, i, 0, 0], evecs[v, i, 1, 0]
            for c in range(3):  # [e0, e1, 0] @ R_v: the major axis in the upper frame
                m[c] = fma(0.0, R[v, 2, c], fma(e1, R[v, 1, c], e0 * R[v, 0, c]))
            along = m[0] * n0[i, 0] + m[1] * n0[i, 1] + m[2] * n0[i, 2]
            for c in range(3):
                m[c] -= along * n0[i, c]
            norm = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
            for c in range(3):
                m[c] /= norm
            for s, sign in enumerate((1.0, -1.0)):
                tilt = sign * theta[v, i]
                w0, w1, w2 = tilt * m[0], tilt * m[1], tilt * m[2]
                row = (2 * v + s) * n + i
                p[row, 0] = w0 * b1[i, 0] + w1 * b1[i, 1] + w2 * b1[i, 2]
                p[row, 1] = w0 * b2[i, 0] + w1 * b2[i, 1] + w2 * b2[i, 2]
                p[row, 2] = r0[v, i]
    cost = _gauss_newton(p, n0, b1, b2, Xv, R, S_n, W, h, iterations)
    best_p = np.empty((n, 3))
    best_cost = np.empty(n)
    for i in range(n):
        best = 0
        low = cost[i]
        if low == low:
            for s in range(1, 4):
                value = cost[s * n + i]
                if value != value:
                    best = s
                    break
                if value < low:
                    best, low = s, value
        best_cost[i] = cost[best * n + i]
        for c in range(3):
            best_p[i, c] = p[best * n + i, c]
    J = _jacobians(best_p, n0, b1, b2, Xv, R, S_n, W, h)
    JTJ = np.empty((n, 3, 3))
    normal = np.empty((n, 3))
    for i in range(n):
        for r in range(3):
            for q in range(3):
                acc = J[i, 0, r] * J[i, 0, q]
                for m6 in range(1, 6):
                    acc = fma(J[i, m6, r], J[i, m6, q], acc)
                JTJ[i, r, q] = acc
        _normal_row(n0[i], b1[i], b2[i], best_p[i, 0], best_p[i, 1], normal[i])
    return best_p, best_cost, JTJ, normal


def fit_circles(
    X: np.ndarray,
    views: tuple[View, View],
    ellipses: tuple[np.ndarray, np.ndarray],
    ellipse_covs: tuple[np.ndarray | None, np.ndarray | None],
    iterations: int = 10,
) -> CircleFit:
    """Circles (normal, radius) of N targets from their centres X (N, 3) mm (upper
    frame) and their fitted edge conics in both views (N, 3) px^-2, with
    covariances (N, 3, 3) px^-4 or None (module docstring).

    Compiled (:func:`_observed_rows`, :func:`_start_shapes`, :func:`_fit_rows`); NumPy does
    only what LAPACK and NumPy's own transcendental functions compute (inverse, Cholesky,
    eigh, pinv; arccos, log, exp), so the result is :func:`_fit_circles_numpy`'s, bit for bit.
    """
    lens = _lens_arrays(views)
    if lens is None:
        return _fit_circles_numpy(X, views, ellipses, ellipse_covs, iterations)
    R2, t2, intr, coeffs = lens
    X = np.ascontiguousarray(X, dtype=np.float64)
    n = len(X)
    # the centres in each view's frame: NumPy's matmul (a (1, 3) @ (3, 3) product is BLAS gemv,
    # whose sum order differs from the (N, 3) @ (3, 3) dgemm's)
    Xv = np.empty((n, 2, 3))
    for v, view in enumerate(views):
        Xv[:, v] = X @ view.R.T + view.t
    has_cov = np.array([c is not None for c in ellipse_covs])
    S_n, S_sym, cov_n, W = _observed_rows(
        Xv, np.ascontiguousarray(ellipses[0], dtype=np.float64), np.ascontiguousarray(ellipses[1], dtype=np.float64),
        _cov_or_empty(ellipse_covs[0]), _cov_or_empty(ellipse_covs[1]), has_cov, intr, coeffs, _LENS_STEP)
    if has_cov.any():
        # whitening W = L^T, inv(cov_n) = L L^T (whitened residual L^T r), LAPACK as in _observed
        with_cov = np.flatnonzero(has_cov)
        L = np.linalg.cholesky(np.linalg.inv(cov_n[with_cov]))
        for j, v in enumerate(with_cov):
            W[:, v] = np.swapaxes(L[j], 1, 2)
    # starts: tilt theta = acos(b/a) about the major axis of each view's ellipse, both signs
    evals, evecs = np.linalg.eigh(S_sym)  # ascending: evals[..., 0] -> major axis a = 1/sqrt
    ratio, scale = _start_shapes(evals, Xv)
    theta, r0 = np.arccos(ratio), np.log(scale)
    p, cost, JTJ, normal = _fit_rows(X, R2, Xv, S_n, W, evecs, theta, r0, _FIT_STEP, iterations)
    return CircleFit(normal, np.exp(p[:, 2]), np.linalg.pinv(JTJ), cost, p)


def _fit_circles_numpy(
    X: np.ndarray,
    views: tuple[View, View],
    ellipses: tuple[np.ndarray, np.ndarray],
    ellipse_covs: tuple[np.ndarray | None, np.ndarray | None],
    iterations: int = 10,
) -> CircleFit:
    """:func:`fit_circles` in NumPy (with :func:`_observed` and the compiled Gauss-Newton
    loop): the formulation the compiled path reproduces bit for bit, kept for views whose
    lens needs ``cv2.projectPoints`` (tilted sensor) and as the tests' reference."""
    n = len(X)
    obs = _observed(views, X, ellipses, ellipse_covs)
    n0 = -X / np.linalg.norm(X, axis=1, keepdims=True)
    b1, b2 = _basis(n0)

    # starts: tilt theta = acos(b/a) about the major axis of each view's ellipse, both signs
    starts = []
    for view, (Xv, S_n, _) in zip(views, obs):
        evals, evecs = np.linalg.eigh(_sym(S_n))  # ascending: evals[0] -> major axis a = 1/sqrt
        a_n, b_n = 1.0 / np.sqrt(np.abs(evals[:, 0])), 1.0 / np.sqrt(np.abs(evals[:, 1]))
        theta = np.arccos(np.clip(b_n / a_n, 0.0, 1.0))
        major = np.column_stack([evecs[:, :, 0], np.zeros(n)]) @ view.R  # image direction -> upper frame
        major -= np.sum(major * n0, axis=1, keepdims=True) * n0
        major /= np.linalg.norm(major, axis=1, keepdims=True)
        r0 = np.log(a_n * Xv[:, 2])
        for sign in (1.0, -1.0):
            w = sign * theta[:, None] * major
            starts.append(np.column_stack([np.sum(w * b1, 1), np.sum(w * b2, 1), r0]))
    k_starts = len(starts)
    p = np.concatenate(starts)  # (k_starts * n, 3)
    idx = np.tile(np.arange(n), k_starts)
    h = np.array([1e-6, 1e-6, 1e-7])  # forward-difference steps of (w1, w2, log r)
    # per-row inputs of the compiled loop: row k = start k // n of target k % n
    R = np.ascontiguousarray(np.stack([view.R for view in views]), dtype=np.float64)
    Xv = np.ascontiguousarray(np.stack([o[0] for o in obs], axis=1))  # (n, 2, 3)
    S_obs = np.ascontiguousarray(np.stack([o[1] for o in obs], axis=1))  # (n, 2, 3)
    W = np.ascontiguousarray(np.stack([o[2] for o in obs], axis=1))  # (n, 2, 3, 3)
    rows = (np.ascontiguousarray(n0[idx]), np.ascontiguousarray(b1[idx]), np.ascontiguousarray(b2[idx]),
            Xv[idx], R, S_obs[idx], W[idx])
    cost = _gauss_newton(p, *rows, h, iterations).reshape(k_starts, n)
    best = np.argmin(cost, axis=0)
    p = p[best * n + np.arange(n)]
    J = _jacobians(p, np.ascontiguousarray(n0), np.ascontiguousarray(b1), np.ascontiguousarray(b2),
                   Xv, R, S_obs, W, h)
    cov = np.linalg.pinv(np.swapaxes(J, 1, 2) @ J)
    normal = _normals(n0, b1, b2, p[:, :2])
    return CircleFit(normal, np.exp(p[:, 2]), cov, cost[best, np.arange(n)], p)


#: step (normalised coordinates) of the central differences of the lens Jacobian
_LENS_STEP = 1e-6
#: projected points per target in centre_offsets: 4 points x (itself, +-h in x, +-h in y), C
_PROBES = 21


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _probe_row(x0, x1, x2, n0, n1, n2, radius, R, t, h, probes):
    """The 21 points :func:`centre_offsets` projects for one target (upper-frame centre
    (x0, x1, x2) mm, normal (n0, n1, n2), radius mm) into probes (21, 3): for each of the four
    points x_e +- sqrt(2) L_k (k = 0, 1; z = 1) the point and its neighbours +-h in x and in y,
    then the circle centre C (view frame R, t, mm)."""
    root2 = math.sqrt(2.0)
    c0 = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]
    c1 = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]
    c2 = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
    m0 = R[0, 0] * n0 + R[0, 1] * n1 + R[0, 2] * n2
    m1 = R[1, 0] * n0 + R[1, 1] * n1 + R[1, 2] * n2
    m2 = R[2, 0] * n0 + R[2, 1] * n1 + R[2, 2] * n2
    r2 = radius * radius
    f = r2 / c2  # ellipse_centre_point: X_e = C - (r^2 / C_z) (z - n_z n)
    ex, ey, ez = c0 + f * m2 * m0, c1 + f * m2 * m1, c2 - f * (1.0 - m2 * m2)
    xe, ye = ex / ez, ey / ez
    s00, s01, s11 = _shape_row(m0, m1, m2, c0, c1, c2, r2)
    det = s00 * s11 - s01 * s01  # Sigma = S^-1 / 4 = L L^T (Cholesky)
    a00, a01, a11 = s11 / det / 4.0, -s01 / det / 4.0, s00 / det / 4.0
    l00 = math.sqrt(a00)
    l10 = a01 / l00
    l11 = math.sqrt(a11 - l10 * l10)
    j = 0
    for lu, lv in ((l00, l10), (0.0, l11)):  # the columns L_0, L_1
        for sign in (1.0, -1.0):
            px, py = xe + sign * root2 * lu, ye + sign * root2 * lv
            for dx, dy in ((0.0, 0.0), (h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)):
                probes[j, 0] = px + dx
                probes[j, 1] = py + dy
                probes[j, 2] = 1.0
                j += 1
    probes[20, 0], probes[20, 1], probes[20, 2] = c0, c1, c2


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _combine_row(uv, h):
    """One target's offset (du, dv) px from the projections uv (21, 2) of :func:`_probe_row`'s
    probes: the |det Df|-weighted mean of the four points minus the projected centre (det Df
    from the central differences: image area per unit area)."""
    tu = tv = weight = 0.0
    for k in range(4):
        b = 5 * k
        j00 = (uv[b + 1, 0] - uv[b + 2, 0]) / (2 * h)
        j10 = (uv[b + 1, 1] - uv[b + 2, 1]) / (2 * h)
        j01 = (uv[b + 3, 0] - uv[b + 4, 0]) / (2 * h)
        j11 = (uv[b + 3, 1] - uv[b + 4, 1]) / (2 * h)
        w = abs(j00 * j11 - j01 * j10)
        tu += w * uv[b, 0]
        tv += w * uv[b, 1]
        weight += w
    return tu / weight - uv[20, 0], tv / weight - uv[20, 1]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _offset_probes(X, normal, radius, R, t, h, probes):
    """:func:`_probe_row` of every target (N,) of one view into probes (N, 21, 3)."""
    for i in range(len(X)):
        _probe_row(X[i, 0], X[i, 1], X[i, 2], normal[i, 0], normal[i, 1], normal[i, 2], radius[i],
                   R, t, h, probes[i])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _offset_combine(uv, h, out):
    """out (N, 2) px: :func:`_combine_row` of the projections uv (N, 21, 2) of every target."""
    for i in range(len(uv)):
        out[i, 0], out[i, 1] = _combine_row(uv[i], h)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _offsets_row(x0, x1, x2, n0, n1, n2, radius, R, t, intr, coeffs, h, probes, uv, out, i):
    """:func:`centre_offsets` of one target, both views, into out[i] (4,) px: the probes of
    each view (:func:`_probe_row`) projected one by one (:func:`project`'s compiled model)."""
    for v in range(2):
        _probe_row(x0, x1, x2, n0, n1, n2, radius, R[v], t[v], h, probes)
        for j in range(_PROBES):
            uv[j, 0], uv[j, 1] = stereo_kernels.project_point(
                probes[j, 0], probes[j, 1], probes[j, 2], intr[v, 0], intr[v, 1], intr[v, 2], intr[v, 3], coeffs[v])
        out[i, 2 * v], out[i, 2 * v + 1] = _combine_row(uv, h)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _centre_offsets_rows(X, normal, radius, R, t, intr, coeffs, h):
    """(N, 4) px :func:`centre_offsets` of N targets in both views, compiled end to end."""
    n = X.shape[0]
    out = np.empty((n, 4))
    probes = np.empty((_PROBES, 3))
    uv = np.empty((_PROBES, 2))
    for i in range(n):
        _offsets_row(X[i, 0], X[i, 1], X[i, 2], normal[i, 0], normal[i, 1], normal[i, 2], radius[i],
                     R, t, intr, coeffs, h, probes, uv, out, i)
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _offset_covariance_rows(X, params, radius, radius_step, cov, R, t, intr, coeffs, h_lens, h):
    """(N, 4, 4) px^2 :func:`offset_covariance`, compiled: D cov D^T with D (4, 3) the forward
    differences (steps h (3,)) of the offsets in (w1, w2, log r) about params (N, 3) (the tilt
    about the line of sight of X (N, 3) mm, as :func:`_normals`); radius (N,) = exp(log r) and
    radius_step (N,) = exp(log r + h_2) mm come from NumPy's exp. cov (N, 3, 3) the fit's."""
    n = X.shape[0]
    out = np.empty((n, 4, 4))
    probes = np.empty((_PROBES, 3))
    uv = np.empty((_PROBES, 2))
    every = np.empty((4, 4))  # the offsets at params, then at its three neighbours
    n0, b1, b2, normal = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    D = np.empty((4, 3))
    DC = np.empty((4, 3))
    for i in range(n):
        _unit_sight(X, i, n0)
        _basis_row(n0, b1, b2)
        for k in range(4):
            w0, w1 = params[i, 0], params[i, 1]
            if k > 0:  # params + h e_k (the h * e_k of the other two components are exact zeros)
                w0 = w0 + h[0] * (1.0 if k == 1 else 0.0)
                w1 = w1 + h[1] * (1.0 if k == 2 else 0.0)
            _normal_row(n0, b1, b2, w0, w1, normal)
            _offsets_row(X[i, 0], X[i, 1], X[i, 2], normal[0], normal[1], normal[2],
                         radius_step[i] if k == 3 else radius[i], R, t, intr, coeffs, h_lens, probes, uv, every, k)
        for r in range(4):
            for j in range(3):
                D[r, j] = (every[1 + j, r] - every[0, r]) / h[j]
        for r in range(4):  # (D cov) D^T, fma chains as NumPy's matmul
            for q in range(3):
                DC[r, q] = fma(D[r, 2], cov[i, 2, q], fma(D[r, 1], cov[i, 1, q], D[r, 0] * cov[i, 0, q]))
        for r in range(4):
            for q in range(4):
                out[i, r, q] = fma(DC[r, 2], D[q, 2], fma(DC[r, 1], D[q, 1], DC[r, 0] * D[q, 0]))
    return out


def centre_offsets(X: np.ndarray, normal: np.ndarray, radius: np.ndarray, views) -> np.ndarray:
    """(N, 4) px: [du, dv] of the upper then the lower view, the centre of the image
    blob minus the image of the circle centre (upper-frame circles X (N, 3), normal
    (N, 3), radius (N,)).

    The blob's centre is the centroid of the distorted image of the ellipse: the
    ellipse centre X_e (exact, pinhole) moved by the lens's curvature over the
    blob: the centroid of the image region f(E) is E[f(x) |det Df(x)|] / E[|det Df|]
    over the uniform ellipse E (normalised coordinates, second moment
    Sigma = S^-1 / 4), taken as the |det Df|-weighted mean of f at the four points
    x_e +- sqrt(2) L_k, Sigma = L L^T (exact to second order in the blob's size).

    Compiled end to end (:func:`_centre_offsets_rows`); through :func:`project` per view where
    a lens needs ``cv2.projectPoints`` (the same arithmetic around the projection).
    """
    lens = _lens_arrays(views)
    X = np.ascontiguousarray(X, dtype=np.float64)
    normal = np.ascontiguousarray(normal, dtype=np.float64)
    radius = np.ascontiguousarray(radius, dtype=np.float64)
    if lens is not None:
        return _centre_offsets_rows(X, normal, radius, *lens, _LENS_STEP)
    n = len(X)
    out = []
    for view in views:
        probes = np.empty((n, _PROBES, 3))
        _offset_probes(np.ascontiguousarray(X, dtype=np.float64), np.ascontiguousarray(normal, dtype=np.float64),
                       np.ascontiguousarray(radius, dtype=np.float64), np.ascontiguousarray(view.R, dtype=np.float64),
                       np.ascontiguousarray(view.t, dtype=np.float64), _LENS_STEP, probes)
        # one cv2.projectPoints call per view: each point x_e +- sqrt(2) L_k, its +-h neighbours
        # in x and in y (the central differences of _lens_jacobian), and the circle centre C
        uv = project(view, probes.reshape(-1, 3)).reshape(n, _PROBES, 2)
        offsets = np.empty((n, 2))
        _offset_combine(uv, _LENS_STEP, offsets)
        out.append(offsets)
    return np.hstack(out)


#: forward-difference steps of (w1, w2, log r) in :func:`offset_covariance`
_OFFSET_STEP = np.array([1e-5, 1e-5, 1e-5])


def offset_covariance(X: np.ndarray, fit: CircleFit, views) -> np.ndarray:
    """(N, 4, 4) px^2 covariance of :func:`centre_offsets` from the circle fit's covariance:
    D cov D^T, D (N, 4, 3) the forward differences of the offsets of the circles about the
    points X (N, 3) mm (upper frame) in the fit's parameters (w1, w2, log r).

    Compiled (:func:`_offset_covariance_rows`; the radii through NumPy's exp, as before);
    :func:`_offset_covariance_numpy` where a lens needs ``cv2.projectPoints``."""
    lens = _lens_arrays(views)
    if lens is None:
        return _offset_covariance_numpy(X, fit, views)
    params = np.ascontiguousarray(fit.params, dtype=np.float64)
    radius_step = np.exp(params[:, 2] + _OFFSET_STEP[2])  # exp(log r + h): the third neighbour
    return _offset_covariance_rows(np.ascontiguousarray(X, dtype=np.float64), params,
                                   np.ascontiguousarray(fit.radius_mm, dtype=np.float64), radius_step,
                                   np.ascontiguousarray(fit.cov, dtype=np.float64), *lens, _LENS_STEP, _OFFSET_STEP)


def _offset_covariance_numpy(X: np.ndarray, fit: CircleFit, views) -> np.ndarray:
    """:func:`offset_covariance` in NumPy: the formulation the compiled one reproduces."""
    n0 = -X / np.linalg.norm(X, axis=1, keepdims=True)
    b1, b2 = _basis(n0)

    h = np.array([1e-5, 1e-5, 1e-5])
    # the offsets at the parameters and at their 3 forward-difference neighbours, in one
    # (row-wise) call: the values of four calls
    p = np.concatenate([fit.params] + [fit.params + h * e for e in np.eye(3)])
    n = len(X)
    every = centre_offsets(
        np.tile(X, (4, 1)), _normals(np.tile(n0, (4, 1)), np.tile(b1, (4, 1)), np.tile(b2, (4, 1)), p[:, :2]),
        np.exp(p[:, 2]), views,
    ).reshape(4, n, 4)
    base = every[0]
    D = np.stack([(every[1 + k] - base) / h[k] for k in range(3)], axis=-1)
    return D @ fit.cov @ np.swapaxes(D, 1, 2)
