"""Centroid plugin "ellipse": ellipse fitted to the sub-pixel edge of each blob.

Detection (threshold, blobs, rejection, local background) is shared with
the other centroid plugins in :mod:`crossfield.imaging.blobs`; this module does the
sub-pixel step (``docs/centroids.md``).

A retro-reflective target images as a flat-topped, blurred ellipse. Its
iso-intensity contour at half the plateau height (above the local
background) is, for a point-symmetric blur, a closed curve with the same
centre as the image ellipse; on a straight edge it lies on the edge itself.
Per blob:

1. f = I - b - level, with b the local background and
   level = ``edge_level`` * (peak - b);
2. edge points: every pair of 4-neighbouring pixels inside the blob's window
   where f changes sign, placed by linear interpolation,
   ``u = u_0 + f_0 / (f_0 - f_1)``; a row pair is kept only where the edge
   runs more across the row than along it (|df/du| >= |df/dv|), a column
   pair likewise, so each edge point comes from its better-conditioned
   direction;
3. ``cv2.fitEllipseDirect`` (direct least-squares ellipse fit, Fitzgibbon,
   Pilu & Fisher 1999) to the points; the blob centre is the ellipse centre.

Uncertainty: from the fit's own residuals. d_i = radial distance of edge
point i from the fitted ellipse (along the ray from the centre),
sigma_d^2 = sum(d_i^2) / (N - 5), and the centre covariance of a geometric
fit, with the centre decoupled from the axes and angle (exact for points
all round the ellipse)::

    cov(u_c, v_c) = sigma_d^2 * (sum_i n_i n_i^T)^-1

where n_i is the unit normal of the ellipse at point i (Gauss-Newton normal
equations, e.g. Ahn et al. 2001, "Least-squares orthogonal distances
fitting of circle, sphere, ellipse..."). It contains the noise and the
interpolation error of the edge points.

Unlike the weighted centroid it does not need the plateau: with
``reject_saturated = False`` it measures saturated targets without bias.
Pixels in u, v; (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from crossfield.plugin_api import (
    Blob,
    BlobDetector,
    CentroidSet,
    DetectorOptions,
    RejectedBlob,
    hookimpl,
    sort_order,
    sort_rejected,
)

#: fewer edge points than this and the fit is not trusted
MIN_EDGE_POINTS = 12


def edge_points(blob: Blob, edge_level: float) -> np.ndarray:
    """Sub-pixel points (N, 2) (u, v) in ROI pixel coordinates where the blob's
    background-subtracted intensity crosses ``edge_level`` * its peak."""
    roi = blob.roi
    h, w = roi.shape
    level = blob.background_dn + edge_level * blob.peak_dn
    # Integer images: I >= level <=> I >= ceil(level); no float copy of the ROI.
    above = roi >= (math.ceil(level) if roi.dtype.kind in "ui" else level)
    inside = blob.window.view(bool)
    flat = roi.ravel()  # (h * w,) pixel p = r * w + c
    parts = []
    # Pairs along rows (u direction): p = (r, c) and p + 1 = (r, c + 1).
    k = np.flatnonzero((above[:, :-1] != above[:, 1:]) & inside[:, :-1] & inside[:, 1:])
    if k.size:
        r, c = np.divmod(k, w - 1)
        p = r * w + c
        up, down = np.maximum(p - w, c), np.minimum(p + w, (h - 1) * w + c)  # clamped rows
        f0 = flat[p] - level
        f1 = flat[p + 1] - level
        gv = flat[down].astype(np.float64) + flat[down + 1] - flat[up] - flat[up + 1]
        keep = np.abs(f1 - f0) * 4.0 >= np.abs(gv)  # |dI/du| >= |dI/dv|
        f0, f1 = f0[keep], f1[keep]
        parts.append(np.column_stack((c[keep] + f0 / (f0 - f1), r[keep])))
    # Pairs along columns (v direction): p = (r, c) and p + w = (r + 1, c).
    k = np.flatnonzero((above[:-1, :] != above[1:, :]) & inside[:-1, :] & inside[1:, :])
    if k.size:
        r, c = np.divmod(k, w)
        p = k
        left, right = p - (c > 0), p + (c < w - 1)  # clamped columns
        f0 = flat[p] - level
        f1 = flat[p + w] - level
        gu = flat[right].astype(np.float64) + flat[right + w] - flat[left] - flat[left + w]
        keep = np.abs(f1 - f0) * 4.0 > np.abs(gu)  # |dI/dv| > |dI/du|
        f0, f1 = f0[keep], f1[keep]
        parts.append(np.column_stack((c[keep], r[keep] + f0 / (f0 - f1))))
    if not parts:
        return np.zeros((0, 2))
    return np.concatenate(parts)


def fit_ellipse(points: np.ndarray) -> tuple[float, float, float, float] | None:
    """Centre (u, v) of the ellipse fitted to (N, 2) points and its standard
    uncertainty (sigma_u, sigma_v), pixels; None if the fit fails."""
    n = len(points)
    if n < MIN_EDGE_POINTS:
        return None
    (uc, vc), (width, height), angle_deg = cv2.fitEllipseDirect(points.astype(np.float32))
    a, b = width / 2.0, height / 2.0
    if not (a > 0 and b > 0 and math.isfinite(uc) and math.isfinite(vc)):
        return None
    theta = math.radians(angle_deg)
    ct, st = math.cos(theta), math.sin(theta)
    du, dv = points[:, 0] - uc, points[:, 1] - vc
    x = ct * du + st * dv  # ellipse frame: x along the "width" axis
    y = -st * du + ct * dv
    rho = np.sqrt((x / a) ** 2 + (y / b) ** 2)
    dist = np.hypot(du, dv)
    ok = rho > 0
    residual = dist[ok] * (1.0 - 1.0 / rho[ok])  # radial distance to the ellipse
    # unit normals of the ellipse at the points' directions, image frame
    nx, ny = x / (a * a), y / (b * b)
    nu, nv = ct * nx - st * ny, st * nx + ct * ny
    norm = np.hypot(nu, nv)
    norm[norm == 0] = 1.0
    nu, nv = nu / norm, nv / norm
    normal = np.array([[nu @ nu, nu @ nv], [nu @ nv, nv @ nv]])
    dof = max(len(residual) - 5, 1)
    sigma_d2 = float(residual @ residual) / dof
    try:
        cov = sigma_d2 * np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        return None
    return uc, vc, math.sqrt(max(cov[0, 0], 0.0)), math.sqrt(max(cov[1, 1], 0.0))


class EllipseCentroids:
    """Thresholded blobs; centre of an ellipse fitted to the sub-pixel edge points.

    Options: as for "weighted" (threshold_sigma, min_area_px, max_area_px,
    min_roundness, reject_saturated, reject_border, bit_depth, dilate_px,
    ring_px, background_stride), plus edge_level: the edge is where the
    background-subtracted intensity crosses edge_level * peak (0 < edge_level < 1).
    """

    method = "ellipse"

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
        edge_level: float = 0.5,
    ) -> None:
        if not 0.0 < edge_level < 1.0:
            raise ValueError(f"edge_level must be in (0, 1), got {edge_level}")
        self.edge_level = float(edge_level)
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
        A blob whose edge cannot be fitted is rejected as ``"fit_failed"``.
        """
        blobs, rejected, _ = self.detector.detect(image)
        kept: list[Blob] = []
        rows: list[tuple[float, float, float, float]] = []
        for blob in blobs:
            fit = fit_ellipse(edge_points(blob, self.edge_level))
            h, w = blob.roi.shape
            if fit is None or not (0 <= fit[0] < w and 0 <= fit[1] < h):
                rejected.append(RejectedBlob(blob.uv, "fit_failed"))
                continue
            kept.append(blob)
            rows.append((blob.x0 + fit[0], blob.y0 + fit[1], fit[2], fit[3]))
        table = np.array(rows, dtype=np.float64).reshape(-1, 4)
        order = sort_order(table[:, :2])
        return CentroidSet(
            camera=camera,
            sequence=sequence,
            uv=table[order, :2],
            sigma_uv=table[order, 2:],
            area_px=np.array([kept[i].area_px for i in order], dtype=np.float64),
            roundness=np.array([kept[i].roundness for i in order], dtype=np.float64),
            peak=np.array([kept[i].peak_dn for i in order], dtype=np.float64),
            rejected=sort_rejected(rejected),
            method=self.method,
        )


@hookimpl
def register_centroids(register) -> None:
    register("ellipse", EllipseCentroids, "Thresholded blobs, ellipse fitted to sub-pixel edge points")
