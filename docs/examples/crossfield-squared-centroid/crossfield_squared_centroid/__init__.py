"""Squared-intensity weighted centroids: an example crossfield plugin.

Registers the centroid implementation ``squared`` through the ``crossfield``
entry-point group (see pyproject.toml). Only crossfield's public API is
used: ``crossfield.hookspecs.hookimpl`` and the data class
``crossfield.types.CentroidSet``.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossfield.hookspecs import hookimpl
from crossfield.types import CentroidSet, RejectedBlob


class SquaredCentroids:
    """Blobs above ``background + threshold_sigma * noise``; centre = sum(w u) / sum(w)
    with w = (I - background)^2 over the blob dilated by ``dilate_px`` pixels.

    Units: pixels (OpenCV convention: (0, 0) is the centre of the top-left
    pixel); DN for intensities.
    """

    def __init__(self, *, threshold_sigma: float = 8.0, min_area_px: int = 30, dilate_px: int = 2) -> None:
        if threshold_sigma <= 0 or min_area_px < 1 or dilate_px < 0:
            raise ValueError("threshold_sigma, min_area_px and dilate_px must be positive")
        self.threshold_sigma = threshold_sigma
        self.min_area_px = min_area_px
        self.dilate_px = dilate_px

    def extract(self, image: np.ndarray, camera: str, sequence: int) -> CentroidSet:
        sample = image[::8, ::8].astype(np.float64)
        background = float(np.median(sample))
        noise = 1.4826 * float(np.median(np.abs(sample - background))) + 0.5
        mask = (image > background + self.threshold_sigma * noise).astype(np.uint8)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        height, width = image.shape
        uv, sigma, area, roundness, peak, rejected = [], [], [], [], [], []
        d = self.dilate_px
        for k in range(1, count):
            x, y, w, h, n = stats[k]
            if n < self.min_area_px:
                rejected.append(RejectedBlob((x + w / 2, y + h / 2), "too_small"))
                continue
            if x - d < 0 or y - d < 0 or x + w + d > width or y + h + d > height:
                rejected.append(RejectedBlob((x + w / 2, y + h / 2), "touches_border"))
                continue
            roi = image[y - d : y + h + d, x - d : x + w + d].astype(np.float64) - background
            window = cv2.dilate((labels[y - d : y + h + d, x - d : x + w + d] == k).astype(np.uint8), np.ones((2 * d + 1,) * 2, np.uint8))
            weights = np.clip(roi, 0, None) ** 2 * window
            total = weights.sum()
            vv, uu = np.mgrid[y - d : y + h + d, x - d : x + w + d]
            u = float((weights * uu).sum() / total)
            v = float((weights * vv).sum() / total)
            # First-order noise propagation of the weighted mean: dw/dI = 2 (I - b).
            var_i = noise**2
            grad = 2 * np.clip(roi, 0, None) * window
            su = float(np.sqrt(((uu - u) ** 2 * grad**2 * var_i).sum()) / total)
            sv = float(np.sqrt(((vv - v) ** 2 * grad**2 * var_i).sum()) / total)
            cu = float((weights * (uu - u) ** 2).sum() / total)
            cv_ = float((weights * (vv - v) ** 2).sum() / total)
            cuv = float((weights * (uu - u) * (vv - v)).sum() / total)
            eig = np.linalg.eigvalsh([[cu, cuv], [cuv, cv_]])
            uv.append((u, v))
            sigma.append((su, sv))
            area.append(float(n))
            roundness.append(float(np.sqrt(max(eig[0], 0) / eig[1])) if eig[1] > 0 else 0.0)
            peak.append(float(roi.max()))
        return CentroidSet(
            camera=camera,
            sequence=sequence,
            uv=np.array(uv, dtype=np.float64).reshape(-1, 2),
            sigma_uv=np.array(sigma, dtype=np.float64).reshape(-1, 2),
            area_px=np.array(area),
            roundness=np.array(roundness),
            peak=np.array(peak),
            rejected=tuple(rejected),
            method="squared",
        )


@hookimpl
def register_centroids(register):
    register("squared", SquaredCentroids, "Squared-intensity weighted centroids (example plugin)")
