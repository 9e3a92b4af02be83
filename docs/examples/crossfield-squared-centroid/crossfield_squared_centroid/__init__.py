"""Squared-intensity weighted centroids: an example crossfield plugin.

Registers the centroid implementation ``squared`` through the ``crossfield``
entry-point group (see pyproject.toml). Only crossfield's public API is
used (docs/plugins.md, "The public API"), through ``crossfield.plugin_api``:
``hookimpl``, the blob detector (threshold, blobs, rejection tests, local
background: the same detection as the built-in centroid plugins) and the data
class ``CentroidSet``. The plugin only does its own sub-pixel step.
"""

from __future__ import annotations

import numpy as np

from crossfield.plugin_api import (
    Background,
    Blob,
    BlobDetector,
    CentroidSet,
    DetectorOptions,
    hookimpl,
    sort_order,
    sort_rejected,
)


def squared_centroid(blob: Blob, background: Background) -> tuple[float, float, float, float]:
    """(u, v, sigma_u, sigma_v) in image pixels of one blob.

    Centre = sum(w u) / sum(w) with w = max(I - b, 0)^2 over the blob's
    window (b: the blob's local background, DN). Uncertainty: first-order
    propagation of the background noise sigma_n through the weighted mean,
    du/dI_i = (u_i - u) dw_i/dI_i / sum(w) with dw/dI = 2 (I - b).
    """
    signal = np.clip(blob.roi.astype(np.float64) - blob.background_dn, 0.0, None) * blob.window
    weights = signal**2
    total = float(weights.sum())
    if not total > 0:
        return float("nan"), float("nan"), float("nan"), float("nan")
    vv, uu = np.mgrid[0 : blob.roi.shape[0], 0 : blob.roi.shape[1]]
    u = float((weights * uu).sum() / total)
    v = float((weights * vv).sum() / total)
    grad = 2.0 * signal
    su = float(np.sqrt(((uu - u) ** 2 * grad**2).sum()) * background.sigma_dn / total)
    sv = float(np.sqrt(((vv - v) ** 2 * grad**2).sum()) * background.sigma_dn / total)
    return blob.x0 + u, blob.y0 + v, su, sv


class SquaredCentroids:
    """Blobs found by crossfield's detector; centre = sum(w u) / sum(w) with
    w = (I - background)^2 over the blob dilated by ``dilate_px`` pixels.

    Options: threshold_sigma (blob threshold = background + threshold_sigma
    * noise), min_area_px (pixels), dilate_px (pixels). Units: pixels
    (OpenCV convention: (0, 0) is the centre of the top-left pixel); DN for
    intensities.
    """

    def __init__(self, *, threshold_sigma: float = 8.0, min_area_px: int = 30, dilate_px: int = 2) -> None:
        # DetectorOptions checks the values (ValueError names the option).
        self.detector = BlobDetector(
            DetectorOptions(threshold_sigma=threshold_sigma, min_area_px=min_area_px, dilate_px=dilate_px)
        )

    def extract(self, image: np.ndarray, camera: str, sequence: int) -> CentroidSet:
        """Centroids of the targets in one (H, W) integer image (DN), raster order."""
        blobs, rejected, background = self.detector.detect(image)
        found = np.array([squared_centroid(blob, background) for blob in blobs], dtype=np.float64).reshape(-1, 4)
        order = sort_order(found[:, :2])
        return CentroidSet(
            camera=camera,
            sequence=sequence,
            uv=found[order, :2],
            sigma_uv=found[order, 2:],
            area_px=np.array([blobs[i].area_px for i in order], dtype=np.float64),
            roundness=np.array([blobs[i].roundness for i in order], dtype=np.float64),
            peak=np.array([blobs[i].peak_dn for i in order], dtype=np.float64),
            rejected=sort_rejected(rejected),
            method="squared",
        )


@hookimpl
def register_centroids(register):
    register("squared", SquaredCentroids, "Squared-intensity weighted centroids (example plugin)")
