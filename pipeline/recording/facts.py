"""The session facts of a recording, loaded by one loader with one set of checks.

A crossfield session recording states what the session was made of in its
metadata records and attachments (:mod:`crossfield.recording.layout`):
the ``crossfield.session`` document (id, start time, recording format,
plan and calibration digests, parent), the resolved config, the plugins,
package versions, acquisition and machine, the measurement plan
(``plan.toml``), the stereo calibration (``calibration.yml``) and, for a
simulated session, the simulator's ground truth. :func:`load_session_facts`
reads and checks all of them; replay (:mod:`crossfield.replay`) and the
viewer (:mod:`crossfield.viz.rerun_mcap`) both use it, so a recording one
of them accepts the other accepts too.

Every failure is one :class:`RecordingError` line naming the file and the
record (metadata name or attachment name) at fault.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crossfield.camera.calibration_io import stereo_calibration_from_yaml
from crossfield.recording.calibration_files import CalibrationFile, recorded_calibration_files
from crossfield.config import Config, parse_config
from crossfield.errors import CrossfieldError, RecordingError
from crossfield.plan import MeasurementPlan, parse_plan
from crossfield.recording import layout as L
from crossfield.recording.codec import ground_truth_from_doc
from crossfield.recording.reader import Recording, open_recording
from crossfield.types import GroundTruth, StereoCalibration


@dataclass(frozen=True)
class SessionFacts:
    """The facts of a recorded session, read from its metadata and attachments.

    session: the ``crossfield.session`` document; config: the recorded,
    resolved config; plugins / packages / acquisition / machine: the
    records of the same names (machine is None for recordings made before
    it was recorded); result: the ``crossfield.result`` document (None when
    the session did not end normally); plan, calibration, ground_truth:
    from the attachments (ground_truth None unless simulated).
    """

    path: Path
    recording: Recording
    session: Mapping[str, Any]
    config: Config
    plugins: Mapping[str, Mapping[str, str]]
    packages: Mapping[str, str]
    acquisition: Mapping[str, Any]
    machine: Mapping[str, Any] | None
    plan: MeasurementPlan
    calibration: StereoCalibration
    ground_truth: GroundTruth | None
    result: Mapping[str, Any] | None = None
    #: The recorded copies of the calibration file(s) the session read
    #: (:mod:`crossfield.recording.calibration_files`); None: the recording kept none.
    calibration_files: tuple[CalibrationFile, ...] | None = None

    @property
    def complete(self) -> bool:
        """True when the file was finished (summary and footer intact)."""
        return self.recording.complete

    @property
    def session_id(self) -> str:
        """The recorded session id (data, never a path)."""
        return str(self.session.get("session_id", ""))

    @property
    def start_time_ns(self) -> int:
        return int(self.session.get("start_time_ns") or 0)


def require_session(recording: Recording) -> dict[str, dict[str, str]]:
    """The recording's metadata records; :class:`RecordingError` (one line) if
    it is not a crossfield session (another program's MCAP, or cut short
    before the session facts were written)."""
    metadata = recording.metadata()
    if L.META_SESSION not in metadata:
        library = recording.library
        if library.startswith("crossfield/"):
            raise RecordingError(
                f"{recording.path}: the recording ends before its session facts were written "
                f"(no {L.META_SESSION!r} metadata)"
            )
        writer = f"written by {library!r}" if library else "its header names no writer"
        raise RecordingError(
            f"{recording.path}: an MCAP file but not a crossfield session recording ({writer}; "
            f"no {L.META_SESSION!r} metadata)"
        )
    return metadata


def _doc(recording: Recording, metadata: Mapping[str, Mapping[str, str]], name: str) -> Any:
    """The JSON document of metadata record ``name`` (its ``json`` key, or the flat record)."""
    record = metadata[name]
    if L.META_JSON not in record:
        return dict(record)
    try:
        return json.loads(record[L.META_JSON])
    except ValueError as exc:
        raise RecordingError(
            f"{recording.path}: metadata {name!r}: key {L.META_JSON!r} is not valid JSON: {exc}"
        ) from None


def _mapping(recording: Recording, name: str, value: Any) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise RecordingError(f"{recording.path}: metadata {name!r} is not a JSON object")
    return value


def load_session_facts(source: str | Path | Recording) -> SessionFacts:
    """Open ``source`` (a path or an open :class:`Recording`) and read its session facts.

    :class:`RecordingError` (one line, naming the file and the record) when
    it is not an MCAP file, is MCAP written by another program, is in a
    recording format this crossfield does not read, or lacks or garbles
    what a replay needs.
    """
    recording = source if isinstance(source, Recording) else open_recording(source)
    path = recording.path
    metadata = require_session(recording)
    session = _mapping(recording, L.META_SESSION, _doc(recording, metadata, L.META_SESSION))
    fmt = session.get("recording_format")
    if fmt not in L.READABLE_FORMATS:
        raise RecordingError(
            f"{path}: recording format {fmt!r} is not one this crossfield reads "
            f"({', '.join(L.READABLE_FORMATS)})"
        )
    for name in L.REQUIRED_METADATA:
        if name not in metadata:
            raise RecordingError(f"{path}: metadata record {name!r} is missing")
    try:
        config_doc = json.loads(metadata[L.META_CONFIG][L.META_JSON])
    except (KeyError, ValueError) as exc:
        raise RecordingError(f"{path}: metadata {L.META_CONFIG!r} is not a config: {exc}") from None
    try:
        config = parse_config(config_doc, f"{path} (recorded config)")
    except CrossfieldError as exc:
        raise RecordingError(str(exc)) from None
    attachments = recording.attachments()
    for name in L.REQUIRED_ATTACHMENTS:
        if name not in attachments:
            raise RecordingError(f"{path}: attachment {name!r} is missing; the session cannot be replayed")
    try:
        plan = parse_plan(
            attachments[L.ATTACHMENT_PLAN].text,
            str(session.get("plan_source") or f"{path}:{L.ATTACHMENT_PLAN}"),
        )
    except (CrossfieldError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: attachment {L.ATTACHMENT_PLAN!r}: {exc}") from None
    try:
        calibration = stereo_calibration_from_yaml(
            attachments[L.ATTACHMENT_CALIBRATION].text, f"{path}:{L.ATTACHMENT_CALIBRATION}"
        )
    except Exception as exc:  # noqa: BLE001 - calibration_io raises CrossfieldError or cv2.error
        raise RecordingError(f"{path}: attachment {L.ATTACHMENT_CALIBRATION!r}: {exc}") from None
    calibration = StereoCalibration(
        calibration.upper,
        calibration.lower,
        calibration.R_lower_upper,
        calibration.t_lower_upper,
        str(session.get("calibration_source") or calibration.source),
    )
    calibration_files = recorded_calibration_files(session, attachments, str(path))
    truth = None
    if L.ATTACHMENT_GROUND_TRUTH in attachments:
        try:
            truth = ground_truth_from_doc(json.loads(attachments[L.ATTACHMENT_GROUND_TRUTH].data))
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise RecordingError(
                f"{path}: attachment {L.ATTACHMENT_GROUND_TRUTH!r} is not a simulator ground truth: {exc!r}"
            ) from None
    machine = _doc(recording, metadata, L.META_MACHINE) if L.META_MACHINE in metadata else None
    result = _doc(recording, metadata, L.META_RESULT) if L.META_RESULT in metadata else None
    return SessionFacts(
        path=path,
        recording=recording,
        session=session,
        config=config,
        plugins=_mapping(recording, L.META_PLUGINS, _doc(recording, metadata, L.META_PLUGINS)),
        packages=dict(metadata[L.META_PACKAGES]),
        acquisition=_mapping(recording, L.META_ACQUISITION, _doc(recording, metadata, L.META_ACQUISITION)),
        machine=machine,
        plan=plan,
        calibration=calibration,
        ground_truth=truth,
        result=result,
        calibration_files=calibration_files,
    )
