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

The fit (:func:`fit_discs`) is one compiled kernel (numba, float64): a
loop over the targets of a :class:`crossfield.imaging.blobs.BlobStack`
(one thread, the GIL released), and per target over the window pixels of its
edge band, accumulating the 7 x 7 normal equations pixel by pixel, on
coordinates relative to the target's seed. :func:`model` is the same
model in numpy (the reference the kernel is tested against).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numba
import numpy as np

__all__ = [
    "PSF_ORDERS",
    "DiscFit",
    "EdgeProfile",
    "edge_band",
    "edge_profile",
    "fit_discs",
    "model",
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

    def lookup(self, delta: np.ndarray, sin_alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """E and dE/ddelta at (delta px, sin alpha): linear in delta (dE/ddelta
        is the slope of that interpolant, so the Jacobian is exact for the
        interpolated model), nearest in alpha."""
        flat = self.table.ravel()
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
    return EdgeProfile(float(blur_sigma_px), order, table, slope)


@dataclass(frozen=True)
class DiscFit:
    """Result of :func:`fit_discs` for N targets.

    params: (N, 7) in :data:`PARAMS` order (px, px^-2, DN).
    cov: (N, 7, 7) inverse Fisher information (J^T W J)^-1 of the last
    iteration (NaN where not ``ok``).
    ok: (N,) bool, the fit converged to a valid disc.
    iterations: (N,) Gauss-Newton iterations run per target.
    pixels: (N,) window pixels in the fit (the edge band).
    """

    params: np.ndarray
    cov: np.ndarray
    ok: np.ndarray
    iterations: np.ndarray
    pixels: np.ndarray


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
    point (the same offset is taken off params' u0, v0); float64. The reference
    of the compiled fit's per-pixel evaluation (:func:`fit_discs`). Derivatives of
    delta = (rho - q) / sqrt(m) - sigma_e^2 kappa / 2 with q = d^T S d = rho^2,
    w = S d, m = |w|^2, kappa = D q / m^(3/2), D = det S: dq/dd = 2 w,
    dm/dd = 2 S w (the chain rule through rho = sqrt(q): d rho = dq / (2 rho)).
    """
    dt = np.float64
    du, dv = np.asarray(du, dtype=dt), np.asarray(dv, dtype=dt)
    pc = np.asarray(params, dtype=dt)
    u0, v0, s11, s12, s22, amp, bg = (pc[:, k : k + 1] for k in range(7))
    sig2 = profile.blur_sigma_px**2 + 1.0 / 12.0
    det64 = s11 * s22 - s12**2
    c_shift = 0.5 * sig2 * det64  # shift = sigma_e^2 kappa / 2 = c_shift q / m^(3/2)
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
    c_d = shift / det64  # d shift / dD
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


@numba.njit(cache=True, error_model="numpy")
def _cholesky_solve(L: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out = (L L^T)^-1 b for the lower Cholesky factor L (7, 7) (forward, then back substitution)."""
    n = L.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * out[k]
        out[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, n):
            s -= L[k, i] * out[k]
        out[i] = s / L[i, i]


@numba.njit(cache=True, error_model="numpy")
def _cholesky(H: np.ndarray, L: np.ndarray) -> bool:
    """Lower Cholesky factor of the symmetric (7, 7) H (upper triangle read) into L;
    False if H is not numerically positive definite (Golub & Van Loan 4.2)."""
    n = H.shape[0]
    for j in range(n):
        s = H[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:  # also NaN
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = H[j, i]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    return True


@numba.njit(cache=True, error_model="numpy")
def _normal_equations(xs, ys, zs, count, p, table, n_delta, sig2, noise_var, inv_gain, H, g, jac, index) -> None:
    """J^T W J into H (7, 7) and J^T W r into g (7,) at parameters p (7,) over the
    ``count`` pixels (xs, ys) px (relative to the reference point), values zs DN:
    :func:`model` and its Jacobian (same formulas), weights 1 / var_i, var_i =
    sigma_n^2 + (mu_i - B) / gain (EMVA 1288), residuals r_i = z_i - mu_i.

    Four passes over the pixels, scratch ``jac`` (8, >= count) and ``index``
    (>= count,): the table position, the table lookup, the Jacobian, the sums.
    Without the lookup (a gather) the first and third compile to SIMD code
    (4 pixels per instruction; one scalar pass has a ~170-cycle dependency chain
    per pixel): 2.2x faster than one pass.
    """
    u0, v0, s11, s12, s22, amp, bg = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
    det = s11 * s22 - s12 * s12
    c_shift = 0.5 * sig2 * det  # shift = sigma_e^2 kappa / 2 = c_shift q / m^(3/2)
    inv_det = 1.0 / det
    # pass 1 (vectorised): where in the edge-profile table (EdgeProfile.lookup: linear in
    # delta, nearest in alpha)
    for i in range(count):
        x = xs[i] - u0
        y = ys[i] - v0
        w1 = s11 * x + s12 * y  # w = S d
        w2 = s12 * x + s22 * y
        q = x * w1 + y * w2  # rho^2
        m = max(w1 * w1 + w2 * w2, 1e-18)  # |S d|^2; d = 0 exactly: guard the divisions
        inv = 1.0 / math.sqrt(m)
        rho = math.sqrt(max(q, 0.0))
        inv3 = inv * inv * inv
        shift = c_shift * q * inv3
        dist = (rho - q) * inv  # first-order signed distance (rho - rho^2) / |S d|
        delta = dist - shift
        sin_alpha = min(abs(w1), abs(w2)) * inv
        t = min(max(delta, -_DELTA_MAX), _DELTA_MAX - 2 * _DELTA_STEP)
        t = (t + _DELTA_MAX) * (1.0 / _DELTA_STEP)
        k = int(t)
        index[i] = k + int(sin_alpha * (_SIN_STEPS / _SIN_MAX) + 0.5) * n_delta
        jac[5, i] = t - k  # t >= 0: t - floor(t)
    # pass 2 (scalar: a gather): E and dE/ddelta
    for i in range(count):
        k = index[i]
        e0 = table[k]
        de = table[k + 1] - e0
        jac[5, i] = e0 + jac[5, i] * de
        jac[6, i] = de * (1.0 / _DELTA_STEP)
    # pass 3 (vectorised): the Jacobian (model()'s derivation; d/du0 = -d/dx), weights, residuals
    for i in range(count):
        x = xs[i] - u0
        y = ys[i] - v0
        w1 = s11 * x + s12 * y  # w = S d
        w2 = s12 * x + s22 * y
        q = x * w1 + y * w2  # rho^2
        m = max(w1 * w1 + w2 * w2, 1e-18)  # |S d|^2; d = 0 exactly: guard the divisions
        inv = 1.0 / math.sqrt(m)
        rho = math.sqrt(max(q, 0.0))
        inv3 = inv * inv * inv
        shift = c_shift * q * inv3
        dist = (rho - q) * inv  # first-order signed distance (rho - rho^2) / |S d|
        E = jac[5, i]
        mu = amp * E + bg
        ap = amp * jac[6, i]  # dmu/ddelta
        dd_drho = (1.0 - 2.0 * rho) * inv
        dm_coef = (1.5 * shift - 0.5 * dist) * (inv * inv) * 2.0  # d delta / dm, times 2
        half = dd_drho / (2.0 * max(rho, 1e-9)) - c_shift * inv3  # d delta / dq
        c_d = shift * inv_det  # d shift / dD
        sw1 = s11 * w1 + s12 * w2
        sw2 = s12 * w1 + s22 * w2
        h2 = 2.0 * half
        jac[0, i] = -((h2 * w1 + dm_coef * sw1) * ap)
        jac[1, i] = -((h2 * w2 + dm_coef * sw2) * ap)
        dm_half = 0.5 * dm_coef
        jac[2, i] = (half * x * x + dm_half * (2.0 * w1 * x) - c_d * s22) * ap
        jac[3, i] = (half * (2.0 * x * y) + dm_half * (2.0 * (w1 * y + w2 * x)) + c_d * (2.0 * s12)) * ap
        jac[4, i] = (half * y * y + dm_half * (2.0 * w2 * y) - c_d * s11) * ap
        jac[6, i] = 1.0 / (max(mu - bg, 0.0) * inv_gain + noise_var)
        jac[7, i] = zs[i] - mu
    # pass 4 (scalar: the sums in scalars, i.e. registers, not in H and g: 2-3x faster)
    h00 = h01 = h02 = h03 = h04 = h05 = h06 = h11 = h12 = h13 = h14 = h15 = h16 = 0.0
    h22 = h23 = h24 = h25 = h26 = h33 = h34 = h35 = h36 = h44 = h45 = h46 = h55 = h56 = h66 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = g6 = 0.0
    for i in range(count):
        j0 = jac[0, i]
        j1 = jac[1, i]
        j2 = jac[2, i]
        j3 = jac[3, i]
        j4 = jac[4, i]
        j5 = jac[5, i]
        w = jac[6, i]
        r = jac[7, i]
        wj = w * j0
        g0 += wj * r
        h00 += wj * j0
        h01 += wj * j1
        h02 += wj * j2
        h03 += wj * j3
        h04 += wj * j4
        h05 += wj * j5
        h06 += wj
        wj = w * j1
        g1 += wj * r
        h11 += wj * j1
        h12 += wj * j2
        h13 += wj * j3
        h14 += wj * j4
        h15 += wj * j5
        h16 += wj
        wj = w * j2
        g2 += wj * r
        h22 += wj * j2
        h23 += wj * j3
        h24 += wj * j4
        h25 += wj * j5
        h26 += wj
        wj = w * j3
        g3 += wj * r
        h33 += wj * j3
        h34 += wj * j4
        h35 += wj * j5
        h36 += wj
        wj = w * j4
        g4 += wj * r
        h44 += wj * j4
        h45 += wj * j5
        h46 += wj
        wj = w * j5
        g5 += wj * r
        h55 += wj * j5
        h56 += wj
        wj = w  # j6 = 1
        g6 += wj * r
        h66 += wj
    H[0, 0] = h00
    H[0, 1] = h01
    H[0, 2] = h02
    H[0, 3] = h03
    H[0, 4] = h04
    H[0, 5] = h05
    H[0, 6] = h06
    g[0] = g0
    H[1, 0] = h01
    H[1, 1] = h11
    H[1, 2] = h12
    H[1, 3] = h13
    H[1, 4] = h14
    H[1, 5] = h15
    H[1, 6] = h16
    g[1] = g1
    H[2, 0] = h02
    H[2, 1] = h12
    H[2, 2] = h22
    H[2, 3] = h23
    H[2, 4] = h24
    H[2, 5] = h25
    H[2, 6] = h26
    g[2] = g2
    H[3, 0] = h03
    H[3, 1] = h13
    H[3, 2] = h23
    H[3, 3] = h33
    H[3, 4] = h34
    H[3, 5] = h35
    H[3, 6] = h36
    g[3] = g3
    H[4, 0] = h04
    H[4, 1] = h14
    H[4, 2] = h24
    H[4, 3] = h34
    H[4, 4] = h44
    H[4, 5] = h45
    H[4, 6] = h46
    g[4] = g4
    H[5, 0] = h05
    H[5, 1] = h15
    H[5, 2] = h25
    H[5, 3] = h35
    H[5, 4] = h45
    H[5, 5] = h55
    H[5, 6] = h56
    g[5] = g5
    H[6, 0] = h06
    H[6, 1] = h16
    H[6, 2] = h26
    H[6, 3] = h36
    H[6, 4] = h46
    H[6, 5] = h56
    H[6, 6] = h66
    g[6] = g6


@numba.njit(cache=True, error_model="numpy")
def _band_pixels(roi, window, off_u, off_v, p, slope_u, slope_v, inside_px, outside_px, xs, ys, zs) -> int:
    """The window pixels of one (S, S) slice in the edge band of shape p[2:5] about the
    reference point, into xs, ys (px, relative to the reference: slice column/row plus
    off_u/off_v) and zs (DN, less the background plane's slope (slope_u, slope_v) DN/px
    times (xs, ys): the model's constant B is then the background at the reference);
    returns their number. The band: first-order signed distance (rho - rho^2) / |S d|
    below ``inside_px`` and above ``-outside_px``."""
    s11, s12, s22 = p[2], p[3], p[4]
    sw = roi.shape[1]
    dist = np.empty(sw)
    count = 0
    for r in range(roi.shape[0]):
        y = r + off_v
        for c in range(sw):  # the row's distances (vectorised), then the compaction
            x = c + off_u
            w1 = s11 * x + s12 * y
            w2 = s12 * x + s22 * y
            q = x * w1 + y * w2
            dist[c] = (math.sqrt(max(q, 0.0)) - q) / math.sqrt(max(w1 * w1 + w2 * w2, 1e-18))
        for c in range(sw):
            d = dist[c]
            if window[r, c] != 0 and d < inside_px and d > -outside_px:
                xs[count] = c + off_u
                ys[count] = y
                zs[count] = roi[r, c] - (slope_u * (c + off_u) + slope_v * y)
                count += 1
    return count


@numba.njit(cache=True, error_model="numpy", nogil=True)
def _fit_stack(
    roi, window, off_u, off_v, slope, start, inside_px, outside_px, table, n_delta, sig2, noise_var, inv_gain,
    max_iterations, tolerance_px, params, cov, ok, iterations, pixels,
) -> None:
    """Fit the T targets of one (T, S, S) stack, one after the other. off_u, off_v:
    (T,) the slice's top-left pixel minus the target's reference point (px); slope:
    (T, 2) DN/px the background plane taken off the values (:func:`_band_pixels`). Writes
    params (T, 7), cov (T, 7, 7), ok, iterations, pixels (T,) (see :func:`fit_discs`).

    One thread: a ``prange`` over the targets halves the time on an idle second
    core, but on this shared 2-core machine a busy one stalls the whole loop
    (8 ms per call seen, against ~1.5 ms serial)."""
    n, sh, sw = roi.shape
    xs = np.empty(sh * sw)
    ys = np.empty(sh * sw)
    zs = np.empty(sh * sw)
    jac = np.empty((8, sh * sw))
    index = np.empty(sh * sw, np.int64)
    H = np.zeros((7, 7))
    L = np.zeros((7, 7))
    g = np.zeros(7)
    step = np.zeros(7)
    e = np.zeros(7)
    col = np.empty(7)
    for t in range(n):
        count = _band_pixels(roi[t], window[t], off_u[t], off_v[t], start[t], slope[t, 0], slope[t, 1],
                             inside_px, outside_px, xs, ys, zs)
        pixels[t] = count
        p = start[t].copy()
        factored = False
        it = 0
        for it in range(1, max_iterations + 1):
            _normal_equations(xs, ys, zs, count, p, table, n_delta, sig2, noise_var, inv_gain, H, g, jac, index)
            factored = _cholesky(H, L)
            if factored:
                _cholesky_solve(L, g, step)
            if not factored or not np.isfinite(step).all():
                step[:] = 0.0
            # trust region: at most 0.5 px for the centre and 20 % for the shape per iteration
            centre = math.hypot(step[0], step[1])
            shape = max(abs(step[2]), abs(step[3]), abs(step[4]))
            shape /= max(max(abs(p[2]), abs(p[3]), abs(p[4])), 1e-12)
            scale = min(1.0, 0.5 / max(centre, 1e-300), 0.2 / max(shape, 1e-300))
            for a in range(7):
                p[a] += step[a] * scale
            if not centre * scale >= tolerance_px:
                break
        iterations[t] = it
        params[t] = p
        # covariance: the inverse Fisher information, (J^T W J)^-1 of the last iteration
        cov[t] = np.nan
        good = np.isfinite(p).all() and p[2] > 0 and p[2] * p[4] - p[3] * p[3] > 0 and p[5] > 0
        if good and factored:
            for a in range(7):
                e[:] = 0.0
                e[a] = 1.0
                _cholesky_solve(L, e, col)
                cov[t, :, a] = col
        ok[t] = good and factored and np.isfinite(cov[t, 0, 0]) and cov[t, 0, 0] > 0 and cov[t, 1, 1] > 0


def fit_discs(
    stacks,
    refs: np.ndarray,
    start: np.ndarray,
    *,
    band: tuple[float, float],
    profile: EdgeProfile,
    noise_sigma_dn: float,
    gain_e_per_dn: float,
    max_iterations: int = 3,
    tolerance_px: float = 1e-4,
) -> DiscFit:
    """Fit the N discs of :class:`crossfield.imaging.blobs.BlobStack` s by Gauss-Newton
    (module docstring), N = all their blobs in stack order.

    The stacks' background plane (``BlobStack.background_gradient``) is taken off the
    values first: the model's background is a constant B, which a vignetting slope
    under the disc would bias.

    refs: (N, 2) reference point of each target (image px); start: (N, 7)
    initial parameters, centre relative to the reference. band:
    ``(inside_px, outside_px)``: only the window pixels less than
    ``inside_px`` inside and ``outside_px`` outside the start's edge
    ``d^T S d = 1`` about the reference, by the first-order signed distance,
    enter the fit (the *edge band*: the pixels left out carry no
    information on the centre or the shape, the profile's slope there is
    nil, only on the amplitude or the background). noise_sigma_dn:
    background noise (DN); gain_e_per_dn: conversion gain. Each target
    iterates until its centre moves by less than ``tolerance_px`` or
    ``max_iterations`` (from the weighted centroid one is as good as three);
    the step is bounded (trust region: 0.5 px for the centre, 20 % for the
    shape); the covariance is the inverse of the last iteration's J^T W J.
    A target whose normal equations are not positive definite (no pixels,
    a degenerate shape) keeps a zero step and is not ``ok``.
    """
    refs = np.asarray(refs, dtype=np.float64).reshape(-1, 2)
    start = np.ascontiguousarray(start, dtype=np.float64)
    n = len(start)
    params = np.empty((n, 7))
    cov = np.empty((n, 7, 7))
    ok = np.zeros(n, np.bool_)
    iterations = np.zeros(n, np.int64)
    pixels = np.zeros(n, np.int64)
    table = np.ascontiguousarray(profile.table).ravel()
    sig2 = profile.blur_sigma_px**2 + 1.0 / 12.0
    inside_px, outside_px = (float(b) for b in band)
    offset = 0
    for st in stacks:
        k = slice(offset, offset + len(st))
        if len(st):
            _fit_stack(
                np.ascontiguousarray(st.roi), np.ascontiguousarray(st.window, dtype=np.uint8),
                st.x0 - refs[k, 0], st.y0 - refs[k, 1],
                np.ascontiguousarray(st.background_gradient, dtype=np.float64),
                start[k], inside_px, outside_px,
                table, profile.table.shape[1], sig2, float(noise_sigma_dn) ** 2, 1.0 / gain_e_per_dn,
                int(max_iterations), float(tolerance_px), params[k], cov[k], ok[k], iterations[k], pixels[k],
            )
        offset += len(st)
    if offset != n:
        raise ValueError(f"start has {n} rows for {offset} blobs")
    return DiscFit(params, cov, ok, iterations, pixels)


def edge_band(stack, t: int, ref: np.ndarray, shape: np.ndarray, band: tuple[float, float]):
    """The pixels :func:`fit_discs` uses for blob ``t`` of ``stack``: du, dv (px, minus
    ``ref`` (2,) image px) and values (DN, less the stack's background plane), (P,) each,
    for the edge shape (3,) px^-2 about ``ref`` and ``band`` = (inside_px, outside_px)
    (as :func:`fit_discs`'s)."""
    size = stack.roi[t].size
    xs, ys, zs = np.empty(size), np.empty(size), np.empty(size)
    p = np.zeros(7)
    p[2:5] = shape
    count = _band_pixels(
        np.ascontiguousarray(stack.roi[t]), np.ascontiguousarray(stack.window[t], dtype=np.uint8),
        float(stack.x0[t] - ref[0]), float(stack.y0[t] - ref[1]), p,
        float(stack.background_gradient[t, 0]), float(stack.background_gradient[t, 1]), float(band[0]), float(band[1]),
        xs, ys, zs,
    )
    return xs[:count], ys[:count], zs[:count]
