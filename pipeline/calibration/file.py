"""The calibration file ``crossfield calibrate`` writes, and its standard deviations read back.

The file is OpenCV FileStorage YAML with the keys of OpenCV's
``samples/cpp/stereo_calib.cpp`` (M1 D1 M2 D2 R T, R1 R2 P1 P2 Q) plus the
image size (:mod:`crossfield.camera.calibration_io`), so the folder, basler
and opencv sources and any OpenCV program read it. The uncertainty sits
under keys of its own, which those readers ignore:

* ``std_M1`` / ``std_M2``: 1 x 4, standard deviations of fx fy cx cy (px);
* ``std_D1`` / ``std_D2``: 1 x n, of the distortion coefficients;
* ``std_R``: 3 x 1, of the rotation vector of R (rad); ``std_T``: 3 x 1 (mm);
* ``cov_params``: p x p covariance of all of them, in the order of
  ``cov_param_names`` (a string, names separated by spaces);
* ``rms_px_upper``, ``rms_px_lower``, ``rms_px_stereo``: RMS reprojection errors (px);
* ``sigma_px``: the corner noise estimated from the residuals (px);
* ``board``: the board definition (TOML text, one line per key, ``;``-joined);
* ``std_jacobian``, ``std_jackknife``: 1 x p, the two standard deviations
  behind the ``std_*`` keys (which hold the larger), in ``cov_param_names``
  order (the jackknife's -1 where not computed);
* ``calobject_warp_mm``, ``calobject_warp_std_mm``: 1 x 2, the board's bow
  (wx, wy) and its std (mm), when estimated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crossfield.calibration.solve import CalibrationResult
from crossfield.camera.calibration_io import stereo_calibration_to_yaml, write_stereo_calibration
from crossfield.errors import ConfigError


def _extra(result: CalibrationResult) -> dict[str, object]:
    std = result.std
    n_int = len(result.param_names) // 2 - 3  # per camera: 4 + n_dist
    upper, lower, rig = std[:n_int], std[n_int : 2 * n_int], std[2 * n_int :]
    board = "; ".join(f"{k} = {v!r}" for k, v in result.board.to_dict().items())
    return {
        "std_M1": upper[:4].reshape(1, 4),
        "std_D1": upper[4:].reshape(1, -1),
        "std_M2": lower[:4].reshape(1, 4),
        "std_D2": lower[4:].reshape(1, -1),
        "std_R": rig[:3].reshape(3, 1),
        "std_T": rig[3:].reshape(3, 1),
        "cov_params": np.asarray(result.covariance),
        "cov_param_names": " ".join(result.param_names),
        "rms_px_upper": float(result.cameras["upper"].rms_px),
        "rms_px_lower": float(result.cameras["lower"].rms_px),
        "rms_px_stereo": float(result.rms_stereo_px),
        "sigma_px": float(result.sigma_px),
        "board": board,
        **_std_sources(result),
    }


def _std_sources(result: CalibrationResult) -> dict[str, object]:
    out: dict[str, object] = {}
    for key in ("std_jacobian", "std_jackknife"):
        v = getattr(result, key)
        if v is not None:
            out[key] = np.where(np.isfinite(v), v, -1.0).reshape(1, -1)
    if result.warp_mm is not None and np.all(np.isfinite(result.warp_mm)):
        out["calobject_warp_mm"] = np.asarray(result.warp_mm, float).reshape(1, 2)
        out["calobject_warp_std_mm"] = np.asarray(result.warp_std_mm, float).reshape(1, 2)
    return out


def write_calibration_result(path: str | Path, result: CalibrationResult) -> Path:
    """Write ``result``'s calibration and uncertainty keys (module docstring) to ``path``."""
    return write_stereo_calibration(path, result.calibration, extra=_extra(result))


def calibration_result_yaml(result: CalibrationResult) -> str:
    """The same file as text (for a recording's attachment)."""
    return stereo_calibration_to_yaml(result.calibration, extra=_extra(result))


#: The keys the budget's calibration term reads (:mod:`crossfield.uncertainty.calibration`):
#: the name each is returned under, and the names accepted in a file (``std_*`` as
#: :func:`write_calibration_result` writes them, ``*_std`` as well).
UNCERTAINTY_KEYS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("T_std", ("std_T", "T_std")),
    ("M1_std", ("std_M1", "M1_std")),
    ("M2_std", ("std_M2", "M2_std")),
    ("T", ("T",)),
    ("M1", ("M1",)),
    ("M2", ("M2",)),
)


def read_uncertainty_keys(text: str) -> dict[str, np.ndarray]:
    """The :data:`UNCERTAINTY_KEYS` found in the FileStorage text ``text`` (YAML, XML or
    JSON: a calibration file's content, from disk or from a recording's copy; never a
    path): name -> matrix (float64; T mm, M px, std as the file states them). A key
    that is missing or not a matrix is left out; a text OpenCV cannot parse gives ``{}``
    (the budget then uses its stated default)."""
    found: dict[str, np.ndarray] = {}
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # a parse error arrives as SystemError wrapping cv2.error
        return found
    try:
        if not fs.isOpened():
            return found
        for key, names in UNCERTAINTY_KEYS:
            for name in names:
                node = fs.getNode(name)
                if not node.empty() and node.isMap():
                    value = node.mat()
                    if value is not None:
                        found.setdefault(key, np.asarray(value, dtype=np.float64))
    finally:
        fs.release()
    return found


@dataclass(frozen=True)
class CalibrationUncertainty:
    """The uncertainty keys of a calibration file: names (p,), covariance (p, p), std (p,)."""

    names: tuple[str, ...]
    covariance: np.ndarray
    source: str

    @property
    def std(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, np.sqrt(np.diag(self.covariance)))))


def read_calibration_uncertainty(path: str | Path) -> CalibrationUncertainty | None:
    """The covariance written by ``crossfield calibrate``, or None if the file has none (e.g. stereo_calib's)."""
    path = Path(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node, names = fs.getNode("cov_params"), fs.getNode("cov_param_names")
        if node.empty() or node.isNone():
            return None
        cov = node.mat()
        labels = tuple(names.string().split()) if not names.empty() else ()
        if cov is None or cov.ndim != 2 or cov.shape[0] != cov.shape[1] or len(labels) != cov.shape[0]:
            raise ConfigError(
                f"{path}: 'cov_params' must be a square matrix with one name per row in 'cov_param_names'"
            )
        return CalibrationUncertainty(labels, np.asarray(cov, float), str(path))
    finally:
        fs.release()
