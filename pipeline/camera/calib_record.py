"""A calibration session recorded to MCAP: the raw image pairs, the detections, the result.

One file per calibration (``crossfield calibrate ... --record CAL.mcap``):

* ``TOPIC_IMAGE`` per camera: every image, ``foxglove.RawImage`` (lossless
  mono8 / mono16), log time = 1 ms x view index;
* ``TOPIC_DETECTIONS``: per view and camera the ids and pixel positions found
  (JSON), for inspection only;
* ``TOPIC_RESULT``: the report (:func:`crossfield.camera.calib_report.report_dict`, JSON);
* metadata ``METADATA_NAME``: board (TOML), solver settings, bit depth, view
  names, source; attachment ``ATTACHMENT_CALIBRATION``: the calibration file written.

Replay (``crossfield calibrate --replay CAL.mcap``, optionally with other
solver settings) reads the raw images back and calibrates them again; it
never trusts the recorded detections or results.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from crossfield.camera.boards import Board, board_from_dict
from crossfield.camera.calib_file import calibration_result_yaml
from crossfield.camera.calib_report import report_dict
from crossfield.camera.calibrate import CalibrationResult, CalibrationSettings, settings_from_dict
from crossfield.errors import RecordingError
from crossfield.recording.codec import protobuf_schema, raw_image_message
from crossfield.types import CAMERAS
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import make_reader
from mcap.writer import Writer

# The names of a calibration recording, defined with every other topic in the layout.
from crossfield.recording.layout import (  # noqa: E402
    CALIBRATION_ATTACHMENT as ATTACHMENT_CALIBRATION,
    CALIBRATION_METADATA as METADATA_NAME,
    CALIBRATION_PROFILE as PROFILE,
    TOPIC_CALIBRATION_DETECTIONS as TOPIC_DETECTIONS,
    TOPIC_CALIBRATION_IMAGE as TOPIC_IMAGE,
    TOPIC_CALIBRATION_RESULT as TOPIC_RESULT,
)


def _ns(view: int) -> int:
    return 1_000_000 * (view + 1)


def record_calibration(
    path: str | Path,
    images: Sequence[Mapping[str, np.ndarray]],
    names: Sequence[str],
    bit_depth: int,
    result: CalibrationResult,
    source: str,
) -> Path:
    """Write the session (module docstring) to ``path``; returns it."""
    path = Path(path)
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile=PROFILE, library="crossfield")
        schema = protobuf_schema(RawImage)
        raw_id = writer.register_schema(schema.name, schema.encoding, schema.data)
        image_channels = {
            cam: writer.register_channel(TOPIC_IMAGE.format(camera=cam), "protobuf", raw_id)
            for cam in CAMERAS
        }
        json_id = writer.register_schema("", "", b"")
        det_channel = writer.register_channel(TOPIC_DETECTIONS, "json", json_id)
        result_channel = writer.register_channel(TOPIC_RESULT, "json", json_id)
        for k, view in enumerate(images):
            for cam in CAMERAS:
                writer.add_message(
                    image_channels[cam], _ns(k), raw_image_message(view[cam], cam, _ns(k)), _ns(k), k
                )
                d = result.detections[k][cam] if k < len(result.detections) else None
                doc = {
                    "view": k,
                    "camera": cam,
                    "ids": [] if d is None else d.ids.tolist(),
                    "image_points_px": [] if d is None else d.image_points.tolist(),
                }
                writer.add_message(det_channel, _ns(k), json.dumps(doc).encode(), _ns(k), k)
        end = _ns(len(images))
        writer.add_message(
            result_channel, end, json.dumps(report_dict(result), allow_nan=False).encode(), end
        )
        settings = {k: getattr(result.settings, k) for k in result.settings.__dataclass_fields__}
        writer.add_metadata(
            METADATA_NAME,
            {
                "board": json.dumps(result.board.to_dict()),
                "settings": json.dumps(settings),
                "bit_depth": str(int(bit_depth)),
                "view_names": json.dumps(list(names)),
                "source": source,
            },
        )
        writer.add_attachment(
            end, end, ATTACHMENT_CALIBRATION, "application/x-yaml", calibration_result_yaml(result).encode()
        )
        writer.finish()
    return path


@dataclass(frozen=True)
class RecordedCalibration:
    """What a replay needs: the raw images and the recorded board, settings and names."""

    images: tuple[dict[str, np.ndarray], ...]
    names: tuple[str, ...]
    bit_depth: int
    board: Board
    settings: CalibrationSettings
    source: str
    calibration_yaml: str


def _image(message: bytes, where: str) -> np.ndarray:
    raw = RawImage()
    raw.ParseFromString(message)
    dtype = {"mono16": "<u2", "mono8": "u1"}.get(raw.encoding)
    if dtype is None:
        raise RecordingError(f"{where}: image encoding {raw.encoding!r}, expected mono8 or mono16")
    itemsize = np.dtype(dtype).itemsize
    if raw.step != raw.width * itemsize or len(raw.data) != raw.step * raw.height:
        raise RecordingError(
            f"{where}: image of {raw.width} x {raw.height} px does not match its {len(raw.data)} bytes"
        )
    return (
        np.frombuffer(raw.data, dtype=dtype)
        .reshape(raw.height, raw.width)
        .astype(np.dtype(dtype).newbyteorder("="))
    )


def read_calibration_recording(path: str | Path) -> RecordedCalibration:
    """Read a calibration recording back (identifiers are data; nothing is evaluated)."""
    path = Path(path)
    try:
        stream = open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open: {exc.strerror}") from None
    with stream:
        try:
            reader = make_reader(stream)
            header = reader.get_header()
            if header.profile != PROFILE:
                raise RecordingError(
                    f"{path}: not a crossfield calibration recording (profile {header.profile!r})"
                )
            meta: dict[str, Any] = {}
            for record in reader.iter_metadata():
                if record.name == METADATA_NAME:
                    meta = dict(record.metadata)
            yaml_text = next(
                (a.data.decode() for a in reader.iter_attachments() if a.name == ATTACHMENT_CALIBRATION), ""
            )
            by_view: dict[int, dict[str, np.ndarray]] = {}
            topics = {TOPIC_IMAGE.format(camera=c): c for c in CAMERAS}
            for _, channel, message in reader.iter_messages(topics=list(topics)):
                view = message.sequence
                by_view.setdefault(view, {})[topics[channel.topic]] = _image(
                    message.data, f"{path}: {channel.topic} view {view}"
                )
        except RecordingError:
            raise
        except Exception as exc:  # the mcap library's own errors for a damaged file
            raise RecordingError(f"{path}: unreadable MCAP: {exc}") from None
    if not meta:
        raise RecordingError(f"{path}: no {METADATA_NAME!r} metadata record")
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
        tuple(views), names, bit_depth, board, settings, meta.get("source", ""), yaml_text
    )
