"""Rendering of circular targets and sensor noise.

Each target is a flat disc of radius ``r`` (mm) with centre ``c`` and unit
normal ``n`` in the camera frame. Its image is computed exactly: every
sub-sample of every pixel is cast back through the lens (distortion
inverted, :func:`optics.pixel_rays`) and intersected with the target plane,
so the blob is the true perspective image of the circle (an ellipse, bent
slightly by distortion) whose centre is *not* the projection of ``c``.
Coverage is integrated over the pixel (``supersample``^2 samples: the
anti-aliasing), then blurred with a Gaussian PSF (optical blur), scaled to
digital numbers, and noised with photon (shot) and read noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossfield.types import CameraIntrinsics
from crossfield.simulator.optics import pixel_rays, project


@dataclass(frozen=True)
class DiscImage:
    """The noise-free image of one disc: coverage in [0, 1] over a ROI.

    origin: (u0, v0) pixel of coverage[0, 0]. centroid_uv: coverage-weighted
    centre (pixels) = the true blob centre a centroid extractor should find.
    """

    origin: tuple[int, int]
    coverage: np.ndarray
    centroid_uv: np.ndarray


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def render_disc(
    centre: np.ndarray,
    normal: np.ndarray,
    radius_mm: float,
    intrinsics: CameraIntrinsics,
    supersample: int = 8,
    pad_px: int = 6,
) -> DiscImage | None:
    """Exact pixel coverage of a disc (camera frame, mm); None if out of view."""
    e1, e2 = _plane_basis(np.asarray(normal, float))
    phi = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    rim = centre + radius_mm * (np.outer(np.cos(phi), e1) + np.outer(np.sin(phi), e2))
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
    S = supersample
    offsets = (np.arange(S) + 0.5) / S - 0.5
    us = (np.arange(u0, u1 + 1)[:, None] + offsets[None, :]).ravel()
    vs = (np.arange(v0, v1 + 1)[:, None] + offsets[None, :]).ravel()
    U, V = np.meshgrid(us, vs)
    x, y = pixel_rays(U, V, intrinsics)
    n = np.asarray(normal, float)
    # Ray-plane intersection: X = s (x, y, 1), n . (X - c) = 0.
    s = (n @ centre) / (n[0] * x + n[1] * y + n[2])
    dx = s * x - centre[0]
    dy = s * y - centre[1]
    dz = s - centre[2]
    inside = (dx * dx + dy * dy + dz * dz) <= radius_mm * radius_mm
    rows, cols = v1 - v0 + 1, u1 - u0 + 1
    coverage = inside.reshape(rows, S, cols, S).mean(axis=(1, 3))
    total = coverage.sum()
    if total == 0:
        return None
    uu = np.arange(u0, u1 + 1)
    vv = np.arange(v0, v1 + 1)
    centroid = np.array([(coverage.sum(axis=0) @ uu) / total, (coverage.sum(axis=1) @ vv) / total])
    return DiscImage((u0, v0), coverage, centroid)


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
    blur_sigma_px: float,
) -> np.ndarray:
    """Noise-free image (height, width) float32 in DN: background + blurred discs.

    discs: (DiscImage, signal DN above background) pairs.
    """
    width, height = size
    image = background_dn.astype(np.float32, copy=True)
    for disc, signal in discs:
        blurred = cv2.GaussianBlur(disc.coverage.astype(np.float32), (0, 0), blur_sigma_px) * np.float32(signal)
        u0, v0 = disc.origin
        rows, cols = blurred.shape
        a0, b0 = max(v0, 0), max(u0, 0)
        a1, b1 = min(v0 + rows, height), min(u0 + cols, width)
        if a1 <= a0 or b1 <= b0:
            continue
        image[a0:a1, b0:b1] += blurred[a0 - v0 : a1 - v0, b0 - u0 : b1 - u0]
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
