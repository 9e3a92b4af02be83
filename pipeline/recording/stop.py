"""The ``/session/stop`` record: why a session stopped taking input before its end.

A live run that is interrupted by the operator (SIGINT) or whose camera or
reference source raises records one :class:`~crossfield.session.SessionStop`
on ``/session/stop`` (JSON, schema ``crossfield.SessionStop``,
``schemas/session_stop.schema.json``; log time: when it stopped) before it
finishes the session as INCOMPLETE. It is a raw input: a replay reads it
(:func:`read_stop`) and stops where the live run stopped, so that its
report states the same reason and the same partial results. Every field read
back is data (text and a count), never a path or code.
"""

from __future__ import annotations

import json
from typing import Any

from crossfield.errors import RecordingError
from crossfield.recording import layout as L
from crossfield.session import STOP_INTERRUPTED, STOP_SOURCE_ERROR, SessionStop

__all__ = ["STAGES_STOPPED", "decode_stop", "read_stop", "stop_doc"]

#: Where a session can stop early: during the CMM import, or between stereo pairs.
STAGES_STOPPED = ("reference", "acquire")


def stop_doc(stop: SessionStop) -> dict[str, Any]:
    """The JSON document of ``/session/stop``."""
    return {
        "kind": stop.kind,
        "stage": stop.stage,
        "source": stop.source,
        "reason": stop.reason,
        "frames": int(stop.frames),
        "message": stop.message,
    }


def decode_stop(data: bytes, timestamp_ns: int, where: str) -> SessionStop:
    """The :class:`SessionStop` of one recorded ``/session/stop`` message, or a
    :class:`RecordingError` naming ``where`` and the field at fault."""
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{where}: not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise RecordingError(f"{where}: not a JSON object")
    checks = {
        "kind": lambda v: v in (STOP_INTERRUPTED, STOP_SOURCE_ERROR),
        "stage": lambda v: v in STAGES_STOPPED,
        "source": lambda v: isinstance(v, str),
        "reason": lambda v: isinstance(v, str) and v != "",
        "frames": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
        "message": lambda v: isinstance(v, str),
    }
    for key, ok in checks.items():
        if key not in doc or not ok(doc[key]):
            raise RecordingError(f"{where}: field {key!r} is missing or invalid ({doc.get(key)!r})")
    return SessionStop(
        kind=doc["kind"],
        stage=doc["stage"],
        source=doc["source"],
        reason=doc["reason"],
        frames=doc["frames"],
        timestamp_ns=int(timestamp_ns),
        message=doc["message"],
    )


def read_stop(recording: Any) -> SessionStop | None:
    """The recorded stop of ``recording`` (an open :class:`crossfield.recording.reader.Recording`),
    None when the session ran to the end of its source; a :class:`RecordingError` when
    the file holds more than one."""
    stops = [
        decode_stop(m.data, m.log_time_ns, f"{recording.path}: {L.TOPIC_SESSION_STOP} sequence {m.sequence}")
        for m in recording.messages(L.TOPIC_SESSION_STOP, decode=False)
    ]
    if len(stops) > 1:
        raise RecordingError(f"{recording.path}: {len(stops)} {L.TOPIC_SESSION_STOP} messages; a session stops once")
    return stops[0] if stops else None
