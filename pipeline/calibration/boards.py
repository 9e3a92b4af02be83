"""Planar calibration boards: the definition read from TOML (``docs/calibration.md``).

Three kinds of board, each a ``[board]`` table:

* ``type = "charuco"`` (the default): ``squares_x`` x ``squares_y`` chessboard
  squares of ``square_mm``, ArUco markers of ``marker_mm`` from ``dictionary``
  (an OpenCV predefined dictionary name such as ``"DICT_5X5_100"``) in the
  white squares; ``legacy_pattern = true`` for boards printed by OpenCV < 4.6
  with an even number of rows. Partial views are usable.
* ``type = "chessboard"``: ``squares_x`` x ``squares_y`` squares of
  ``square_mm``; the inner corners ((squares_x - 1) x (squares_y - 1)) are
  the points; the whole board must be in view; squares_x + squares_y must
  be odd (an even x odd board is not symmetric under a half turn).
* ``type = "circles"``: OpenCV's asymmetric circle grid, ``circles_x``
  circles per row, ``circles_y`` rows, ``spacing_mm`` between the rows (a
  row's circles are ``2 * spacing_mm`` apart, every other row shifted by
  ``spacing_mm``), circles of ``diameter_mm``; the whole grid must be in view.

The board frame (mm): origin at the outer top-left corner of the pattern as
printed, x along the squares_x direction, y along squares_y (down the
printed page), z = x cross y into the board. Point ids: ChArUco corner ids
(row-major over the inner corners), the same numbering for the chessboard,
row-major for the circle grid.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossfield.errors import ConfigError

BOARD_TYPES = ("charuco", "chessboard", "circles")

_KEYS: dict[str, dict[str, type]] = {
    "charuco": {
        "squares_x": int,
        "squares_y": int,
        "square_mm": float,
        "marker_mm": float,
        "dictionary": str,
        "legacy_pattern": bool,
    },
    "chessboard": {"squares_x": int, "squares_y": int, "square_mm": float},
    "circles": {"circles_x": int, "circles_y": int, "spacing_mm": float, "diameter_mm": float},
}
_DEFAULTS: dict[str, Any] = {"legacy_pattern": False, "dictionary": "DICT_5X5_100"}


@dataclass(frozen=True)
class Board:
    """A planar calibration target (all lengths in mm; see the module docstring for the frame).

    Fields not used by ``type`` are 0 / "" (e.g. ``marker_mm`` of a chessboard).
    """

    type: str = "charuco"
    squares_x: int = 11
    squares_y: int = 8
    square_mm: float = 15.0
    marker_mm: float = 11.0
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False
    circles_x: int = 0
    circles_y: int = 0
    spacing_mm: float = 0.0
    diameter_mm: float = 0.0
    source: str = "<default board>"

    # ---- geometry -------------------------------------------------------------------------------

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(columns, rows) of points as OpenCV's detectors take it."""
        if self.type == "circles":
            return (self.circles_x, self.circles_y)
        return (self.squares_x - 1, self.squares_y - 1)

    @property
    def n_points(self) -> int:
        cols, rows = self.pattern_size
        return cols * rows

    def object_points(self) -> np.ndarray:
        """(n_points, 3) float64 board-frame coordinates (mm) of every point, indexed by point id."""
        cols, rows = self.pattern_size
        r, c = np.divmod(np.arange(cols * rows), cols)
        if self.type == "circles":
            # OpenCV samples/cpp/calibration.cpp, ASYMMETRIC_CIRCLES_GRID: ((2 j + i % 2) s, i s, 0).
            x = (2 * c + r % 2) * self.spacing_mm
            y = r * self.spacing_mm
        else:
            x = (c + 1) * self.square_mm
            y = (r + 1) * self.square_mm
        return np.stack([x, y, np.zeros_like(x)], axis=1).astype(np.float64)

    @property
    def extent_mm(self) -> tuple[float, float]:
        """(width, height) of the printed pattern (mm), without the white margin."""
        if self.type == "circles":
            return (
                (2 * self.circles_x - 1) * self.spacing_mm + self.diameter_mm,
                (self.circles_y - 1) * self.spacing_mm + self.diameter_mm,
            )
        return (self.squares_x * self.square_mm, self.squares_y * self.square_mm)

    @property
    def pattern_origin_mm(self) -> tuple[float, float]:
        """Board-frame coordinates (mm) of the pattern's top-left corner (circles: first circle's bounding box)."""
        if self.type == "circles":
            return (-self.diameter_mm / 2, -self.diameter_mm / 2)
        return (0.0, 0.0)

    # ---- OpenCV objects -------------------------------------------------------------------------

    def aruco_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ChArUco board (``type == "charuco"`` only)."""
        board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            float(self.square_mm),
            float(self.marker_mm),
            self.aruco_dictionary(),
        )
        board.setLegacyPattern(bool(self.legacy_pattern))
        return board

    def to_dict(self) -> dict[str, Any]:
        keys = ["type", *_KEYS[self.type]]
        return {k: getattr(self, k) for k in keys}


def _check_value(source: str, key: str, value: Any, kind: type) -> Any:
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 2:
            raise ConfigError(f"{source}: [board] {key} must be an integer >= 2, got {value!r}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ConfigError(f"{source}: [board] {key} must be a length in mm > 0, got {value!r}")
        return float(value)
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: [board] {key} must be true or false, got {value!r}")
        return value
    if not isinstance(value, str):
        raise ConfigError(f"{source}: [board] {key} must be a string, got {value!r}")
    return value


def board_from_dict(data: dict[str, Any], source: str = "<board>") -> Board:
    """A :class:`Board` from the ``[board]`` table's contents; errors name ``source`` and the key."""
    kind = data.get("type", "charuco")
    if kind not in BOARD_TYPES:
        raise ConfigError(f"{source}: [board] type must be one of {', '.join(BOARD_TYPES)}, got {kind!r}")
    allowed = _KEYS[kind]
    unknown = sorted(set(data) - set(allowed) - {"type"})
    if unknown:
        raise ConfigError(
            f"{source}: [board] unknown key {unknown[0]!r} for type {kind!r} (keys: {', '.join(allowed)})"
        )
    values: dict[str, Any] = {"type": kind, "source": source}
    for key, expected in allowed.items():
        if key not in data:
            if key in _DEFAULTS:
                values[key] = _DEFAULTS[key]
                continue
            raise ConfigError(
                f"{source}: [board] {key} is missing (type {kind!r} needs {', '.join(k for k in allowed if k not in _DEFAULTS)})"
            )
        values[key] = _check_value(source, key, data[key], expected)
    if kind == "charuco":
        if not values["marker_mm"] < values["square_mm"]:
            raise ConfigError(f"{source}: [board] marker_mm ({values['marker_mm']}) must be < square_mm")
        name = values["dictionary"]
        if not name.startswith("DICT_") or not isinstance(getattr(cv2.aruco, name, None), int):
            raise ConfigError(f"{source}: [board] dictionary {name!r} is not an OpenCV predefined dictionary")
        board = Board(**values)
        markers = (board.squares_x * board.squares_y) // 2
        size = len(board.aruco_dictionary().bytesList)
        if markers > size:
            raise ConfigError(f"{source}: [board] needs {markers} markers, dictionary {name} has only {size}")
        return board
    if kind == "chessboard" and (values["squares_x"] + values["squares_y"]) % 2 == 0:
        raise ConfigError(
            f"{source}: [board] a chessboard of {values['squares_x']} x {values['squares_y']} squares looks the same "
            f"after a half turn, so its corners cannot be numbered; use an odd number of squares one way and an "
            f"even number the other (e.g. 9 x 6)"
        )
    if kind == "circles" and not values["diameter_mm"] < 2 * values["spacing_mm"] * 0.7071:
        raise ConfigError(f"{source}: [board] circles overlap: diameter_mm must be < spacing_mm * sqrt(2)")
    return Board(**values)


def read_board_file(path: str | Path) -> dict:
    """The TOML document of a board file, checked to hold a ``[board]`` table (its other
    tables, e.g. ``[calibration]``, are the caller's); a :class:`ConfigError` naming the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: board file not found") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a board file: a binary file, not UTF-8 TOML text") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    if not isinstance(data.get("board"), dict):
        raise ConfigError(f"{path}: no [board] table")
    return data


def load_board(path: str | Path) -> Board:
    """Read ``[board]`` from a TOML file (see the module docstring for the keys)."""
    return board_from_dict(read_board_file(path)["board"], str(path))


def board_toml(board: Board) -> str:
    """The ``[board]`` table for ``board`` (what :func:`load_board` reads)."""
    lines = ["[board]"]
    for key, value in board.to_dict().items():
        text = (
            f'"{value}"'
            if isinstance(value, str)
            else ("true" if value is True else "false" if value is False else repr(value))
        )
        lines.append(f"{key} = {text}")
    return "\n".join(lines) + "\n"
