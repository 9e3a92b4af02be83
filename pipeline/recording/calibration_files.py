"""The calibration file(s) a session measured with, recorded whole inside the recording.

The budget's calibration term (:mod:`crossfield.uncertainty.calibration`) reads the
calibration file's ``std_*`` keys. A live session reads each file named by its
calibration's ``source`` **once, at the start** (:func:`read_calibration_files`); the
recorder attaches those bytes (attachment ``calibration/stereo.yml``, or
``calibration/stereo-1.yml``, ``-2`` ... for a pair of files; the integrity chain covers
them as every attachment) and lists them with their SHA-256 under
``calibration_files`` in the ``crossfield.session`` record; the budget is computed from
the same bytes. Replay and audit parse the recorded copies
(:func:`recorded_calibration_files`) and never open the recorded path to read a
calibration from it: the path is data, and the file may have changed or gone.
:func:`disk_notes` says, one line per file, when the file now at that path differs from
the recorded copy or is gone (it only hashes a regular file there). A recording made
before the copies were kept has no ``calibration_files`` key: the budget then reads the
path as it did then, and :func:`no_copy_note` says so.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crossfield.errors import RecordingError

#: Suffixes of the files a calibration source names that are calibration files
#: (OpenCV FileStorage YAML / XML / JSON).
CALIBRATION_SUFFIXES = {".yml": "text/yaml", ".yaml": "text/yaml", ".xml": "application/xml", ".json": "application/json"}
#: The ``crossfield.session`` key listing the recorded copies.
SESSION_KEY = "calibration_files"
#: Attachment names of the copies: ``calibration/stereo<suffix>`` (one file) or
#: ``calibration/stereo-<n><suffix>`` (n = 1, 2, ... in the source's order).
ATTACHMENT_PREFIX = "calibration/stereo"
#: A file at a recorded path larger than this is not read to be hashed (bytes).
_DISK_LIMIT = 64 << 20


@dataclass(frozen=True)
class CalibrationFile:
    """One calibration file as the session read it.

    path: the file's path as the calibration source names it (recorded; in a replay,
    data, never opened to read the calibration); data: its bytes; attachment: the
    recording's attachment name of the copy."""

    path: str
    data: bytes
    attachment: str

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.data).hexdigest()

    @property
    def text(self) -> str:
        """The file as text (FileStorage is UTF-8 / ASCII; undecodable bytes replaced)."""
        return self.data.decode("utf-8", errors="replace")

    @property
    def media_type(self) -> str:
        return CALIBRATION_SUFFIXES.get(Path(self.path).suffix.lower(), "text/plain")

    def entry(self) -> dict[str, Any]:
        """The ``calibration_files`` entry of the session record."""
        return {"attachment": self.attachment, "path": self.path, "sha256": self.sha256, "bytes": len(self.data)}


def calibration_paths(source: str) -> list[str]:
    """The calibration files a calibration ``source`` names (paths joined by ``", "``, as
    :func:`crossfield.camera.calibration_io.read_stereo_calibration` names them): the
    parts with a FileStorage suffix."""
    return [p for p in str(source or "").split(", ") if p and Path(p).suffix.lower() in CALIBRATION_SUFFIXES]


def _attachment(index: int, count: int, path: str) -> str:
    suffix = Path(path).suffix.lower()
    return f"{ATTACHMENT_PREFIX}{suffix}" if count == 1 else f"{ATTACHMENT_PREFIX}-{index + 1}{suffix}"


def read_calibration_files(source: str) -> tuple[CalibrationFile, ...]:
    """Read, now, every calibration file ``source`` names that is a regular file (the
    simulator's own calibration names none: ``()``)."""
    paths = [p for p in calibration_paths(source) if Path(p).is_file()]
    out = []
    for k, path in enumerate(paths):
        try:
            data = Path(path).read_bytes()
        except OSError:
            continue  # as before: a file that cannot be read gives the budget no std_* keys
        out.append(CalibrationFile(path, data, _attachment(k, len(paths), path)))
    return tuple(out)


def session_calibration_files(acquisition: Any) -> tuple[CalibrationFile, ...]:
    """The calibration files of a session's acquisition: the recorded copies of a replay
    (``recorded_calibration_files``, not None), else the files its calibration's source
    names, read now (a live session, or a replay of a recording that kept no copy)."""
    recorded = getattr(acquisition, "recorded_calibration_files", None)
    if recorded is not None:
        return tuple(recorded)
    return read_calibration_files(acquisition.calibration.source)


def recorded_calibration_files(
    session: Mapping[str, Any], attachments: Mapping[str, Any], where: str
) -> tuple[CalibrationFile, ...] | None:
    """The copies a recording lists under ``calibration_files`` (None: it lists none,
    recorded before the copies were kept). ``attachments``: name -> attachment (with
    ``data``). :class:`RecordingError` (naming ``where``) for a malformed entry or a
    listed attachment that is missing; digests are the audit's to compare
    (:func:`copy_problems`)."""
    entries = session.get(SESSION_KEY)
    if entries is None:
        return None
    if not isinstance(entries, list):
        raise RecordingError(f"{where}: crossfield.session {SESSION_KEY!r} is not a list")
    out = []
    for entry in entries:
        if not (
            isinstance(entry, Mapping)
            and isinstance(entry.get("attachment"), str)
            and isinstance(entry.get("path"), str)
        ):
            raise RecordingError(f"{where}: crossfield.session {SESSION_KEY!r}: malformed entry {entry!r}")
        found = attachments.get(entry["attachment"])
        if found is None:
            raise RecordingError(
                f"{where}: attachment {entry['attachment']!r} (the copy of the calibration file "
                f"{entry['path']}) is missing"
            )
        out.append(CalibrationFile(entry["path"], bytes(found.data), entry["attachment"]))
    return tuple(out)


def copy_problems(session: Mapping[str, Any], files: Sequence[CalibrationFile]) -> list[str]:
    """Each recorded copy whose SHA-256 is not the one the session record lists."""
    listed = {e.get("attachment"): e.get("sha256") for e in session.get(SESSION_KEY) or [] if isinstance(e, Mapping)}
    return [
        f"attachment {f.attachment!r}: SHA-256 {f.sha256} is not the recorded {listed.get(f.attachment)} "
        f"(the copy of the calibration file {f.path})"
        for f in files
        if listed.get(f.attachment) != f.sha256
    ]


def _short(digest: str) -> str:
    return f"{digest[:12]}…"


def disk_notes(files: Sequence[CalibrationFile]) -> list[str]:
    """One line per recorded copy whose file on disk (at its recorded path, relative to
    the current folder when relative) differs from it or is gone; nothing for a file that
    is unchanged. Only a regular file is read, to hash it (never parsed)."""
    notes = []
    for f in files:
        disk = Path(f.path)
        try:
            regular = disk.is_file()
            size = disk.stat().st_size if regular else 0
        except OSError:
            regular = False
        if not regular:
            notes.append(
                f"the calibration file on disk at {f.path} is gone; the budget uses the recorded copy "
                f"(sha256 {_short(f.sha256)})"
            )
            continue
        if size > _DISK_LIMIT:
            notes.append(
                f"the calibration file on disk at {f.path} differs from the recorded copy ({size} bytes on "
                f"disk vs {len(f.data)} recorded); the budget uses the recorded copy"
            )
            continue
        try:
            now = hashlib.sha256(disk.read_bytes()).hexdigest()
        except OSError as exc:
            notes.append(f"the calibration file on disk at {f.path} cannot be read ({exc.strerror}); "
                         f"the budget uses the recorded copy")  # fmt: skip
            continue
        if now != f.sha256:
            notes.append(
                f"the calibration file on disk at {f.path} differs from the recorded copy (sha256 "
                f"{_short(now)} on disk vs {_short(f.sha256)} recorded); the budget uses the recorded copy"
            )
    return notes


def no_copy_note(source: str) -> str | None:
    """The note on a recording that kept no copy of the calibration file(s) its source
    names (None when it names none: nothing was read then either)."""
    paths = calibration_paths(source)
    if not paths:
        return None
    return (
        f"the recording holds no copy of the calibration file {', '.join(paths)} (recorded before the copies "
        f"were kept): the budget's calibration term is read from that path on disk, as it is now"
    )
