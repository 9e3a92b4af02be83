"""Centroid plugin "modelfit": maximum-likelihood fit of a blurred elliptical disc per target.

Detection (threshold, blobs, rejection, local background, the window of
each blob) and the CentroidSet are the shared
:class:`crossfield.imaging.centroids.BlobCentroids` (the batched detector,
``detect_stacks``: one gather per ROI size class); the
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

from collections.abc import Sequence

import numpy as np

from crossfield.plugin_api import (
    PSF_ORDERS,
    Background,
    BlobCentroids,
    BlobStack,
    SubPixel,
    edge_profile,
    fit_discs,
    hookimpl,
    shape_from_moments,
)

#: a fitted centre further than this from its seed (px) is a failed fit
MAX_SHIFT_PX = 1.5
#: window pixels further inside / outside the seed's edge than these multiples of sigma_e
#: (3.5 / 3.0 px at blur 0.9 px) are left out of the fit: the edge profile's slope there is
#: < 0.1 % / 0.6 % of its peak, they would inform only the amplitude / background, and cost time
INSIDE_SIGMAS = 3.7
OUTSIDE_SIGMAS = 3.2


class ModelFitCentroids(BlobCentroids):
    """Blobs from the shared detector; centres from an ML blurred-disc fit.

    Options: the detection options of :class:`~crossfield.imaging.centroids.BlobCentroids`
    (threshold_sigma, min_area_px, max_area_px, min_roundness, reject_saturated,
    reject_border, bit_depth, dilate_px, ring_px, background_stride), plus
    gain_e_per_dn: conversion gain (e-/DN) for the photon noise;
    blur_sigma_px: the Gaussian PSF sigma (px);
    psf_order: ``"optical"`` (PSF on the scene, then pixel integration: a
      real camera) or ``"pixel"`` (pixel coverage blurred on the pixel grid:
      how the simulator and the synthetic test images are rendered);
    max_iterations: Gauss-Newton iteration limit.
    A blob whose fit does not converge to a disc near its seed is rejected as
    ``"fit_failed"``; the fitted edge conics go to ``CentroidSet.ellipse``
    (with ``ellipse_cov``).
    """

    method = "modelfit"
    fits_conics = True

    def __init__(
        self,
        *,
        gain_e_per_dn: float = 2.86,
        blur_sigma_px: float = 0.9,
        psf_order: str = "optical",
        max_iterations: int = 1,
        **detector,
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
        super().__init__(**detector)

    def subpixel(self, stacks: Sequence[BlobStack], background: Background) -> SubPixel:
        """The ML disc fit of every blob, seeded by its weighted centroid and second moments."""
        seeds = np.concatenate([st.uv for st in stacks])
        n = len(seeds)
        sigma_e = float(np.sqrt(self.blur_sigma_px**2 + 1.0 / 12.0))
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
        params, cov = fit.params, fit.cov
        params[:, :2] += seeds
        with np.errstate(invalid="ignore"):  # a failed fit's covariance may be anything; it is rejected
            sigma_uv = np.sqrt(np.stack((cov[:, 0, 0], cov[:, 1, 1]), axis=-1))
        return SubPixel(
            uv=params[:, :2],
            sigma_uv=sigma_uv,
            ok=good,
            peak=params[:, 5],
            ellipse=params[:, 2:5],
            ellipse_cov=cov[:, 2:5, 2:5],
        )


@hookimpl
def register_centroids(register) -> None:
    register("modelfit", ModelFitCentroids, "Shared blob detector, ML fit of a blurred elliptical disc (vectorised)")
