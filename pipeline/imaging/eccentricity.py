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

Units: mm in the camera frames, pixels in the images, normalised image
coordinates where stated; views are given as ``p_view = R @ p_upper + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

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
    """(N, 3) view-frame points (mm) -> (N, 2) distorted pixels (cv2.projectPoints)."""
    if len(X_view) == 0:
        return np.zeros((0, 2))
    uv, _ = cv2.projectPoints(np.ascontiguousarray(X_view, dtype=np.float64).reshape(-1, 1, 3),
                              np.zeros(3), np.zeros(3), view.K, view.dist)
    return uv.reshape(-1, 2)


def _lens_jacobian(view: View, X_view: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(N, 2, 2) d(uv px) / d(normalised x, y) at the image of X_view."""
    x = X_view[:, :2] / X_view[:, 2:3]
    ones = np.ones((len(x), 1))
    cols = []
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        plus = project(view, np.hstack([x + e, ones]))
        minus = project(view, np.hstack([x - e, ones]))
        cols.append((plus - minus) / (2 * h))
    return np.stack(cols, axis=-1)


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

    def residuals(p, idx):
        normal = _normals(n0[idx], b1[idx], b2[idx], p[:, :2])
        r = np.exp(p[:, 2])
        k = len(idx)
        # both views' predicted shapes in one call (row-wise: the same values as one call per view)
        pred = predicted_shape(
            np.concatenate([Xv[idx] for Xv, _, _ in obs]),
            np.concatenate([normal @ view.R.T for view in views]),
            np.concatenate([r, r]),
        )
        parts = [
            np.einsum("nij,nj->ni", Wc[idx], S_n[idx] - pred[v * k:(v + 1) * k])
            for v, (_, S_n, Wc) in enumerate(obs)
        ]
        return np.concatenate(parts, axis=1)  # (K, 6)

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
    h = np.array([1e-6, 1e-6, 1e-7])
    probe = np.vstack([np.zeros(3), np.diag(h)])  # p and its 3 forward-difference neighbours

    def jacobian(p, idx):
        """Residuals (K, 6) and their Jacobian (K, 6, 3): one batched call for p and its 3 probes."""
        k = len(p)
        res = residuals((p[None] + probe[:, None]).reshape(-1, 3), np.tile(idx, 4)).reshape(4, k, 6)
        return res[0], np.moveaxis((res[1:] - res[0]) / h[:, None, None], 0, -1)

    for _ in range(iterations):
        res, J = jacobian(p, idx)
        JtJ = np.swapaxes(J, 1, 2) @ J
        step = -np.linalg.solve(JtJ + 1e-9 * np.eye(3), np.einsum("nki,nk->ni", J, res)[:, :, None])[:, :, 0]
        step = np.clip(step, -0.2, 0.2)
        p = p + step
        if np.abs(step).max() < 1e-7:
            break
    res = residuals(p, idx)
    cost = np.sum(res**2, axis=1).reshape(k_starts, n)
    best = np.argmin(cost, axis=0)
    p = p[best * n + np.arange(n)]
    _, J = jacobian(p, np.arange(n))
    cov = np.linalg.pinv(np.swapaxes(J, 1, 2) @ J)
    normal = _normals(n0, b1, b2, p[:, :2])
    return CircleFit(normal, np.exp(p[:, 2]), cov, cost[best, np.arange(n)], p)


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
    h = 1e-6  # the step of _lens_jacobian's central differences
    out = []
    for view in views:
        C = X @ view.R.T + view.t
        nv = normal @ view.R.T
        Xe = ellipse_centre_point(C, nv, radius)
        xe = Xe[:, :2] / Xe[:, 2:3]
        S = _sym(predicted_shape(C, nv, radius))
        L = np.linalg.cholesky(np.linalg.inv(S) / 4.0)
        # the four points x_e +- sqrt(2) L_k (z = 1), in the order (k, sign) = (0, +), (0, -), (1, +), (1, -)
        points = [xe + sign * np.sqrt(2.0) * L[:, :, k] for k in range(2) for sign in (1.0, -1.0)]
        # one cv2.projectPoints call per view: each point, its +-h neighbours in x and in y (the
        # central differences of _lens_jacobian), and the circle centre C; the projection is
        # per point, so the values are those of one call per point
        probes = [p for x in points for p in (x, x + (h, 0.0), x - (h, 0.0), x + (0.0, h), x - (0.0, h))]
        uv = project(view, np.vstack([np.column_stack([x, np.ones(n)]) for x in probes] + [C]))
        uv = uv.reshape(len(probes) + 1, n, 2)
        J = np.stack([np.stack([(uv[5 * i + 1] - uv[5 * i + 2]) / (2 * h), (uv[5 * i + 3] - uv[5 * i + 4]) / (2 * h)],
                               axis=-1) for i in range(4)])  # (4, N, 2, 2) d(uv) / d(x, y)
        w = np.abs(np.linalg.det(J))[:, :, None]  # image area per unit area
        total = np.zeros((n, 2))
        weight = np.zeros((n, 1))
        for i in range(4):
            total += w[i] * uv[5 * i]
            weight += w[i]
        out.append(total / weight - uv[-1])
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
