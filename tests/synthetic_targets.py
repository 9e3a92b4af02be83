"""Synthetic target images with known sub-pixel ellipse centres (test/bench helper).

Renders what a 12-bit Basler scA1600-14gm-like camera sees of circular
retro-reflective targets: uniform ellipses, anti-aliased by super-sampling,
blurred by a Gaussian PSF (cv2.GaussianBlur), on a dark background, with
photon (Poisson, through a gain in e-/DN) and read (Gaussian) noise.

Pixel convention: (0, 0) is the centre of the top-left pixel (OpenCV), so
pixel (row r, column c) covers u in [c - 0.5, c + 0.5], v in [r - 0.5, r + 0.5].
The truth for a centroid is the centre (u0, v0) of the rendered image
ellipse (not the projection of a circle's centre: that differs by the
perspective bias, which the centroid stage does not model).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

HEIGHT, WIDTH = 1236, 1626


@dataclass(frozen=True)
class Ellipse:
    """An image ellipse: centre (u0, v0) px, semi-axes a >= b px, angle theta rad
    (of the a axis from +u towards +v), plateau amplitude in DN above background."""

    u0: float
    v0: float
    a: float
    b: float
    theta: float = 0.0
    amplitude: float = 3000.0


def coverage(ellipse: Ellipse, shape: tuple[int, int], supersample: int = 8) -> tuple[np.ndarray, int, int]:
    """Fraction of each pixel inside ``ellipse`` (super-sampled), on the ROI that holds it.

    Returns (coverage (h, w) float32 in [0, 1], row0, col0) of the ROI; the ROI
    has a margin of 8 px for the blur and is clipped to ``shape``.
    """
    e = ellipse
    margin = 8
    r0 = max(int(np.floor(e.v0 - e.a)) - margin, 0)
    r1 = min(int(np.ceil(e.v0 + e.a)) + margin + 1, shape[0])
    c0 = max(int(np.floor(e.u0 - e.a)) - margin, 0)
    c1 = min(int(np.ceil(e.u0 + e.a)) + margin + 1, shape[1])
    if r1 <= r0 or c1 <= c0:
        return np.zeros((0, 0), np.float32), r0, c0
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(c0, c1)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(r0, r1)[:, None] + offsets[None, :]).ravel()
    du = u[None, :] - e.u0
    dv = v[:, None] - e.v0
    c, sn = np.cos(e.theta), np.sin(e.theta)
    x = du * c + dv * sn
    y = -du * sn + dv * c
    inside = (x / e.a) ** 2 + (y / e.b) ** 2 <= 1.0
    cov = inside.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3)).astype(np.float32)
    return cov, r0, c0


def render(
    ellipses: list[Ellipse],
    rng: np.random.Generator | None,
    *,
    shape: tuple[int, int] = (HEIGHT, WIDTH),
    background_dn: float = 150.0,
    blur_sigma_px: float = 0.9,
    read_noise_dn: float = 3.0,
    gain_e_per_dn: float = 2.86,
    bit_depth: int = 12,
    extra: np.ndarray | None = None,
    supersample: int = 8,
) -> np.ndarray:
    """A (H, W) uint16 image of ``ellipses`` plus optional ``extra`` signal (DN).

    rng None gives the noise-free image (still rounded to integer DN).
    supersample: sub-samples per pixel and axis of the coverage (8: edge
    quantised to 1/8 px, which moves a blob's centre by ~0.003 px from
    (u0, v0); 32 for centroid-efficiency work).
    Photon noise: signal_dn * gain is Poisson in electrons; read noise is
    Gaussian with ``read_noise_dn`` standard deviation in DN.
    """
    signal = np.zeros(shape, np.float32)
    for e in ellipses:
        cov, r0, c0 = coverage(e, shape, supersample)
        if cov.size:
            h, w = cov.shape
            signal[r0 : r0 + h, c0 : c0 + w] += cov * np.float32(e.amplitude)
    if extra is not None:
        signal += extra.astype(np.float32)
    if blur_sigma_px > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
    image = signal.astype(np.float64) + background_dn
    if rng is not None:
        electrons = rng.poisson(np.clip(image, 0, None) * gain_e_per_dn)
        image = electrons / gain_e_per_dn + rng.normal(0.0, read_noise_dn, shape)
    top = 2**bit_depth - 1
    return np.clip(np.rint(image), 0, top).astype(np.uint16)


def random_targets(
    rng: np.random.Generator,
    count: int = 20,
    *,
    shape: tuple[int, int] = (HEIGHT, WIDTH),
    diameter_px: tuple[float, float] = (30.0, 60.0),
    min_roundness: float = 0.7,
    amplitude_dn: tuple[float, float] = (2400.0, 3400.0),
) -> list[Ellipse]:
    """``count`` non-overlapping random ellipses away from the border."""
    out: list[Ellipse] = []
    tries = 0
    while len(out) < count:
        tries += 1
        if tries > 10000:
            raise RuntimeError("could not place the targets")
        a = rng.uniform(*diameter_px) / 2
        b = a * rng.uniform(min_roundness, 1.0)
        u0 = rng.uniform(a + 20, shape[1] - a - 20)
        v0 = rng.uniform(a + 20, shape[0] - a - 20)
        if any(np.hypot(u0 - e.u0, v0 - e.v0) < a + e.a + 25 for e in out):
            continue
        out.append(Ellipse(u0, v0, a, b, rng.uniform(0, np.pi), rng.uniform(*amplitude_dn)))
    return out


def distractors(shape: tuple[int, int] = (HEIGHT, WIDTH)) -> dict[str, list[Ellipse]]:
    """Non-target blobs by the reason the centroid stage should reject them for
    (saturation: amplitude above the 12-bit range), placed along the top of the frame."""
    h, w = shape
    return {
        "too_small": [Ellipse(60.0, 40.0, 1.0, 1.0, 0.0, 1500.0), Ellipse(140.4, 45.6, 1.3, 0.9, 0.3, 900.0)],
        "not_round": [Ellipse(300.0, 50.0, 30.0, 4.0, 0.2, 2500.0)],
        "saturated": [Ellipse(480.0, 60.0, 18.0, 16.0, 1.0, 6000.0)],
        "touches_border": [
            Ellipse(w - 8.0, h / 2, 20.0, 18.0, 0.0, 2800.0),
            Ellipse(w / 2, 5.0, 15.0, 15.0, 0.0, 2800.0),
        ],
    }
