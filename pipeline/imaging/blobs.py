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
   integer frame.
3. The blobs: the 8-connected components of the pixels above the threshold,
   holes filled (:func:`crossfield.imaging.runs.blob_runs`: one compiled
   pass that reads the frame once and yields each blob as pixel runs; the
   blobs of ``cv2.findContours(RETR_EXTERNAL)`` with each outer contour
   filled, to the pixel, at a third of its time on a target frame).
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
import numba
import numpy as np

from crossfield.imaging.runs import BlobRuns, blob_runs, paint_runs
from crossfield.types import RejectedBlob

__all__ = [
    "REASONS",
    "Background",
    "Blob",
    "BlobDetector",
    "BlobStack",
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
    component: (h, w) uint8 0/1, the blob, its holes filled.
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
class BlobStack:
    """Accepted blobs of one size class, as (T, S, S) stacks (``BlobDetector.detect_stacks``).

    x0, y0: (T,) column and row of each stack slice's top-left pixel in the
    image (the slice holds the blob's ROI, bounding box + ``dilate_px`` +
    ``ring_px``, clipped to the image). roi: (T, S, S) the image pixels (DN,
    a copy); window: (T, S, S) uint8 0/1 as :class:`Blob`'s, inside the
    ROI. background_dn, area_px, roundness, peak_dn, saturated: (T,), as
    :class:`Blob`'s; uv: (T, 2) intensity-weighted centroids (image px);
    moments: (T, 3) the background-subtracted second central moments
    (c20, c11, c02) over the window (px^2); background_gradient: (T, 2) DN/px,
    the slope (d/du, d/dv) of the plane through the ring's pixels
    (``background_dn`` is its value at the ring's centroid).
    window_moments, mask_moments: (T, 6) the raw moments (m00, m10, m01, m20,
    m11, m02; slice coordinates, u = column, v = row, exact integer sums) of
    the image over the window and of the window itself, as :class:`Blob`'s
    ``cv2.moments`` in ROI coordinates; ring_count: (T,) the ring's pixels
    (the local background is their mean).
    """

    x0: np.ndarray
    y0: np.ndarray
    roi: np.ndarray
    window: np.ndarray
    background_dn: np.ndarray
    area_px: np.ndarray
    roundness: np.ndarray
    peak_dn: np.ndarray
    saturated: np.ndarray
    uv: np.ndarray
    moments: np.ndarray
    background_gradient: np.ndarray
    window_moments: np.ndarray
    mask_moments: np.ndarray
    ring_count: np.ndarray

    def __len__(self) -> int:
        return len(self.x0)


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
        cdf = np.cumsum(np.bincount(sample.ravel().astype(np.intp, copy=False)))
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

    def _blobs(self, image: np.ndarray) -> tuple[Background, BlobRuns]:
        """Steps 1-3 (module docstring): the background and the filled blobs."""
        if not isinstance(image, np.ndarray) or image.ndim != 2:
            raise ValueError(f"expected a 2-D image array, got {getattr(image, 'shape', type(image))}")
        background = estimate_background(image, self.options.threshold_sigma, self.options.stride)
        return background, blob_runs(image, background.threshold_dn)

    def detect(self, image: np.ndarray) -> tuple[list[Blob], list[RejectedBlob], Background]:
        """Blobs of one (H, W) image (integer DN, any bit depth up to 16).

        Returns the accepted blobs (in raster order of their first pixel), the
        rejected ones with their reasons, and the global background estimate.
        """
        opts = self.options
        background, found = self._blobs(image)
        # Integer threshold: no float conversion of the frame; bool -> uint8 view.
        mask = (image > background.threshold_dn).view(np.uint8)

        height, width = image.shape
        margin = opts.dilate_px + opts.ring_px
        sat = opts.saturation_dn
        min_area, max_area, min_roundness = opts.min_area_px, opts.max_area_px, opts.min_roundness
        reject_border, reject_saturated = opts.reject_border, opts.reject_saturated
        blobs: list[Blob] = []
        rejected: list[RejectedBlob] = []
        for index, ((x, y, w, h), area) in enumerate(zip(found.boxes.tolist(), found.area.tolist())):
            box_uv = (x + (w - 1) / 2, y + (h - 1) / 2)
            if reject_border and (x == 0 or y == 0 or x + w == width or y + h == height):
                rejected.append(RejectedBlob(box_uv, "touches_border"))
                continue
            if area < min_area:
                rejected.append(RejectedBlob(box_uv, "too_small"))
                continue
            if area > max_area:
                rejected.append(RejectedBlob(box_uv, "too_large"))
                continue
            x0, y0 = max(x - margin, 0), max(y - margin, 0)
            x1, y1 = min(x + w + margin, width), min(y + h + margin, height)
            at = (np.array([index]), np.array([x0]), np.array([y0]))  # blob, ROI column, row
            component = np.zeros((1, y1 - y0, x1 - x0), np.uint8)
            dilated = np.zeros_like(component)
            paint_runs(found.runs, found.offsets, *at, component, 0)
            paint_runs(found.runs, found.offsets, *at, dilated, opts.dilate_px)
            component, dilated = component[0], dilated[0]
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


    def detect_stacks(
        self, image: np.ndarray, size_step: int = 8
    ) -> tuple[list[BlobStack], list[RejectedBlob], Background]:
        """The blobs of :meth:`detect` (same tests, reasons, windows, background
        and moments), vectorised over blobs: one (T, S, S) stack per size class.

        Blobs are grouped by ROI side rounded up to ``size_step`` px; within a
        class the blobs and their dilations are painted from their runs
        (:func:`crossfield.imaging.runs.paint_runs`), and the per-pixel sums,
        the background plane and the per-blob moments are one compiled pass
        (:func:`_gather`, the GIL released); the rejection tests are
        whole-stack array operations. Each ROI keeps its
        :meth:`detect` extent (bounding box + margin, clipped to the image)
        inside its slice, so the results do not depend on the class size and
        stay exact under flips and transposition of the image. Returns the
        stacks (accepted blobs, in :meth:`detect`'s order within a class), the
        rejected blobs and the global background.
        """
        opts = self.options
        background, found = self._blobs(image)
        rejected: list[RejectedBlob] = []
        if not len(found):
            return [], rejected, background
        boxes = found.boxes
        x, y, w, h = boxes.T
        height, width = image.shape
        reason = np.full(len(boxes), -1)  # index into REASONS, -1: accepted so far
        where = np.column_stack((x + (w - 1) / 2, y + (h - 1) / 2))  # the rejected blob's uv
        if opts.reject_border:
            reason[(x == 0) | (y == 0) | (x + w == width) | (y + h == height)] = 0
        reason[(found.area < opts.min_area_px) & (reason < 0)] = 1
        reason[(found.area > opts.max_area_px) & (reason < 0)] = 2
        margin = opts.dilate_px + opts.ring_px
        side = -(-(np.maximum(w, h) + 2 * margin) // size_step) * size_step
        stacks = []
        live = np.flatnonzero(reason < 0)
        for size in np.unique(side[live]):
            rows = live[side[live] == size]
            stack = self._stack(image, found, rows, int(size), background, reason, where)
            if len(stack):
                stacks.append(stack)
        for i in np.flatnonzero(reason >= 0):
            rejected.append(RejectedBlob((float(where[i, 0]), float(where[i, 1])), REASONS[reason[i]]))
        return stacks, rejected, background

    def _stack(self, image, found, rows, size, background, reason, where) -> BlobStack:
        """Step 4 for the blobs ``rows`` (T,) of ``found`` in (T, size, size) slices; writes
        the rejection codes into ``reason`` and the not_round blobs' centroids into ``where``."""
        opts = self.options
        height, width = image.shape
        x, y, w, h = found.boxes[rows].T
        margin = opts.dilate_px + opts.ring_px
        sh, sw = min(size, height), min(size, width)
        # slice origin: the ROI inside, the slice inside the image
        xs = np.minimum(np.maximum(x - margin, 0), width - sw)
        ys = np.minimum(np.maximum(y - margin, 0), height - sh)
        # the ROI of detect(): bounding box + margin, clipped to the image, in slice coordinates
        n = len(rows)
        rect = np.empty((n, 4), np.int64)
        rect[:, 0] = np.maximum(y - margin, 0) - ys
        rect[:, 1] = np.minimum(y + h + margin, height) - ys
        rect[:, 2] = np.maximum(x - margin, 0) - xs
        rect[:, 3] = np.minimum(x + w + margin, width) - xs
        filled = np.zeros((n, sh, sw), np.uint8)
        dilated = np.zeros((n, sh, sw), np.uint8)
        paint_runs(found.runs, found.offsets, rows, xs, ys, filled, 0)
        paint_runs(found.runs, found.offsets, rows, xs, ys, dilated, opts.dilate_px)
        roi = np.empty((n, sh, sw), image.dtype)
        window = np.empty((n, sh, sw), np.uint8)
        max_value = np.empty(n)
        b, total, roundness = np.empty(n), np.empty(n), np.empty(n)
        uv, moments, gradient = np.empty((n, 2)), np.empty((n, 3)), np.empty((n, 2))
        M, N, ring_count = np.empty((n, 6)), np.empty((n, 6)), np.empty(n, np.int64)
        _gather(
            image, xs, ys, rect, filled, dilated, background.threshold_dn, background.level_dn,
            roi, window, max_value, b, total, uv, moments, roundness, gradient, M, N, ring_count,
        )
        saturated = max_value >= opts.saturation_dn
        mine = reason[rows]
        for code, bad in (
            (3, saturated & opts.reject_saturated),
            (4, ~(total > 0)),
            (5, roundness < opts.min_roundness),
        ):
            mine[bad & (mine < 0)] = code
        hit = mine == 5
        where[rows[hit]] = uv[hit]
        reason[rows] = mine
        ok = np.flatnonzero(mine < 0)
        return BlobStack(
            x0=xs[ok],
            y0=ys[ok],
            roi=roi[ok],
            window=window[ok],
            background_dn=b[ok],
            area_px=found.area[rows[ok]],
            roundness=roundness[ok],
            peak_dn=max_value[ok] - b[ok],
            saturated=saturated[ok],
            uv=uv[ok],
            moments=moments[ok],
            background_gradient=gradient[ok],
            window_moments=M[ok],
            mask_moments=N[ok],
            ring_count=ring_count[ok],
        )


@numba.njit(cache=True, nogil=True)
def _gather(
    image, xs, ys, rect, filled, dilated, threshold_dn, level_dn,
    roi, window, max_value, b, total, uv, moments, roundness, gradient, M, N, ring_count,
) -> None:
    """Step 4 and the moments of :meth:`BlobDetector._stack` for the T slices at
    columns ``xs``, rows ``ys`` (T,) of ``image``, GIL released: :func:`_slice_sums`,
    then per blob the background plane (:func:`_ring_gradient`) and the moments
    (:func:`_blob_moments`). Writes roi, window (T, S, S) and max_value, b,
    total, roundness (T,), uv (T, 2), moments (T, 3), gradient (T, 2), and the
    raw window moments M, N (T, 6) and ring_count (T,) of :func:`_slice_sums`."""
    n = len(xs)
    ring_sum = np.empty(n)
    ring_moments, ring_values = np.empty((n, 6)), np.empty((n, 3))
    _slice_sums(
        image, xs, ys, rect, filled, dilated, threshold_dn,
        roi, window, max_value, ring_count, ring_sum, M, N, ring_moments, ring_values,
    )
    _ring_gradient(ring_moments, ring_values, gradient)
    _blob_moments(M, N, ring_count, ring_sum, level_dn, xs, ys, b, total, uv, moments, roundness)


@numba.njit(cache=True, nogil=True)
def _slice_sums(
    image, xs, ys, rect, filled, dilated, threshold_dn,
    roi, window, max_value, ring_count, ring_sum, M, N, ring_moments, ring_values,
) -> None:
    """Step 4 of :meth:`BlobDetector._stack` in one pass over the (T, S, S) slices at
    columns ``xs``, rows ``ys`` (T,) of ``image``, each pixel once.

    rect: (T, 4) detect()'s ROI in slice coordinates (row from, row to, column
    from, column to); filled, dilated: (T, S, S) uint8 the filled blob and
    its dilation. Writes roi (T, S, S) the image pixels; window (T, S, S) 0/1
    (dilated, inside the ROI, not another blob's pixel: above the threshold and
    outside the blob); max_value (highest
    value in it, 0 if none); ring_count and ring_sum (the ROI's pixels neither
    in the dilation nor above the threshold, and their sum, DN); M, N (T, 6) the
    raw moments m00, m10, m01, m20, m11, m02 (slice coordinates, u = column, v =
    row) of the image over the window and of the window; ring_moments (T, 6) the
    same moments of the ring and ring_values (T, 3) sum z, z u, z v over the ring
    (for the background plane, :func:`_ring_gradient`). Exact integer sums:
    the same values as cv2.moments' in ``detect`` (doubles, exact below 2^53).
    """
    n, sh, sw = roi.shape
    thr = np.int64(threshold_dn)
    for t in range(n):
        y0, x0 = ys[t], xs[t]
        r_lo, r_hi, c_lo, c_hi = rect[t, 0], rect[t, 1], rect[t, 2], rect[t, 3]
        top = rc = rs = 0
        m0 = m1 = m2 = m3 = m4 = m5 = k0 = k1 = k2 = k3 = k4 = k5 = 0
        g1 = g2 = g3 = g4 = g5 = h1 = h2 = 0  # ring: sum c, r, c^2, c r, r^2; z c, z r
        for r in range(sh):
            row_in = np.int64(r >= r_lo and r < r_hi)
            # the row's sums of z, z c, z c^2, 1, c, c^2 over its window pixels: integer,
            # branch-free (0/1 factors), so the compiler vectorises the loop
            z0 = z1 = z2 = n0 = n1 = n2 = 0
            q0 = q1 = q2 = qz0 = qz1 = 0  # the row's ring: count, sum c, c^2; sum z, z c
            for c in range(sw):
                z = np.int64(image[y0 + r, x0 + c])
                roi[t, r, c] = z
                comp = np.int64(filled[t, r, c] != 0)
                above = np.int64(z > thr)
                grown = np.int64(dilated[t, r, c] != 0)
                inside = row_in * np.int64(c >= c_lo) * np.int64(c < c_hi)
                win = grown * inside * (1 - above * (1 - comp))  # not another blob's pixel
                window[t, r, c] = win
                top = max(top, z * comp)
                ring = inside * (1 - grown) * (1 - above)
                q0 += ring
                q1 += ring * c
                q2 += ring * c * c
                qz0 += z * ring
                qz1 += z * ring * c
                zw = z * win
                z0 += zw
                z1 += zw * c
                z2 += zw * c * c
                n0 += win
                n1 += win * c
                n2 += win * c * c
            rc += q0
            rs += qz0
            g1 += q1
            g2 += q0 * r
            g3 += q2
            g4 += q1 * r
            g5 += q0 * r * r
            h1 += qz1
            h2 += qz0 * r
            m0 += z0
            m1 += z1
            m2 += z0 * r
            m3 += z2
            m4 += z1 * r
            m5 += z0 * r * r
            k0 += n0
            k1 += n1
            k2 += n0 * r
            k3 += n2
            k4 += n1 * r
            k5 += n0 * r * r
        max_value[t] = top
        ring_count[t] = rc
        ring_sum[t] = rs
        M[t, 0], M[t, 1], M[t, 2], M[t, 3], M[t, 4], M[t, 5] = m0, m1, m2, m3, m4, m5
        N[t, 0], N[t, 1], N[t, 2], N[t, 3], N[t, 4], N[t, 5] = k0, k1, k2, k3, k4, k5
        ring_moments[t, 0], ring_moments[t, 1], ring_moments[t, 2] = rc, g1, g2
        ring_moments[t, 3], ring_moments[t, 4], ring_moments[t, 5] = g3, g4, g5
        ring_values[t, 0], ring_values[t, 1], ring_values[t, 2] = rs, h1, h2


#: fewest ring pixels for a background plane (fewer: the gradient is taken as 0)
MIN_RING_PLANE_PX = 24


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _ring_gradient(R: np.ndarray, Z: np.ndarray, gradient: np.ndarray) -> None:
    """Writes gradient (T, 2) DN/px: the slope (d/du, d/dv) of the least-squares plane
    through each slice's ring pixels, from their moments R (T, 6) (n, sum u, sum v,
    sum u^2, sum u v, sum v^2) and value sums Z (T, 3) (sum z, sum z u, sum z v)
    (:func:`_slice_sums`).

    The plane z = b + g . (x - x_r) through the ring's centroid x_r: g solves
    C g = c, C the ring pixels' (2, 2) coordinate covariance and c their
    coordinate-value covariance. A vignetted or stray-light background slopes
    by ~0.01-0.05 DN/px; under a 14 px disc a slope left in the data moves a
    model-fit centre by ~5e-4 px (a quarter of its noise), which the plane takes
    off. Fewer than ``MIN_RING_PLANE_PX`` ring pixels, or a degenerate C: g = 0.
    """
    for t in range(len(R)):
        n = max(R[t, 0], 1.0)
        cu, cv, mz = R[t, 1] / n, R[t, 2] / n, Z[t, 0] / n
        a, b, d = R[t, 3] / n - cu * cu, R[t, 4] / n - cu * cv, R[t, 5] / n - cv * cv
        e, f = Z[t, 1] / n - mz * cu, Z[t, 2] / n - mz * cv
        det = a * d - b * b
        if R[t, 0] >= MIN_RING_PLANE_PX and det > 1e-6 * max(a * d, 1e-300):
            gradient[t, 0] = (d * e - b * f) / det
            gradient[t, 1] = (a * f - b * e) / det
        else:
            gradient[t, 0] = 0.0
            gradient[t, 1] = 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _blob_moments(M, N, ring_count, ring_sum, level_dn, xs, ys, b, total, uv, moments, roundness) -> None:
    """Per blob of a stack, from :func:`_slice_sums`' sums: the local background b (the
    ring's mean, ``level_dn`` if no ring), the background-subtracted total, the
    intensity-weighted centroid uv (image px), the second central moments (c20, c11,
    c02) px^2 and the roundness (minor/major axis ratio: square root of the ratio of
    the covariance's eigenvalues). sum(u^p v^q (I - b)) over the window = M_pq - b N_pq;
    the operations and their order are ``detect``'s, so uv has the same bits."""
    for t in range(len(b)):
        bt = ring_sum[t] / ring_count[t] if ring_count[t] > 0 else level_dn
        tot = M[t, 0] - bt * N[t, 0]
        su = M[t, 1] - bt * N[t, 1]
        sv = M[t, 2] - bt * N[t, 2]
        safe = tot if tot > 0 else 1.0
        uc = su / safe
        vc = sv / safe
        c20 = (M[t, 3] - bt * N[t, 3] - uc * su) / safe
        c11 = (M[t, 4] - bt * N[t, 4] - uc * sv) / safe
        c02 = (M[t, 5] - bt * N[t, 5] - vc * sv) / safe
        e = c20 - c02
        root = math.sqrt(e * e + 4.0 * c11 * c11)
        major, minor = c20 + c02 + root, c20 + c02 - root
        roundness[t] = math.sqrt(max(minor, 0.0) / major) if major > 0 else 0.0
        b[t] = bt
        total[t] = tot
        uv[t, 0] = xs[t] + uc
        uv[t, 1] = ys[t] + vc
        moments[t, 0] = c20
        moments[t, 1] = c11
        moments[t, 2] = c02


def sort_order(uv: np.ndarray) -> np.ndarray:
    """Indices that put (N, 2) centroids in raster order (by v, then u), so the
    output does not depend on the order the contours were found in."""
    if len(uv) == 0:
        return np.zeros(0, np.intp)
    return np.lexsort((uv[:, 0], uv[:, 1]))


def sort_rejected(rejected: list[RejectedBlob]) -> tuple[RejectedBlob, ...]:
    """Rejected blobs in raster order of their approximate centres."""
    return tuple(sorted(rejected, key=lambda r: (r.uv[1], r.uv[0], r.reason)))
