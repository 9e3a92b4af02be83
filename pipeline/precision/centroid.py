"""Cramér-Rao bound of a target centroid: a blurred disc image on a background.

Image model (the simulator's, ``crossfield.simulator.render``): a flat disc of
radius ``R`` px with its centre at ``c = (u0, v0)``, blurred by a Gaussian PSF
of standard deviation ``s`` px, integrated over each pixel, scaled by the
contrast ``A`` (DN above background) and added to a background ``b`` (DN)::

    mu_j(theta) = b + A * integral_{pixel j} P(x - c) dx,   theta = (u0, v0, A, b)
    P(x) = Pr(|x + n| <= R), n ~ N(0, s^2 I)  (the blurred disc, a non-central chi^2 cdf)

Noise: independent Gaussian per pixel with the EMVA 1288 linear variance
``var_j = gain * mu_j + read^2`` (DN^2; photon noise in DN plus read noise).
For a Gaussian whose variance depends on the mean, the Fisher information is
(Kay, *Fundamentals of Statistical Signal Processing I*, eq. 3.31)::

    F = sum_j  d(mu_j) d(mu_j)^T * (1 / var_j + gain^2 / (2 var_j^2))

and the bound on the centre is ``sqrt(diag(F^-1))[:2]`` (the amplitude and the
background are estimated too: nuisance parameters). The gradient of the blurred
disc is analytic: ``dP/drho = -(R / s^2) exp(-(rho^2 + R^2) / (2 s^2)) I_1(rho R / s^2)``
(derivative of Marcum's Q_1), integrated over each pixel by an S x S midpoint rule.

Closed form for checking: a large disc (R >> s) is edge-limited; each edge
element is a 1-D blurred step, and with constant noise sigma_n::

    sigma_u = (sigma_n / A) * sqrt(2 s_eff / (sqrt(pi) R)),   s_eff^2 = s^2 + 1/12

(:func:`edge_limited_bound`; the 1/12 px^2 is the pixel's box integration).
All lengths in pixels, intensities in DN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special, stats


@dataclass(frozen=True)
class NoiseModel:
    """Pixel noise: variance ``gain_dn_per_e * mean_dn + read_noise_dn^2`` (DN^2).

    gain_dn_per_e: conversion gain (DN per electron; 0 = read noise only).
    read_noise_dn: RMS read noise (DN).
    """

    gain_dn_per_e: float = 0.35
    read_noise_dn: float = 2.5

    def variance(self, mean_dn: np.ndarray) -> np.ndarray:
        """Per-pixel noise variance (DN^2) at mean level ``mean_dn`` (DN)."""
        return self.gain_dn_per_e * np.maximum(mean_dn, 0.0) + self.read_noise_dn**2


@dataclass(frozen=True)
class CentroidBound:
    """Cramér-Rao bound of a disc centroid: sigma_u, sigma_v (px) and the (4, 4)
    Fisher information of (u0, v0, A, b) (px, px, DN, DN)."""

    sigma_u_px: float
    sigma_v_px: float
    fisher: np.ndarray


def _check(name: str, value: float, minimum: float = 0.0, strict: bool = True) -> float:
    value = float(value)
    if not math.isfinite(value) or value < minimum or (strict and value == minimum):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum}, got {value!r}")
    return value


def blurred_disc(
    radius_px: float, blur_sigma_px: float, centre_px: tuple[float, float], supersample: int = 8
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Pixel-integrated blurred disc of unit contrast and its gradient.

    Returns (P, dP_du0, dP_dv0, (us, vs)): P (n, n) in [0, 1] on the pixel grid
    ``us`` (columns) x ``vs`` (rows), px; dP/du0 and dP/dv0 (1/px) its
    derivatives with respect to the disc centre. Only pixels within
    ``4 sigma + 1`` px of the rim are integrated (``supersample``^2 midpoints);
    the others are 0 or 1 with a zero gradient (to ~1e-7).
    """
    R = _check("radius_px", radius_px)
    s = _check("blur_sigma_px", blur_sigma_px)
    half = int(math.ceil(R + 5.0 * s + 2.0))
    cu, cv = (int(round(c)) for c in centre_px)
    us = np.arange(cu - half, cu + half + 1, dtype=np.float64)
    vs = np.arange(cv - half, cv + half + 1, dtype=np.float64)
    dx = us[None, :] - centre_px[0]
    dy = vs[:, None] - centre_px[1]
    rho_pix = np.sqrt(dx * dx + dy * dy)
    P = (rho_pix < R).astype(np.float64)
    d_u = np.zeros_like(P)
    d_v = np.zeros_like(P)
    edge = np.abs(rho_pix - R) < 4.0 * s + 1.0
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ox, oy = (a.ravel() for a in np.meshgrid(offsets, offsets))
    x = np.broadcast_to(dx, P.shape)[edge][:, None] + ox[None, :]  # (n_edge, S^2) sub-samples
    y = np.broadcast_to(dy, P.shape)[edge][:, None] + oy[None, :]
    rho = np.sqrt(x * x + y * y)
    # P and dP/drho depend on rho only: tabulate them finely (step s / 200) and interpolate.
    low, top = max(float(rho.min()) - s, 0.0), float(rho.max()) + s
    table = np.linspace(low, top, int(200 * (top - low) / s) + 2)
    value = np.interp(rho, table, stats.ncx2.cdf(R * R / (s * s), 2, table**2 / (s * s)))
    # dP/drho (Marcum Q_1 derivative), scaled Bessel to avoid overflow.
    slope_table = -(R / (s * s)) * np.exp(-((table - R) ** 2) / (2 * s * s)) * special.ive(1, table * R / (s * s))
    slope = np.interp(rho, table, slope_table)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_t = np.where(rho > 0, x / rho, 0.0)
        sin_t = np.where(rho > 0, y / rho, 0.0)
    # d/du0 P(x - c) = -dP/dx; the pixel value is the mean over its sub-samples.
    P[edge] = value.mean(axis=1)
    d_u[edge] = (-slope * cos_t).mean(axis=1)
    d_v[edge] = (-slope * sin_t).mean(axis=1)
    return P, d_u, d_v, (us, vs)


def centroid_crb(
    radius_px: float,
    blur_sigma_px: float,
    contrast_dn: float,
    background_dn: float,
    noise: NoiseModel = NoiseModel(),
    *,
    centre_px: tuple[float, float] = (0.0, 0.0),
    supersample: int | None = None,
) -> CentroidBound:
    """Cramér-Rao bound (px per axis) on the centre of a blurred disc (module docstring).

    radius_px: disc radius in the image (px); blur_sigma_px: Gaussian PSF sigma
    (px, > 0); contrast_dn: disc signal above background (DN); background_dn:
    background level (DN); noise: the pixel noise model; centre_px: the disc
    centre (its sub-pixel phase changes the bound slightly).
    """
    contrast = _check("contrast_dn", contrast_dn)
    background = _check("background_dn", background_dn, strict=False)
    s = _check("blur_sigma_px", blur_sigma_px)
    if supersample is None:
        supersample = int(min(32, max(6, math.ceil(6.0 / s))))
    P, d_u, d_v, _ = blurred_disc(radius_px, s, centre_px, supersample)
    mu = background + contrast * P
    var = noise.variance(mu)
    if np.any(var <= 0):
        raise ValueError("the noise model gives zero variance: set read_noise_dn > 0 or gain_dn_per_e > 0")
    weight = 1.0 / var + noise.gain_dn_per_e**2 / (2.0 * var * var)
    grads = np.stack([contrast * d_u, contrast * d_v, P, np.ones_like(P)])  # d mu / d theta
    G = grads.reshape(4, -1)
    F = (G * weight.ravel()) @ G.T
    cov = np.linalg.inv(F)
    return CentroidBound(float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1])), F)


def edge_limited_bound(radius_px: float, blur_sigma_px: float, contrast_dn: float, noise_sigma_dn: float) -> float:
    """1-D edge-limited centroid bound (px per axis) of a large disc (R >> sigma) with
    constant pixel noise ``noise_sigma_dn``: ``(sigma_n / A) sqrt(2 s_eff / (sqrt(pi) R))``,
    ``s_eff^2 = blur^2 + 1/12`` (module docstring)."""
    s_eff = math.sqrt(blur_sigma_px**2 + 1.0 / 12.0)
    return noise_sigma_dn / contrast_dn * math.sqrt(2.0 * s_eff / (math.sqrt(math.pi) * radius_px))
