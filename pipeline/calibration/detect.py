"""Finding a calibration board's points in one image (OpenCV detectors + sub-pixel refinement).

* ChArUco: ``cv2.aruco.CharucoDetector.detectBoard`` (markers, then the
  chessboard corners between them; partial views give the visible corners);
* chessboard: ``cv2.findChessboardCornersSB`` (whole board), and where it
  fails the classic ``cv2.findChessboardCorners`` (adaptive threshold,
  normalised image; at half resolution on large images), so the views the
  classic detector finds are found;
* circles: ``cv2.findCirclesGrid`` with ``CALIB_CB_ASYMMETRIC_GRID`` (whole grid).

The detectors run on an 8-bit copy. Chessboard corners are then refined
with ``cv2.cornerSubPix`` on the full-depth image (float32). ChArUco
corners are **not** refined again: the CharucoDetector already refines each
corner in a window bounded by its neighbouring markers, and a second
cornerSubPix pass with a window of a third of the square reaches the marker
edges when squares are small (measured against rendered truth, a 6 mm board
at 400 mm: 0.34 px RMS, 1.7 px max, against 0.05 px / 0.20 px without it;
``tests/test_board_corners.py``). The 8-bit copy loses nothing measurable:
a 12-bit image's shot noise (~30 DN) is far above the 16 DN step.
Pixels: (0, 0) is the centre of the top-left pixel (OpenCV convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from crossfield.calibration.boards import Board
from crossfield.types import frozen_array

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


@dataclass(frozen=True)
class BoardDetection:
    """The board points found in one image.

    ids: (N,) int point ids (see :mod:`crossfield.calibration.boards`);
    image_points: (N, 2) px; object_points: (N, 3) board frame, mm.
    """

    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "ids", frozen_array(self.ids, np.int64, (None,)))
        object.__setattr__(self, "image_points", frozen_array(self.image_points, shape=(len(self.ids), 2)))
        object.__setattr__(self, "object_points", frozen_array(self.object_points, shape=(len(self.ids), 3)))

    def __len__(self) -> int:
        return len(self.ids)

    def subset(self, ids: np.ndarray) -> BoardDetection:
        """The points whose id is in ``ids``, in the order of ``ids``."""
        index = {int(i): k for k, i in enumerate(self.ids)}
        rows = [index[int(i)] for i in ids]
        return BoardDetection(self.ids[rows], self.image_points[rows], self.object_points[rows])

    def orientation(self) -> float:
        """Sign of the board-to-image map's determinant: +1 as seen from the front, -1 if mirrored.

        The homography from board (x, y) to pixels (Hartley & Zisserman 4.1)
        keeps the orientation for any view of the printed side through a
        pinhole lens; a reflected image (sensor read-out reversed in x or y,
        a mirror in the path) reverses it. 0 if it cannot be told (< 4
        points or collinear).
        """
        if len(self) < 4:
            return 0.0
        H, _ = cv2.findHomography(self.object_points[:, :2], self.image_points, 0)
        if H is None:
            return 0.0
        centre = np.append(self.object_points[:, :2].mean(axis=0), 1.0)
        w = H[2] @ centre
        # Jacobian of the homography at the centre of the points: det(A - p h^T) / w^3 (sign only).
        p = H[:2] @ centre / w
        J = (H[:2, :2] - np.outer(p, H[2, :2])) / w
        return float(np.sign(np.linalg.det(J)))


def to_uint8(image: np.ndarray, bit_depth: int) -> np.ndarray:
    """A uint8 copy of a (H, W) image holding ``bit_depth``-bit values (8- or 16-bit array)."""
    if image.dtype == np.uint8:
        return image
    shift = max(int(bit_depth) - 8, 0)
    return np.clip(image.astype(np.uint32) >> shift, 0, 255).astype(np.uint8)


def _refine(image: np.ndarray, corners: np.ndarray, half_window: int) -> np.ndarray:
    """cornerSubPix on the float32 image; corners (N, 2) px."""
    pts = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    win = (half_window, half_window)
    refined = cv2.cornerSubPix(image.astype(np.float32), pts, win, (-1, -1), _SUBPIX_CRITERIA)
    return refined.reshape(-1, 2).astype(np.float64)


def _half_window(image_points: np.ndarray, ids: np.ndarray, board: Board) -> int:
    """cornerSubPix half window: about a third of the smallest imaged square side (px), 3..15."""
    cols = board.pattern_size[0]
    by_id = {int(i): p for i, p in zip(ids, image_points)}
    sides = [
        np.linalg.norm(by_id[i + 1] - p) for i, p in by_id.items() if (i % cols) < cols - 1 and i + 1 in by_id
    ]
    sides += [np.linalg.norm(by_id[i + cols] - p) for i, p in by_id.items() if i + cols in by_id]
    if not sides:
        return 5
    return int(np.clip(min(sides) / 3.0, 3, 15))


def _first_square_black(grey8: np.ndarray, pts: np.ndarray, cols: int) -> np.ndarray:
    """Order chessboard corners so that corner 0 touches the printed black top-left square.

    findChessboardCornersSB may start from either end of the grid (a half
    turn); the colours tell: the square beyond corner 0 is black, its
    neighbour along the row white (``Board`` requires squares_x + squares_y
    odd, so a half turn swaps the two).
    """
    h, w = grey8.shape

    def value(p: np.ndarray) -> float:
        x, y = int(round(p[0])), int(round(p[1]))
        return float(grey8[min(max(y, 0), h - 1), min(max(x, 0), w - 1)])

    outer = pts[0] + 0.5 * (pts[0] - pts[cols + 1])  # centre of square (0, 0)
    beside = outer + (pts[1] - pts[0])  # centre of square (1, 0)
    return pts if value(outer) < value(beside) else pts[::-1].copy()


def _classic_chessboard(grey8: np.ndarray, pattern_size: tuple[int, int]) -> tuple[bool, np.ndarray | None]:
    """OpenCV's classic ``findChessboardCorners`` (adaptive threshold, normalised), for views SB misses.

    On images wider than 1000 px it runs at half resolution: at full size it
    takes 4-18 s on a 1626 x 1236 view without a whole board (0.4 s at half
    size) and found the same views in the station's tests. Corners are mapped
    back with the pixel-centre convention (u_full = 2 u_half + 0.5) and refined
    at full resolution by the caller.
    """
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    if grey8.shape[1] <= 1000:
        return cv2.findChessboardCorners(grey8, pattern_size, flags=flags)
    half = cv2.resize(grey8, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    found, corners = cv2.findChessboardCorners(half, pattern_size, flags=flags)
    if not found:
        return False, None
    return True, corners * 2.0 + 0.5


class BoardDetector:
    """Detects one :class:`Board` in grey images (reusable across images).

    min_points: a view with fewer points is reported as not detected (None).
    """

    def __init__(self, board: Board, *, min_points: int = 6):
        self.board = board
        self.min_points = max(int(min_points), 4)
        self._object = board.object_points()
        if board.type == "charuco":
            params = cv2.aruco.CharucoParameters()
            params.minMarkers = 2
            detector_params = cv2.aruco.DetectorParameters()
            detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            self._charuco = cv2.aruco.CharucoDetector(board.charuco_board(), params, detector_params)

    def detect(self, image: np.ndarray, bit_depth: int = 8) -> BoardDetection | None:
        """The board's points in a (H, W) uint8/uint16 image, or None if not found."""
        grey8 = to_uint8(image, bit_depth)
        kind = self.board.type
        if kind == "charuco":
            corners, ids, _, _ = self._charuco.detectBoard(grey8)
            if ids is None or len(ids) < self.min_points:
                return None
            ids = ids.ravel().astype(np.int64)
            pts = corners.reshape(-1, 2).astype(np.float64)
        elif kind == "chessboard":
            found, corners = cv2.findChessboardCornersSB(
                grey8, self.board.pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE
            )
            if not found:
                found, corners = _classic_chessboard(grey8, self.board.pattern_size)
            if not found:
                return None
            ids = np.arange(self.board.n_points)
            pts = _first_square_black(
                grey8, corners.reshape(-1, 2).astype(np.float64), self.board.pattern_size[0]
            )
            pts = _refine(image, pts, _half_window(pts, ids, self.board))
        else:
            found, centres = cv2.findCirclesGrid(
                grey8,
                self.board.pattern_size,
                flags=cv2.CALIB_CB_ASYMMETRIC_GRID,  # dark circles on white
            )
            if not found:
                return None
            ids = np.arange(self.board.n_points)
            pts = centres.reshape(-1, 2).astype(np.float64)
        if len(ids) < self.min_points:
            return None
        return BoardDetection(ids, pts, self._object[ids])
