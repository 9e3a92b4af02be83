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

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from crossfield.aggregate import SessionAccumulator
from crossfield.camera.calibration_io import stereo_calibration_from_yaml
from crossfield.config import parse_config
from crossfield.errors import CrossfieldError, RecordingError
from crossfield.plan import parse_plan
from crossfield.recording.reader import Recording, open_recording
from crossfield.replay import ground_truth_from_doc
from crossfield.viz.rerun_log import RerunLogger
from crossfield.session import FrameResult, SessionInfo, SessionSummary
from crossfield.types import (
    CAMERAS,
    CameraPoints,
    CentroidSet,
    CharacteristicResult,
    Correspondence,
    Measurement,
    ProbedPoint,
    ReferenceData,
    Registration,
    RejectedBlob,
    RigidFit,
    StereoCentroids,
    StereoFrame,
)

#: The topics read, in the order the recorder writes a pair's messages.
TOPICS = (
    "/reference",
    "/camera/upper/image",
    "/camera/lower/image",
    "/centroids/upper",
    "/centroids/lower",
    "/points/camera/json",
    "/registration",
    "/measurement",
    "/frames",
    "/log",
)

#: foxglove.Log levels (enum values) -> the pipeline's level names.
_FOXGLOVE_LEVELS = {0: "info", 1: "debug", 2: "info", 3: "warning", 4: "error", 5: "critical"}
_DTYPES = {"mono16": np.dtype("<u2"), "mono8": np.dtype("u1")}


def _nan(value: Any) -> float:
    """JSON null (not finite when recorded) -> NaN."""
    return math.nan if value is None else float(value)


def _array(values: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    out = np.array(
        [[_nan(v) for v in row] if isinstance(row, list) else _nan(row) for row in values], dtype=np.float64
    )
    return out.reshape(shape) if shape is not None else out


def centroid_set(doc: Mapping[str, Any]) -> CentroidSet:
    """A ``/centroids/<camera>`` document (``crossfield.CentroidSet``) as a :class:`CentroidSet`."""
    n = len(doc["uv"])
    return CentroidSet(
        camera=str(doc["camera"]),
        sequence=int(doc["sequence"]),
        uv=_array(doc["uv"], (n, 2)),
        sigma_uv=_array(doc["sigma_uv"], (n, 2)),
        area_px=_array(doc["area_px"], (n,)),
        roundness=_array(doc["roundness"], (n,)),
        peak=_array(doc["peak"], (n,)),
        rejected=tuple(
            RejectedBlob((_nan(b["uv"][0]), _nan(b["uv"][1])), str(b["reason"]))
            for b in doc.get("rejected", ())
        ),
        method=str(doc.get("method", "")),
    )


def camera_points(doc: Mapping[str, Any]) -> CameraPoints:
    """A ``/points/camera/json`` document (``crossfield.CameraPoints``)."""
    n = len(doc["xyz_mm"])
    return CameraPoints(
        sequence=int(doc["sequence"]),
        xyz=_array(doc["xyz_mm"], (n, 3)),
        sigma_xyz=_array(doc["sigma_xyz_mm"], (n, 3)),
        upper_index=np.array(doc["upper_index"], dtype=np.int64),
        lower_index=np.array(doc["lower_index"], dtype=np.int64),
        residual_px=_array(doc["residual_px"], (n,)),
        rejected=tuple(str(r) for r in doc.get("rejected", ())),
        method=str(doc.get("method", "")),
    )


def registration(doc: Mapping[str, Any]) -> Registration:
    """A ``/registration`` document (``crossfield.Registration``)."""
    rows = doc["residuals"]
    fit = RigidFit(
        R=_array(doc["R_global_camera"], (3, 3)),
        t=_array(doc["t_global_camera_mm"], (3,)),
        residuals=_array([r["residual_mm"] for r in rows], (len(rows), 3)),
        rms_mm=_nan(doc["rms_mm"]),
        method=str(doc.get("method", "")),
        scale=1.0 if doc.get("scale") is None else float(doc["scale"]),
    )
    correspondence = Correspondence(
        camera_index=np.array([int(r["camera_index"]) for r in rows], dtype=np.int64),
        control_ids=tuple(str(r["control_id"]) for r in rows),
        unmatched_camera=tuple(int(i) for i in doc.get("unmatched_camera", ())),
        unmatched_control=tuple(str(c) for c in doc.get("unmatched_control", ())),
    )
    return Registration(int(doc["sequence"]), fit, correspondence)


def measurement(doc: Mapping[str, Any]) -> Measurement:
    """A ``/measurement`` document (``crossfield.Measurement``)."""

    def optional(value: Any) -> float | None:
        return None if value is None else float(value)

    return Measurement(
        sequence=int(doc["sequence"]),
        characteristics=tuple(
            CharacteristicResult(
                name=str(c["name"]),
                kind=str(c["kind"]),
                measured_mm=_nan(c["measured_mm"]),
                nominal_mm=_nan(c["nominal_mm"]),
                tolerance_mm=_nan(c["tolerance_mm"]),
                deviation_mm=_nan(c["deviation_mm"]),
                passed=bool(c["passed"]),
                uncertainty_mm=optional(c.get("uncertainty_mm")),
                actual_mm=optional(c.get("actual_mm")),
                error_mm=optional(c.get("error_mm")),
                elements=tuple(str(e) for e in c.get("elements", ())),
            )
            for c in doc["characteristics"]
        ),
        target_points={str(k): tuple(_nan(v) for v in xyz) for k, xyz in doc["target_points_mm"].items()},
        missing_targets=tuple(str(t) for t in doc.get("missing_targets", ())),
    )


def reference_data(doc: Mapping[str, Any]) -> ReferenceData:
    """A ``/reference`` document (``crossfield.ReferenceData``)."""
    return ReferenceData(
        points=tuple(
            ProbedPoint(
                label=str(p["label"]),
                xyz=_array(p["xyz_mm"], (3,)),
                sigma_mm=_nan(p["sigma_mm"]),
                device_sequence=int(p.get("device_sequence", -1)),
                device_time_s=_nan(p.get("device_time_s")),
                probe_vector=_array(p.get("probe_vector") or [0.0, 0.0, 0.0], (3,)),
                probe_diameter_mm=_nan(p.get("probe_diameter_mm")),
            )
            for p in doc["points"]
        ),
        problems=tuple(str(p) for p in doc.get("problems", ())),
        source=str(doc.get("source", "")),
    )


def image(message: Any, where: str) -> np.ndarray:
    """(H, W) pixels of a decoded foxglove.RawImage (mono16 little-endian or mono8)."""
    dtype = _DTYPES.get(message.encoding)
    if dtype is None:
        raise RecordingError(
            f"{where}: image encoding {message.encoding!r}; crossfield writes mono16 or mono8"
        )
    height, width = int(message.height), int(message.width)
    if message.step != width * dtype.itemsize or len(message.data) != height * message.step:
        raise RecordingError(
            f"{where}: image size {width}x{height} does not match its {len(message.data)} bytes"
        )
    return np.frombuffer(message.data, dtype=dtype).reshape(height, width)


def session_info(recording: Recording) -> SessionInfo:
    """The session facts of a crossfield recording (metadata and attachments).

    :class:`RecordingError` naming the file when it is not one.
    """
    path = recording.path
    metadata = recording.metadata()
    if "crossfield.session" not in metadata:
        raise RecordingError(
            f"{path}: not a crossfield session recording (no 'crossfield.session' metadata); "
            f"`rerun {path}` shows any MCAP file with Rerun's own import"
        )
    session = recording.metadata_doc("crossfield.session")
    attachments = recording.attachments()
    for name in ("plan.toml", "calibration.yml"):
        if name not in attachments:
            raise RecordingError(f"{path}: attachment {name!r} is missing")
    try:
        config = parse_config(recording.metadata_doc("crossfield.config"), f"{path} (recorded config)")
        plan = parse_plan(
            attachments["plan.toml"].text, str(session.get("plan_source") or f"{path}:plan.toml")
        )
        calibration = stereo_calibration_from_yaml(
            attachments["calibration.yml"].text, f"{path}:calibration.yml"
        )
    except CrossfieldError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    truth = None
    if "simulator_ground_truth.json" in attachments:
        truth = ground_truth_from_doc(json.loads(attachments["simulator_ground_truth.json"].data))

    def doc(name: str) -> Any:
        return recording.metadata_doc(name) if name in metadata else {}

    return SessionInfo(
        session_id=str(session.get("session_id") or path.stem),
        out_dir=path.parent,
        config=config,
        calibration=calibration,
        plan=plan,
        plugins=doc("crossfield.plugins"),
        packages=doc("crossfield.packages"),
        acquisition=doc("crossfield.acquisition"),
        ground_truth=truth,
        start_time_ns=int(session.get("start_time_ns") or 0),
        parent=session.get("parent"),
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
        if topic.startswith("/camera/"):
            p = pair(m)
            if not logger.wants_images(p.sequence):
                continue
            camera = topic.split("/")[2]
            p.images[camera] = image(RawImage.FromString(m.data), where)
            p.bit_depth = int(m.channel_metadata.get("bit_depth", 16))
            if all(c in p.images for c in CAMERAS):
                yield (
                    "frame",
                    StereoFrame(
                        p.sequence, p.timestamp_ns, p.images["upper"], p.images["lower"], p.bit_depth
                    ),
                )
                p.images = {}
            continue
        if topic == "/log":
            message = Log.FromString(m.data)
            yield (
                "log",
                (_FOXGLOVE_LEVELS.get(int(message.level), "info"), message.message, int(m.log_time_ns)),
            )
            continue
        try:
            doc = json.loads(m.data)
        except ValueError as exc:
            raise RecordingError(f"{where}: not valid JSON: {exc}") from None
        try:
            if topic == "/reference":
                yield "reference", reference_data(doc)
            elif topic.startswith("/centroids/"):
                pair(m).centroids[topic.split("/")[2]] = centroid_set(doc)
            elif topic == "/points/camera/json":
                pair(m).points = camera_points(doc)
            elif topic == "/registration":
                pair(m).registration = registration(doc)
            elif topic == "/measurement":
                pair(m).measurement = measurement(doc)
            elif topic == "/frames":
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


def log_recording(mcap_path: str | Path, logger: RerunLogger) -> SessionSummary:
    """Feed the recorded session ``mcap_path`` to ``logger``; close it; return the summary.

    A recording cut short (killed writer) is shown up to its last complete
    chunk; the summary's ``incomplete`` says so.
    """
    recording = open_recording(mcap_path)
    info = session_info(recording)
    logger.on_session_start(session=info)
    reference = ReferenceData(points=())
    accumulator = SessionAccumulator(info.plan)  # bounded, as in a live session
    for kind, payload in _events(recording, logger):
        if kind == "reference":
            reference = payload
            logger.on_reference(reference=reference)
        elif kind == "frame":
            logger.on_frame(frame=payload)
        elif kind == "done":
            logger.on_frame_done(result=payload)
            accumulator.add(payload)
        else:
            level, text, time_ns = payload
            logger.on_log(level=level, message=text, timestamp_ns=time_ns)
    # The session's end as recorded (crossfield.result), or where the recording stops.
    result = (
        recording.metadata_doc("crossfield.result") if "crossfield.result" in recording.metadata() else {}
    )
    incomplete = result.get("incomplete")
    if not recording.complete or not result:
        incomplete = f"the recording ends early ({recording.damage or 'no session result recorded'})"
    summary = SessionSummary.of_session(
        info, reference, accumulator, incomplete, (Path(p) for p in result.get("report_files", ()))
    )
    logger.on_session_end(summary=summary)
    return summary
