"""A second, independent image model: the model-mismatch renderer (issue 22).

It shares no code with the centroid plugins' models (``crossfield.imaging``) nor
with the default renderer (:mod:`crossfield.simulator.render`,
:mod:`crossfield.simulator.optics`), so that accuracy and uncertainty are checked
on images the estimator's own model did not make. Its parts:

* **Lens** (:class:`TrueLens`): pinhole with a pixel aspect (fx != fy) and
  OpenCV's *full* distortion model - rational radial ``(1 + k1 r^2 + k2 r^4 + k3 r^6)
  / (1 + k4 r^2 + k5 r^4 + k6 r^6)``, tangential p1 p2 and thin prism s1..s4
  (Weng, Cohen & Herniou 1992, eq. (8)-(12); OpenCV's ``projectPoints`` with 12
  coefficients) - of which the estimator's plumb-bob (k1 k2 p1 p2 k3) sees only a
  least-squares fit (:func:`fit_plumb_bob`).
* **Targets**: tilted physical discs, each fine sample of the sensor is traced
  back through the lens (its ray) to the disc's plane and tested against the
  disc's rim there (exact projection, no ellipse assumed), with a linear
  coverage ramp across one sample for anti-aliasing.
* **PSF**: a Gaussian (sigma_g px) convolved with a defocus disc (pillbox of
  radius rho px), applied as its optical transfer function
  ``exp(-2 pi^2 sigma^2 |k|^2) * 2 J1(2 pi rho |k|) / (2 pi rho |k|)`` (Goodman,
  Introduction to Fourier Optics, 3rd ed., eq. (6-32) for the defocus limit,
  Gaussian for the rest), together with the pixel's sensitive area: a centred
  square of side ``sqrt(fill_factor)`` px (``sinc(a k_u) sinc(a k_v)``), on a
  fine grid of ``oversample`` samples per pixel; the pixel value is the
  convolution read at the pixel centre.
* **Sensor** (:class:`MismatchSensor`, EMVA 1288 Release 4.0, sec. 2 linear
  model): photo-electrons with PRNU (relative gain, per pixel), dark signal
  with DSNU (electrons, per pixel), Poisson shot noise of signal plus dark
  electrons, a full well, Gaussian read noise (electrons), conversion gain K
  (DN/e-), black level offset, a 12-bit ADC: ``DN = clip(round(K (e + n_read)
  + offset), 0, 4095)``.

Frames: camera frame OpenCV style (x right, y down, z forward), mm; pixels with
(0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import j1

__all__ = [
    "MismatchSensor",
    "PSF",
    "TrueLens",
    "apply_sensor",
    "conic_of_disc",
    "fit_plumb_bob",
    "fixed_pattern",
    "render_disc_electrons",
]


# --------------------------------------------------------------------------
# The lens
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class TrueLens:
    """Pinhole + OpenCV's 12-coefficient distortion (rational radial, tangential, thin prism).

    fx, fy: focal lengths (px; fy / fx - 1 is the pixel-aspect error); cx, cy:
    principal point (px). k: (k1 .. k6) radial, p: (p1, p2) tangential, s:
    (s1 .. s4) thin prism (unitless, on normalised coordinates). image_size:
    (width, height) px.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k: tuple[float, float, float, float, float, float]
    p: tuple[float, float]
    s: tuple[float, float, float, float]
    image_size: tuple[int, int]

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised (x, y) -> distorted normalised (any shape); Weng et al. 1992, OpenCV's order."""
        k1, k2, k3, k4, k5, k6 = self.k
        p1, p2 = self.p
        s1, s2, s3, s4 = self.s
        r2 = x * x + y * y
        r4 = r2 * r2
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
        return xd, yd

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points (mm) -> (N, 2) px."""
        P = np.asarray(points, dtype=np.float64)
        xd, yd = self.distort(P[:, 0] / P[:, 2], P[:, 1] / P[:, 2])
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def rays(self, u: np.ndarray, v: np.ndarray, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (u, v) (any shape) -> undistorted normalised (x, y); the ray is (x, y, 1).

        Newton's method on ``distort(x, y) = (xd, yd)`` with a numerical 2x2
        Jacobian (central differences, step 1e-6), started at (xd, yd); converges
        to < 1e-12 in 4-6 steps for a C-mount lens's distortion.
        """
        xd = (np.asarray(u, float) - self.cx) / self.fx
        yd = (np.asarray(v, float) - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        h = 1e-6
        for _ in range(iterations):
            fx0, fy0 = self.distort(x, y)
            ex, ey = fx0 - xd, fy0 - yd
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x, y + h)
            a11, a21 = (ax - fx0) / h, (ay - fy0) / h
            a12, a22 = (bx - fx0) / h, (by - fy0) / h
            det = a11 * a22 - a12 * a21
            x = x - (a22 * ex - a12 * ey) / det
            y = y - (-a21 * ex + a11 * ey) / det
        return x, y

    def camera_matrix(self) -> np.ndarray:
        """(3, 3) K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (px)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def opencv_coeffs(self) -> np.ndarray:
        """(12,) ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4``, the order of ``cv2.projectPoints``."""
        return np.array([*self.k[:2], *self.p, self.k[2], *self.k[3:], *self.s], dtype=np.float64)


def fit_plumb_bob(lens: TrueLens, grid: int = 41) -> np.ndarray:
    """The plumb-bob coefficients ``k1 k2 p1 p2 k3`` (5,) that best fit ``lens``'s distortion.

    Linear least squares of ``distort_true(x, y) - (x, y)`` on OpenCV's
    five-coefficient basis over a ``grid x grid`` of normalised points
    covering the image: what a calibration with the plumb-bob model finds
    for this lens, the pinhole held (the residual - thin prism, the rational
    terms' misfit - is the model's error).
    """
    w, h = lens.image_size
    u, v = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
    x = ((u - lens.cx) / lens.fx).ravel()
    y = ((v - lens.cy) / lens.fy).ravel()
    xd, yd = lens.distort(x, y)
    r2 = x * x + y * y
    # xd - x = x (k1 r2 + k2 r4 + k3 r6) + 2 p1 x y + p2 (r2 + 2 x^2); yd - y likewise.
    A = np.zeros((2 * x.size, 5))
    A[0::2] = np.stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3], axis=1)
    A[1::2] = np.stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3], axis=1)
    b = np.empty(2 * x.size)
    b[0::2], b[1::2] = xd - x, yd - y
    coeffs, *_ = np.linalg.lstsq(A, b, rcond=None)
    return coeffs


# --------------------------------------------------------------------------
# The PSF and the pixel
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class PSF:
    """Gaussian (sigma_px) convolved with a defocus pillbox (radius defocus_px), and the
    pixel's sensitive area: a centred square covering ``fill_factor`` of the pixel (0, 1]."""

    sigma_px: float = 0.6
    defocus_px: float = 0.7
    fill_factor: float = 0.6

    def transfer(self, ku: np.ndarray, kv: np.ndarray) -> np.ndarray:
        """The combined transfer function at spatial frequencies (cycles / px), any shape:
        Gaussian x pillbox x pixel aperture (all real, even: no shift of a centroid)."""
        k = np.hypot(ku, kv)
        out = np.exp(-2.0 * np.pi**2 * self.sigma_px**2 * k * k)
        if self.defocus_px > 0:
            z = 2.0 * np.pi * self.defocus_px * k
            safe = np.where(z > 1e-12, z, 1.0)
            out = out * np.where(z > 1e-12, 2.0 * j1(safe) / safe, 1.0)
        a = np.sqrt(self.fill_factor)
        # the aperture's integral over its area a^2: sinc * area (np.sinc(x) = sin(pi x) / (pi x))
        return out * (a * a) * np.sinc(a * ku) * np.sinc(a * kv)


def _blur_and_sample(irradiance: np.ndarray, oversample: int, psf: PSF) -> np.ndarray:
    """Fine irradiance (H s, W s) (signal per px^2, samples at pixel centre + (j - (s-1)/2) / s)
    -> (H, W) pixel values: (E * PSF * aperture) read at the pixel centres, by FFT.

    The fine grid is padded by the caller; the convolution is circular (a blob with
    its margin does not wrap). Pixel centres fall between fine samples for an even
    ``oversample``: the read-out is a half-sample shift, done in Fourier space."""
    s = oversample
    H, W = irradiance.shape
    ku = np.fft.rfftfreq(W, d=1.0 / s)[None, :]  # cycles per px (real input: half the u spectrum)
    kv = np.fft.fftfreq(H, d=1.0 / s)[:, None]
    spectrum = np.fft.rfft2(irradiance) * psf.transfer(ku, kv)
    # pixel centre of pixel 0 is at fine coordinate (s - 1) / 2: shift by that (Fourier shift theorem)
    shift = (s - 1) / 2.0 / s  # px
    spectrum *= np.exp(2j * np.pi * ku * shift) * np.exp(2j * np.pi * kv * shift)
    # the inverse DFT of DFT(E) * OTF is sum_j E_j K(x - x_j) / s^2: the convolution integral, a fine
    # sample covering 1/s^2 px^2
    blurred = np.fft.irfft2(spectrum, s=(H, W))
    return blurred[::s, ::s]


# --------------------------------------------------------------------------
# A tilted disc
# --------------------------------------------------------------------------


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, n)
    e1 /= np.linalg.norm(e1)
    return n, e1, np.cross(n, e1)


def render_disc_electrons(
    centre: np.ndarray,
    normal: np.ndarray,
    radius_mm: float,
    lens: TrueLens,
    psf: PSF,
    oversample: int = 8,
    pad_px: int = 6,
) -> tuple[tuple[int, int], np.ndarray] | None:
    """The image of a disc of unit radiance over a ROI: (origin (u0, v0), (h, w) image), None if
    out of view.

    centre (3,) and normal (3,) in this camera's frame (mm). The image is in px^2
    of the blob's area per pixel (the sum over pixels is ``fill_factor`` times the
    blob's image area in px^2 when the aperture is the whole pixel: 1 x area):
    multiply by the irradiance in electrons per px^2. Each fine sample's ray is
    intersected with the disc's plane (``t = (n . c) / (n . ray)``) and its
    distance rho to the centre compared with the radius, with a linear ramp
    ``clip(1/2 + (r - rho) / |d rho|)`` across one sample (|d rho| the change of
    rho from sample to sample), then blurred and read out (:class:`PSF`).
    """
    n, e1, e2 = _plane_axes(normal)
    c = np.asarray(centre, float)
    phi = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    rim = c + radius_mm * (np.outer(np.cos(phi), e1) + np.outer(np.sin(phi), e2))
    if np.any(rim[:, 2] <= 0):
        return None
    uv = lens.project(rim)
    blur = 3.0 * psf.sigma_px + psf.defocus_px + 1.0
    u0 = int(np.floor(uv[:, 0].min() - blur)) - pad_px
    v0 = int(np.floor(uv[:, 1].min() - blur)) - pad_px
    u1 = int(np.ceil(uv[:, 0].max() + blur)) + pad_px
    v1 = int(np.ceil(uv[:, 1].max() + blur)) + pad_px
    width, height = lens.image_size
    if u1 < 0 or v1 < 0 or u0 >= width or v0 >= height:
        return None
    cols, rows = u1 - u0 + 1, v1 - v0 + 1
    s = oversample
    fine_u = u0 + (np.arange(cols * s) - (s - 1) / 2.0) / s
    fine_v = v0 + (np.arange(rows * s) - (s - 1) / 2.0) / s
    x, y = _local_rays(lens, fine_u, fine_v)
    denominator = n[0] * x + n[1] * y + n[2]
    t = (n @ c) / denominator  # ray (x, y, 1) meets the plane at t (x, y, 1)
    d = np.stack([t * x - c[0], t * y - c[1], t - c[2]])
    rho = np.hypot(np.tensordot(e1, d, 1), np.tensordot(e2, d, 1))
    step = np.hypot(*np.gradient(rho))  # mm per fine sample
    coverage = np.clip(0.5 + (radius_mm - rho) / np.maximum(step, 1e-12), 0.0, 1.0)
    coverage[~(t > 0)] = 0.0  # the plane behind the camera (or parallel to the ray)
    return (u0, v0), _blur_and_sample(coverage, s, psf)


def _local_rays(lens: TrueLens, fine_u: np.ndarray, fine_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rays (x, y) of the fine grid ``fine_v x fine_u`` (px): exact rays (:meth:`TrueLens.rays`)
    on a 9 x 9 grid over the ROI, fitted by a bicubic polynomial in the ROI's scaled coordinates
    (10 terms, least squares) and evaluated on the grid; the lens's distortion is smooth over a
    ROI of < 100 px, and the fit reproduces the exact rays to < 1e-10 (normalised, < 1e-6 px)."""
    cu, hu = 0.5 * (fine_u[0] + fine_u[-1]), 0.5 * (fine_u[-1] - fine_u[0])
    cv, hv = 0.5 * (fine_v[0] + fine_v[-1]), 0.5 * (fine_v[-1] - fine_v[0])
    g = np.linspace(-1, 1, 9)
    a, b = np.meshgrid(g, g)
    x, y = lens.rays(cu + hu * a.ravel(), cv + hv * b.ravel(), iterations=8)

    def basis(p: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
        return [np.ones_like(p), p, q, p * p, p * q, q * q, p**3, p * p * q, p * q * q, q**3]

    B = np.stack(basis(a.ravel(), b.ravel()), axis=1)
    coeff, *_ = np.linalg.lstsq(B, np.stack([x, y], axis=1), rcond=None)
    p = ((fine_u - cu) / hu)[None, :]
    q = ((fine_v - cv) / hv)[:, None]
    terms = basis(p, q)
    X = sum(c * t for c, t in zip(coeff[:, 0], terms))
    Y = sum(c * t for c, t in zip(coeff[:, 1], terms))
    shape = (fine_v.size, fine_u.size)
    return np.broadcast_to(X, shape), np.broadcast_to(Y, shape)


def conic_of_disc(centre: np.ndarray, normal: np.ndarray, radius_mm: float, K: np.ndarray) -> np.ndarray:
    """(3, 3) image conic of a disc's rim through a distortion-free camera K (Hartley &
    Zisserman 2.2.3: C' = H^-T C H^-1, H = K [e1 e2 c] maps plane coordinates to pixels,
    C = diag(1, 1, -r^2)). Its centre -A^-1 b and area pi (b^T A^-1 b - c) / sqrt(det A)
    (A = C'[:2, :2], b = C'[:2, 2], c = C'[2, 2]) are the blob's exact area centroid and area."""
    _, e1, e2 = _plane_axes(normal)
    H = K @ np.column_stack([e1, e2, np.asarray(centre, float)])
    Hinv = np.linalg.inv(H)
    C = Hinv.T @ np.diag([1.0, 1.0, -radius_mm**2]) @ Hinv
    return C / C[0, 0]


# --------------------------------------------------------------------------
# The sensor (EMVA 1288)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class MismatchSensor:
    """EMVA 1288 linear camera: electrons -> DN.

    gain_dn_per_e: conversion gain K (DN/e-); read_noise_e: temporal dark noise
    sigma_d (e-); dark_e: mean dark signal mu_d (e-, per exposure); dsnu_e: DSNU,
    the spatial std of the dark signal (e-); prnu: PRNU, the spatial relative std
    of the gain; full_well_e: saturation capacity (e-); offset_dn: black level
    (DN); bit_depth: ADC bits (12: 0..4095 DN).
    """

    gain_dn_per_e: float = 0.4
    read_noise_e: float = 7.0
    dark_e: float = 30.0
    dsnu_e: float = 4.0
    prnu: float = 0.006
    full_well_e: float = 10000.0
    offset_dn: float = 40.0
    bit_depth: int = 12

    @property
    def max_dn(self) -> int:
        return (1 << self.bit_depth) - 1


def fixed_pattern(shape: tuple[int, int], sensor: MismatchSensor, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's fixed pattern: per-pixel gain (1 + PRNU N(0, 1)) and dark signal
    (mu_d + DSNU N(0, 1), e-, >= 0), each (h, w) float64."""
    gain = 1.0 + sensor.prnu * rng.standard_normal(shape)
    dark = np.maximum(sensor.dark_e + sensor.dsnu_e * rng.standard_normal(shape), 0.0)
    return gain, dark


def apply_sensor(
    photo_e: np.ndarray,
    gain: np.ndarray,
    dark_e: np.ndarray,
    sensor: MismatchSensor,
    rng: np.random.Generator,
) -> np.ndarray:
    """One exposure: mean photo-electrons (h, w) -> uint16 DN (EMVA 1288 eq. (1)-(6)).

    e = min(Poisson(photo_e * gain + dark_e), full well); DN = clip(round(K (e +
    N(0, sigma_d^2)) + offset), 0, 2^bits - 1). Mean ``K (mu_e + mu_d) + offset``,
    temporal variance ``K^2 (mu_e + mu_d + sigma_d^2) + 1/12`` (quantisation) below
    saturation.
    """
    mean_e = np.maximum(photo_e * gain + dark_e, 0.0)
    electrons = np.minimum(rng.poisson(mean_e).astype(np.float64), sensor.full_well_e)
    electrons += sensor.read_noise_e * rng.standard_normal(photo_e.shape)
    dn = np.rint(sensor.gain_dn_per_e * electrons + sensor.offset_dn)
    return np.clip(dn, 0, sensor.max_dn).astype(np.uint16)
