"""What a path given on the command line is, and one line when it is the wrong kind.

Every command that reads a session, a report or a recording first asks
:func:`require` whether the path is of a kind it takes; if not, the user gets one
line naming what the path is and what the command wants
(``s/session.mcap: a session recording (MCAP); export wants a session folder or
its report.json``), exit status 2 (:func:`crossfield.cli.main`).

The kinds (:data:`KINDS`) are recognised by content, not by name: a folder by the
session files in it, a file by its first bytes (the MCAP magic, then the MCAP
header's profile, :data:`crossfield.recording.layout.CALIBRATION_PROFILE` and
:data:`~crossfield.recording.layout.VERIFICATION_PROFILE`; Rerun's ``RRF``), a JSON
file by its ``format`` key. Nothing read from the file is used as a path.
"""

from __future__ import annotations

import json
from collections.abc import Collection
from pathlib import Path

from crossfield.errors import CrossfieldError
from crossfield.recording import layout as L
from crossfield.recording import layout as L

__all__ = ["KINDS", "InputError", "kind_of", "require"]

#: kind -> how it is named to the user.
KINDS: dict[str, str] = {
    "missing": "does not exist",
    "session-folder": "a session folder",
    "folder": "a folder without session.mcap or report.json",
    "report": "a session's report.json",
    "seal": "a recording's seal (session.mcap.seal.json)",
    "json": "a JSON file that is not a crossfield report.json",
    "session-recording": "a session recording (MCAP)",
    "calibration-recording": f"a calibration recording (MCAP profile {L.CALIBRATION_PROFILE!r}, "
    "from `crossfield calibrate --record`)",
    "verification-recording": f"a verification recording (MCAP profile {L.VERIFICATION_PROFILE!r}, "
    "from `crossfield verify --record`)",
    "other-recording": "an MCAP file of an unknown profile",
    "rerun": "a Rerun recording (.rrd)",
    "other": "a file that is neither a recording nor a report",
}

#: kind -> the commands that do read it, named when another command is given it.
READ_BY: dict[str, str] = {
    "calibration-recording": "crossfield calibrate --replay, crossfield audit",
    "verification-recording": "crossfield verify --recording, crossfield audit",
    "session-recording": "crossfield replay, view, compare, audit",
    "report": "crossfield export",
}

MCAP_MAGIC = b"\x89MCAP0\r\n"
RERUN_MAGIC = b"RRF"
_PROFILES = {
    "": "session-recording",
    L.CALIBRATION_PROFILE: "calibration-recording",
    L.VERIFICATION_PROFILE: "verification-recording",
}


class InputError(CrossfieldError):
    """A path of the wrong kind for the command (one line: what it is, what is wanted)."""


def _folder_kind(path: Path) -> str:
    """``session-folder`` if the folder holds a session's files, else ``folder``."""
    names = ("session.mcap", "report.json", "session.rrd")
    return "session-folder" if any((path / name).is_file() for name in names) else "folder"


def _json_kind(path: Path) -> str:
    """``report``, ``seal`` or ``json`` by the document's keys; ``other`` if not JSON."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, OSError):
        return "other"
    if isinstance(doc, dict) and str(doc.get("format", "")).startswith("crossfield-report/"):
        return "report"
    if isinstance(doc, dict) and "chain_head" in doc and "file_sha256" in doc:
        return "seal"
    return "json"


def _file_kind(path: Path) -> str:
    """The kind of a regular file by its first bytes (and an MCAP file's profile)."""
    from crossfield.recording.reader import open_recording
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError:
        return "other"
    if head == MCAP_MAGIC:
        return _PROFILES.get(open_recording(path).profile, "other-recording")
    if head.startswith(RERUN_MAGIC):
        return "rerun"
    if head.lstrip()[:1] in (b"{", b"["):
        return _json_kind(path)
    return "other"


def kind_of(path: str | Path) -> str:
    """What ``path`` is: one key of :data:`KINDS`."""
    path = Path(path)
    if not path.exists():
        return "missing"
    if path.is_dir():
        return _folder_kind(path)
    return _file_kind(path)


def require(
    path: str | Path, kinds: Collection[str], command: str, wants: str, *, recording: bool = True
) -> str:
    """The kind of ``path`` if it is one of ``kinds``; else :class:`InputError`
    ``PATH: <what it is>; <command> wants <wants>``. A missing path passes through, and
    for a command that reads a recording (``recording``) so do a file that is not
    MCAP and an MCAP of another program: the reader names their fault in one line."""
    kind = kind_of(path)
    if kind in kinds or kind == "missing" or (recording and kind in ("other", "other-recording")):
        return kind
    raise InputError(f"{path}: {KINDS[kind]}; {command} wants {wants}{_hint(path, kind, kinds)}")


def _hint(path: str | Path, kind: str, kinds: Collection[str]) -> str:
    """What to give instead: a folder's session.mcap, or the commands that read ``kind``."""
    if kind == "session-folder" and "session-recording" in kinds:
        return f": give {Path(path) / 'session.mcap'}"
    return f" (read by {READ_BY[kind]})" if kind in READ_BY else ""
