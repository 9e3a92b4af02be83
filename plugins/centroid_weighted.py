"""Centroid plugin "weighted": thresholded blobs, intensity-weighted sub-pixel centroids.

Detection (threshold, blobs, rejection, local background) is shared with
the other centroid plugins in :mod:`crossfield.imaging.blobs`; this module does the
sub-pixel step and its uncertainty (``docs/centroids.md``).

Centroid over the blob's window W (blob dilated by ``dilate_px``), with
w_i = I_i - b the background-subtracted value of pixel i (DN) and b the
local background (mean of a ring around the blob)::

    u_c = sum(u_i w_i) / S,   v_c = sum(v_i w_i) / S,   S = sum(w_i)

(first image moments, e.g. Luhmann et al., Close-Range Photogrammetry, 5.2.4.2).
Negative w_i (noise in the window's dark margin) are kept: clipping them
would bias the centroid towards the window centre.

Uncertainty: first-order propagation of independent pixel noise through
the weighted mean (du_c/dI_i = (u_i - u_c)/S)::

    sigma_u^2 = sum((u_i - u_c)^2 var_i) / S^2 + (sum(u_i - u_c) / S)^2 var_b
    var_i     = sigma_n^2 + max(w_i, 0) / gain

sigma_n is the background noise of the image (read noise and the
background's own photon noise, measured as IQR/1.349 of a subsample), the
second term of var_i the photon noise of the target signal (Poisson in
electrons, gain in e-/DN), and var_b = sigma_n^2 / N_ring the variance of
the local background mean, whose error moves the centroid by
-sum(u_i - u_c)/S per DN. All sums come from ``cv2.moments`` of the raw
image over the window and of the window mask, so no per-pixel Python work
is done.
Pixels in u, v; (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import math

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


def weighted_centroid(
    blob: Blob, background: Background, gain_e_per_dn: float
) -> tuple[float, float, float, float]:
    """Intensity-weighted centroid of one blob and its standard uncertainty.

    Returns (u, v, sigma_u, sigma_v) in pixels, image coordinates. See the
    module docstring for the formulas. The sums over the window W of
    w_i = I_i - b are taken from the raw moments M of I over W and the
    moments N of W itself (ROI coordinates): sum(u^p w) = M_p - b N_p.
    """
    M, N = blob.window_moments, blob.mask_moments
    b = blob.background_dn
    total = M["m00"] - b * N["m00"]  # S = sum(w_i)
    if not total > 0:
        return float("nan"), float("nan"), float("nan"), float("nan")
    su = M["m10"] - b * N["m10"]  # sum(u_i w_i)
    sv = M["m01"] - b * N["m01"]
    uc, vc = su / total, sv / total
    # sum((u_i - u_c)^2 w_i), the photon-noise sums
    photon_u = max(M["m20"] - b * N["m20"] - uc * su, 0.0) / gain_e_per_dn
    photon_v = max(M["m02"] - b * N["m02"] - vc * sv, 0.0) / gain_e_per_dn
    n_window = N["m00"]
    # sums over the window of (u_i - u_c) and (u_i - u_c)^2
    du_sum = N["m10"] - n_window * uc
    dv_sum = N["m01"] - n_window * vc
    du2_sum = N["mu20"] + du_sum * du_sum / n_window
    dv2_sum = N["mu02"] + dv_sum * dv_sum / n_window
    noise_var = background.sigma_dn**2
    background_var = noise_var / blob.ring_count if blob.ring_count else noise_var
    var_u = (noise_var * du2_sum + photon_u) / total**2 + (du_sum / total) ** 2 * background_var
    var_v = (noise_var * dv2_sum + photon_v) / total**2 + (dv_sum / total) ** 2 * background_var
    return blob.x0 + uc, blob.y0 + vc, math.sqrt(var_u), math.sqrt(var_v)


class WeightedCentroids:
    """Thresholded blobs with intensity-weighted sub-pixel centroids.

    Options (config keys; lengths in pixels, levels in DN):

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
    gain_e_per_dn: camera conversion gain (electrons per DN, EMVA 1288 1/K),
      for the photon noise in the uncertainty; the default is the simulator's
      scA1600-14gm-like sensor (0.35 DN/e-).
    """

    method = "weighted"

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
        gain_e_per_dn: float = 2.86,
    ) -> None:
        if not gain_e_per_dn > 0:
            raise ValueError(f"gain_e_per_dn must be > 0, got {gain_e_per_dn}")
        self.gain_e_per_dn = float(gain_e_per_dn)
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

    def extract(self, image: np.ndarray, camera: str, sequence: int) -> CentroidSet:
        """Centroids of the targets in one (H, W) integer image (DN).

        Returns a CentroidSet in raster order (by v, then u), pixel units.
        """
        blobs, rejected, background = self.detector.detect(image)
        n = len(blobs)
        uv = np.empty((n, 2))
        sigma = np.empty((n, 2))
        for i, blob in enumerate(blobs):
            u, v, su, sv = weighted_centroid(blob, background, self.gain_e_per_dn)
            uv[i] = u, v
            sigma[i] = su, sv
        order = sort_order(uv)
        return CentroidSet(
            camera=camera,
            sequence=sequence,
            uv=uv[order],
            sigma_uv=sigma[order],
            area_px=np.array([blobs[i].area_px for i in order], dtype=np.float64),
            roundness=np.array([blobs[i].roundness for i in order], dtype=np.float64),
            peak=np.array([blobs[i].peak_dn for i in order], dtype=np.float64),
            rejected=sort_rejected(rejected),
            method=self.method,
        )


@hookimpl
def register_centroids(register) -> None:
    register("weighted", WeightedCentroids, "Thresholded blobs, intensity-weighted centroids")
