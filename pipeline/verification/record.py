"""A verification session recorded to MCAP (``crossfield verify --record VERIFY.mcap``).

Written through the session recorder's file sink
(:class:`crossfield.recording.writer.McapFileSink`, MCAP profile
``crossfield-verification``), so it has the integrity chain and seal of a
measurement session (names: :mod:`crossfield.recording.layout`;
docs/recording.md, docs/calibration.md):

* ``/verification/{camera}/image``: every scale-bar pair, ``foxglove.RawImage``
  (lossless), sequence = the pair's index over all positions, log time
  1 ms x (index + 1);
* ``/verification/position``: per position (sequence = its index) the name,
  its pairs, the lengths, E and pass (mm, JSON);
* ``/verification/result``: :meth:`crossfield.verification.procedure.VerificationResult.to_dict`;
* metadata ``crossfield.verification.procedure``: certified length, its standard
  uncertainty, MPE (mm), the positions and their pairs, the stage plugins and
  options, the source, the calibration's source and SHA-256;
  ``crossfield.packages``, ``crossfield.machine``; attachment
  ``calibration.yml``: the calibration file under test.

Reading it back (:func:`read_verification_recording`) gives the raw pairs and
the recorded inputs, never the recorded results.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from crossfield.errors import CrossfieldError, RecordingError
from crossfield.jsonable import plain
from crossfield.recording import layout as L
from crossfield.recording.codec import decode_image, dump_json, raw_image_message
from crossfield.recording.reader import open_recording
from crossfield.recording.seal import Seal
from crossfield.recording.writer import ChannelSpec, McapFileSink, protobuf_channel, write_provenance
from crossfield.types import CAMERAS, StereoFrame
from crossfield.verification.procedure import PositionResult, VerificationResult

POSITION_CHANNEL = ChannelSpec(L.TOPIC_VERIFICATION_POSITION, "json", None)
RESULT_CHANNEL = ChannelSpec(L.TOPIC_VERIFICATION_RESULT, "json", None)


def pair_time_ns(index: int) -> int:
    """Log time (ns) of the ``index``-th recorded pair (over all positions): 1 ms x (index + 1)."""
    return 1_000_000 * (index + 1)


def position_doc(index: int, position: PositionResult, pairs: Sequence[int]) -> dict[str, Any]:
    """The ``/verification/position`` document: name, recorded pair indices, lengths and E (mm)."""
    return {
        "position": index,
        "name": position.name,
        "pairs": list(pairs),
        "lengths_mm": list(position.lengths_mm),
        "length_mm": position.length_mm,
        "error_mm": position.error_mm,
        "passed": position.passed,
    }


def record_verification(
    path: str | Path,
    named_frames: Sequence[tuple[str, Sequence[StereoFrame]]],
    result: VerificationResult,
    calibration_text: str,
    stages: Mapping[str, Mapping[str, Any]],
    source: str,
    *,
    signing_key: str | Path | None = None,
    overwrite: bool = False,
) -> Seal:
    """Record a verification session to ``path`` (module docstring) with the session's integrity
    chain and seal (:class:`crossfield.recording.writer.McapFileSink`, MCAP profile
    ``crossfield-verification``); returns the seal.

    calibration_text: the calibration file under test (attached); stages: per stage
    (centroid, triangulate) ``{"plugin": name, "options": {...}}``; source: how it was made.
    """
    sink = McapFileSink(
        path, overwrite=overwrite, writer_thread=False, signing_key=signing_key, profile=L.VERIFICATION_PROFILE
    )
    yaml_bytes = calibration_text.encode("utf-8")
    layout, index = [], 0
    for name, frames in named_frames:
        layout.append({"name": name, "pairs": list(range(index, index + len(frames)))})
        index += len(frames)
    bit_depths = {int(f.bit_depth) for _, frames in named_frames for f in frames}
    try:
        sink.metadata(
            L.VERIFICATION_METADATA,
            {
                "certified_length_mm": repr(float(result.certified_mm)),
                "certified_u_mm": repr(float(result.certified_u_mm)),
                "mpe_mm": repr(float(result.mpe_mm)),
                "positions": json.dumps(layout),
                "stages": json.dumps(plain(dict(stages)), allow_nan=False),
                "source": source,
                "calibration_source": result.calibration_source,
                "calibration_sha256": hashlib.sha256(yaml_bytes).hexdigest(),
            },
        )
        write_provenance(sink)
        sink.attachment(L.ATTACHMENT_CALIBRATION, "application/x-yaml", yaml_bytes, 0)
        if len(bit_depths) != 1:
            raise CrossfieldError(f"the scale-bar pairs have bit depths {sorted(bit_depths)}; one is expected")
        (bit_depth,) = bit_depths
        channels = {
            cam: protobuf_channel(
                L.TOPIC_VERIFICATION_IMAGE.format(camera=cam), RawImage, ((L.CHANNEL_BIT_DEPTH, str(bit_depth)),)
            )
            for cam in CAMERAS
        }
        index = 0
        for k, ((_, frames), position) in enumerate(zip(named_frames, result.positions)):
            for frame in frames:
                t = pair_time_ns(index)
                for cam in CAMERAS:
                    sink.message(channels[cam], t, raw_image_message(frame.image(cam), cam, t), index)
                index += 1
                sink.flush()
            t = pair_time_ns(index - 1)
            sink.message(POSITION_CHANNEL, t, dump_json(position_doc(k, position, layout[k]["pairs"])), k)
        sink.message(RESULT_CHANNEL, pair_time_ns(index), dump_json(result.to_dict()), 0)
    finally:
        sink.close()
    assert sink.seal is not None
    return sink.seal


@dataclass(frozen=True)
class RecordedVerification:
    """A verification read back: positions as (name, pairs), the bar, the MPE, the stage
    plugins, the attached calibration text and the metadata record as written."""

    named_frames: tuple[tuple[str, tuple[StereoFrame, ...]], ...]
    certified_mm: float
    certified_u_mm: float
    mpe_mm: float
    stages: Mapping[str, Mapping[str, Any]]
    calibration_text: str
    source: str
    metadata: Mapping[str, str] = field(default_factory=dict)


def read_verification_recording(path: str | Path, *, validate_crcs: bool = True) -> RecordedVerification:
    """Read a ``crossfield verify --record`` file back: raw pairs and recorded inputs
    (identifiers are data; nothing is evaluated). Errors name the file and the record.
    validate_crcs=False (the audit) reads what the file holds, damaged chunks included."""
    path = Path(path)
    rec = open_recording(path, validate_crcs=validate_crcs)
    if rec.profile != L.VERIFICATION_PROFILE:
        raise RecordingError(f"{path}: not a crossfield verification recording (profile {rec.profile!r})")
    meta = rec.metadata().get(L.VERIFICATION_METADATA)
    if not meta:
        raise RecordingError(f"{path}: no {L.VERIFICATION_METADATA!r} metadata record")
    try:
        layout = json.loads(meta["positions"])
        stages = json.loads(meta["stages"])
        certified, u, mpe = (float(meta[k]) for k in ("certified_length_mm", "certified_u_mm", "mpe_mm"))
        positions = [(str(p["name"]), [int(i) for i in p["pairs"]]) for p in layout]
        if not isinstance(stages, dict):
            raise TypeError("'stages' is not a table")
    except (KeyError, ValueError, TypeError) as exc:
        raise RecordingError(f"{path}: metadata {L.VERIFICATION_METADATA!r} is damaged: {exc}") from None
    found = rec.attachments().get(L.ATTACHMENT_CALIBRATION)
    topics = {L.TOPIC_VERIFICATION_IMAGE.format(camera=c): c for c in CAMERAS}
    pairs: dict[int, dict[str, np.ndarray]] = {}
    depth: dict[int, int] = {}
    for m in rec.messages(list(topics), decode=False, file_order=True):
        pairs.setdefault(m.sequence, {})[topics[m.topic]] = decode_image(m.data, f"{path}: {m.topic} pair {m.sequence}")[0]
        depth[m.sequence] = int(m.channel_metadata.get(L.CHANNEL_BIT_DEPTH, 12))
    named = []
    for name, indices in positions:
        frames = []
        for i in indices:
            if set(pairs.get(i, {})) != set(CAMERAS):
                raise RecordingError(f"{path}: pair {i} of position {name!r} lacks an image")
            frames.append(StereoFrame(i, pair_time_ns(i), pairs[i]["upper"], pairs[i]["lower"], depth[i]))
        named.append((name, tuple(frames)))
    return RecordedVerification(
        tuple(named),
        certified,
        u,
        mpe,
        stages,
        found.data.decode("utf-8", errors="replace") if found else "",
        meta.get("source", ""),
        dict(meta),
    )
