"""Target blob detection shared by the centroid plugins (``docs/centroids.md``).

One job: find the bright, target-like blobs of one image and hand each one
over as a small region of interest (ROI) with its masks and local
background, so that a centroid plugin only does its sub-pixel work there.

Steps (all full-frame work is on integer data; nothing full-frame is float):

1. Background and noise from a strided subsample (every ``stride``-th row and
   column): median and interquartile range of a histogram, interpolated
   within the 1-DN bins; noise sigma = IQR / 1.349 (Gaussian). Targets cover a
   few per cent of the frame, far below the 25 % breakdown of the quartiles.
2. Threshold = background + ``threshold_sigma`` * noise, compared on the
   uint16 frame straight into a 0/1 uint8 mask (``numpy`` ``>`` viewed as
   uint8, no copy).
3. Outer contours of the mask (``cv2.findContours``, ``RETR_EXTERNAL``). On
   OpenCV 5 this is several times faster than ``connectedComponentsWithStats``
   on a 2-Mpixel frame; each contour, filled, is one blob.
4. Per blob, in an ROI = bounding box + ``dilate_px`` + ``ring_px``:
   rejection tests (border, area, saturation), then the masks the centroid
   plugins need: ``window`` (blob dilated by ``dilate_px`` to take in the
   blurred edge below the threshold, minus other blobs' pixels) and the
   background ``ring`` (the rest of the ROI, minus any pixel above the
   threshold); the local background is the mean of the ring. The raw
   moments of the image over the window and of the window itself give the
   background-subtracted second moments, hence the roundness test.

Pixel coordinates: (0, 0) is the centre of the top-left pixel (OpenCV), u to
the right (column), v down (row).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from crossfield.types import RejectedBlob

__all__ = [
    "REASONS",
    "Background",
    "Blob",
    "BlobDetector",
    "DetectorOptions",
    "estimate_background",
    "sort_order",
    "sort_rejected",
]

#: Rejection reasons, in the order the tests are applied.
REASONS: tuple[str, ...] = ("touches_border", "too_small", "too_large", "saturated", "no_signal", "not_round")

_IQR_TO_SIGMA = 1.0 / 1.3489795  # IQR of a unit Gaussian
_QUANTISATION_SIGMA = 1.0 / math.sqrt(12.0)  # noise floor: 1-DN rounding


@dataclass(frozen=True)
class Background:
    """Global background level and noise of one image, in DN."""

    level_dn: float
    sigma_dn: float
    threshold_dn: int  # pixels strictly above this are blob pixels


@dataclass(slots=True)
class Blob:
    """One accepted blob, ready for sub-pixel work.

    x0, y0: column and row of the ROI's top-left pixel in the image.
    roi: (h, w) view of the image (uint16, not a copy; do not write).
    component: (h, w) uint8 0/1, the blob: its outer contour, filled.
    window: (h, w) uint8 0/1, component dilated by ``dilate_px``, minus the
    pixels of other blobs: where the sub-pixel estimators may look.
    window_count: pixels in ``window``. window_moments: ``cv2.moments`` of the
    raw image (DN, not background-subtracted) times ``window``; mask_moments:
    ``cv2.moments`` of ``window``; both in ROI coordinates.
    background_dn: local background (mean of the ring), DN.
    ring_count: number of ring pixels the background is the mean of.
    area_px: pixels in ``component``. roundness: minor/major axis ratio from
    the second central moments of the background-subtracted intensity over
    the window. peak_dn: highest raw value in the component minus
    ``background_dn``. saturated: a component pixel is at the saturation
    level. uv: intensity-weighted centroid (u, v), image pixels.
    """

    x0: int
    y0: int
    roi: np.ndarray
    component: np.ndarray
    window: np.ndarray
    window_count: int
    window_moments: dict
    mask_moments: dict
    background_dn: float
    ring_count: int
    area_px: int
    roundness: float
    peak_dn: float
    saturated: bool
    uv: tuple[float, float]


@dataclass(frozen=True)
class DetectorOptions:
    """Detection options shared by the centroid plugins (see ``docs/centroids.md``)."""

    threshold_sigma: float = 8.0
    min_area_px: int = 50
    max_area_px: int = 20000
    min_roundness: float = 0.5
    reject_saturated: bool = True
    reject_border: bool = True
    bit_depth: int = 12
    dilate_px: int = 2
    ring_px: int = 3
    stride: int = 8

    def __post_init__(self) -> None:
        if not self.threshold_sigma > 0:
            raise ValueError(f"threshold_sigma must be > 0, got {self.threshold_sigma}")
        if self.min_area_px < 1 or self.max_area_px < self.min_area_px:
            raise ValueError(
                f"need 1 <= min_area_px <= max_area_px, got {self.min_area_px}, {self.max_area_px}"
            )
        if not 0.0 <= self.min_roundness <= 1.0:
            raise ValueError(f"min_roundness must be in [0, 1], got {self.min_roundness}")
        if not 1 <= self.bit_depth <= 16:
            raise ValueError(f"bit_depth must be in 1..16, got {self.bit_depth}")
        if self.dilate_px < 0 or self.ring_px < 1 or self.stride < 1:
            raise ValueError("need dilate_px >= 0, ring_px >= 1, stride >= 1")

    @property
    def saturation_dn(self) -> int:
        """The highest DN of the bit depth: a pixel there is saturated."""
        return 2**self.bit_depth - 1


def _histogram_quantile(cdf: np.ndarray, q: float) -> float:
    """Quantile ``q`` of integer data from its cumulative histogram ``cdf``,
    interpolated linearly inside the 1-DN bin [v - 0.5, v + 0.5]."""
    target = q * cdf[-1]
    v = int(np.searchsorted(cdf, target, side="left"))
    below = cdf[v - 1] if v > 0 else 0
    inside = cdf[v] - below
    return v - 0.5 + (target - below) / inside if inside else float(v)


def estimate_background(image: np.ndarray, threshold_sigma: float, stride: int = 8) -> Background:
    """Robust background level and noise (DN) from a strided subsample of ``image``.

    Median and interquartile range of every ``stride``-th pixel of every
    ``stride``-th row; sigma = IQR / 1.349, floored at the 1-DN rounding noise.
    """
    sample = image[::stride, ::stride]
    if sample.dtype.kind in "ui":
        counts = np.bincount(sample.ravel().astype(np.intp, copy=False))
        cdf = np.cumsum(counts)
        level = _histogram_quantile(cdf, 0.5)
        iqr = _histogram_quantile(cdf, 0.75) - _histogram_quantile(cdf, 0.25)
    else:
        q25, level, q75 = np.percentile(sample, [25.0, 50.0, 75.0])
        iqr = q75 - q25
    sigma = max(iqr * _IQR_TO_SIGMA, _QUANTISATION_SIGMA)
    return Background(float(level), float(sigma), math.floor(level + threshold_sigma * sigma))


class BlobDetector:
    """Finds target-like blobs; ``detect(image)`` -> (blobs, rejected, background)."""

    def __init__(self, options: DetectorOptions) -> None:
        self.options = options
        d = options.dilate_px
        # A digital disc of radius d + 0.5, symmetric under flips and transposition
        # (OpenCV's MORPH_ELLIPSE kernels are not).
        y, x = np.mgrid[-d : d + 1, -d : d + 1]
        self._kernel = (x * x + y * y <= (d + 0.5) ** 2).astype(np.uint8) if d > 0 else None

    def detect(self, image: np.ndarray) -> tuple[list[Blob], list[RejectedBlob], Background]:
        """Blobs of one (H, W) image (integer DN, any bit depth up to 16).

        Returns the accepted blobs (in contour order), the rejected ones with
        their reasons, and the global background estimate.
        """
        if not isinstance(image, np.ndarray) or image.ndim != 2:
            raise ValueError(f"expected a 2-D image array, got {getattr(image, 'shape', type(image))}")
        opts = self.options
        background = estimate_background(image, opts.threshold_sigma, opts.stride)
        # Integer threshold: no float conversion of the frame; bool -> uint8 view.
        mask = (image > background.threshold_dn).view(np.uint8)
        if not mask.flags.c_contiguous:
            mask = np.ascontiguousarray(mask)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)

        height, width = image.shape
        margin = opts.dilate_px + opts.ring_px
        sat = opts.saturation_dn
        min_area, max_area, min_roundness = opts.min_area_px, opts.max_area_px, opts.min_roundness
        reject_border, reject_saturated = opts.reject_border, opts.reject_saturated
        kernel = self._kernel
        blobs: list[Blob] = []
        rejected: list[RejectedBlob] = []
        for contour in contours:
            x, y, w, h = cv2.boundingRect(contour)
            box_uv = (x + (w - 1) / 2, y + (h - 1) / 2)
            if reject_border and (x == 0 or y == 0 or x + w == width or y + h == height):
                rejected.append(RejectedBlob(box_uv, "touches_border"))
                continue
            if w * h < min_area:  # fewer pixels than its box: surely too small
                rejected.append(RejectedBlob(box_uv, "too_small"))
                continue
            x0, y0 = max(x - margin, 0), max(y - margin, 0)
            x1, y1 = min(x + w + margin, width), min(y + h + margin, height)
            component = np.zeros((y1 - y0, x1 - x0), np.uint8)
            cv2.drawContours(component, (contour,), -1, 1, thickness=-1, offset=(-x0, -y0))
            area = cv2.countNonZero(component)
            if area < min_area:
                rejected.append(RejectedBlob(box_uv, "too_small"))
                continue
            if area > max_area:
                rejected.append(RejectedBlob(box_uv, "too_large"))
                continue
            roi = image[y0:y1, x0:x1]
            mask_roi = mask[y0:y1, x0:x1]
            # Pixels of other blobs in this ROI (above the threshold, outside
            # the contour); usually none, which allows the short paths below.
            others = cv2.countNonZero(cv2.subtract(mask_roi, component))
            if others:
                max_value = cv2.minMaxLoc(roi, component)[1]
            else:  # everything outside the blob is below the threshold
                max_value = float(roi.max())
            saturated = max_value >= sat
            if saturated and reject_saturated:
                rejected.append(RejectedBlob(box_uv, "saturated"))
                continue
            dilated = cv2.dilate(component, kernel) if kernel is not None else component
            window = cv2.bitwise_or(cv2.subtract(dilated, mask_roi), component) if others else dilated
            # Raw intensity moments M over the window (the float32 product is
            # exact for integer DN; cv2.moments accumulates in double) and the
            # moments N of the window mask: sum(u^p v^q (I - b)) = M_pq - b N_pq.
            M = cv2.moments(cv2.multiply(roi, window, dtype=cv2.CV_32F))
            N = cv2.moments(window)  # 0/1 mask: as binaryImage=True, faster
            window_count = int(N["m00"])
            if others:
                ring = cv2.bitwise_or(dilated, mask_roi)
                cv2.bitwise_xor(ring, 1, dst=ring)  # 1 where neither blob, nor dilation, nor other blob
                ring_count = cv2.countNonZero(ring)
                ring_sum = cv2.mean(roi, ring)[0] * ring_count
            else:  # ring = ROI minus window: sums by difference
                ring_count = roi.size - window_count
                ring_sum = cv2.sumElems(roi)[0] - M["m00"]
            b = ring_sum / ring_count if ring_count else background.level_dn
            total = M["m00"] - b * N["m00"]
            if not total > 0:
                rejected.append(RejectedBlob(box_uv, "no_signal"))
                continue
            su, sv = M["m10"] - b * N["m10"], M["m01"] - b * N["m01"]
            uc, vc = su / total, sv / total
            uv = (x0 + uc, y0 + vc)
            # Second central moments of the background-subtracted intensity ->
            # axis ratio (eigenvalues of the 2x2 covariance; axes ~ square roots).
            c20 = M["m20"] - b * N["m20"] - uc * su
            c02 = M["m02"] - b * N["m02"] - vc * sv
            c11 = M["m11"] - b * N["m11"] - uc * sv
            root = math.sqrt((c20 - c02) ** 2 + 4.0 * c11 * c11)
            major, minor = c20 + c02 + root, c20 + c02 - root
            roundness = math.sqrt(max(minor, 0.0) / major) if major > 0 else 0.0
            if roundness < min_roundness:
                rejected.append(RejectedBlob(uv, "not_round"))
                continue
            blobs.append(
                Blob(
                    x0,
                    y0,
                    roi,
                    component,
                    window,
                    window_count,
                    M,
                    N,
                    b,
                    ring_count,
                    int(area),
                    roundness,
                    float(max_value - b),
                    bool(saturated),
                    uv,
                )
            )
        return blobs, rejected, background


def sort_order(uv: np.ndarray) -> np.ndarray:
    """Indices that put (N, 2) centroids in raster order (by v, then u), so the
    output does not depend on the order the contours were found in."""
    if len(uv) == 0:
        return np.zeros(0, np.intp)
    return np.lexsort((uv[:, 0], uv[:, 1]))


def sort_rejected(rejected: list[RejectedBlob]) -> tuple[RejectedBlob, ...]:
    """Rejected blobs in raster order of their approximate centres."""
    return tuple(sorted(rejected, key=lambda r: (r.uv[1], r.uv[0], r.reason)))
