"""Rendering of circular targets and sensor noise.

Each target is a flat disc of radius ``r`` (mm) with centre ``c`` and unit
normal ``n`` in the camera frame. Its image is the true perspective image of
the circle (an ellipse, bent slightly by distortion) whose centre is *not*
the projection of ``c``, formed as in a camera: the rim is projected through
the lens, a Gaussian PSF (optical blur) acts on the blob and each pixel
integrates the result (:func:`render_disc`: an integral along the blob's
outline, by Green's theorem). It is scaled to digital numbers and
noised with photon (shot) and read noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from crossfield.simulator.optics import project
from crossfield.types import CameraIntrinsics


@dataclass(frozen=True)
class DiscImage:
    """The noise-free image of one disc over a ROI, for a unit signal.

    origin: (u0, v0) pixel of image[0, 0]. image: (h, w) float64, the disc's
    image through the PSF and the pixel (a fraction in [0, 1]: multiply by the
    signal in DN). gradient: (2, h, w) px^-1, d image / d (u, v) of a shift of
    the disc in the image (the translation derivatives a Cramer-Rao bound
    needs). centroid_uv: the centre of the blob's area
    (pixels), the exact centroid of its outline = the true blob centre a
    centroid extractor should find (the PSF and the pixel do not move it).
    """

    origin: tuple[int, int]
    image: np.ndarray
    gradient: np.ndarray
    centroid_uv: np.ndarray


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def _pixel_psf(s: np.ndarray, first: int, count: int, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 1-D kernel of a Gaussian PSF (sigma px) times the unit pixel, k = G_sigma (x) box,
    at x = s - j for the ``count`` pixels j = first, first + 1, ... (s: (N,) px; returns (N, count)):
    k(x) = Phi((x + 1/2) / sigma) - Phi((x - 1/2) / sigma), its integral
    K(x) = sigma [psi((x + 1/2) / sigma) - psi((x - 1/2) / sigma)], psi(z) = z Phi(z) + phi(z)
    (psi' = Phi), and its derivative k'(x) = [phi((x + 1/2) / sigma) - phi((x - 1/2) / sigma)] / sigma.
    Each is a difference across a pixel's two boundaries j -+ 1/2, which neighbouring pixels
    share: evaluated once per boundary."""
    z = (s[:, None] - (np.arange(first, first + count + 1) - 0.5)) / sigma  # (N, count + 1)
    P = ndtr(z)
    g = np.exp(-0.5 * z * z) / _SQRT_2PI
    psi = z * P + g
    return P[:, :-1] - P[:, 1:], sigma * (psi[:, :-1] - psi[:, 1:]), (g[:, :-1] - g[:, 1:]) / sigma


_SQRT_2PI = float(np.sqrt(2.0 * np.pi))


def render_disc(
    centre: np.ndarray,
    normal: np.ndarray,
    radius_mm: float,
    intrinsics: CameraIntrinsics,
    blur_sigma_px: float = 0.9,
    pad_px: int = 6,
) -> DiscImage | None:
    """The image of a disc (camera frame, mm) through a Gaussian PSF and the pixel; None if out of view.

    A real camera's order: the PSF (sigma ``blur_sigma_px`` > 0) acts on the
    scene, then each pixel integrates. Pixel (i, j) holds the integral over the
    blob B of k(u - j) k(v - i), k the 1-D PSF-times-pixel kernel of
    :func:`_pixel_psf`:

    1. The rim x(phi) = c + r (cos phi e1 + sin phi e2) is projected through the
       lens (:func:`optics.project`, distortion included) at N equally spaced
       phi: the blob's outline (u(phi), v(phi)), a smooth periodic curve; its
       derivative u'(phi) is the spectral one (FFT).
    2. Green's theorem turns the area integral into one along the outline
       (d/dv [k(u - j) K(v - i)] is the integrand, K' = k):
       image[i, j] = -oint k(u - j) K(v - i) u'(phi) dphi
       (orientation counter-clockwise in (u, v)), by the trapezoidal rule in
       phi, which converges geometrically for a smooth periodic integrand
       (Trefethen & Weideman, SIAM Review 56, 2014): N keeps >= 2 points per
       blur sigma along the outline (error < 1e-9 of the signal). A
       (rows, N) @ (N, cols) product.
    3. Area and centre of the blob from the same rule: A = oint u v' dphi,
       centroid = (oint u^2 v' / 2, -oint v^2 u' / 2) / A.

    The translation derivatives (``DiscImage.gradient``) are the same integrals
    of the shifted kernel: d/du = -oint k'(u - j) K(v - i) u' dphi and
    d/dv = -oint k(u - j) k(v - i) u' dphi.
    """
    if not blur_sigma_px > 0:
        raise ValueError(f"blur_sigma_px must be > 0, got {blur_sigma_px}")
    e1, e2 = _plane_basis(np.asarray(normal, float))

    def outline(n: int) -> np.ndarray:
        phi = np.arange(n) * (2 * np.pi / n)
        return centre + radius_mm * (np.outer(np.cos(phi), e1) + np.outer(np.sin(phi), e2))

    coarse = outline(64)  # the outline's length in px sets N
    if np.any(coarse[:, 2] <= 0):
        return None
    uv = project(coarse, intrinsics)
    perimeter = np.linalg.norm(np.diff(uv, axis=0, append=uv[:1]), axis=1).sum()
    n = int(2 ** np.ceil(np.log2(max(2.0 * perimeter / blur_sigma_px, 128.0))))
    rim = outline(n)
    if np.any(rim[:, 2] <= 0):
        return None
    uv = project(rim, intrinsics)
    width, height = intrinsics.image_size
    u0 = int(np.floor(uv[:, 0].min())) - pad_px
    v0 = int(np.floor(uv[:, 1].min())) - pad_px
    u1 = int(np.ceil(uv[:, 0].max())) + pad_px
    v1 = int(np.ceil(uv[:, 1].max())) + pad_px
    if u1 < 0 or v1 < 0 or u0 >= width or v0 >= height:
        return None
    u, v = uv[:, 0], uv[:, 1]
    wavenumber = 1j * np.fft.fftfreq(n, 1.0 / n)
    du = np.fft.ifft(wavenumber * np.fft.fft(u)).real * (2 * np.pi / n)  # u'(phi) dphi
    dv = np.fft.ifft(wavenumber * np.fft.fft(v)).real * (2 * np.pi / n)
    area = float(u @ dv)  # 3.
    centroid = np.array([0.5 * (u * u) @ dv, -0.5 * (v * v) @ du]) / area
    weight = -du * np.sign(area)  # 2. counter-clockwise
    k_u, _, dk_u = _pixel_psf(u, u0, u1 - u0 + 1, blur_sigma_px)  # (N, cols)
    k_v, K_v, _ = _pixel_psf(v, v0, v1 - v0 + 1, blur_sigma_px)  # (N, rows)
    K_v *= weight[:, None]
    k_v *= weight[:, None]
    image = K_v.T @ k_u
    gradient = np.stack([K_v.T @ dk_u, k_v.T @ k_u])
    return DiscImage((u0, v0), image, gradient, centroid)


@dataclass(frozen=True)
class SensorModel:
    """Sensor of a Basler scA1600-14gm-like camera (12-bit ADC in 16-bit words).

    gain_dn_per_e: conversion gain (DN per electron); read_noise_dn: RMS
    read noise (DN); bit_depth: ADC bits; blur_sigma_px: Gaussian PSF sigma.
    """

    gain_dn_per_e: float = 0.35
    read_noise_dn: float = 2.5
    bit_depth: int = 12
    blur_sigma_px: float = 0.9

    @property
    def max_dn(self) -> int:
        return (1 << self.bit_depth) - 1


def compose_clean_image(
    size: tuple[int, int],
    discs: list[tuple[DiscImage, float]],
    background_dn: np.ndarray,
) -> np.ndarray:
    """Noise-free image (height, width) float32 in DN: background + the discs' images.

    discs: (DiscImage, signal DN above background) pairs.
    """
    width, height = size
    image = background_dn.astype(np.float32, copy=True)
    for disc, signal in discs:
        blob = disc.image.astype(np.float32) * np.float32(signal)
        u0, v0 = disc.origin
        rows, cols = blob.shape
        a0, b0 = max(v0, 0), max(u0, 0)
        a1, b1 = min(v0 + rows, height), min(u0 + cols, width)
        if a1 <= a0 or b1 <= b0:
            continue
        image[a0:a1, b0:b1] += blob[a0 - v0 : a1 - v0, b0 - u0 : b1 - u0]
    return image


def background_image(size: tuple[int, int], level_dn: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth, slightly vignetted background (height, width) float32 in DN."""
    width, height = size
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = ((u - width / 2) / width) ** 2 + ((v - height / 2) / height) ** 2
    tilt = rng.uniform(-0.15, 0.15, size=2).astype(np.float32)
    return level_dn * (1 - 0.5 * r2 + tilt[0] * (u / width - 0.5) + tilt[1] * (v / height - 0.5))


def add_noise(clean_dn: np.ndarray, sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Photon + read noise, quantisation and clipping; returns uint16 DN.

    Shot noise variance in DN^2 is ``gain * signal`` (Poisson in electrons,
    EMVA 1288 linear model), approximated as Gaussian (signal >> 10 e-).
    """
    noise = rng.standard_normal(clean_dn.shape, dtype=np.float32)
    sigma = np.sqrt(clean_dn * np.float32(sensor.gain_dn_per_e) + np.float32(sensor.read_noise_dn**2))
    noisy = clean_dn + noise * sigma
    np.clip(noisy, 0, sensor.max_dn, out=noisy)
    return np.rint(noisy).astype(np.uint16)
