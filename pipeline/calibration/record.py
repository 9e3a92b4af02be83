"""A calibration session recorded to MCAP: the raw image pairs, the detections, the result.

One file per calibration (``crossfield calibrate ... --record CAL.mcap``),
written through the session recorder's file sink
(:class:`crossfield.recording.writer.McapFileSink`), so it carries the same
integrity chain and seal as a measurement session (``docs/recording.md``):
MCAP profile ``CALIBRATION_PROFILE``;

* ``TOPIC_IMAGE`` per camera: every image, ``foxglove.RawImage`` (lossless
  mono8 / mono16), sequence = view index, log time = 1 ms x (view index + 1);
* ``TOPIC_DETECTIONS``: per view and camera the ids and pixel positions found (JSON);
* ``TOPIC_RESULT``: the report (:func:`crossfield.calibration.report.report_dict`, JSON);
* metadata ``METADATA_NAME``: board (JSON), solver settings, bit depth, view
  names, source, OpenCV version, the SHA-256 of the calibration file, the
  wall-clock time of the recording (``recorded_utc``; the log times are view
  indices, not clock times);
  ``crossfield.packages`` and ``crossfield.machine`` as a session's;
  attachment ``ATTACHMENT_CALIBRATION``: the calibration file written.

Replay (``crossfield calibrate --replay CAL.mcap``, optionally with other
solver settings) reads the raw images back and calibrates them again; it
never trusts the recorded detections or results. ``crossfield audit CAL.mcap``
checks the chain and that the recorded results reproduce
(:mod:`crossfield.audit.calibration`).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from crossfield.calibration.boards import Board, board_from_dict
from crossfield.calibration.file import calibration_result_yaml
from crossfield.calibration.report import report_dict
from crossfield.calibration.solve import CalibrationResult, CalibrationSettings, settings_from_dict
from crossfield.errors import RecordingError
from crossfield.recording import layout as L
from crossfield.recording.codec import decode_image, dump_json, raw_image_message, utc_text
from crossfield.recording.reader import Recording, open_recording
from crossfield.recording.seal import Seal
from crossfield.recording.writer import DEFAULT_COMPRESSION, ChannelSpec, McapFileSink, protobuf_channel, write_provenance
from crossfield.types import CAMERAS

# The names of a calibration recording, defined with every other topic in the layout.
ATTACHMENT_CALIBRATION = L.CALIBRATION_ATTACHMENT
METADATA_NAME = L.CALIBRATION_METADATA
PROFILE = L.CALIBRATION_PROFILE
TOPIC_DETECTIONS = L.TOPIC_CALIBRATION_DETECTIONS
TOPIC_IMAGE = L.TOPIC_CALIBRATION_IMAGE
TOPIC_RESULT = L.TOPIC_CALIBRATION_RESULT

#: The JSON channels (schema-less JSON: the documents are described in docs/calibration.md).
DETECTIONS_CHANNEL = ChannelSpec(TOPIC_DETECTIONS, "json", None)
RESULT_CHANNEL = ChannelSpec(TOPIC_RESULT, "json", None)


def view_time_ns(view: int) -> int:
    """Log time of view ``view``'s messages (ns): 1 ms x (view + 1)."""
    return 1_000_000 * (view + 1)


def image_channel(camera: str, bit_depth: int) -> ChannelSpec:
    """The image channel of ``camera`` (its channel metadata names the bit depth)."""
    return protobuf_channel(
        TOPIC_IMAGE.format(camera=camera), RawImage, ((L.CHANNEL_BIT_DEPTH, str(int(bit_depth))),)
    )


def detection_doc(view: int, camera: str, detection: Any) -> dict[str, Any]:
    """The ``TOPIC_DETECTIONS`` document of one view and camera (ids, px; empty if none found)."""
    return {
        "view": view,
        "camera": camera,
        "ids": [] if detection is None else detection.ids.tolist(),
        "image_points_px": [] if detection is None else detection.image_points.tolist(),
    }


def record_calibration(
    path: str | Path,
    images: Sequence[Mapping[str, np.ndarray]],
    names: Sequence[str],
    bit_depth: int,
    result: CalibrationResult,
    source: str,
    *,
    signing_key: str | Path | None = None,
    overwrite: bool = False,
    compression: str = DEFAULT_COMPRESSION,
) -> Seal:
    """Write the session (module docstring) to ``path`` with its integrity chain and seal
    (sidecar ``<path>.seal.json``; signed with ``signing_key`` when given); returns the seal.
    An existing file is an error unless ``overwrite``. compression: the chunks' (lossless,
    as a session's ``[session] compression``)."""
    sink = McapFileSink(
        path, overwrite=overwrite, writer_thread=False, signing_key=signing_key, profile=PROFILE,
        compression=compression,
    )
    yaml_text = calibration_result_yaml(result).encode()
    try:
        settings = {k: getattr(result.settings, k) for k in result.settings.__dataclass_fields__}
        sink.metadata(
            METADATA_NAME,
            {
                "board": json.dumps(result.board.to_dict()),
                "settings": json.dumps(settings),
                "bit_depth": str(int(bit_depth)),
                "view_names": json.dumps(list(names)),
                "source": source,
                "opencv_version": cv2.__version__,
                "calibration_sha256": hashlib.sha256(yaml_text).hexdigest(),
                "recorded_utc": utc_text(time.time_ns()),
            },
        )
        write_provenance(sink)
        for k, view in enumerate(images):
            t = view_time_ns(k)
            for cam in CAMERAS:
                sink.message(image_channel(cam, bit_depth), t, raw_image_message(view[cam], cam, t), k)
                d = result.detections[k][cam] if k < len(result.detections) else None
                sink.message(DETECTIONS_CHANNEL, t, dump_json(detection_doc(k, cam, d)), k)
            sink.flush()
        end = view_time_ns(len(images))
        sink.message(RESULT_CHANNEL, end, dump_json(report_dict(result)), 0)
        sink.attachment(ATTACHMENT_CALIBRATION, "application/x-yaml", yaml_text, end)
    finally:
        sink.close()
    assert sink.seal is not None
    return sink.seal


@dataclass(frozen=True)
class RecordedCalibration:
    """What a replay needs: the raw images and the recorded board, settings and names.

    metadata: the ``METADATA_NAME`` record as written (str -> str)."""

    images: tuple[dict[str, np.ndarray], ...]
    names: tuple[str, ...]
    bit_depth: int
    board: Board
    settings: CalibrationSettings
    source: str
    calibration_yaml: str
    metadata: Mapping[str, str] = field(default_factory=dict)


def open_calibration_recording(path: str | Path, *, validate_crcs: bool = True) -> Recording:
    """The recording at ``path``; :class:`RecordingError` unless it is a calibration recording."""
    path = Path(path)
    rec = open_recording(path, validate_crcs=validate_crcs)
    if rec.profile != PROFILE:
        raise RecordingError(f"{path}: not a crossfield calibration recording (profile {rec.profile!r})")
    return rec


def read_calibration_recording(path: str | Path, *, validate_crcs: bool = True) -> RecordedCalibration:
    """Read a calibration recording back (identifiers are data; nothing is evaluated).

    validate_crcs=False (the audit) reads what the file holds, damaged chunks included."""
    path = Path(path)
    rec = open_calibration_recording(path, validate_crcs=validate_crcs)
    meta = rec.metadata().get(METADATA_NAME)
    if not meta:
        raise RecordingError(f"{path}: no {METADATA_NAME!r} metadata record")
    found = rec.attachments().get(ATTACHMENT_CALIBRATION)
    yaml_text = found.data.decode("utf-8", errors="replace") if found else ""
    by_view: dict[int, dict[str, np.ndarray]] = {}
    topics = {TOPIC_IMAGE.format(camera=c): c for c in CAMERAS}
    for m in rec.messages(list(topics), decode=False, file_order=True):
        where = f"{path}: {m.topic} view {m.sequence}"
        by_view.setdefault(m.sequence, {})[topics[m.topic]] = decode_image(m.data, where)[0]
    incomplete = [k for k, v in by_view.items() if set(v) != set(CAMERAS)]
    if incomplete or not by_view:
        raise RecordingError(f"{path}: view {incomplete[0] if incomplete else 0} lacks an image")
    views = [by_view[k] for k in sorted(by_view)]
    try:
        board = board_from_dict(json.loads(meta["board"]), f"{path}: metadata board")
        settings = settings_from_dict(json.loads(meta["settings"]), f"{path}: metadata settings")
        names = tuple(str(n) for n in json.loads(meta["view_names"]))
        bit_depth = int(meta["bit_depth"])
    except (KeyError, ValueError, TypeError) as exc:
        raise RecordingError(f"{path}: metadata {METADATA_NAME!r} is damaged: {exc}") from None
    if len(names) != len(views):
        names = tuple(f"view {k}" for k in range(len(views)))
    return RecordedCalibration(
        tuple(views), names, bit_depth, board, settings, meta.get("source", ""), yaml_text, dict(meta)
    )
