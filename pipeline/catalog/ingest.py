"""Adding a session folder to the catalog: one transaction per session, added once.

A session folder is what ``crossfield run`` writes (``recordings/<session>/``):
``report.json`` (the session's facts, characteristics, registration, consistency test and
seal, docs/report.md), the recording ``session.mcap`` and its seal ``session.mcap.seal.json``
(docs/replay-and-audit.md). :func:`read_session` turns one into a :class:`SessionRecord`
(no database involved); :func:`add_record` writes it in one transaction, so a session is
in the catalog whole or not at all (a killed ingest leaves nothing).

Identity: a session is its id (report.json ``session.id``) *and* its recording
(file SHA-256 and chain head). The same session added twice is one row (the second add
is "present"); a different recording under an id already catalogued is refused,
naming both files (:class:`CatalogConflict`). The file's SHA-256 is computed from its
bytes at ingest and must equal its seal's: a recording changed after it was sealed is
refused (the catalog would otherwise anchor the changed file).

Nothing in the folder is executed or used as a path but the folder's own files; report.json
is read as JSON (no pickle), the recording's metadata through crossfield's reader.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from crossfield.catalog import schema as S
from crossfield.errors import CrossfieldError

REPORT = "report.json"
RECORDING = "session.mcap"

#: The station-health figures taken from each session: name -> (unit, where it comes from).
HEALTH: dict[str, tuple[str, str]] = {
    "registration_rms_mm": ("mm", "report.json registration.rms_mm (session aggregate)"),
    "rotation_spread_rad": ("rad", "report.json registration.rotation_spread_rad (frame-to-frame)"),
    "consistency_birge_ratio": ("1", "report.json uncertainty.consistency.birge_ratio"),
    "consistency_p_value": ("1", "report.json uncertainty.consistency.p_value"),
    "consistency_warning": ("count", "1 when the chi-square consistency test warned, else 0"),
    "cmm_inflation": ("1", "report.json uncertainty.consistency.cmm_inflation"),
    "frames_failed": ("count", "report.json frames_failed"),
    "problems": ("count", "report.json problems (number of entries)"),
    "calibration_rms_px": ("px", "the recorded calibration file's rms_px_stereo (crossfield calibrate)"),
}


class CatalogError(CrossfieldError):
    """A session folder that cannot be catalogued (the message names the file at fault)."""


class CatalogConflict(CatalogError):
    """A different recording under a session id that is already catalogued."""


@dataclass(frozen=True)
class SessionRecord:
    """One session's rows, as :func:`read_session` reads them from its folder.

    session: the ``sessions`` row; characteristics: the ``characteristics`` rows (mm);
    seal: the ``seals`` row; health: the ``station_health`` rows (units in :data:`HEALTH`).
    """

    session: Mapping[str, Any]
    characteristics: tuple[Mapping[str, Any], ...]
    seal: Mapping[str, Any]
    health: tuple[Mapping[str, Any], ...] = field(default_factory=tuple)

    @property
    def id(self) -> str:
        return str(self.session["id"])


@dataclass(frozen=True)
class IngestResult:
    """What happened to one folder: status "added", "present" (already catalogued, same
    recording) or "error" (``error`` says why: a conflict, an unreadable file)."""

    folder: str
    session_id: str | None
    status: str
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {"folder": self.folder, "session_id": self.session_id, "status": self.status, "error": self.error}


# --------------------------------------------------------------------------
# Reading a folder
# --------------------------------------------------------------------------


def _finite(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def _text(value: Any) -> str:
    return "" if value is None else str(value)


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False, default=str)


def _utc(ns: int) -> _dt.datetime:
    """Naive UTC datetime of ``ns`` ns since the epoch (microseconds kept)."""
    return _dt.datetime(1970, 1, 1) + _dt.timedelta(microseconds=int(ns) // 1000)


def _load_report(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise CatalogError(f"{path}: cannot read: {exc.strerror}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise CatalogError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("session"), dict):
        raise CatalogError(f"{path}: not a crossfield session report (no 'session' object)")
    return doc


def _recording_facts(mcap: Path) -> tuple[dict[str, Any], dict[str, Any], float | None]:
    """The recording's ``crossfield.session`` and ``crossfield.machine`` metadata and the
    calibration file's stereo RMS (px), if it states one."""
    from crossfield.recording.reader import open_recording

    try:
        with open_recording(mcap, validate_crcs=False) as rec:
            docs = {}
            for name in ("crossfield.session", "crossfield.machine"):
                try:
                    doc = rec.metadata_doc(name)
                except CrossfieldError:
                    doc = None
                docs[name] = doc if isinstance(doc, dict) else {}
            rms = None
            try:
                text = rec.attachment("calibration.yml").data.decode("utf-8", "replace")
                rms = _calibration_rms(text)
            except (CrossfieldError, KeyError):
                pass
    except CrossfieldError as exc:
        raise CatalogError(f"{mcap}: cannot read the recording: {exc}") from None
    return docs["crossfield.session"], docs["crossfield.machine"], rms


def _calibration_rms(text: str) -> float | None:
    """``rms_px_stereo`` of an OpenCV FileStorage calibration file (``crossfield calibrate``)."""
    import cv2

    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except cv2.error:
        return None
    try:
        node = fs.getNode("rms_px_stereo")
        return None if node.empty() else _finite(node.real())
    finally:
        fs.release()


def read_session(folder: str | Path, *, station: str | None = None) -> SessionRecord:
    """The catalog rows of the session in ``folder`` (CatalogError naming the file at fault).

    station: the station's name (``[catalog] station``, ``--station``); default the
    hostname of the machine the session was recorded on (its ``crossfield.machine``).
    """
    from crossfield.recording import seal
    from crossfield.recording.integrity import file_sha256

    folder = Path(folder).resolve()
    report_path = folder / REPORT
    report = _load_report(report_path)
    integrity = report.get("integrity") or {}
    mcap = folder / str(integrity.get("recording") or RECORDING)
    if mcap.name != Path(mcap.name).name or mcap.parent != folder:
        raise CatalogError(f"{report_path}: integrity.recording {integrity.get('recording')!r} is not a file name")
    if not mcap.is_file():
        raise CatalogError(f"{mcap}: no recording (a session is catalogued with its recording and seal)")
    try:
        sidecar = seal.read_sidecar(mcap)
    except seal.SealError as exc:
        raise CatalogError(str(exc)) from None
    if sidecar is None:
        raise CatalogError(f"{seal.sidecar_path(mcap)}: no seal next to the recording")
    actual = file_sha256(mcap)
    if sidecar.get("file_sha256") != actual:
        raise CatalogError(
            f"{mcap}: its SHA-256 {actual} differs from its seal's {sidecar.get('file_sha256')}: "
            f"changed since it was sealed, not catalogued"
        )
    head = sidecar.get("chain_head")
    if not seal.is_digest(head):
        raise CatalogError(f"{seal.sidecar_path(mcap)}: chain_head {head!r} is not a SHA-256")
    if integrity.get("chain_head") not in (None, head):
        raise CatalogError(
            f"{report_path}: integrity.chain_head {integrity.get('chain_head')} differs from the seal's {head}"
        )
    facts, machine, calibration_rms = _recording_facts(mcap)
    sess = report["session"]
    session_id = _text(sess.get("id"))
    if not session_id:
        raise CatalogError(f"{report_path}: session.id is empty")
    if facts.get("session_id") not in (None, session_id):
        raise CatalogError(
            f"{mcap}: the recording's session id {facts.get('session_id')!r} is not the report's {session_id!r}"
        )
    start_ns = sess.get("start_time_ns")
    if not isinstance(start_ns, int):
        raise CatalogError(f"{report_path}: session.start_time_ns is not an integer")
    frames = [f for f in report.get("frames") or [] if isinstance(f, dict)]
    last_ns = max((f["timestamp_ns"] for f in frames if isinstance(f.get("timestamp_ns"), int)), default=None)
    job = report.get("job") or {}
    plan = report.get("plan") or {}
    calibration = report.get("calibration") or {}
    verdict = "incomplete" if report.get("incomplete") else ("pass" if report.get("passed") else "fail")
    packages = report.get("packages") or {}
    session_row = {
        "id": session_id,
        "station": station or _text(machine.get("hostname")) or "unknown",
        "operator": _text(job.get("operator")),
        "part": _text(job.get("part")),
        "serial": _text(job.get("serial")),
        "job_order": _text(job.get("order")),
        "job_json": _json(job),
        "start_utc": _utc(start_ns),
        "start_time_ns": start_ns,
        "end_utc": _utc(last_ns) if last_ns is not None else None,
        "plan_name": _text(plan.get("name")),
        "plan_sha256": plan.get("sha256") if seal.is_digest(plan.get("sha256")) else None,
        "calibration_source": _text(calibration.get("source") or facts.get("calibration_source")),
        "calibration_sha256": (
            facts.get("calibration_sha256") if seal.is_digest(facts.get("calibration_sha256")) else None
        ),
        "crossfield_version": _text(packages.get("crossfield") or facts.get("crossfield_version")),
        "plugins_json": _json(report.get("plugins") or {}),
        "packages_json": _json(packages),
        "verdict": verdict,
        "frames_processed": int(report.get("frames_processed") or 0),
        "frames_failed": int(report.get("frames_failed") or 0),
        "folder": str(folder),
        "ingested_utc": _dt.datetime.now(_dt.UTC).replace(tzinfo=None),
    }
    rows = []
    for i, c in enumerate(report.get("characteristics") or []):
        if not isinstance(c, dict):
            raise CatalogError(f"{report_path}: characteristics[{i}] is not an object")
        rows.append(
            {
                "session_id": session_id,
                "no": int(c.get("no") or i + 1),
                "name": _text(c.get("name")),
                "kind": _text(c.get("kind")),
                "measured_mm": _finite(c.get("measured_mm")),
                "nominal_mm": _finite(c.get("nominal_mm")),
                "upper_tol_mm": _finite(c.get("upper_tol_mm", c.get("tolerance_mm"))),
                "lower_tol_mm": _finite(c.get("lower_tol_mm", c.get("tolerance_mm"))),
                "expanded_uncertainty_mm": _finite(c.get("expanded_uncertainty_mm")),
                "coverage_factor": _finite(c.get("coverage_factor")),
                "decision": c.get("decision"),
                "decision_rule": c.get("decision_rule"),
                "budget_json": _json(c.get("budget") or []),
            }
        )
    signature = sidecar.get("signature") if isinstance(sidecar.get("signature"), dict) else None
    public_key = signature.get("public_key") if signature else None
    if public_key is not None and not seal.is_digest(public_key):
        raise CatalogError(f"{seal.sidecar_path(mcap)}: signature.public_key {public_key!r} is not 64 hex digits")
    seal_row = {
        "session_id": session_id,
        "recording": mcap.name,
        "chain_head": head,
        "file_sha256": actual,
        "signature_json": _json(signature) if signature else None,
        "public_key": public_key,
        "public_key_fingerprint": key_fingerprint(public_key) if public_key else None,
    }
    registration = report.get("registration") or {}
    consistency = (report.get("uncertainty") or {}).get("consistency") or {}
    values = {
        "registration_rms_mm": registration.get("rms_mm"),
        "rotation_spread_rad": registration.get("rotation_spread_rad"),
        "consistency_birge_ratio": consistency.get("birge_ratio"),
        "consistency_p_value": consistency.get("p_value"),
        "consistency_warning": (1.0 if consistency.get("warning") else 0.0) if consistency else None,
        "cmm_inflation": consistency.get("cmm_inflation"),
        "frames_failed": report.get("frames_failed"),
        "problems": len(report.get("problems") or []),
        "calibration_rms_px": calibration_rms,
    }
    health = tuple(
        {"session_id": session_id, "figure": name, "value": _finite(v), "unit": HEALTH[name][0]}
        for name, v in values.items()
        if _finite(v) is not None
    )
    return SessionRecord(session_row, tuple(rows), seal_row, health)


def key_fingerprint(public_key_hex: str) -> str:
    """SHA-256 (hex) of the raw 32-byte Ed25519 public key given as 64 hex digits."""
    import hashlib

    return hashlib.sha256(bytes.fromhex(public_key_hex)).hexdigest()


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------


def _existing(conn: Connection, session_id: str) -> Mapping[str, Any] | None:
    q = (
        sa.select(S.sessions.c.folder, S.seals.c.recording, S.seals.c.file_sha256, S.seals.c.chain_head)
        .select_from(S.sessions.join(S.seals, S.seals.c.session_id == S.sessions.c.id, isouter=True))
        .where(S.sessions.c.id == session_id)
    )
    row = conn.execute(q).mappings().first()
    return dict(row) if row is not None else None


def _compare(record: SessionRecord, row: Mapping[str, Any]) -> str:
    """"present" when ``row`` (the catalogued session) is ``record``'s recording, else raise."""
    if row["file_sha256"] == record.seal["file_sha256"] and row["chain_head"] == record.seal["chain_head"]:
        return "present"
    here = Path(record.session["folder"]) / record.seal["recording"]
    there = Path(row["folder"]) / str(row["recording"])
    raise CatalogConflict(
        f"{here}: session {record.id} is already catalogued with another recording ({there}: "
        f"SHA-256 {row['file_sha256']}, chain head {row['chain_head']}; this one: SHA-256 "
        f"{record.seal['file_sha256']}, chain head {record.seal['chain_head']}); refused"
    )


def _insert_rows(conn: Connection, record: SessionRecord) -> None:
    conn.execute(S.sessions.insert(), [dict(record.session)])
    if record.characteristics:
        conn.execute(S.characteristics.insert(), [dict(r) for r in record.characteristics])
    conn.execute(S.seals.insert(), [dict(record.seal)])
    if record.health:
        conn.execute(S.station_health.insert(), [dict(r) for r in record.health])


def add_record(eng: Engine, record: SessionRecord) -> str:
    """Write ``record`` in one transaction: "added", or "present" when the same recording is
    already catalogued; :class:`CatalogConflict` when another recording holds its id."""
    for attempt in (0, 1):
        try:
            with eng.begin() as conn:
                row = _existing(conn, record.id)
                if row is not None:
                    return _compare(record, row)
                _insert_rows(conn, record)
                return "added"
        except sa.exc.IntegrityError:
            # another writer added the same id between our look and our insert
            # (PostgreSQL, READ COMMITTED): look again, once
            if attempt:
                raise
    raise AssertionError("unreachable")


def add_folder(eng: Engine, folder: str | Path, *, station: str | None = None) -> IngestResult:
    """Read and add one session folder; an error is a result, not an exception."""
    try:
        record = read_session(folder, station=station)
    except CatalogError as exc:
        return IngestResult(str(folder), None, "error", str(exc))
    try:
        return IngestResult(str(folder), record.id, add_record(eng, record))
    except CatalogError as exc:
        return IngestResult(str(folder), record.id, "error", str(exc))
    except sa.exc.SQLAlchemyError as exc:
        return IngestResult(str(folder), record.id, "error", f"{folder}: the catalog refused it: {exc}")


def session_folders(paths: Iterable[str | Path]) -> Iterator[Path]:
    """The session folders under ``paths``: a folder holding a report.json, or any folder
    below one that does (sorted; each once). CatalogError for a path that does not exist."""
    seen: set[Path] = set()
    for p in paths:
        path = Path(p)
        if path.is_file() and path.name in (REPORT, RECORDING):
            path = path.parent
        if not path.is_dir():
            raise CatalogError(f"{p}: no such session folder")
        found = [path] if (path / REPORT).is_file() else sorted(r.parent for r in path.rglob(REPORT))
        for folder in found:
            key = folder.resolve()
            if key not in seen:
                seen.add(key)
                yield folder
