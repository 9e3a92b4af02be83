"""acquire "folder": stereo pairs read from image files in a folder.

Format (``docs/triangulation.md``, "Image-folder source"):

* one image per camera and frame, named by ``pattern`` (default
  ``"{camera}_{seq}.png"``, e.g. ``upper_0001.png`` / ``lower_0001.png``):
  ``{camera}`` is ``upper`` or ``lower``, ``{seq}`` a run of digits giving
  the frame's sequence number, ``*`` matches any characters; files that do
  not match the pattern are ignored;
* single-channel 16-bit PNG or TIFF (8-bit accepted when ``bit_depth <= 8``),
  holding ``bit_depth``-bit values, read with ``cv2.IMREAD_UNCHANGED``;
* the stereo calibration as OpenCV FileStorage YAML
  (:mod:`crossfield.camera.calibration_io`): ``calibration`` names one file or a list
  of files (``["intrinsics.yml", "extrinsics.yml"]``), relative paths being
  taken relative to the folder; by default the folder's ``calibration.yml``,
  else its ``intrinsics.yml`` + ``extrinsics.yml``.

Frames are yielded in increasing sequence number; ``timestamp_ns`` is the
upper image file's modification time (ns since the epoch). The measurement
plan comes from the session config (``default_plan`` is None).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossfield.plugin_api import (
    CAMERAS,
    Acquisition,
    ConfigError,
    Register,
    StereoCalibration,
    StereoFrame,
    hookimpl,
    pattern_regex,
    read_stereo_calibration,
)

DEFAULT_CALIBRATION_FILES: tuple[tuple[str, ...], ...] = (
    ("calibration.yml",),
    ("calibration.yaml",),
    ("intrinsics.yml", "extrinsics.yml"),
)


class FolderAcquisition:
    """Stereo pairs from paired image files in a folder, with an OpenCV stereo calibration.

    path: the folder. pattern: file-name pattern (``{camera}``, ``{seq}``, ``*``).
    calibration: calibration file or list of files (FileStorage YAML, keys
    M1 D1 M2 D2 R T; camera 1 = upper; ``p_lower = R p_upper + T``, T in mm);
    "" = look in the folder. bit_depth: significant bits per pixel (1..16).
    """

    ground_truth = None
    default_plan = None

    def __init__(
        self,
        *,
        path: str,
        pattern: str = "{camera}_{seq}.png",
        calibration: str | list[str] = "",
        bit_depth: int = 12,
    ):
        if isinstance(bit_depth, bool) or not isinstance(bit_depth, int) or not 1 <= bit_depth <= 16:
            raise ValueError(f"option 'bit_depth' must be an integer 1..16, got {bit_depth!r}")
        self.folder = Path(path).expanduser()
        if not self.folder.is_dir():
            raise ConfigError(f"{self.folder}: image folder not found")
        self.pattern = pattern
        self.bit_depth = bit_depth
        self.pairs = self._scan(pattern_regex(pattern))
        self.calibration_files = self._calibration_files(calibration)
        first_sequence = next(iter(self.pairs))
        first_sizes = tuple(self._image_size(self.pairs[first_sequence][camera]) for camera in CAMERAS)
        self.calibration: StereoCalibration = read_stereo_calibration(
            self.calibration_files, image_sizes=first_sizes
        )

    # ---- set-up --------------------------------------------------------------------------------

    def _scan(self, regex: re.Pattern[str]) -> dict[int, dict[str, Path]]:
        found: dict[int, dict[str, Path]] = {}
        for entry in sorted(self.folder.iterdir()):
            match = regex.match(entry.name)
            if match is None or not entry.is_file():
                continue
            camera, sequence = match["camera"], int(match["seq"])
            slot = found.setdefault(sequence, {})
            if camera in slot:
                raise ConfigError(
                    f"{entry}: same camera and sequence number ({camera}, {sequence}) as {slot[camera]}"
                )
            slot[camera] = entry
        if not found:
            raise ConfigError(f"{self.folder}: no image files match the pattern {self.pattern!r}")
        for sequence, slot in sorted(found.items()):
            for camera in CAMERAS:
                if camera not in slot:
                    (present,) = slot.values()
                    match = regex.match(present.name)
                    name = present.name
                    partner = name[: match.start("camera")] + camera + name[match.end("camera") :]
                    raise ConfigError(
                        f"{present}: no {camera} image to pair it with (expected a file like {partner} "
                        f"matching the pattern {self.pattern!r})"
                    )
        return dict(sorted(found.items()))

    def _calibration_files(self, calibration: str | list[str]) -> list[Path]:
        if isinstance(calibration, str):
            names = [calibration] if calibration else []
        elif isinstance(calibration, (list, tuple)) and all(isinstance(c, str) and c for c in calibration):
            names = list(calibration)
        else:
            raise ValueError(f"option 'calibration' must be a path or a list of paths, got {calibration!r}")
        if names:
            return [p if p.is_absolute() else self.folder / p for p in map(Path, names)]
        for candidate in DEFAULT_CALIBRATION_FILES:
            paths = [self.folder / name for name in candidate]
            if all(p.is_file() for p in paths):
                return paths
        tried = "; ".join(" + ".join(c) for c in DEFAULT_CALIBRATION_FILES)
        raise ConfigError(
            f"{self.folder}: no calibration given and none found in the folder (looked for {tried}); "
            f"set the option 'calibration'"
        )

    def _image_size(self, path: Path) -> tuple[int, int]:
        image = self._read(path)
        return (image.shape[1], image.shape[0])

    # ---- reading -------------------------------------------------------------------------------

    def _read(self, path: Path) -> np.ndarray:
        """The image at ``path`` as a (H, W) uint16 array, checked; errors name the file."""
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            if not path.is_file():
                raise ConfigError(f"{path}: image file disappeared")
            raise ConfigError(f"{path}: unreadable image (not a PNG/TIFF that OpenCV can decode)")
        if image.ndim != 2:
            raise ConfigError(f"{path}: expected a single-channel (grey) image, got shape {image.shape}")
        if image.dtype == np.uint8 and self.bit_depth <= 8:
            image = image.astype(np.uint16)
        elif image.dtype != np.uint16:
            raise ConfigError(
                f"{path}: expected 16-bit unsigned pixels for bit_depth {self.bit_depth}, got {image.dtype}"
            )
        peak = int(image.max()) if image.size else 0
        if peak >= 1 << self.bit_depth:
            raise ConfigError(
                f"{path}: pixel value {peak} exceeds the {self.bit_depth}-bit range; the values may be "
                f"MSB-aligned (set bit_depth = 16) or the option 'bit_depth' is wrong"
            )
        return image

    def _checked(self, path: Path, camera: str) -> np.ndarray:
        image = self._read(path)
        want = self.calibration.camera(camera).image_size
        if (image.shape[1], image.shape[0]) != want:
            raise ConfigError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]} px, the {camera} camera's "
                f"calibration ({self.calibration.source}) is for {want[0]}x{want[1]} px"
            )
        return image

    def frames(self) -> Iterator[StereoFrame]:
        """Yield the pairs in increasing sequence number (StereoFrame, uint16 images)."""
        for sequence, slot in self.pairs.items():
            images = {camera: self._checked(slot[camera], camera) for camera in CAMERAS}
            yield StereoFrame(
                sequence=sequence,
                timestamp_ns=os.stat(slot["upper"]).st_mtime_ns,
                upper=images["upper"],
                lower=images["lower"],
                bit_depth=self.bit_depth,
            )

    def describe(self) -> dict[str, Any]:
        """Source parameters for the session record (JSON-able)."""
        sequences = list(self.pairs)
        return {
            "source": "folder",
            "path": str(self.folder),
            "pattern": self.pattern,
            "pairs": len(sequences),
            "first_sequence": sequences[0],
            "last_sequence": sequences[-1],
            "bit_depth": self.bit_depth,
            "calibration_files": [str(p) for p in self.calibration_files],
            "image_size": {c: list(self.calibration.camera(c).image_size) for c in CAMERAS},
        }

    def close(self) -> None:
        """Nothing to release (files are opened per frame)."""


@hookimpl
def register_acquires(register: Register[Acquisition]) -> None:
    register("folder", FolderAcquisition, "Paired 16-bit PNG/TIFF images from a folder + OpenCV calibration")
