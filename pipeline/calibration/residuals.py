"""Residual maps: the reprojection residuals binned over the image, per camera.

Corner noise averages out in a bin; what the model does not fit does not:
an unmodelled distortion, a decentred lens or a bent board shows as a
pattern of mean residual vectors (mrcal docs, "Residual maps" / "how good is
this calibration"). A good calibration's map is noise: bin means of about
``sigma / sqrt(count)`` px pointing anywhere.

Residual = observed - projected (px); pixels: (0, 0) is the centre of the
top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Bins across (columns, rows) of the image.
RESIDUAL_GRID = (16, 12)


@dataclass(frozen=True)
class ResidualMap:
    """Binned residuals of one camera.

    mean_px: (rows, cols, 2) mean residual (du, dv) px per bin (NaN where
    empty); count: (rows, cols) points per bin; centres_px: (rows, cols, 2)
    bin centres (u, v) px; sigma_px: RMS of one residual coordinate about its
    bin's mean (the corner noise, without the pattern).
    """

    camera: str
    image_size: tuple[int, int]
    mean_px: np.ndarray
    count: np.ndarray
    centres_px: np.ndarray
    sigma_px: float

    @property
    def amplitude_px(self) -> float:
        """RMS length of the bin means (px) over the bins with >= 3 points."""
        ok = self.count >= 3
        return float(np.sqrt(np.mean(np.sum(self.mean_px[ok] ** 2, axis=-1)))) if ok.any() else float("nan")

    @property
    def noise_amplitude_px(self) -> float:
        """The amplitude that corner noise alone gives: sqrt(mean over bins of 2 sigma^2 / count) px."""
        ok = self.count >= 3
        return float(np.sqrt(np.mean(2 * self.sigma_px**2 / self.count[ok]))) if ok.any() else float("nan")

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: the grid, means (px, None where empty), counts and amplitudes."""
        mean = np.where(np.isnan(self.mean_px), None, np.round(self.mean_px, 5)).tolist()
        return {
            "grid": [int(self.count.shape[1]), int(self.count.shape[0])],
            "mean_px": mean,
            "count": self.count.tolist(),
            "amplitude_px": self.amplitude_px,
            "noise_amplitude_px": self.noise_amplitude_px,
            "sigma_px": self.sigma_px,
        }


def residual_map(
    camera: str,
    points_px: np.ndarray,
    residuals_px: np.ndarray,
    image_size: tuple[int, int],
    grid: tuple[int, int] = RESIDUAL_GRID,
) -> ResidualMap:
    """Bin (N, 2) residuals (px) at (N, 2) observed points (px) over a cols x rows grid of the image."""
    points_px = np.asarray(points_px, float).reshape(-1, 2)
    residuals_px = np.asarray(residuals_px, float).reshape(-1, 2)
    if len(points_px) != len(residuals_px):
        raise ValueError(f"{len(points_px)} points but {len(residuals_px)} residuals")
    cols, rows = grid
    w, h = image_size
    c = np.clip((points_px[:, 0] + 0.5) / w * cols, 0, cols - 1).astype(int)
    r = np.clip((points_px[:, 1] + 0.5) / h * rows, 0, rows - 1).astype(int)
    count = np.zeros((rows, cols), int)
    total = np.zeros((rows, cols, 2))
    np.add.at(count, (r, c), 1)
    np.add.at(total, (r, c), residuals_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count[..., None]
    mean[count == 0] = np.nan
    cu = (np.arange(cols) + 0.5) * w / cols - 0.5
    cv = (np.arange(rows) + 0.5) * h / rows - 0.5
    centres = np.stack(np.meshgrid(cu, cv), axis=-1)
    scatter = residuals_px - mean[r, c]
    sigma = float(np.sqrt(np.mean(scatter**2))) if len(residuals_px) else float("nan")
    return ResidualMap(camera, (int(w), int(h)), mean, count, centres, sigma)
