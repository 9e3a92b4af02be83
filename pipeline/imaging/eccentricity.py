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

Speed: the circle fit's Gauss-Newton loop (:func:`_gauss_newton`) and the
per-target arithmetic of :func:`centre_offsets` are compiled (numba, scalar
3 x 3 algebra per target, the same formulas as :func:`predicted_shape` and
:func:`ellipse_centre_point`); the lens goes through one compiled projection per
view (:func:`project`, ``cv2.projectPoints``' model without its Jacobian). Against the NumPy formulas the points move by < 1e-9 mm and the
offsets by < 1e-9 px (rounding of the finite differences); tests/centroid/test_eccentricity.py.

Units: mm in the camera frames, pixels in the images, normalised image
coordinates where stated; views are given as ``p_view = R @ p_upper + t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shape_row(x, y, z, cx, cy, cz, r2):
    """:func:`predicted_shape` of one circle on scalars: normal (x, y, z), centre (cx, cy, cz)
    mm (view frame), radius^2 r2 mm^2; returns (s_uu, s_uv, s_vv) normalised."""
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
    # G = H^-1 for H = [e1 e2 C] (columns): the adjugate over the determinant
    g00, g01, g02 = e2y * cz - cy * e2z, e2z * cx - cz * e2x, e2x * cy - cx * e2y
    g10, g11, g12 = cy * e1z - e1y * cz, cz * e1x - e1z * cx, cx * e1y - e1x * cy
    g20, g21, g22 = e1y * e2z - e2y * e1z, e1z * e2x - e2z * e1x, e1x * e2y - e2x * e1y
    det = e1x * g00 + e1y * g01 + e1z * g02
    g00, g01, g02, g10, g11, g12 = g00 / det, g01 / det, g02 / det, g10 / det, g11 / det, g12 / det
    g20, g21, g22 = g20 / det, g21 / det, g22 / det
    # Q = G^T diag(1, 1, -r^2) G; A = Q[:2, :2], q = Q[:2, 2]; S = A / (c^T A c - s), c = -A^-1 q
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
def _row_residuals(p0, p1, p2, n0, b1, b2, Xv, R, S_obs, W, out):
    """The 6 whitened shape residuals of one row (``residuals`` of :func:`fit_circles`) into ``out``.

    p0, p1, p2: the tilt (w1, w2) rad and log r; n0, b1, b2 (3,): the line of sight and its
    perpendicular basis (upper frame); Xv (2, 3): the centre in each view's frame (mm);
    R (2, 3, 3) the views' rotations; S_obs (2, 3) the observed normalised shapes; W (2, 3, 3)
    their whitening. Residual = W (S_obs - S(C, R n, r)), S as :func:`predicted_shape`.
    """
    # _normals: n0 rotated by the rotation vector w1 b1 + w2 b2 (Rodrigues)
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
    r2 = math.exp(p2) ** 2
    for v in range(2):
        x = R[v, 0, 0] * m0 + R[v, 0, 1] * m1 + R[v, 0, 2] * m2  # the normal in the view's frame
        y = R[v, 1, 0] * m0 + R[v, 1, 1] * m1 + R[v, 1, 2] * m2
        z = R[v, 2, 0] * m0 + R[v, 2, 1] * m1 + R[v, 2, 2] * m2
        s0, s1, s2 = _shape_row(x, y, z, Xv[v, 0], Xv[v, 1], Xv[v, 2], r2)
        d0, d1, d2 = S_obs[v, 0] - s0, S_obs[v, 1] - s1, S_obs[v, 2] - s2
        for i in range(3):
            out[3 * v + i] = W[v, i, 0] * d0 + W[v, i, 1] * d1 + W[v, i, 2] * d2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row_jacobian(p, n0, b1, b2, Xv, R, S_obs, W, h, res, J):
    """Residuals res (6,) at p (3,) and their forward-difference Jacobian J (6, 3), steps h (3,)."""
    _row_residuals(p[0], p[1], p[2], n0, b1, b2, Xv, R, S_obs, W, res)
    probe = np.empty(6)
    for j in range(3):
        q = p.copy()
        q[j] += h[j]
        _row_residuals(q[0], q[1], q[2], n0, b1, b2, Xv, R, S_obs, W, probe)
        for i in range(6):
            J[i, j] = (probe[i] - res[i]) / h[j]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gauss_newton(p, n0, b1, b2, Xv, R, S_obs, W, h, iterations):
    """The circle fit's Gauss-Newton loop over the K rows (every start of every target) in place
    on p (K, 3): step = -(J^T J + 1e-9 I)^-1 J^T r, clipped to +-0.2, all rows together
    until the largest step is below 1e-7 (or ``iterations``). Returns the (K,) costs sum(r^2)
    at the end. Row k's inputs: n0, b1, b2 (K, 3); Xv (K, 2, 3); S_obs (K, 2, 3); W (K, 2, 3, 3)."""
    k_rows = len(p)
    res = np.empty(6)
    J = np.empty((6, 3))
    step = np.empty((k_rows, 3))
    for _ in range(iterations):
        largest = 0.0
        for k in range(k_rows):
            _row_jacobian(p[k], n0[k], b1[k], b2[k], Xv[k], R, S_obs[k], W[k], h, res, J)
            # normal equations (J^T J + 1e-9 I) s = -J^T r, solved by Cramer's rule (3 x 3)
            a = np.zeros((3, 3))
            g = np.zeros(3)
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
        _row_residuals(p[k, 0], p[k, 1], p[k, 2], n0[k], b1[k], b2[k], Xv[k], R, S_obs[k], W[k], res)
        cost[k] = np.sum(res * res)
    return cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobians(p, n0, b1, b2, Xv, R, S_obs, W, h):
    """(K, 6, 3) forward-difference Jacobians of the residuals at the rows p (K, 3)."""
    out = np.empty((len(p), 6, 3))
    res = np.empty(6)
    for k in range(len(p)):
        _row_jacobian(p[k], n0[k], b1[k], b2[k], Xv[k], R, S_obs[k], W[k], h, res, out[k])
    return out


def fit_circles(
    X: np.ndarray,
    views: tuple[View, View],
    ellipses: tuple[np.ndarray, np.ndarray],
    ellipse_covs: tuple[np.ndarray | None, np.ndarray | None],
    iterations: int = 10,
) -> CircleFit:
    """Circles (normal, radius) of N targets from their centres X (N, 3) mm (upper
    frame) and their fitted edge conics in both views (N, 3) px^-2, with
    covariances (N, 3, 3) px^-4 or None (module docstring)."""
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _offset_probes(X, normal, radius, R, t, h, probes):
    """The points :func:`centre_offsets` projects, per target (N,): probes (N, 21, 3) = for each
    of the four points x_e +- sqrt(2) L_k (k = 0, 1; z = 1) the point and its neighbours
    +-h in x and in y, then the circle centre C (view frame, mm)."""
    root2 = math.sqrt(2.0)
    for i in range(len(X)):
        c = np.empty(3)
        m = np.empty(3)
        for a in range(3):
            c[a] = R[a, 0] * X[i, 0] + R[a, 1] * X[i, 1] + R[a, 2] * X[i, 2] + t[a]
            m[a] = R[a, 0] * normal[i, 0] + R[a, 1] * normal[i, 1] + R[a, 2] * normal[i, 2]
        r2 = radius[i] * radius[i]
        f = r2 / c[2]  # ellipse_centre_point: X_e = C - (r^2 / C_z) (z - n_z n)
        ex, ey, ez = c[0] + f * m[2] * m[0], c[1] + f * m[2] * m[1], c[2] - f * (1.0 - m[2] * m[2])
        xe, ye = ex / ez, ey / ez
        s00, s01, s11 = _shape_row(m[0], m[1], m[2], c[0], c[1], c[2], r2)
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
                    probes[i, j, 0] = px + dx
                    probes[i, j, 1] = py + dy
                    probes[i, j, 2] = 1.0
                    j += 1
        probes[i, 20, 0], probes[i, 20, 1], probes[i, 20, 2] = c[0], c[1], c[2]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _offset_combine(uv, h, out):
    """out (N, 2) px: the |det Df|-weighted mean of the four projected points minus the
    projected centre, from the projections uv (N, 21, 2) of :func:`_offset_probes`' probes
    (det Df from the central differences: image area per unit area)."""
    for i in range(len(uv)):
        tu = tv = weight = 0.0
        for k in range(4):
            b = 5 * k
            j00 = (uv[i, b + 1, 0] - uv[i, b + 2, 0]) / (2 * h)
            j10 = (uv[i, b + 1, 1] - uv[i, b + 2, 1]) / (2 * h)
            j01 = (uv[i, b + 3, 0] - uv[i, b + 4, 0]) / (2 * h)
            j11 = (uv[i, b + 3, 1] - uv[i, b + 4, 1]) / (2 * h)
            w = abs(j00 * j11 - j01 * j10)
            tu += w * uv[i, b, 0]
            tv += w * uv[i, b, 1]
            weight += w
        out[i, 0] = tu / weight - uv[i, 20, 0]
        out[i, 1] = tv / weight - uv[i, 20, 1]


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
    """
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


def offset_covariance(X: np.ndarray, fit: CircleFit, views) -> np.ndarray:
    """(N, 4, 4) px^2 covariance of :func:`centre_offsets` from the circle fit's covariance."""
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
