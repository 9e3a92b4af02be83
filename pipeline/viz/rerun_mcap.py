"""Show a recorded session (``session.mcap``) with the full Rerun logger.

The recorded stage results are read back (``crossfield.recording.reader``) into the
pipeline's data classes and handed to a :class:`crossfield.viz.rerun_log.RerunLogger`
through the same observer hooks, in the order they were recorded:
``on_session_start``, ``on_reference``, per pair ``on_frame`` (images) and
``on_frame_done`` (centroids, points, registration, measurement, error),
``on_log``, ``on_session_end``. So ``crossfield view session.mcap`` shows
exactly what the live ``session.rrd`` shows, for any recording, including
one whose ``.rrd`` was not written.

This is display only: nothing is recomputed (that is ``crossfield replay``,
:mod:`crossfield.replay`), except the session summary for the report
document, which :func:`crossfield.session.summarise` aggregates from the
recorded per-pair characteristics exactly as the live session did. The
reference axes drawn are fitted to the recorded CMM points
(:func:`crossfield.viz.rerun_log.fit_reference_axes`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from crossfield.chain.aggregate import session_accumulator, session_summary
from crossfield.errors import RecordingError
from crossfield.recording import codec
from crossfield.recording import layout as L
from crossfield.recording.facts import SessionFacts, load_session_facts
from crossfield.recording.reader import Recording, open_recording
from crossfield.session import FrameResult, SessionInfo, SessionSummary
from crossfield.types import (
    CAMERAS,
    CameraPoints,
    CentroidSet,
    Measurement,
    ReferenceData,
    Registration,
    StereoCentroids,
    StereoFrame,
)
from crossfield.viz.rerun_log import RerunLogger

#: The topics read, in the order the recorder writes a pair's messages.
TOPICS = (
    L.TOPIC_REFERENCE,
    *L.IMAGE_TOPICS,
    *L.CENTROID_TOPICS,
    L.TOPIC_POINTS_CAMERA_JSON,
    L.TOPIC_REGISTRATION,
    L.TOPIC_MEASUREMENT,
    L.TOPIC_FRAMES,
    L.TOPIC_LOG,
)


def session_info(recording: Recording) -> SessionInfo:
    """The session facts of a crossfield recording (metadata and attachments), as the
    :class:`SessionInfo` the live session had (:func:`crossfield.recording.facts.load_session_facts`).

    :class:`RecordingError` naming the file and the record when it is not one.
    """
    return info_from_facts(load_session_facts(recording))


def info_from_facts(facts: SessionFacts) -> SessionInfo:
    """The :class:`SessionInfo` of a recorded session's facts (its folder: the recording's)."""
    path = facts.path
    return SessionInfo(
        session_id=facts.session_id or path.stem,
        out_dir=path.parent,
        config=facts.config,
        calibration=facts.calibration,
        plan=facts.plan,
        plugins=facts.plugins,
        packages=facts.packages,
        acquisition=facts.acquisition,
        ground_truth=facts.ground_truth,
        start_time_ns=facts.start_time_ns,
        parent=facts.session.get("parent"),
        calibration_files=facts.calibration_files,
    )


@dataclass
class _Pair:
    """What has been read of one stereo pair so far."""

    sequence: int
    timestamp_ns: int
    images: dict[str, np.ndarray] = field(default_factory=dict)
    bit_depth: int = 16
    centroids: dict[str, CentroidSet] = field(default_factory=dict)
    points: CameraPoints | None = None
    registration: Registration | None = None
    measurement: Measurement | None = None


def _events(recording: Recording, logger: RerunLogger) -> Iterator[tuple[str, Any]]:
    """("reference" | "frame" | "done" | "log", payload) in the recorded order."""
    pairs: dict[int, _Pair] = {}
    path = recording.path

    def pair(m: Any) -> _Pair:
        return pairs.setdefault(int(m.sequence), _Pair(int(m.sequence), int(m.log_time_ns)))

    for m in recording.messages(TOPICS, file_order=True, decode=False):
        topic = m.topic
        where = f"{path}: {topic} #{m.sequence}"
        if topic in L.IMAGE_TOPICS:
            p = pair(m)
            if not logger.wants_images(p.sequence):
                continue
            camera = L.CAMERA_OF_TOPIC[topic]
            p.images[camera] = codec.raw_image_pixels(RawImage.FromString(m.data), where)
            p.bit_depth = int(m.channel_metadata.get(L.CHANNEL_BIT_DEPTH, 16))
            if all(c in p.images for c in CAMERAS):
                yield (
                    "frame",
                    StereoFrame(
                        p.sequence, p.timestamp_ns, p.images["upper"], p.images["lower"], p.bit_depth
                    ),
                )
                p.images = {}
            continue
        if topic == L.TOPIC_LOG:
            level, text = codec.decode_log(m.data, where)
            yield "log", (level, text, int(m.log_time_ns))
            continue
        doc = codec.decode_json(m.data, where)
        try:
            if topic == L.TOPIC_REFERENCE:
                yield "reference", codec.reference_data(doc)
            elif topic in L.CENTROID_TOPICS:
                pair(m).centroids[L.CAMERA_OF_TOPIC[topic]] = codec.centroid_set(doc)
            elif topic == L.TOPIC_POINTS_CAMERA_JSON:
                pair(m).points = codec.camera_points(doc)
            elif topic == L.TOPIC_REGISTRATION:
                pair(m).registration = codec.registration(doc)
            elif topic == L.TOPIC_MEASUREMENT:
                pair(m).measurement = codec.measurement(doc)
            elif topic == L.TOPIC_FRAMES:
                p = pairs.pop(int(doc["sequence"]), None) or _Pair(
                    int(doc["sequence"]), int(doc["timestamp_ns"])
                )
                centroids = None
                if all(c in p.centroids for c in CAMERAS):
                    centroids = StereoCentroids(p.sequence, p.centroids["upper"], p.centroids["lower"])
                yield (
                    "done",
                    FrameResult(
                        p.sequence,
                        int(doc["timestamp_ns"]),
                        centroids,
                        p.points,
                        p.registration,
                        p.measurement,
                        error=doc.get("error"),
                    ),
                )
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{where}: unexpected content: {exc!r}") from None


def recorded_station_moved(recording: Recording) -> str | None:
    """The session pose's motion-test line as the recorded ``/report`` states it (None:
    the station did not move, or no report was recorded). The viewer does not refit the
    joint pose (that needs the register plugin: ``crossfield replay`` does)."""
    if not recording.complete:
        return None  # a cut-short recording has no /report
    for m in recording.messages([L.TOPIC_REPORT]):
        moved = m.decoded.get("station_moved") if isinstance(m.decoded, dict) else None
        return moved if isinstance(moved, str) else None
    return None


def log_recording(mcap_path: str | Path, logger: RerunLogger) -> SessionSummary:
    """Feed the recorded session ``mcap_path`` to ``logger``; close it; return the summary.

    A recording cut short (killed writer) is shown up to its last complete
    chunk; the summary's ``incomplete`` says so.
    """
    recording = open_recording(mcap_path)
    facts = load_session_facts(recording)
    info = info_from_facts(facts)
    logger.on_session_start(session=info)
    reference = ReferenceData(points=())
    accumulator = session_accumulator(info, reference)  # as live
    for kind, payload in _events(recording, logger):
        if kind == "reference":
            reference = payload
            logger.on_reference(reference=reference)
            accumulator.reference_source = session_accumulator(info, reference).reference_source
            accumulator.set_reference(reference)  # its line fits: the CMM's own Type A evidence
        elif kind == "frame":
            logger.on_frame(frame=payload)
        elif kind == "done":
            logger.on_frame_done(result=payload)
            accumulator.add(payload)
        else:
            level, text, time_ns = payload
            logger.on_log(level=level, message=text, timestamp_ns=time_ns)
    # The session's end as recorded (crossfield.result), or where the recording stops.
    result = dict(facts.result or {})
    incomplete = result.get("incomplete")
    if not recording.complete or not result:
        incomplete = f"the recording ends early ({recording.damage or 'no session result recorded'})"
    summary = session_summary(
        info, reference, accumulator, incomplete=incomplete,
        report_files=(Path(p) for p in result.get("report_files", ())),
        station_moved=recorded_station_moved(recording),
    )
    logger.on_session_end(summary=summary)
    return summary
