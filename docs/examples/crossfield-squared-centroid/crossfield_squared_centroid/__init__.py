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


def squared_centroid(
    blob: Blob, background: Background, gain_e_per_dn: float = 2.86
) -> tuple[float, float, float, float]:
    """(u, v, sigma_u, sigma_v) in image pixels of one blob.

    Centre = sum(w u) / sum(w) with w = max(I - b, 0)^2 over the blob's
    window (b: the blob's local background, DN). Uncertainty: first-order
    propagation of independent pixel noise through the weighted mean,
    du/dI_i = (u_i - u) dw_i/dI_i / sum(w) with dw/dI = 2 (I - b), with the
    pixel variance var_i = sigma_n^2 + (I_i - b) / gain (read and background
    noise plus the signal's photon noise, gain in e-/DN), and the local
    background's error (variance sigma_n^2 / N_ring), which moves the centre by
    du/db = -sum((u_i - u) dw_i/dI_i) / sum(w): the same noise model as the
    built-in ``weighted`` centroid. Stating only the sigma_n term understates
    sigma_uv (a bright target's photon noise dominates), which the session's
    motion test then reads as a moving station.
    """
    signal = np.clip(blob.roi.astype(np.float64) - blob.background_dn, 0.0, None) * blob.window
    weights = signal**2
    total = float(weights.sum())
    if not total > 0:
        return float("nan"), float("nan"), float("nan"), float("nan")
    vv, uu = np.mgrid[0 : blob.roi.shape[0], 0 : blob.roi.shape[1]]
    u = float((weights * uu).sum() / total)
    v = float((weights * vv).sum() / total)
    grad = 2.0 * signal  # dw_i / dI_i
    noise_var = background.sigma_dn**2
    pixel_var = noise_var + signal / gain_e_per_dn
    background_var = noise_var / blob.ring_count if blob.ring_count else noise_var
    du, dv = (uu - u) * grad / total, (vv - v) * grad / total  # du/dI_i, dv/dI_i
    var_u = float((du**2 * pixel_var).sum() + du.sum() ** 2 * background_var)
    var_v = float((dv**2 * pixel_var).sum() + dv.sum() ** 2 * background_var)
    return blob.x0 + u, blob.y0 + v, float(np.sqrt(var_u)), float(np.sqrt(var_v))


class SquaredCentroids:
    """Blobs found by crossfield's detector; centre = sum(w u) / sum(w) with
    w = (I - background)^2 over the blob dilated by ``dilate_px`` pixels.

    Options: threshold_sigma (blob threshold = background + threshold_sigma
    * noise), min_area_px (pixels), dilate_px (pixels), gain_e_per_dn (camera
    conversion gain, electrons per DN, for the photon noise). Units: pixels
    (OpenCV convention: (0, 0) is the centre of the top-left pixel); DN for
    intensities.
    """

    def __init__(
        self, *, threshold_sigma: float = 8.0, min_area_px: int = 30, dilate_px: int = 2, gain_e_per_dn: float = 2.86
    ) -> None:
        if isinstance(gain_e_per_dn, bool) or not isinstance(gain_e_per_dn, (int, float)) or not gain_e_per_dn > 0:
            raise ValueError(f"option 'gain_e_per_dn' must be a number > 0, got {gain_e_per_dn!r}")
        self.gain_e_per_dn = float(gain_e_per_dn)
        # DetectorOptions checks the values (ValueError names the option).
        self.detector = BlobDetector(
            DetectorOptions(threshold_sigma=threshold_sigma, min_area_px=min_area_px, dilate_px=dilate_px)
        )

    def extract(self, image: np.ndarray, camera: str, sequence: int) -> CentroidSet:
        """Centroids of the targets in one (H, W) integer image (DN), raster order."""
        blobs, rejected, background = self.detector.detect(image)
        found = np.array([squared_centroid(blob, background, self.gain_e_per_dn) for blob in blobs], dtype=np.float64).reshape(-1, 4)
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
