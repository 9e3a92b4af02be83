"""How well calibration views cover each image: pure functions for the live view and the report.

* Cells: the image is divided into ``grid`` x ``grid`` cells
  (:data:`COVERAGE_GRID`); a cell is covered when a board point fell in it
  (:func:`coverage_cells`). The report's coverage share
  (:func:`crossfield.calibration.report.coverage_fraction`) is this count.
* Regions: the image in thirds (top-left ... bottom-right); a region whose
  cells are less than half covered is named as still empty
  (:func:`empty_regions`), so the user knows where to hold the board next.
* Tilt: per view the angle between the board's normal and the camera's
  optical axis (deg), and the spread of the views' orientations = the
  largest angle between the normals of two views. Zhang's method needs
  views at different orientations (Zhang 2000, sec. 3.3: parallel planes
  add no constraint). The pose of a view is found with a provisional
  pinhole camera: ``cv2.initCameraMatrix2D`` (the closed-form focal length
  from the views' homographies, principal point at the image centre, Zhang
  2000 sec. 3.1) and ``cv2.solvePnP`` (``SOLVEPNP_IPPE``, planar targets),
  no distortion: good to a few degrees, enough to guide the user.

Pixels: (0, 0) is the centre of the top-left pixel (OpenCV convention);
image sizes are (width, height) px; board points are mm in the board frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from crossfield.calibration.detect import BoardDetection

__all__ = [
    "COVERAGE_GRID",
    "REGION_NAMES",
    "CameraCoverage",
    "board_normals",
    "camera_coverage",
    "coverage_cells",
    "coverage_line",
    "coverage_picture",
    "empty_regions",
]

#: The image is divided into COVERAGE_GRID x COVERAGE_GRID cells.
COVERAGE_GRID = 8

#: The image in thirds, row by row (index = 3 * row + column).
REGION_NAMES: tuple[str, ...] = (
    "top-left", "top", "top-right",
    "left", "centre", "right",
    "bottom-left", "bottom", "bottom-right",
)  # fmt: skip


def coverage_cells(points: np.ndarray, image_size: tuple[int, int], grid: int = COVERAGE_GRID) -> np.ndarray:
    """Board points per cell: (grid, grid) int array, [row, column] (row 0 = top of the image).

    points: (N, 2) px (u, v); image_size: (width, height) px. A point on or
    beyond the image border counts in the border cell.
    """
    counts = np.zeros((grid, grid), dtype=np.int64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) == 0:
        return counts
    w, h = image_size
    col = np.clip((points[:, 0] / w * grid).astype(int), 0, grid - 1)
    row = np.clip((points[:, 1] / h * grid).astype(int), 0, grid - 1)
    np.add.at(counts, (row, col), 1)
    return counts


def empty_regions(counts: np.ndarray) -> tuple[str, ...]:
    """The :data:`REGION_NAMES` whose cells (by cell centre) are less than half covered."""
    grid = counts.shape[0]
    third = np.minimum(((np.arange(grid) + 0.5) / grid * 3).astype(int), 2)  # region of each row/col
    out = []
    for r in range(3):
        for c in range(3):
            block = counts[np.ix_(third == r, third == c)]
            if block.size and np.mean(block > 0) < 0.5:
                out.append(REGION_NAMES[3 * r + c])
    return tuple(out)


def board_normals(detections: Sequence[BoardDetection], image_size: tuple[int, int]) -> np.ndarray:
    """The board's unit normal in the camera frame per view, (V, 3), pointing away from the camera (+z).

    Provisional pinhole (module docstring): ``initCameraMatrix2D`` over all
    the views, then ``solvePnP`` (IPPE) per view; the normal is the third
    column of the board-to-camera rotation, sign chosen so that n_z > 0.
    Empty (0, 3) if no view has 4 points.
    """
    views = [d for d in detections if len(d) >= 4]
    if not views:
        return np.zeros((0, 3))
    obj = [np.ascontiguousarray(d.object_points, np.float32).reshape(-1, 1, 3) for d in views]
    img = [np.ascontiguousarray(d.image_points, np.float32).reshape(-1, 1, 2) for d in views]
    K = cv2.initCameraMatrix2D(obj, img, tuple(int(s) for s in image_size), 1.0)
    normals = []
    for o, i in zip(obj, img):
        ok, rvec, _ = cv2.solvePnP(o, i, K, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            continue
        n = cv2.Rodrigues(rvec)[0][:, 2]
        normals.append(n if n[2] >= 0 else -n)
    return np.array(normals).reshape(-1, 3)


@dataclass(frozen=True)
class CameraCoverage:
    """One camera's coverage so far.

    counts: (grid, grid) board points per cell ([row, column]); views: views
    in which the board was found; tilts_deg: (V,) angle between each view's
    board normal and the optical axis (deg); spread_deg: largest angle
    between the normals of two views (deg, 0 with fewer than 2 views).
    """

    camera: str
    image_size: tuple[int, int]
    counts: np.ndarray
    views: int
    tilts_deg: tuple[float, ...]
    spread_deg: float

    @property
    def fraction(self) -> float:
        """Share of the cells holding at least one board point (0..1)."""
        return float(np.mean(self.counts > 0))

    @property
    def empty(self) -> tuple[str, ...]:
        """Regions still less than half covered (:func:`empty_regions`)."""
        return empty_regions(self.counts)


def camera_coverage(
    camera: str,
    detections: Sequence[BoardDetection | None],
    image_size: tuple[int, int],
    grid: int = COVERAGE_GRID,
) -> CameraCoverage:
    """The coverage of one camera's image by ``detections`` (None = board not found in that view)."""
    found = [d for d in detections if d is not None and len(d)]
    points = np.concatenate([d.image_points for d in found]) if found else np.zeros((0, 2))
    normals = board_normals(found, image_size)
    tilts = tuple(float(np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0)))) for n in normals)
    spread = 0.0
    if len(normals) >= 2:
        cosines = np.clip(normals @ normals.T, -1.0, 1.0)
        spread = float(np.degrees(np.arccos(cosines.min())))
    return CameraCoverage(
        camera, (int(image_size[0]), int(image_size[1])), coverage_cells(points, image_size, grid),
        len(found), tilts, spread,
    )


def coverage_line(coverage: Mapping[str, CameraCoverage]) -> str:
    """One line per update: per camera cells covered, empty regions, tilt range and spread."""
    parts = []
    for cam, c in coverage.items():
        text = f"{cam} {c.views} views, {int(np.sum(c.counts > 0))}/{c.counts.size} cells ({c.fraction:.0%})"
        if c.tilts_deg:
            text += (
                f", tilt {min(c.tilts_deg):.0f}-{max(c.tilts_deg):.0f} deg (spread {c.spread_deg:.0f} deg)"
            )
        empty = c.empty
        if len(empty) == len(REGION_NAMES):
            text += ", empty: everywhere"
        else:
            text += f", empty: {', '.join(empty)}" if empty else ", no empty region"
        parts.append(text)
    return "; ".join(parts)


def coverage_picture(
    coverage: CameraCoverage,
    points: np.ndarray | None = None,
    image: np.ndarray | None = None,
    *,
    scale: float = 0.25,
) -> np.ndarray:
    """A small RGB picture of the coverage: covered cells tinted green, empty ones red, over
    the (optional) latest image, with the (optional) latest view's points (N, 2) px as dots.

    image: (H, W) uint8 grey at full size (px); returns (round(H*scale), round(W*scale), 3) uint8.
    """
    w, h = coverage.image_size
    sw, sh = max(1, round(w * scale)), max(1, round(h * scale))
    if image is None:
        base = np.full((sh, sw), 96, np.uint8)
    else:
        base = cv2.resize(np.asarray(image, np.uint8), (sw, sh), interpolation=cv2.INTER_AREA)
    rgb = np.repeat(base[:, :, None], 3, axis=2).astype(np.float32)
    grid = coverage.counts.shape[0]
    rows = np.minimum((np.arange(sh) + 0.5) / sh * grid, grid - 1).astype(int)
    cols = np.minimum((np.arange(sw) + 0.5) / sw * grid, grid - 1).astype(int)
    hit = coverage.counts[np.ix_(rows, cols)] > 0
    tint = np.where(hit[:, :, None], np.array([40.0, 200.0, 40.0]), np.array([220.0, 40.0, 40.0]))
    rgb = 0.6 * rgb + 0.4 * tint
    for g in range(1, grid):  # cell borders
        rgb[:, min(sw - 1, round(g * sw / grid))] = 255.0
        rgb[min(sh - 1, round(g * sh / grid)), :] = 255.0
    out = np.clip(rgb, 0, 255).astype(np.uint8)
    if points is not None:
        for u, v in np.asarray(points, np.float64).reshape(-1, 2) * scale:
            cv2.circle(out, (int(round(u)), int(round(v))), 1, (255, 255, 0), -1)
    return out
