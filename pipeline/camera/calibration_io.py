"""Read and write the stereo calibration as OpenCV FileStorage YAML.

The format is the one OpenCV's ``samples/cpp/stereo_calib.cpp`` writes
(``docs/triangulation.md``, "Calibration files"):

* ``intrinsics.yml``: ``M1``, ``D1``, ``M2``, ``D2`` (camera matrices in
  pixels, distortion coefficients in OpenCV order);
* ``extrinsics.yml``: ``R``, ``T`` (and ``R1 R2 P1 P2 Q`` from
  ``stereoRectify``, which crossfield ignores when reading).

Camera 1 is the **upper** camera, camera 2 the **lower** one, and
``p_lower = R @ p_upper + T`` with ``T`` in millimetres (calibrate with the
board's square size given in mm). One file holding all six keys works as
well as the pair. Optional keys ``image_width`` / ``image_height`` (both
cameras) or ``image_width1`` / ``image_height1`` / ``image_width2`` /
``image_height2`` (per camera) give the image size, which stereo_calib.cpp
does not store; without them the caller must supply the size (the folder
source takes it from the first image pair).

Every error is a :class:`crossfield.errors.ConfigError` naming the file and
the key at fault.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossfield.errors import ConfigError
from crossfield.types import CameraIntrinsics, StereoCalibration

__all__ = [
    "DIST_LENGTHS",
    "REQUIRED_KEYS",
    "Size",
    "read_stereo_calibration",
    "stereo_calibration_from_yaml",
    "stereo_calibration_to_yaml",
    "write_stereo_calibration",
]

#: Keys a stereo calibration must provide (across the file or files given).
REQUIRED_KEYS: tuple[str, ...] = ("M1", "D1", "M2", "D2", "R", "T")
#: Lengths of OpenCV's distortion vectors (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]).
DIST_LENGTHS: tuple[int, ...] = (4, 5, 8, 12, 14)
_ROTATION_TOLERANCE = 1e-6

Size = tuple[int, int]


class _Store:
    """Key lookup over one or more opened FileStorage objects, remembering where each key was found."""

    def __init__(self, storages: list[tuple[str, cv2.FileStorage]]):
        self.storages = storages

    @property
    def names(self) -> str:
        return ", ".join(name for name, _ in self.storages)

    def node(self, key: str) -> tuple[str, cv2.FileNode] | None:
        for name, fs in self.storages:
            node = fs.getNode(key)
            if not node.empty() and not node.isNone():
                return name, node
        return None

    def matrix(self, key: str) -> tuple[str, np.ndarray]:
        found = self.node(key)
        if found is None:
            raise ConfigError(f"{self.names}: calibration key {key!r} is missing")
        name, node = found
        try:
            value = node.mat() if node.isMap() else None
        except cv2.error:
            value = None
        if value is None:
            raise ConfigError(f"{name}: calibration key {key!r} is not an OpenCV matrix (!!opencv-matrix)")
        return name, np.asarray(value, dtype=np.float64)

    def integer(self, key: str) -> tuple[str, int] | None:
        found = self.node(key)
        if found is None:
            return None
        name, node = found
        if not (node.isInt() or node.isReal()) or node.real() != int(node.real()) or node.real() <= 0:
            raise ConfigError(f"{name}: calibration key {key!r} must be a positive integer")
        return name, int(node.real())


def _open(text_or_path: str, source: str, memory: bool) -> cv2.FileStorage:
    flags = cv2.FILE_STORAGE_READ | (cv2.FILE_STORAGE_MEMORY if memory else 0)
    try:
        fs = cv2.FileStorage(text_or_path, flags)
    except (cv2.error, SystemError) as exc:  # a parse error arrives as SystemError wrapping cv2.error
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        lines = [line for line in str(cause).strip().splitlines() if line.strip()]
        detail = lines[-1].split("error: ", 1)[-1] if lines else "parse error"
        raise ConfigError(f"{source}: not a readable OpenCV FileStorage (YAML/XML) file: {detail}") from None
    if not fs.isOpened():
        raise ConfigError(f"{source}: cannot open as an OpenCV FileStorage (YAML/XML) file")
    return fs


def _camera_matrix(store: _Store, key: str) -> np.ndarray:
    name, M = store.matrix(key)
    if M.shape != (3, 3):
        raise ConfigError(f"{name}: calibration key {key!r} must be a 3x3 camera matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)) or M[0, 0] <= 0 or M[1, 1] <= 0 or not np.allclose(M[2], [0, 0, 1]):
        raise ConfigError(
            f"{name}: calibration key {key!r} is not a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
            f"with fx, fy > 0"
        )
    return M


def _dist_coeffs(store: _Store, key: str) -> np.ndarray:
    name, D = store.matrix(key)
    if D.ndim != 2 or 1 not in D.shape or D.size not in DIST_LENGTHS or not np.all(np.isfinite(D)):
        raise ConfigError(
            f"{name}: calibration key {key!r} must be a row or column vector of "
            f"{', '.join(map(str, DIST_LENGTHS))} finite coefficients, got shape {D.shape}"
        )
    return D.ravel()


def _image_size(store: _Store, camera_number: int, fallback: Size | None) -> Size:
    sizes = []
    for axis in ("width", "height"):
        found = store.integer(f"image_{axis}{camera_number}") or store.integer(f"image_{axis}")
        sizes.append(None if found is None else found[1])
    if None not in sizes:
        return (sizes[0], sizes[1])
    if fallback is None:
        raise ConfigError(
            f"{store.names}: no image size for camera {camera_number}: keys 'image_width'/'image_height' "
            f"(or 'image_width{camera_number}'/'image_height{camera_number}') are missing and no size "
            f"was given by the image source"
        )
    return (int(fallback[0]), int(fallback[1]))


def _calibration_from(store: _Store, image_sizes: Sequence[Size] | None) -> StereoCalibration:
    upper = CameraIntrinsics(
        _camera_matrix(store, "M1"), _dist_coeffs(store, "D1"),
        _image_size(store, 1, None if image_sizes is None else image_sizes[0]),
    )
    lower = CameraIntrinsics(
        _camera_matrix(store, "M2"), _dist_coeffs(store, "D2"),
        _image_size(store, 2, None if image_sizes is None else image_sizes[1]),
    )
    name, R = store.matrix("R")
    if R.shape == (3, 1) or R.shape == (1, 3):  # a rotation vector is accepted too (Rodrigues)
        R = cv2.Rodrigues(R.reshape(3, 1))[0]
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ConfigError(f"{name}: calibration key 'R' must be a 3x3 rotation matrix, got shape {R.shape}")
    orthogonality = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if orthogonality > _ROTATION_TOLERANCE or abs(det - 1.0) > _ROTATION_TOLERANCE:
        raise ConfigError(
            f"{name}: calibration key 'R' is not a rotation (max |R^T R - I| = {orthogonality:.2e}, "
            f"det = {det:.6f}; a right-handed rotation has det = +1)"
        )
    name, T = store.matrix("T")
    if T.size != 3 or 1 not in T.shape or not np.all(np.isfinite(T)):
        raise ConfigError(f"{name}: calibration key 'T' must be a 3-vector (mm), got shape {T.shape}")
    return StereoCalibration(upper, lower, R, T.ravel(), source=store.names)


def read_stereo_calibration(
    paths: str | Path | Iterable[str | Path], *, image_sizes: Sequence[Size] | None = None
) -> StereoCalibration:
    """Read a stereo calibration from one FileStorage file or several (e.g. intrinsics + extrinsics).

    paths: one path, or a list of paths searched in order for each key.
    image_sizes: ((width, height) upper, (width, height) lower) in pixels, used
    when the files do not store the image size.
    Returns a :class:`StereoCalibration` (R, T map upper to lower, T in mm);
    ``source`` names the files.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise ConfigError("no calibration file given")
    storages = []
    for path in paths:
        if not path.is_file():
            raise ConfigError(f"{path}: calibration file not found")
        storages.append((str(path), _open(str(path), str(path), memory=False)))
    try:
        return _calibration_from(_Store(storages), image_sizes)
    finally:
        for _, fs in storages:
            fs.release()


def stereo_calibration_from_yaml(
    text: str, source: str = "<calibration>", *, image_sizes: Sequence[Size] | None = None
) -> StereoCalibration:
    """Parse FileStorage YAML text (as :func:`stereo_calibration_to_yaml` writes it).

    Used to read a calibration back from a recording's attachment; errors name ``source``.
    """
    fs = _open(text, source, memory=True)
    try:
        return _calibration_from(_Store([(source, fs)]), image_sizes)
    finally:
        fs.release()


def _write(
    fs: cv2.FileStorage, calibration: StereoCalibration, rectification: bool, extra: Mapping[str, Any] | None = None
) -> None:
    fs.writeComment(
        "crossfield stereo calibration (OpenCV stereo_calib.cpp keys). Camera 1 = upper, camera 2 = lower; "
        "p_lower = R * p_upper + T, T in mm; pixel (0,0) = centre of the top-left pixel."
    )
    fs.write("M1", np.asarray(calibration.upper.camera_matrix, dtype=np.float64))
    fs.write("D1", np.asarray(calibration.upper.dist_coeffs, dtype=np.float64).reshape(1, -1))
    fs.write("M2", np.asarray(calibration.lower.camera_matrix, dtype=np.float64))
    fs.write("D2", np.asarray(calibration.lower.dist_coeffs, dtype=np.float64).reshape(1, -1))
    fs.write("R", np.asarray(calibration.R_lower_upper, dtype=np.float64))
    fs.write("T", np.asarray(calibration.t_lower_upper, dtype=np.float64).reshape(3, 1))
    if calibration.upper.image_size == calibration.lower.image_size:
        fs.write("image_width", int(calibration.upper.image_size[0]))
        fs.write("image_height", int(calibration.upper.image_size[1]))
    else:
        for number, camera in ((1, calibration.upper), (2, calibration.lower)):
            fs.write(f"image_width{number}", int(camera.image_size[0]))
            fs.write(f"image_height{number}", int(camera.image_size[1]))
    if rectification:
        # What stereo_calib.cpp stores next to R and T, so that other tools find them; not read back.
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
            np.asarray(calibration.upper.camera_matrix, dtype=np.float64),
            np.asarray(calibration.upper.dist_coeffs, dtype=np.float64),
            np.asarray(calibration.lower.camera_matrix, dtype=np.float64),
            np.asarray(calibration.lower.dist_coeffs, dtype=np.float64),
            calibration.upper.image_size,
            np.asarray(calibration.R_lower_upper, dtype=np.float64),
            np.asarray(calibration.t_lower_upper, dtype=np.float64).reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=-1,
        )
        for key, value in (("R1", R1), ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)):
            fs.write(key, value)
    for key, value in (extra or {}).items():  # e.g. the standard deviations `crossfield calibrate` adds
        fs.write(key, np.asarray(value, dtype=np.float64) if isinstance(value, np.ndarray) else value)


def stereo_calibration_to_yaml(
    calibration: StereoCalibration, *, rectification: bool = True, extra: Mapping[str, Any] | None = None
) -> str:
    """The calibration as FileStorage YAML text (one document with all keys, then ``extra``'s)."""
    fs = cv2.FileStorage("calibration.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    _write(fs, calibration, rectification, extra)
    return fs.releaseAndGetString()


def write_stereo_calibration(
    path: str | Path, calibration: StereoCalibration, *, rectification: bool = True,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``calibration`` to one FileStorage file (``.yml``/``.yaml``/``.xml``).

    Keys: M1 D1 M2 D2 R T image_width image_height (per-camera sizes as
    image_width1 ... when the cameras differ), plus R1 R2 P1 P2 Q from
    ``cv2.stereoRectify`` when ``rectification`` is true, then the keys of
    ``extra`` (numpy arrays as matrices, numbers, strings). Returns the path.
    """
    path = Path(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    except cv2.error as exc:
        raise ConfigError(f"{path}: cannot write calibration: {exc}") from None
    if not fs.isOpened():
        raise ConfigError(f"{path}: cannot open for writing")
    try:
        _write(fs, calibration, rectification, extra)
    finally:
        fs.release()
    return path
