"""Which centroids of a stereo pair stand for which plan ids: the labels every view of a
session shows (the Rerun view, :mod:`crossfield.viz.rerun_log`; the Foxglove overlays,
:mod:`crossfield.recording.foxglove_overlay`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from crossfield.types import CAMERAS

__all__ = ["centroid_names"]


def centroid_names(result: Any) -> dict[str, dict[int, tuple[str, str]]]:
    """camera -> {centroid index: (plan id, role)} of the centroids whose camera point was
    matched to a control point ("control") or identified as a target ("target"); the rule
    of the Rerun view (the measurement reports the mapped camera point itself)."""
    points, registration, measurement = result.points, result.registration, result.measurement
    if points is None or registration is None:
        return {}
    by_point: dict[int, tuple[str, str]] = {}
    corr = registration.correspondence
    for cid, index in zip(corr.control_ids, corr.camera_index):
        by_point[int(index)] = (str(cid), "control")
    if measurement is not None and measurement.target_points and len(points):
        global_xyz = registration.fit.apply(points.xyz)
        for tid, xyz in measurement.target_points.items():
            d = np.linalg.norm(global_xyz - np.asarray(xyz, dtype=np.float64), axis=1)
            i = int(np.argmin(d))
            if d[i] < 1e-6:
                by_point[i] = (str(tid), "target")
    out: dict[str, dict[int, tuple[str, str]]] = {camera: {} for camera in CAMERAS}
    for i, named in by_point.items():
        if 0 <= i < len(points):
            out["upper"][int(points.upper_index[i])] = named
            out["lower"][int(points.lower_index[i])] = named
    return out
