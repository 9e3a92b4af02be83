"""Centroid plugin "weighted": thresholded blobs, intensity-weighted sub-pixel centroids.

Detection (threshold, blobs, rejection, local background) and the
CentroidSet are shared with the other centroid plugins
(:class:`crossfield.imaging.centroids.BlobCentroids`, on the batched blob stacks
of :mod:`crossfield.imaging.blobs`); this module does the sub-pixel step and its
uncertainty (``docs/centroids.md``).

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
-sum(u_i - u_c)/S per DN. All sums come from the raw moments of the image
over the window and of the window mask: per blob from ``cv2.moments``
(:func:`weighted_centroid`, a :class:`~crossfield.imaging.blobs.Blob`), and in the
plugin from the compiled blob stacks (:func:`weighted_centroids`, the moments
the detector's gather pass sums anyway), so no per-blob OpenCV call is made.
Pixels in u, v; (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from crossfield.plugin_api import Background, Blob, BlobCentroids, BlobStack, SubPixel, hookimpl


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


def weighted_centroids(stack: BlobStack, background: Background, gain_e_per_dn: float) -> np.ndarray:
    """:func:`weighted_centroid` of every blob of a stack, vectorised: (T, 4) rows
    (u, v, sigma_u, sigma_v), image px, NaN where the background-subtracted sum is not > 0.

    The same formulas on the stack's raw moments (slice coordinates, exact integer
    sums, :class:`~crossfield.imaging.blobs.BlobStack`) instead of ``cv2.moments``
    of one ROI; mu20 = m20 - (m10 / m00) m10 as OpenCV computes it.
    """
    M, N = stack.window_moments, stack.mask_moments
    b = stack.background_dn
    total = M[:, 0] - b * N[:, 0]
    good = total > 0
    safe = np.where(good, total, 1.0)
    su = M[:, 1] - b * N[:, 1]
    sv = M[:, 2] - b * N[:, 2]
    uc, vc = su / safe, sv / safe
    photon_u = np.maximum(M[:, 3] - b * N[:, 3] - uc * su, 0.0) / gain_e_per_dn
    photon_v = np.maximum(M[:, 5] - b * N[:, 5] - vc * sv, 0.0) / gain_e_per_dn
    n_window = N[:, 0]
    du_sum = N[:, 1] - n_window * uc
    dv_sum = N[:, 2] - n_window * vc
    mu20 = N[:, 3] - N[:, 1] / n_window * N[:, 1]
    mu02 = N[:, 5] - N[:, 2] / n_window * N[:, 2]
    du2_sum = mu20 + du_sum * du_sum / n_window
    dv2_sum = mu02 + dv_sum * dv_sum / n_window
    noise_var = background.sigma_dn**2
    ring = stack.ring_count
    background_var = np.where(ring > 0, noise_var / np.maximum(ring, 1), noise_var)
    var_u = (noise_var * du2_sum + photon_u) / safe**2 + (du_sum / safe) ** 2 * background_var
    var_v = (noise_var * dv2_sum + photon_v) / safe**2 + (dv_sum / safe) ** 2 * background_var
    out = np.column_stack((stack.x0 + uc, stack.y0 + vc, np.sqrt(var_u), np.sqrt(var_v)))
    out[~good] = np.nan
    return out


class WeightedCentroids(BlobCentroids):
    """Thresholded blobs with intensity-weighted sub-pixel centroids.

    Options: the detection options of :class:`~crossfield.imaging.centroids.BlobCentroids`
    (threshold_sigma, min_area_px, max_area_px, min_roundness, reject_saturated,
    reject_border, bit_depth, dilate_px, ring_px, background_stride), plus
    gain_e_per_dn: camera conversion gain (electrons per DN, EMVA 1288 1/K),
    for the photon noise in the uncertainty; the default is the simulator's
    scA1600-14gm-like sensor (0.35 DN/e-).
    """

    method = "weighted"

    def __init__(self, *, gain_e_per_dn: float = 2.86, **detector) -> None:
        if not gain_e_per_dn > 0:
            raise ValueError(f"gain_e_per_dn must be > 0, got {gain_e_per_dn}")
        self.gain_e_per_dn = float(gain_e_per_dn)
        super().__init__(**detector)

    def subpixel(self, stacks: Sequence[BlobStack], background: Background) -> SubPixel:
        """The weighted centroid of every blob (all accepted: the detector has already
        rejected the blobs without signal)."""
        table = np.concatenate([weighted_centroids(st, background, self.gain_e_per_dn) for st in stacks])
        return SubPixel(uv=table[:, :2], sigma_uv=table[:, 2:], ok=np.ones(len(table), bool))


@hookimpl
def register_centroids(register) -> None:
    register("weighted", WeightedCentroids, "Thresholded blobs, intensity-weighted centroids")
