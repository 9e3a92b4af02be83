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


def _pixel_grid(radius_px: float, blur_sigma_px: float, centre_px: tuple[float, float], supersample: int):
    """Pixel centres (n, n) around the disc and the sub-sample offsets of each."""
    half = int(math.ceil(radius_px + 5.0 * blur_sigma_px + 2.0))
    cu, cv = (int(round(c)) for c in centre_px)
    us = np.arange(cu - half, cu + half + 1, dtype=np.float64)
    vs = np.arange(cv - half, cv + half + 1, dtype=np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    return us, vs, offsets


def blurred_disc(
    radius_px: float, blur_sigma_px: float, centre_px: tuple[float, float], supersample: int = 8
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Pixel-integrated blurred disc of unit contrast and its gradient.

    Returns (P, dP_du0, dP_dv0, (us, vs)): P (n, n) in [0, 1] on the pixel grid
    ``us`` (columns) x ``vs`` (rows), px; dP/du0 and dP/dv0 (1/px) its
    derivatives with respect to the disc centre.
    """
    R = _check("radius_px", radius_px)
    s = _check("blur_sigma_px", blur_sigma_px)
    us, vs, offsets = _pixel_grid(R, s, centre_px, supersample)
    # Sub-samples: (rows, S, cols, S).
    x = (us[:, None] + offsets[None, :]).ravel()[None, :] - centre_px[0]
    y = (vs[:, None] + offsets[None, :]).ravel()[:, None] - centre_px[1]
    rho2 = x * x + y * y
    rho = np.sqrt(rho2)
    # P and dP/drho depend on rho only: tabulate them finely (step s / 200) and interpolate.
    table = np.linspace(0.0, float(rho.max()) + s, int(200 * (rho.max() + s) / s) + 2)
    value = np.interp(rho, table, stats.ncx2.cdf(R * R / (s * s), 2, table**2 / (s * s)))
    # dP/drho (Marcum Q_1 derivative), scaled Bessel to avoid overflow.
    slope_table = -(R / (s * s)) * np.exp(-((table - R) ** 2) / (2 * s * s)) * special.ive(1, table * R / (s * s))
    slope = np.interp(rho, table, slope_table)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_t = np.where(rho > 0, x / rho, 0.0)
        sin_t = np.where(rho > 0, y / rho, 0.0)
    # d/du0 P(x - c) = -dP/dx.
    d_u = -slope * cos_t
    d_v = -slope * sin_t
    n_r, n_c, S = len(vs), len(us), supersample

    def integrate(a: np.ndarray) -> np.ndarray:
        return np.broadcast_to(a, (n_r * S, n_c * S)).reshape(n_r, S, n_c, S).mean(axis=(1, 3))

    return integrate(value), integrate(d_u), integrate(d_v), (us, vs)


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
        supersample = int(min(32, max(8, math.ceil(4.0 / s))))
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
