"""The common part of the blob-based centroid plugins: options, detection, the CentroidSet.

One job: a centroid plugin built on :mod:`crossfield.imaging.blobs` differs
from the others only in its sub-pixel step. :class:`BlobCentroids` holds the
ten detector options (and their checks, :class:`~crossfield.imaging.blobs.DetectorOptions`),
runs the batched detector (:meth:`~crossfield.imaging.blobs.BlobDetector.detect_stacks`:
the blobs of one ROI size class as (T, S, S) stacks, gathered by one compiled
pass) and assembles the :class:`~crossfield.types.CentroidSet`: raster order,
the blobs whose sub-pixel step failed rejected as ``"fit_failed"`` at their
intensity-weighted centroid, area and roundness from the detector. A
subclass declares its own options as keyword-only ``__init__`` parameters
(it passes the detector's on with ``**detector``) and implements
:meth:`BlobCentroids.subpixel`; its signature, the one the registry reads
the options from (``crossfield.chain.registry.Implementation.options``), is its own
parameters plus the detector's (:meth:`BlobCentroids.__init_subclass__`).

Pixels in u, v; (0, 0) is the centre of the top-left pixel (OpenCV).
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from crossfield.imaging.blobs import (
    Background,
    BlobDetector,
    BlobStack,
    DetectorOptions,
    sort_order,
    sort_rejected,
)
from crossfield.types import CentroidSet, RejectedBlob

__all__ = ["BlobCentroids", "SubPixel"]


@dataclass(frozen=True)
class SubPixel:
    """A sub-pixel step's result for the T blobs of the stacks (concatenated in stack order).

    uv: (T, 2) centres, image px; sigma_uv: (T, 2) their standard uncertainties, px;
    ok: (T,) bool, False where the step failed (the blob is rejected as ``"fit_failed"``);
    peak: (T,) DN above the local background, or None for the stacks' ``peak_dn``;
    ellipse: (T, 3) fitted edge conics (px^-2) and ellipse_cov (T, 3, 3), or None.
    """

    uv: np.ndarray
    sigma_uv: np.ndarray
    ok: np.ndarray
    peak: np.ndarray | None = None
    ellipse: np.ndarray | None = None
    ellipse_cov: np.ndarray | None = None


class BlobCentroids:
    """Base of the blob-based centroid plugins: the detector and the CentroidSet (module docstring).

    Options (config keys; lengths in pixels, levels in DN), shared by every subclass:

    threshold_sigma: blob threshold = background + threshold_sigma * noise.
    min_area_px, max_area_px: accepted blob area (pixels above the threshold,
      holes filled). min_roundness: accepted minor/major axis ratio.
    reject_saturated: reject blobs with a pixel at 2**bit_depth - 1.
    reject_border: reject blobs touching the image border.
    bit_depth: bits per pixel of the camera (12 for the scA1600-14gm).
    dilate_px: the centroid window is the blob dilated by this much, to
      take in the blurred edge below the threshold.
    ring_px: width of the ring around the window the local background is
      taken from. background_stride: subsampling step of the global
      background/noise estimate.
    """

    #: the name in ``CentroidSet.method``
    method: ClassVar[str] = ""
    #: the sub-pixel step fits edge conics (``CentroidSet.ellipse``; empty, not None, with no blob)
    fits_conics: ClassVar[bool] = False

    def __init__(
        self,
        *,
        threshold_sigma: float = 8.0,
        min_area_px: int = 50,
        max_area_px: int = 20000,
        min_roundness: float = 0.5,
        reject_saturated: bool = True,
        reject_border: bool = True,
        bit_depth: int = 12,
        dilate_px: int = 2,
        ring_px: int = 3,
        background_stride: int = 8,
    ) -> None:
        self.detector = BlobDetector(
            DetectorOptions(
                threshold_sigma=threshold_sigma,
                min_area_px=min_area_px,
                max_area_px=max_area_px,
                min_roundness=min_roundness,
                reject_saturated=reject_saturated,
                reject_border=reject_border,
                bit_depth=bit_depth,
                dilate_px=dilate_px,
                ring_px=ring_px,
                stride=background_stride,
            )
        )

    def __init_subclass__(cls, **kwargs: object) -> None:
        """The subclass's signature: the detector's options, then its own keyword-only ones
        (its ``**detector`` catch-all left out), so the registry lists and checks them all."""
        super().__init_subclass__(**kwargs)
        own = [
            p for p in inspect.signature(cls.__init__).parameters.values()
            if p.kind is inspect.Parameter.KEYWORD_ONLY
        ]
        base = [p for p in inspect.signature(BlobCentroids.__init__).parameters.values()
                if p.kind is inspect.Parameter.KEYWORD_ONLY]
        names = {p.name for p in own}
        cls.__signature__ = inspect.Signature(
            [p for p in base if p.name not in names] + own, return_annotation=None
        )

    def subpixel(self, stacks: Sequence[BlobStack], background: Background) -> SubPixel:
        """The sub-pixel centres of the blobs of ``stacks`` (at least one blob in all)."""
        raise NotImplementedError

    def extract(self, image: np.ndarray, camera: str, sequence: int) -> CentroidSet:
        """Centroids of the targets in one (H, W) integer image (DN).

        Returns a CentroidSet in raster order (by v, then u), pixel units. A
        blob whose sub-pixel step fails is rejected as ``"fit_failed"`` (at its
        intensity-weighted centroid).
        """
        stacks, rejected, background = self.detector.detect_stacks(image)
        count = sum(len(st) for st in stacks)
        if count:
            result = self.subpixel(stacks, background)
            seeds = np.concatenate([st.uv for st in stacks])
            area = np.concatenate([st.area_px for st in stacks]).astype(np.float64)
            roundness = np.concatenate([st.roundness for st in stacks])
            peak = result.peak if result.peak is not None else np.concatenate([st.peak_dn for st in stacks])
        else:
            conics = (np.zeros((0, 3)), np.zeros((0, 3, 3))) if self.fits_conics else (None, None)
            result = SubPixel(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), None, *conics)
            seeds = np.zeros((0, 2))
            area = roundness = peak = np.zeros(0)
        for i in np.flatnonzero(~result.ok):
            rejected.append(RejectedBlob((float(seeds[i, 0]), float(seeds[i, 1])), "fit_failed"))
        keep = np.flatnonzero(result.ok)
        kept = keep[sort_order(result.uv[keep])]
        with_conics = result.ellipse is not None
        return CentroidSet(
            camera=camera,
            sequence=sequence,
            uv=result.uv[kept],
            sigma_uv=result.sigma_uv[kept],
            area_px=area[kept],
            roundness=roundness[kept],
            peak=peak[kept],
            rejected=sort_rejected(rejected),
            method=self.method,
            ellipse=result.ellipse[kept] if with_conics else None,
            ellipse_cov=result.ellipse_cov[kept] if with_conics and result.ellipse_cov is not None else None,
        )
