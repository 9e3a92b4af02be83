"""Maximum-likelihood fit of a blurred elliptical disc, batched over targets.

One job: given the pixels of many target windows at once, find for each the
elliptical disc (centre, shape), its amplitude and background that best
explain the pixel values under the sensor's noise (``docs/centroids.md``,
"modelfit").

Image model of one target, pixel i at x_i = (u_i, v_i) (pixels, OpenCV
convention)::

    mu_i = B + A * E(delta_i, alpha_i)
    delta_i = (rho_i - rho_i^2) / |S d_i| - sigma_e^2 kappa_i / 2

with d_i = x_i - (u_0, v_0), S the (2, 2) positive-definite shape matrix of
the disc's edge (``d^T S d = 1`` on the edge, px^-2), rho_i = sqrt(d^T S d)
the elliptical radius, (1 - rho) / |grad rho| = (rho - rho^2) / |S d| the
first-order signed distance (px) from the edge (positive inside), kappa_i
= det(S) rho^2 / |S d|^3 the curvature of the level set of rho through the
pixel (a blurred curved edge crosses half its height sigma_e^2 kappa / 2
inside the edge, to first order), sigma_e^2 = blur^2 + 1/12 (PSF plus the
pixel's box), and alpha_i the direction of the edge normal (S d) folded
into [0, 45] degrees.

E is the edge-spread function of a straight edge seen through the PSF and
the square pixel, tabulated once per blur (:class:`EdgeProfile`) for one of
two image-formation orders:

* ``"optical"``: a Gaussian PSF of sigma ``blur`` acting on the scene, then
  integration over the pixel (a real camera): E = Gaussian (x) trapezoid;
* ``"pixel"``: pixel integration first, then a sampled Gaussian kernel on
  the pixel grid (``cv2.GaussianBlur`` of the coverage: how crossfield's
  simulator and the synthetic test images are rendered). The difference is
  not the order (a continuous Gaussian and the pixel box commute) but the
  sampled kernel: a comb of point masses at integer offsets, which leaves
  the box's kinks at half-pixel offsets in the profile; the two profiles
  differ by up to 2 % of the amplitude (edge along a pixel axis; 0.1 % at
  45 degrees), enough to bias the centre with the sub-pixel phase.

The model is point-symmetric about (u_0, v_0) in both cases.

Noise: independent Gaussian per pixel, var_i = sigma_n^2 + (mu_i - B) / gain
(read/background noise plus the photon noise of the target signal, EMVA 1288),
evaluated at the current model. The estimate maximises the likelihood by
Gauss-Newton (Nocedal & Wright 10.3), parameters p = (u_0, v_0, s_uu, s_uv,
s_vv, A, B); the Jacobian neglects dE/dalpha (the profile's slow change with
the edge direction: the estimating equations stay unbiased, as the residuals
have zero mean at the truth). Its covariance is the inverse Fisher
information ``(J^T W J)^-1`` at the solution (the Cramer-Rao bound of the
model, Kay, Fundamentals of Statistical Signal Processing I, 3.7).

All targets are solved together: the pixels of their edge bands are
packed into (N, P) arrays (:func:`pack_stacks`; padding has weight 0),
the model and Jacobian are evaluated in float32 on
coordinates relative to each target's seed and the normal equations are
one batched matrix product, so each iteration is a few dozen array
operations whatever the number of targets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

__all__ = [
    "PSF_ORDERS",
    "DiscFit",
    "EdgeProfile",
    "edge_profile",
    "fit_discs",
    "model",
    "pack_stacks",
    "shape_from_moments",
]

#: Parameter order of the fit.
PARAMS: tuple[str, ...] = ("u0", "v0", "s_uu", "s_uv", "s_vv", "amplitude", "background")
#: Image-formation orders the edge profile is tabulated for.
PSF_ORDERS: tuple[str, ...] = ("optical", "pixel")

_DELTA_STEP = 1.0 / 64.0  # px, table step of the signed distance
_DELTA_MAX = 8.0  # px, table range +-
_SIN_STEPS = 32  # table steps of sin(alpha) over [0, sin 45 deg]
_SIN_MAX = math.sqrt(0.5)


def _trapezoid_cdf(z: np.ndarray, c: float, s: float) -> np.ndarray:
    """CDF at z of c Y1 + s Y2, Y1, Y2 ~ U(-1/2, 1/2), c >= s >= 0: the fraction
    of a unit pixel on the inner side of a straight edge at signed distance z
    from its centre, normal (c, s)."""
    zp = np.clip(z + 0.5 * (c + s), 0.0, c + s)
    if s < 1e-9:
        return zp / c
    return np.where(
        zp <= s,
        zp * zp / (2 * c * s),
        np.where(zp <= c, (zp - 0.5 * s) / c, 1.0 - (c + s - zp) ** 2 / (2 * c * s)),
    )


@dataclass(frozen=True)
class EdgeProfile:
    """Tabulated edge-spread function E(delta, alpha) and dE/ddelta.

    table, slope: (n_sin, n_delta), rows by sin(alpha) on [0, sin 45 deg],
    columns by delta on [-_DELTA_MAX, _DELTA_MAX] (px).
    """

    blur_sigma_px: float
    order: str
    table: np.ndarray
    slope: np.ndarray
    table32: np.ndarray  # the table as float32, for the float32 fit

    def lookup(self, delta: np.ndarray, sin_alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """E and dE/ddelta at (delta px, sin alpha), in delta's dtype: linear in
        delta (dE/ddelta is the slope of that interpolant, so the Jacobian is
        exact for the interpolated model), nearest in alpha."""
        flat = self.table32.ravel() if delta.dtype == np.float32 else self.table.ravel()
        x = np.clip(delta, -_DELTA_MAX, _DELTA_MAX - 2 * _DELTA_STEP)
        x += _DELTA_MAX
        x *= 1.0 / _DELTA_STEP
        k = x.astype(np.intp)
        row = sin_alpha * (_SIN_STEPS / _SIN_MAX)
        row += 0.5
        k += row.astype(np.intp) * self.table.shape[1]  # nearest row: floor(y + 1/2), y >= 0
        f = x
        f -= np.floor(x)
        e0 = flat[k]
        de = flat[k + 1]
        de -= e0
        f *= de
        f += e0
        de *= 1.0 / _DELTA_STEP
        return f, de


@lru_cache(maxsize=8)
def edge_profile(blur_sigma_px: float, order: str = "optical") -> EdgeProfile:
    """The edge profile table for a Gaussian blur (px) and an image-formation order."""
    if order not in PSF_ORDERS:
        raise ValueError(f"unknown image-formation order {order!r}; expected one of {PSF_ORDERS}")
    delta = np.arange(-_DELTA_MAX, _DELTA_MAX + _DELTA_STEP / 2, _DELTA_STEP)
    rows = []
    for sin_a in np.linspace(0.0, _SIN_MAX, _SIN_STEPS + 1):
        s = float(sin_a)
        c = math.sqrt(1.0 - s * s)
        if blur_sigma_px <= 0:
            rows.append(_trapezoid_cdf(delta, c, s))
            continue
        if order == "pixel":
            # sampled 2-D Gaussian kernel on the pixel grid (cv2.GaussianBlur's for float images)
            ksize = int(round(blur_sigma_px * 8 + 1)) | 1
            g = cv2.getGaussianKernel(ksize, blur_sigma_px).ravel()
            n = np.arange(ksize) - ksize // 2
            offsets = (n[:, None] * c + n[None, :] * s).ravel()
            weights = (g[:, None] * g[None, :]).ravel()
        else:
            # continuous Gaussian along the normal (projection of the isotropic 2-D PSF)
            offsets = np.linspace(-6.0, 6.0, 241) * blur_sigma_px
            weights = np.exp(-0.5 * (offsets / blur_sigma_px) ** 2)
            weights /= weights.sum()
        rows.append(weights @ _trapezoid_cdf(delta[None, :] + offsets[:, None], c, s))
    table = np.array(rows)
    slope = np.gradient(table, _DELTA_STEP, axis=1)
    table.flags.writeable = False
    slope.flags.writeable = False
    table32 = table.astype(np.float32)
    table32.flags.writeable = False
    return EdgeProfile(float(blur_sigma_px), order, table, slope, table32)


@dataclass(frozen=True)
class DiscFit:
    """Result of :func:`fit_discs` for N targets.

    params: (N, 7) in :data:`PARAMS` order (px, px^-2, DN).
    cov: (N, 7, 7) inverse Fisher information at the solution.
    ok: (N,) bool, the fit converged to a valid disc.
    iterations: Gauss-Newton iterations run.
    """

    params: np.ndarray
    cov: np.ndarray
    ok: np.ndarray
    iterations: int


def shape_from_moments(c20: np.ndarray, c11: np.ndarray, c02: np.ndarray, sigma_e: float) -> np.ndarray:
    """Edge shape matrices (N, 3) (s_uu, s_uv, s_vv) px^-2 from intensity second
    central moments (N,) px^2 of blurred uniform discs.

    A uniform ellipse with ``d^T S d <= 1`` has covariance S^-1 / 4; blur adds
    sigma_e^2 I. So S = (4 (C - sigma_e^2 I))^-1, with C floored to stay
    positive definite.
    """
    a = np.maximum(c20 - sigma_e**2, 0.25)
    c = np.maximum(c02 - sigma_e**2, 0.25)
    b = np.clip(c11, -0.95 * np.sqrt(a * c), 0.95 * np.sqrt(a * c))
    det = 4.0 * (a * c - b * b)
    return np.column_stack((c / det, -b / det, a / det))


def model(
    params: np.ndarray, du: np.ndarray, dv: np.ndarray, profile: EdgeProfile, jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """The disc model mu (N, P) DN and its Jacobian (N, 7, P) at P pixels of N targets.

    params: (N, 7) the parameters of each target (:data:`PARAMS`),
    du, dv: (N, P) pixel coordinates (px) minus each target's *reference*
    point (the same offset is taken off params' u0, v0); the arithmetic is in
    du's dtype (float32 in :func:`fit_discs`, float64 otherwise). Derivatives of
    delta = (rho - q) / sqrt(m) - sigma_e^2 kappa / 2 with q = d^T S d = rho^2,
    w = S d, m = |w|^2, kappa = D q / m^(3/2), D = det S: dq/dd = 2 w,
    dm/dd = 2 S w (the chain rule through rho = sqrt(q): d rho = dq / (2 rho)).
    """
    dt = du.dtype if du.dtype in (np.float32, np.float64) else np.float64
    pc = np.asarray(params, dtype=np.float64)
    col = [pc[:, k : k + 1].astype(dt) for k in range(7)]
    u0, v0, s11, s12, s22, amp, bg = col
    sig2 = profile.blur_sigma_px**2 + 1.0 / 12.0
    det64 = pc[:, 2:3] * pc[:, 4:5] - pc[:, 3:4] ** 2
    c_shift = (0.5 * sig2 * det64).astype(dt)  # shift = sigma_e^2 kappa / 2 = c_shift q / m^(3/2)
    x = du - u0
    y = dv - v0
    w1 = s11 * x
    w1 += s12 * y
    w2 = s12 * x
    w2 += s22 * y
    q = x * w1
    q += y * w2
    m = w1 * w1
    m += w2 * w2
    np.maximum(m, 1e-18, out=m)  # d = 0 exactly: deep inside, guard the divisions
    inv = np.sqrt(m)
    np.reciprocal(inv, out=inv)  # 1 / |S d|
    rho = np.sqrt(np.maximum(q, 0.0))
    inv3 = inv * inv
    inv3 *= inv
    shift = c_shift * q
    shift *= inv3
    dist = rho - q
    dist *= inv  # first-order signed distance (rho - rho^2) / |S d|
    delta = dist - shift
    sin_alpha = np.minimum(np.abs(w1), np.abs(w2))
    sin_alpha *= inv
    E, slope = profile.lookup(delta, sin_alpha)
    mu = amp * E
    mu += bg
    if not jacobian:
        return mu, None
    ap = amp * slope  # dmu/ddelta
    rho_safe = np.maximum(rho, 1e-9)
    dd_drho = 1.0 - 2.0 * rho
    dd_drho *= inv
    # d delta / dm (distance and curvature terms) = -dist / (2 m) + 1.5 shift / m
    dm_coef = 1.5 * shift
    dm_coef -= 0.5 * dist
    dm_coef *= inv * inv
    dm_coef *= 2.0
    c_q = c_shift * inv3  # -d shift / dq
    half = dd_drho / (2.0 * rho_safe)
    half -= c_q  # d delta / dq
    c_d = shift / det64.astype(dt)  # d shift / dD
    # d delta / dx = 2 half w + dm_coef S w   (x = u - u0: d/du0 = -d/dx)
    sw1 = s11 * w1
    sw1 += s12 * w2
    sw2 = s12 * w1
    sw2 += s22 * w2
    J = np.empty((du.shape[0], 7, du.shape[1]), dt)
    h2 = 2.0 * half
    t = h2 * w1
    t += dm_coef * sw1
    np.multiply(t, -ap, out=J[:, 0])
    t = h2 * w2
    t += dm_coef * sw2
    np.multiply(t, -ap, out=J[:, 1])
    # shape: dq/ds = (x^2, 2xy, y^2); dm/ds = 2 (w1 x, w1 y + w2 x, w2 y); dD/ds = (s22, -2 s12, s11)
    dm_coef *= 0.5
    t = half * x * x
    t += dm_coef * (2.0 * w1 * x)
    t -= c_d * s22
    np.multiply(t, ap, out=J[:, 2])
    t = half * (2.0 * x * y)
    t += dm_coef * (2.0 * (w1 * y + w2 * x))
    t += c_d * (2.0 * s12)
    np.multiply(t, ap, out=J[:, 3])
    t = half * y * y
    t += dm_coef * (2.0 * w2 * y)
    t -= c_d * s11
    np.multiply(t, ap, out=J[:, 4])
    J[:, 5] = E
    J[:, 6] = 1.0
    return mu, J


def _normal_equations(J, W, r):
    """Per-target J^T W J (N, 7, 7) and J^T W r (N, 7), float64, from J (N, 7, P), W, r (N, P)."""
    JW = J * W[:, None, :]
    H = np.matmul(JW, np.swapaxes(J, 1, 2)).astype(np.float64)
    g = np.matmul(JW, r[:, :, None])[:, :, 0].astype(np.float64) if r is not None else None
    return H, g


def fit_discs(
    du: np.ndarray,
    dv: np.ndarray,
    values: np.ndarray,
    mask: np.ndarray,
    start: np.ndarray,
    *,
    profile: EdgeProfile,
    noise_sigma_dn: float,
    gain_e_per_dn: float,
    max_iterations: int = 3,
    tolerance_px: float = 1e-4,
    dtype: type = np.float32,
) -> DiscFit:
    """Fit N discs at once by Gauss-Newton (module docstring).

    du, dv: (N, P) pixel coordinates relative to each target's reference
    point (``start``'s u0, v0 are relative to the same point); values: (N, P)
    DN; mask: (N, P) 1 for the target's pixels, 0 for padding; start: (N, 7)
    initial parameters. noise_sigma_dn: background noise (DN);
    gain_e_per_dn: conversion gain. Every target takes the same Gauss-Newton
    steps (no per-target bookkeeping: from the weighted centroid two or three
    suffice), until no centre moves by more than ``tolerance_px``; the
    covariance uses the last iteration's Jacobian. Model, Jacobian and the
    normal-equation products are in ``dtype`` (float32: half the memory
    traffic; coordinates are relative, so ~1e-6 px resolution), the
    parameters, the 7 x 7 solves and the covariance in float64.
    """
    p = np.array(start, dtype=np.float64, copy=True)
    n = len(p)
    du, dv, values = (np.asarray(a, dtype=dtype) for a in (du, dv, values))
    mask = np.asarray(mask, dtype=dtype)
    noise_var = noise_sigma_dn**2
    inv_gain = 1.0 / gain_e_per_dn
    iterations = 0
    H = np.zeros((n, 7, 7))
    for iterations in range(1, max_iterations + 1):
        mu, J = model(p, du, dv, profile)
        # weights 1 / var_i, var_i = sigma_n^2 + (mu_i - B) / gain (EMVA 1288), padding 0
        var = mu - p[:, 6:7].astype(dtype)
        np.maximum(var, 0.0, out=var)
        var *= inv_gain
        var += noise_var
        W = np.divide(mask, var, out=var)
        r = values - mu
        H, g = _normal_equations(J, W, r)
        try:
            step = np.linalg.solve(H, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.einsum("nij,nj->ni", np.linalg.pinv(H), g)
        step[~np.isfinite(step).all(axis=1)] = 0.0
        # trust region: at most 0.5 px for the centre and 20 % for the shape per iteration
        centre = np.hypot(step[:, 0], step[:, 1])
        shape = np.abs(step[:, 2:5]).max(axis=1) / np.maximum(np.abs(p[:, 2:5]).max(axis=1), 1e-12)
        scale = np.minimum(1.0, np.minimum(0.5 / np.maximum(centre, 1e-300), 0.2 / np.maximum(shape, 1e-300)))
        p += step * scale[:, None]
        if not (centre * scale >= tolerance_px).any():
            break
    det_s = p[:, 2] * p[:, 4] - p[:, 3] ** 2
    ok = np.isfinite(p).all(axis=1) & (p[:, 2] > 0) & (det_s > 0) & (p[:, 5] > 0)
    cov = np.full((n, 7, 7), np.nan)
    if ok.any():
        try:
            cov[ok] = np.linalg.inv(H[ok])
        except np.linalg.LinAlgError:
            cov[ok] = np.linalg.pinv(H[ok])
    ok &= np.isfinite(cov[:, 0, 0]) & (cov[:, 0, 0] > 0) & (cov[:, 1, 1] > 0)
    return DiscFit(p, cov, ok, iterations)


def _signed_distance(x: np.ndarray, y: np.ndarray, s11, s12, s22) -> np.ndarray:
    """First-order signed distance (px, positive inside) of offsets (x, y) px from
    the edge d^T S d = 1: (rho - rho^2) / |S d| (module docstring)."""
    w1 = s11 * x + s12 * y
    w2 = s12 * x + s22 * y
    q = x * w1 + y * w2
    return (np.sqrt(np.maximum(q, 0.0)) - q) / np.sqrt(np.maximum(w1 * w1 + w2 * w2, 1e-18))


def pack_stacks(
    stacks,
    refs: np.ndarray,
    dtype: type = np.float64,
    band: tuple[np.ndarray, float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pack the window pixels of the blobs of :class:`crossfield.imaging.blobs.BlobStack` s
    into padded (N, P) arrays, N = all their blobs in stack order, P = the largest window.

    refs: (N, 2) reference point of each target (image px). Returns du, dv
    (N, P) pixel coordinates (px) minus the target's reference, values (N, P)
    DN and mask (N, P) (1 = pixel, 0 = padding, which repeats the target's
    first pixel), all in ``dtype``. Vectorised: one ``np.nonzero`` per stack,
    one scatter per array.

    band: ``(shapes, inside_px, outside_px)`` keeps only the window pixels
    less than ``inside_px`` inside and ``outside_px`` outside the edge
    ``d^T S d = 1`` of ``shapes`` (N, 3) px^-2 centred on ``refs``, by the
    first-order signed distance: the *edge band*. The pixels left out carry
    no information on the centre or the shape (the profile's slope there is
    nil), only on the amplitude (plateau) or the background (far outside).
    """
    refs = np.asarray(refs, dtype=np.float64)
    n_all = sum(len(st) for st in stacks)
    refs = refs.reshape(n_all, 2)
    ts, us, vs, zs, offset = [], [], [], [], 0
    for st in stacks:
        n, _, sw = st.window.shape
        win = st.window.reshape(n, -1)
        t, k = np.nonzero(win)  # row-major: sorted by target
        per = np.count_nonzero(win, axis=1)
        r, c = np.divmod(k, sw)
        # coordinates relative to each target's reference: per-target offsets repeated
        # over its (contiguous) pixels rather than gathered pixel by pixel
        us.append((c + np.repeat(st.x0 - refs[offset : offset + n, 0], per)).astype(np.float32))
        vs.append((r + np.repeat(st.y0 - refs[offset : offset + n, 1], per)).astype(np.float32))
        zs.append(st.roi.reshape(n, -1)[t, k])
        ts.append(t + offset)
        offset += n
    if sum(t.size for t in ts) == 0:  # no blob, or no pixel at all: all padding
        empty = np.zeros((n_all, 1 if n_all else 0), dtype)
        return empty, empty.copy(), empty.copy(), empty.copy()
    t_all, u_all, v_all, z_all = (np.concatenate(a) for a in (ts, us, vs, zs))
    counts = np.bincount(t_all, minlength=n_all)
    if band is not None:
        shapes, inside_px, outside_px = band
        sh = np.repeat(np.asarray(shapes, dtype=np.float32), counts, axis=0)
        dist = _signed_distance(u_all, v_all, sh[:, 0], sh[:, 1], sh[:, 2])
        keep = (dist < inside_px) & (dist > -outside_px)
        t_all, u_all, v_all, z_all = t_all[keep], u_all[keep], v_all[keep], z_all[keep]
        if t_all.size == 0:
            empty = np.zeros((n_all, 1), dtype)
            return empty, empty.copy(), empty.copy(), empty.copy()
        counts = np.bincount(t_all, minlength=n_all)
    width = max(int(counts.max()), 1)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    flat = np.arange(t_all.size) + np.repeat(np.arange(n_all) * width - starts, counts)  # row t, place in row
    first = np.minimum(starts, t_all.size - 1)  # padding: the target's first pixel (any, if none)
    out = []
    for col in (u_all, v_all, z_all):
        a = np.repeat(col[first].astype(dtype), width)
        a[flat] = col
        out.append(a.reshape(n_all, width))
    mask = np.zeros(n_all * width, dtype)
    mask[flat] = 1.0
    return out[0], out[1], out[2], mask.reshape(n_all, width)
