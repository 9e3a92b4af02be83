"""The stereo calibration's parameter uncertainty, as a relative scale of camera-frame distances.

Stereo depth is ``Z = f B / disparity`` and lateral positions ``X = x Z / f``:
an error of the baseline B or of the focal length f scales the triangulated
points (to first order, about the rig). The rigid registration to the
controls cannot absorb a scale, so a camera point p moves by ``s (p - g_bar)``
(g_bar the control centroid, global frame) for a relative scale error s, with

    u(s)^2 = (u(|T|) / |T|)^2 + (u(f) / f)^2 ,

u(|T|) from the calibration file's ``std_T`` (mm, per component) and u(f)
from ``std_M1`` / ``std_M2`` (px, standard deviations of fx fy cx cy: fx
first), the keys ``crossfield calibrate`` writes (``T_std``, ``M1_std``,
``M2_std`` are read as well; the reader is
:func:`crossfield.calibration.file.read_uncertainty_keys`). Without
them the stated default :data:`DEFAULT_SCALE_U` is used. The file's content is
the one the session read at its start, which a replay and an audit take from
the recording's copy (:mod:`crossfield.recording.calibration_files`), never
from the recorded path.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["DEFAULT_SCALE_U", "CalibrationUncertainty", "calibration_uncertainty"]

#: Relative scale uncertainty of a calibration that states none (1e-5 = 10 ppm,
#: 3 um over 300 mm; a good target-board calibration of a 50 mm baseline).
DEFAULT_SCALE_U = 1.0e-5


class CalibrationUncertainty:
    """scale_u: relative standard uncertainty of camera-frame distances; source: where it came from."""

    def __init__(self, scale_u: float, source: str) -> None:
        self.scale_u = float(scale_u)
        self.source = source

    def __repr__(self) -> str:
        return f"CalibrationUncertainty(scale_u={self.scale_u!r}, source={self.source!r})"


def calibration_uncertainty(
    source: str = "", default: float = DEFAULT_SCALE_U, files: Sequence[Any] | None = None
) -> CalibrationUncertainty:
    """The relative scale uncertainty of the calibration in ``files`` (the calibration
    files' contents, :class:`crossfield.recording.calibration_files.CalibrationFile`:
    read at a live session's start, or the recorded copies in a replay; the first file
    holding a key wins), or ``default`` when they state no standard deviations. Without
    ``files`` the files ``source`` names (paths joined by ``", "``) are read now."""
    from crossfield.calibration.file import read_uncertainty_keys  # the one reader of the std_* keys
    from crossfield.recording.calibration_files import read_calibration_files

    keys: dict[str, np.ndarray] = {}
    for f in read_calibration_files(source) if files is None else files:
        for key, value in read_uncertainty_keys(f.text).items():
            keys.setdefault(key, value)
    terms = []
    if "T_std" in keys and "T" in keys:
        T = keys["T"].reshape(-1)
        norm = float(np.linalg.norm(T))
        if norm > 0:
            # u(|T|) = |T^ . u(T)| for independent components: sqrt(sum (T_i/|T| u_i)^2)
            terms.append(float(np.sqrt(np.sum((T / norm * keys["T_std"].reshape(-1)) ** 2))) / norm)
    for m, m_std in (("M1", "M1_std"), ("M2", "M2_std")):
        if m_std in keys and m in keys:
            std = keys[m_std].reshape(-1)
            f = float(keys[m].reshape(-1)[0])
            u_f = float(std[0]) if std.size else 0.0  # fx (OpenCV's stdDeviationsIntrinsics order)
            if f > 0:
                terms.append(u_f / f / math.sqrt(2.0))  # two cameras, averaged in the disparity
    if not terms:
        return CalibrationUncertainty(default, "stated default")
    return CalibrationUncertainty(math.sqrt(sum(t * t for t in terms)), "calibration file std_* keys")
