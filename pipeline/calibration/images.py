"""Calibration image pairs from a folder, named like the folder source's pairs.

File names follow a pattern as the folder source's (``upper_0000.png`` / ``lower_0000.png``).

8-bit or 16-bit single-channel PNG/TIFF; the bit depth of 16-bit files is
the smallest of 10, 12, 14, 16 that holds every pixel value unless given.
Errors name the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crossfield.camera.pair_files import pattern_regex
from crossfield.errors import ConfigError
from crossfield.types import CAMERAS


@dataclass(frozen=True)
class ImagePairs:
    """images: per pair a dict camera -> (H, W) uint8/uint16 array; names: the upper files' names."""

    images: tuple[dict[str, np.ndarray], ...]
    names: tuple[str, ...]
    bit_depth: int
    folder: Path


def _read(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ConfigError(f"{path}: unreadable image (not a PNG/TIFF that OpenCV can decode)")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ConfigError(
            f"{path}: expected an 8- or 16-bit grey image, got {image.dtype} of shape {image.shape}"
        )
    return image


def read_image_pairs(
    folder: str | Path, pattern: str = "{camera}_{seq}.png", bit_depth: int | None = None
) -> ImagePairs:
    """Every complete (upper, lower) pair in ``folder``, in increasing sequence number."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder}: image folder not found")
    try:
        regex = pattern_regex(pattern)
    except ValueError as exc:
        raise ConfigError(f"--pattern: {exc}") from None
    found: dict[int, dict[str, Path]] = {}
    for entry in sorted(folder.iterdir()):
        match = regex.match(entry.name)
        if match and entry.is_file():
            found.setdefault(int(match["seq"]), {})[match["camera"]] = entry
    if not found:
        raise ConfigError(f"{folder}: no image files match the pattern {pattern!r}")
    images, names = [], []
    for seq, slot in sorted(found.items()):
        missing = [c for c in CAMERAS if c not in slot]
        if missing:
            (present,) = slot.values()
            raise ConfigError(f"{present}: no {missing[0]} image to pair it with")
        pair = {cam: _read(slot[cam]) for cam in CAMERAS}
        for cam in CAMERAS:
            first = images[0][cam] if images else pair[cam]
            if pair[cam].shape != first.shape or pair[cam].dtype != first.dtype:
                raise ConfigError(
                    f"{slot[cam]}: {pair[cam].dtype} {pair[cam].shape[::-1]} differs from the "
                    f"first {cam} image's {first.dtype} {first.shape[::-1]}"
                )
        images.append(pair)
        names.append(slot["upper"].name)
    if bit_depth is None:
        if images[0]["upper"].dtype == np.uint8:
            bit_depth = 8
        else:
            peak = max(int(v[c].max()) for v in images for c in CAMERAS)
            bit_depth = next(b for b in (10, 12, 14, 16) if peak < 1 << b)
    return ImagePairs(tuple(images), tuple(names), int(bit_depth), folder)


def write_image_pairs(folder: str | Path, images, *, pattern: str = "{camera}_{seq:04d}.png") -> list[Path]:
    """Write pairs as 16-bit (or 8-bit) PNGs named like the folder source's; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, view in enumerate(images):
        for cam in CAMERAS:
            path = folder / pattern.format(camera=cam, seq=k)
            if not cv2.imwrite(str(path), view[cam]):
                raise ConfigError(f"{path}: cannot write the image")
            paths.append(path)
    return paths
