"""One small picture per camera for the report: :class:`ThumbnailObserver`.

The report stage gets the :class:`~crossfield.session.SessionSummary`, never an
image. This observer, registered by the runner for every session (live run,
replay, audit: :func:`crossfield.chain.runner.run_session`), keeps for each camera
ONE downsampled 8-bit copy of the image of the session's first *measured*
stereo pair (else the first registered one, else the first with centroids,
else the first pair: a session whose centroid stage failed still shows why),
with that pair's centroids (px) and the target label of each: the control
point id the correspondence gave it, or the measured target id the measure
stage found there. The summary carries them (``summary.thumbnails``) and
report.html draws them (:func:`crossfield.report.figures.thumbnail_chart`).

Memory is bounded whatever the session's length: between ``on_frame`` and
``on_frame_done`` it holds a reference to the current pair (no copy), and
afterwards at most one thumbnail per camera (each at most ``max_width`` px
wide); a pair is downsampled only when it is better than the one kept (at
most four times per session).

Pixel convention (OpenCV, ``docs/conventions.md``): (0, 0) is the centre of
the top-left pixel. The image is reduced by an integer factor ``f`` by block
means (f x f pixels per thumbnail pixel, the last ``w mod f`` columns and
``h mod f`` rows dropped), so thumbnail pixel ``j`` is the mean of image
pixels ``f j .. f j + f - 1``, centred at ``f j + (f - 1) / 2``: an image
coordinate ``u`` is at thumbnail coordinate ``(u - (f - 1) / 2) / f``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from crossfield.hookspecs import hookimpl
from crossfield.session import CameraThumbnail, FrameResult
from crossfield.types import CAMERAS, CentroidSet, StereoFrame

__all__ = [
    "KIND_CONTROL",
    "KIND_TARGET",
    "LABEL_TOLERANCE_MM",
    "MAX_WIDTH_PX",
    "STATUS_RANK",
    "CameraThumbnail",
    "ThumbnailObserver",
    "downsample",
    "point_labels",
]

#: Default largest thumbnail width (px).
MAX_WIDTH_PX = 480

#: A measured target position (global, mm) names the camera point whose
#: registered position lies within this distance (the measure stage reports
#: ``fit.apply(p)`` of the point it identified: 0 mm for the built-in one).
LABEL_TOLERANCE_MM = 0.5

#: What a labelled centroid is: a common control point (correspondence) or a
#: measured target (measure stage); "" for a centroid left unidentified.
KIND_CONTROL = "control"
KIND_TARGET = "target"

#: How far a pair got (``CameraThumbnail.status``): the first pair of the highest rank is kept.
STATUS_RANK = {"image": 1, "centroids": 2, "registered": 3, "measured": 4}


def downsample(image: np.ndarray, bit_depth: int, max_width: int = MAX_WIDTH_PX) -> tuple[np.ndarray, int]:
    """``image`` (h, w) DN of ``bit_depth`` bits as (h // f, w // f) uint8 block
    means, f = ceil(w / max_width); returns (thumbnail, f)."""
    h, w = image.shape
    f = max(1, math.ceil(w / max_width))
    h2, w2 = (h // f) * f, (w // f) * f
    # INTER_AREA at an integer factor is the block mean (4x faster than numpy's reshape-mean)
    mean = cv2.resize(np.asarray(image[:h2, :w2], dtype=np.float32), (w2 // f, h2 // f),
                      interpolation=cv2.INTER_AREA)
    full_scale = float(2 ** int(bit_depth) - 1)
    return np.clip(np.rint(mean * (255.0 / full_scale)), 0, 255).astype(np.uint8), f


def point_labels(result: FrameResult, camera: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(labels, kinds) of each centroid of ``camera`` in ``result`` (a
    :class:`~crossfield.session.FrameResult`): control ids from the
    registration's correspondence, measured target ids from the measurement's
    ``target_points`` (each matched to the camera point whose registered
    position is nearest, within :data:`LABEL_TOLERANCE_MM`, and not a control point)."""
    cset: CentroidSet = getattr(result.centroids, camera)
    labels, kinds = [""] * len(cset), [""] * len(cset)
    points, registration = result.points, result.registration
    if points is None or registration is None or not len(points):
        return tuple(labels), tuple(kinds)
    index = getattr(points, f"{camera}_index")
    corr = registration.correspondence
    for k, cid in zip(corr.camera_index, corr.control_ids):
        labels[index[k]], kinds[index[k]] = cid, KIND_CONTROL
    if result.measurement is not None and result.measurement.target_points:
        global_xyz = registration.fit.apply(points.xyz)
        for tid, xyz in result.measurement.target_points.items():
            d = np.linalg.norm(global_xyz - np.asarray(xyz, dtype=np.float64), axis=1)
            k = int(np.argmin(d))
            if d[k] <= LABEL_TOLERANCE_MM and not labels[index[k]]:  # a control keeps its id
                labels[index[k]], kinds[index[k]] = tid, KIND_TARGET
    return tuple(labels), tuple(kinds)


class ThumbnailObserver:
    """Observer plugin: keeps one :class:`CameraThumbnail` per camera (see the module)."""

    def __init__(self, max_width: int = MAX_WIDTH_PX) -> None:
        if isinstance(max_width, bool) or not isinstance(max_width, int) or max_width < 1:
            raise ValueError(f"max_width must be a positive number of pixels, got {max_width!r}")
        self.max_width = max_width
        self._frame: StereoFrame | None = None  # the pair in flight, until on_frame_done
        self._rank = 0
        self._kept: tuple[CameraThumbnail, ...] = ()

    @hookimpl
    def on_frame(self, frame: StereoFrame) -> None:
        self._frame = frame if self._rank < STATUS_RANK["measured"] else None

    @hookimpl
    def on_frame_done(self, result: FrameResult) -> None:
        frame, self._frame = self._frame, None
        if frame is None or frame.sequence != result.sequence:
            return
        if result.measurement is not None:
            status = "measured"
        elif result.registration is not None:
            status = "registered"
        else:
            status = "centroids" if result.centroids is not None else "image"
        if STATUS_RANK[status] <= self._rank:
            return
        kept = []
        for camera in CAMERAS:
            image = frame.image(camera)
            small, f = downsample(image, frame.bit_depth, self.max_width)
            if result.centroids is None:
                uv, (labels, kinds) = np.zeros((0, 2)), ((), ())
            else:
                uv, (labels, kinds) = getattr(result.centroids, camera).uv, point_labels(result, camera)
            kept.append(CameraThumbnail(
                camera, int(frame.sequence), small, f, (int(image.shape[0]), int(image.shape[1])),
                uv, labels, kinds, status,
            ))
        self._kept, self._rank = tuple(kept), STATUS_RANK[status]

    def thumbnails(self) -> tuple[CameraThumbnail, ...]:
        """The kept thumbnails, one per camera (``CAMERAS`` order); () before any pair."""
        return self._kept
