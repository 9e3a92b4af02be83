"""Centroid plugin "modelfit": maximum-likelihood fit of a blurred elliptical disc per target.

Detection (threshold, blobs, rejection, local background, the window of
each blob) is the shared :class:`crossfield.imaging.blobs.BlobDetector` in
its batched form (``detect_stacks``: one gather per ROI size class); the
intensity-weighted centroid and second moments of each blob seed the fit.
The sub-pixel step is :func:`crossfield.imaging.disc_model.fit_discs`: a
compiled kernel over the targets of each stack (numba, one thread, one target
after the other), Gauss-Newton on the Gaussian likelihood of
the window pixels in the edge band (3.7 sigma_e inside to 3.2 sigma_e
outside the seed's edge) under the model ``B + A E(signed distance)``
(``docs/centroids.md``, "modelfit").

One Gauss-Newton step by default (``max_iterations``): from the weighted
centroid it is as good as the converged fit (``docs/centroids.md``).
Uncertainty: the inverse Fisher information of the model at the last step's
start (the solution, to 4 % of its noise),
so sigma_uv is the Cramer-Rao bound of the model (its efficiency is
measured in ``bench/bench_centroid.py``). The fitted edge conic of each
target (``CentroidSet.ellipse``, with its covariance) goes to the
triangulation, which removes the perspective eccentricity of tilted circles
(:mod:`crossfield.imaging.eccentricity`).
Pixels in u, v; (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import numpy as np

from crossfield.plugin_api import (
    PSF_ORDERS,
    BlobDetector,
    CentroidSet,
    DetectorOptions,
    RejectedBlob,
    edge_profile,
    fit_discs,
    hookimpl,
    shape_from_moments,
    sort_order,
    sort_rejected,
)

#: a fitted centre further than this from its seed (px) is a failed fit
MAX_SHIFT_PX = 1.5
#: window pixels further inside / outside the seed's edge than these multiples of sigma_e
#: (3.5 / 3.0 px at blur 0.9 px) are left out of the fit: the edge profile's slope there is
#: < 0.1 % / 0.6 % of its peak, they would inform only the amplitude / background, and cost time
INSIDE_SIGMAS = 3.7
OUTSIDE_SIGMAS = 3.2


class ModelFitCentroids:
    """Blobs from the shared detector; centres from an ML blurred-disc fit.

    Options: the detection options of "weighted" (threshold_sigma,
    min_area_px, max_area_px, min_roundness, reject_saturated, reject_border,
    bit_depth, dilate_px, ring_px, background_stride), plus
    gain_e_per_dn: conversion gain (e-/DN) for the photon noise;
    blur_sigma_px: the Gaussian PSF sigma (px);
    psf_order: ``"optical"`` (PSF on the scene, then pixel integration: a
      real camera) or ``"pixel"`` (pixel coverage blurred on the pixel grid:
      how the simulator and the synthetic test images are rendered);
    max_iterations: Gauss-Newton iteration limit.
    """

    method = "modelfit"

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
        blur_sigma_px: float = 0.9,
        psf_order: str = "optical",
        max_iterations: int = 1,
    ) -> None:
        if not gain_e_per_dn > 0:
            raise ValueError(f"gain_e_per_dn must be > 0, got {gain_e_per_dn}")
        if not blur_sigma_px >= 0:
            raise ValueError(f"blur_sigma_px must be >= 0, got {blur_sigma_px}")
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
            raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
        self.gain_e_per_dn = float(gain_e_per_dn)
        self.blur_sigma_px = float(blur_sigma_px)
        self.max_iterations = max_iterations
        if psf_order not in PSF_ORDERS:
            raise ValueError(f"psf_order must be one of {', '.join(PSF_ORDERS)}, got {psf_order!r}")
        self.profile = edge_profile(self.blur_sigma_px, psf_order)
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

        Returns a CentroidSet in raster order (by v, then u), pixel units, with
        the fitted edge conics (``ellipse``, ``ellipse_cov``). A blob whose fit
        does not converge to a disc near its seed is rejected as ``"fit_failed"``.
        """
        stacks, rejected, background = self.detector.detect_stacks(image)
        seeds = np.concatenate([st.uv for st in stacks]) if stacks else np.zeros((0, 2))
        n = len(seeds)
        sigma_e = float(np.sqrt(self.blur_sigma_px**2 + 1.0 / 12.0))
        if n:
            moments = np.concatenate([st.moments for st in stacks])
            start = np.zeros((n, 7))  # centre relative to the seed (the weighted centroid)
            start[:, 2:5] = shape_from_moments(moments[:, 0], moments[:, 1], moments[:, 2], sigma_e)
            start[:, 5] = np.concatenate([st.peak_dn for st in stacks])
            start[:, 6] = np.concatenate([st.background_dn for st in stacks])
            fit = fit_discs(
                stacks, seeds, start,
                band=(INSIDE_SIGMAS * sigma_e, OUTSIDE_SIGMAS * sigma_e),
                profile=self.profile,
                noise_sigma_dn=background.sigma_dn,
                gain_e_per_dn=self.gain_e_per_dn,
                max_iterations=self.max_iterations,
            )
            good = fit.ok & (np.hypot(fit.params[:, 0], fit.params[:, 1]) < MAX_SHIFT_PX)
            fit.params[:, :2] += seeds
        else:
            good = np.zeros(0, bool)
        for i in np.flatnonzero(~good):
            rejected.append(RejectedBlob((float(seeds[i, 0]), float(seeds[i, 1])), "fit_failed"))
        keep = np.flatnonzero(good)
        if keep.size:
            params, cov = fit.params[keep], fit.cov[keep]
        else:
            params, cov = np.zeros((0, 7)), np.zeros((0, 7, 7))
        order = sort_order(params[:, :2])
        params, cov = params[order], cov[order]
        kept = keep[order]
        area = np.concatenate([st.area_px for st in stacks]).astype(np.float64) if n else np.zeros(0)
        roundness = np.concatenate([st.roundness for st in stacks]) if n else np.zeros(0)
        return CentroidSet(
            camera=camera,
            sequence=sequence,
            uv=params[:, :2],
            sigma_uv=np.sqrt(np.stack((cov[:, 0, 0], cov[:, 1, 1]), axis=-1)) if len(cov) else np.zeros((0, 2)),
            area_px=area[kept],
            roundness=roundness[kept],
            peak=params[:, 5],
            rejected=sort_rejected(rejected),
            method=self.method,
            ellipse=params[:, 2:5],
            ellipse_cov=cov[:, 2:5, 2:5],
        )


@hookimpl
def register_centroids(register) -> None:
    register("modelfit", ModelFitCentroids, "Shared blob detector, ML fit of a blurred elliptical disc (vectorised)")
