"""Audit a recorded session (``crossfield audit SESSION.mcap``).

Three checks, each with its findings named:

* **integrity**: the SHA-256 chain written while recording
  (:mod:`crossfield.recording.integrity`) is recomputed over every message, metadata
  record and attachment in file order; a changed, removed, added or
  reordered message is named by topic, sequence and time, a chunk whose
  CRC-32 fails by its byte offset and the messages it holds. A recording
  that was cut short is checked up to where it ends and reported as
  incomplete.
* **provenance**: what the session was made of: config, plugins with their
  packages and versions (and whether the same versions are installed now),
  package versions, the machine, the plan and calibration with their
  SHA-256 (recorded digest against the attached file).
* **reproduction**: the session is replayed from its raw inputs with the
  recorded plugins and options (:mod:`crossfield.replay`), each result
  message rebuilt exactly as the recorder builds it, and compared with the
  recorded message of the same topic, sequence and time, bit for bit.
  Every difference is listed (for JSON results down to the field).
  Provenance labels that name the run rather than its results are not
  compared: see :data:`IGNORED`.

The audit passes when all three pass; an incomplete recording never passes.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pluggy

from crossfield.errors import ConfigError, CrossfieldError, RecordingError
from crossfield.recording import layout as L
from crossfield.recording import seal
from crossfield.recording.codec import decode_log
from crossfield.recording.facts import require_session
from crossfield.recording.integrity import IntegrityResult, file_sha256, name_message, verify
from crossfield.recording.reader import open_recording
from crossfield.provenance import package_versions
from crossfield.registry import STAGES, implementations

LOG_TOPIC = L.TOPIC_LOG

#: Raw inputs: replay reads them, so they are not "reproduced".
RAW_TOPICS = L.RAW_TOPICS

#: JSON paths (per topic) not compared by the reproduction check: they name
#: the run (session id, folder, replay parent, time of the replay, the
#: serial port the bytes came from, how it was written: ``frames_note`` says
#: where the rows report.json omits are, which depends on ``session.record``;
#: the audit's replay writes no file), not a result.
IGNORED: dict[str, tuple[str, ...]] = {
    L.TOPIC_REPORT: (
        "session.id",
        "session.out_dir",
        "session.parent",
        "config.session.name",
        "config.session.output_dir",
        "config.session.record",
        "config.session.rerun",
        "config.session.rerun_image_every",
        "config.session.signing_key",
        "frames_note",
        "config_source",
        "reference.source",
        "packages",
        "plugins",
    ),
    L.TOPIC_REFERENCE: ("source",),
}

#: Findings of these kinds mean "cut short", not "altered".
_TRUNCATION = {"truncated", "uncovered"}


@dataclass
class AuditReport:
    path: str
    file_sha256: str
    complete: bool
    integrity: IntegrityResult
    provenance: dict[str, Any]
    reproduction: dict[str, Any]
    seal: dict[str, Any] = field(default_factory=lambda: {"passed": True, "level": "self-consistency"})
    notes: list[str] = field(default_factory=list)
    #: "session", "calibration" (:mod:`crossfield.camera.calib_audit`) or "verification"
    #: (:mod:`crossfield.verification_audit`).
    kind: str = "session"

    @property
    def intact(self) -> bool:
        """No finding but truncation: what is in the file is as it was written."""
        return self.integrity.has_chain and all(p.kind in _TRUNCATION for p in self.integrity.problems)

    @property
    def passed(self) -> bool:
        return (
            self.complete
            and self.integrity.passed
            and self.provenance.get("passed", False)
            and self.reproduction.get("passed", False)
            and self.seal.get("passed", False)
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "path": self.path,
            "file_sha256": self.file_sha256,
            "passed": self.passed,
            "complete": self.complete,
            "intact": self.intact,
            "integrity": self.integrity.to_json(),
            "provenance": self.provenance,
            "reproduction": self.reproduction,
            "seal": self.seal,
            "notes": self.notes,
        }


# --------------------------------------------------------------------------
# Provenance
# --------------------------------------------------------------------------


def attachment_check(
    attachments: Mapping[str, Any], name: str, recorded: str | None, problems: list[str], notes: list[str]
) -> dict[str, Any]:
    """Attachment ``name`` against the SHA-256 recorded for it (None: none recorded, a note);
    a missing attachment or another digest is appended to ``problems``."""
    found = attachments.get(name)
    actual = hashlib.sha256(found.data).hexdigest() if found else None
    ok = found is not None and (recorded is None or recorded == actual)
    if found is None:
        problems.append(f"attachment {name!r} is missing")
    elif recorded is not None and recorded != actual:
        problems.append(f"attachment {name!r}: SHA-256 {actual} differs from the recorded {recorded}")
    elif recorded is None:
        notes.append(f"no recorded SHA-256 for {name!r} (recorded before it was recorded)")
    return {"recorded_sha256": recorded, "sha256": actual, "ok": ok}


def package_notes(packages: Mapping[str, str]) -> list[str]:
    """A note per recorded package version that differs from the one installed now."""
    current = package_versions()
    return [
        f"package {name}: recorded {version}, installed {current.get(name, 'not installed')}"
        for name, version in packages.items()
        if current.get(name, "not installed") != version
    ]


def recording_provenance(path: Path, record_name: str, source_key: str) -> dict[str, Any]:
    """Provenance of a calibration or verification recording: its metadata record
    ``record_name`` (``record``), the ``calibration.yml`` attachment against the record's
    ``calibration_sha256`` (its source under ``source_key``), package notes, the machine."""
    problems: list[str] = []
    notes: list[str] = []
    rec = open_recording(path, validate_crcs=False)
    try:
        meta = rec.metadata()
        attachments = rec.attachments()
    except RecordingError as exc:
        return {"passed": False, "problems": [str(exc)], "notes": [], "record": {}, "calibration": {}}
    record = meta.get(record_name) or {}
    if not record:
        problems.append(f"metadata record {record_name!r} is missing")
    calibration = attachment_check(
        attachments, L.ATTACHMENT_CALIBRATION, record.get("calibration_sha256"), problems, notes
    )
    calibration["source"] = record.get(source_key)
    packages = meta.get(L.META_PACKAGES, {})
    return {
        "passed": not problems,
        "problems": problems,
        "notes": notes + package_notes(packages),
        "record": dict(record),
        "packages": dict(packages),
        "machine": dict(meta.get(L.META_MACHINE, {})),
        "calibration": calibration,
        "attachments": sorted(attachments),
        "writer": rec.library,
        "profile": rec.profile,
    }


def provenance(path: Path, pm: pluggy.PluginManager | None) -> dict[str, Any]:
    """The session's recorded facts and their consistency (hashes, versions)."""
    rec = open_recording(path, validate_crcs=False)
    meta = rec.metadata()
    problems: list[str] = []
    notes: list[str] = []
    docs: dict[str, Any] = {}
    for name in L.METADATA_RECORDS:
        if name in meta:
            docs[name] = rec.metadata_doc(name)
        elif name == L.META_RESULT:
            notes.append(f"no {L.META_RESULT} record: the session did not end normally")
        elif name == L.META_MACHINE:
            notes.append(f"no {L.META_MACHINE} record (recorded before the machine was recorded)")
        else:
            problems.append(f"metadata record {name!r} is missing")
    session = docs.get(L.META_SESSION, {})
    attachments = rec.attachments()

    plan = attachment_check(attachments, L.ATTACHMENT_PLAN, session.get("plan_sha256"), problems, notes)
    plan.update({"name": session.get("plan_name"), "source": session.get("plan_source")})
    calibration = attachment_check(
        attachments, L.ATTACHMENT_CALIBRATION, session.get("calibration_sha256"), problems, notes
    )
    calibration["source"] = session.get("calibration_source")

    plugins = docs.get(L.META_PLUGINS, {})
    installed_plugins: dict[str, Any] = {}
    if pm is not None:
        for stage in STAGES:
            entry = plugins.get(stage) or {}
            available = implementations(pm, stage)
            impl = available.get(str(entry.get("name")))
            now = None if impl is None else {"package": impl.package, "version": impl.version}
            installed_plugins[stage] = now
            if impl is None:
                notes.append(f"{stage} plugin {entry.get('name')!r} is not installed here")
            elif (impl.package, impl.version) != (entry.get("package"), entry.get("version")):
                notes.append(
                    f"{stage} plugin {entry.get('name')!r}: recorded "
                    f"{entry.get('package')} {entry.get('version')}, "
                    f"installed {impl.package} {impl.version}"
                )
    packages = docs.get(L.META_PACKAGES, {})
    notes += package_notes(packages)
    return {
        "passed": not problems,
        "problems": problems,
        "notes": notes,
        "session": session,
        "config": docs.get(L.META_CONFIG),
        "config_toml": meta.get(L.META_CONFIG, {}).get("toml"),
        "plugins": plugins,
        "installed_plugins": installed_plugins,
        "packages": packages,
        "acquisition": docs.get(L.META_ACQUISITION),
        "machine": docs.get(L.META_MACHINE),
        "result": docs.get(L.META_RESULT),
        "plan": plan,
        "calibration": calibration,
        "ground_truth": L.ATTACHMENT_GROUND_TRUTH in attachments,
        "attachments": sorted(attachments),
        "writer": rec.library,
    }


# --------------------------------------------------------------------------
# Reproduction
# --------------------------------------------------------------------------


def json_differences(
    a: Any, b: Any, path: str = "", ignored: tuple[str, ...] = ()
) -> list[tuple[str, Any, Any]]:
    """Every leaf where ``a`` and ``b`` differ: (dotted path, a value, b value); exact equality."""
    if path in ignored:
        return []
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in list(a) + [k for k in b if k not in a]:
            sub = f"{path}.{key}" if path else str(key)
            if key not in a or key not in b:
                if sub not in ignored:
                    out.append((sub, a.get(key, "<absent>"), b.get(key, "<absent>")))
                continue
            out.extend(json_differences(a[key], b[key], sub, ignored))
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        out = []
        for k, (x, y) in enumerate(zip(a, b)):
            out.extend(json_differences(x, y, f"{path}[{k}]", ignored))
        return out
    if type(a) is not type(b) or a != b:
        return [(path, a, b)]
    return []


def _keyed(messages: list[tuple[str, int, int, bytes]]) -> dict[tuple[str, int, int, int], bytes]:
    """(topic, sequence, log_time, occurrence) -> data."""
    seen: dict[tuple[str, int, int], int] = {}
    out = {}
    for topic, log_time, sequence, data in messages:
        key = (topic, sequence, log_time)
        k = seen.get(key, 0)
        seen[key] = k + 1
        out[key + (k,)] = data
    return out


def _decode_log(data: bytes) -> str:
    try:
        return decode_log(data, L.TOPIC_LOG)[1]
    except RecordingError:
        return f"<{len(data)} bytes>"


def reproduction(path: Path, pm: pluggy.PluginManager, *, limit: int = 500) -> dict[str, Any]:
    """Replay with the recorded plugins and compare every result message (see module doc)."""
    from crossfield.recording.facts import load_session_facts
    from crossfield.recording.recorder import SessionRecorder
    from crossfield.recording.writer import MemorySink
    from crossfield.replay import replay_session

    # CRCs are not validated here: the integrity check names every damaged
    # chunk and message; the reproduction compares what the file holds.
    try:
        recorded = load_session_facts(open_recording(path, validate_crcs=False))
    except RecordingError as exc:
        return {"passed": False, "error": f"the session cannot be replayed: {exc}", "differences": []}
    sink = MemorySink(skip_topics=RAW_TOPICS)
    capture = SessionRecorder(sink)
    with tempfile.TemporaryDirectory(prefix="crossfield-audit-") as tmp:
        try:
            summary = replay_session(
                path, pm, output_dir=tmp, record=False, rerun=False, observers=[capture], recorded=recorded
            )
        except CrossfieldError as exc:
            return {"passed": False, "error": f"the replay failed: {exc}", "differences": []}
        finally:
            if not capture.closed:
                capture.close()
    rec = recorded.recording
    try:
        recorded_messages = [
            (m.topic, m.log_time_ns, m.sequence, m.data)
            for m in rec.messages(decode=False, file_order=True)
            if m.topic not in RAW_TOPICS
        ]
    except RecordingError as exc:
        return {"passed": False, "error": f"the recorded results cannot be read: {exc}", "differences": []}
    # The log is compared apart: a live run may log device events (a link
    # lost and back, a timeout) that a replay of the recorded bytes cannot
    # see; every result a log line reports is also on /frames, /reference or
    # /report, which are compared.
    logs_a = {k: v for k, v in _keyed(recorded_messages).items() if k[0] == LOG_TOPIC}
    logs_b = {k: v for k, v in _keyed(sink.messages).items() if k[0] == LOG_TOPIC}
    a = {k: v for k, v in _keyed(recorded_messages).items() if k[0] != LOG_TOPIC}
    b = {k: v for k, v in _keyed(sink.messages).items() if k[0] != LOG_TOPIC}
    log_notes = [
        {
            "log_time_ns": k[2],
            "recorded": _decode_log(v) if v is not None else None,
            "replayed": _decode_log(logs_b[k]) if k in logs_b else None,
        }
        for k, v in logs_a.items()
        if logs_b.get(k) != v
    ] + [
        {"log_time_ns": k[2], "recorded": None, "replayed": _decode_log(v)}
        for k, v in logs_b.items()
        if k not in logs_a
    ]
    differences: list[dict[str, Any]] = []
    identical = 0
    for key in a:
        if key not in b:
            continue
        if a[key] == b[key]:
            identical += 1
            continue
        topic, sequence, log_time, _ = key
        ignored = IGNORED.get(topic, ())
        try:
            ja, jb = json.loads(a[key]), json.loads(b[key])
        except ValueError:
            differences.append(
                {
                    "topic": topic,
                    "sequence": sequence,
                    "log_time_ns": log_time,
                    "path": "<data>",
                    "recorded": f"<{len(a[key])} bytes>",
                    "replayed": f"<{len(b[key])} bytes>",
                }
            )
            continue
        found = json_differences(ja, jb, "", ignored)
        if not found:
            identical += 1
        for p, x, y in found:
            differences.append(
                {
                    "topic": topic,
                    "sequence": sequence,
                    "log_time_ns": log_time,
                    "path": p,
                    "recorded": x,
                    "replayed": y,
                }
            )
    only_recorded = [k for k in a if k not in b]
    only_replayed = [k for k in b if k not in a]
    incomplete = not recorded.complete
    passed = not differences and not only_recorded and (not only_replayed or incomplete)

    def named(keys: list) -> list[dict[str, Any]]:
        return [{"topic": t, "sequence": s, "log_time_ns": lt} for t, s, lt, _ in keys[:limit]]

    return {
        "passed": passed,
        "plugins": {stage: (recorded.plugins.get(stage) or {}).get("name") for stage in STAGES},
        "frames_replayed": summary.frames_processed,
        "messages_compared": sum(1 for k in a if k in b),
        "messages_identical": identical,
        "differences": differences[:limit],
        "differences_total": len(differences),
        "only_recorded": named(only_recorded),
        "only_replayed": named(only_replayed),
        "only_replayed_note": (
            "computed by the replay but not in the cut-short recording "
            "(the session report, results of pairs cut off)"
            if incomplete and only_replayed
            else None
        ),
        "ignored": {k: list(v) for k, v in IGNORED.items()},
        "log_lines_identical": len(logs_a) - sum(1 for n in log_notes if n["recorded"] is not None),
        "log_differences": log_notes[:limit],
        "replay_incomplete": summary.incomplete,
    }


# --------------------------------------------------------------------------
# The audit
# --------------------------------------------------------------------------


# --------------------------------------------------------------------------
# The seal: the chain head and file SHA-256 against what was kept outside
# --------------------------------------------------------------------------


def parse_head(text: str) -> str:
    """A chain head given by the user (``--expect-head``): 64 hex digits."""
    head = str(text).strip().lower()
    if not seal.is_digest(head):
        raise ConfigError(f"--expect-head: {text!r} is not a SHA-256 chain head (64 hex digits)")
    return head


def seal_check(
    path: Path,
    integrity: IntegrityResult,
    actual_sha256: str,
    *,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> dict[str, Any]:
    """Check the recording's chain head and SHA-256 against the sidecar, a head
    kept elsewhere (``expect_head``) and the station's signature (``public_key``).

    ``level`` says what the audit proves (docs/replay-and-audit.md): "self-consistency"
    (the file agrees with itself), "agreement with a head kept elsewhere",
    "signed by the station's key".
    """
    problems: list[str] = []
    notes: list[str] = []
    head = integrity.chain_sha256
    final = integrity.final_record_doc or {}
    recorded_head = final.get("chain_sha256")
    levels = ["self-consistency"]
    try:
        sidecar = seal.read_sidecar(path)
    except seal.SealError as exc:
        sidecar = None
        problems.append(str(exc))
    if sidecar is None:
        notes.append(f"no seal next to the recording ({seal.sidecar_path(path).name})")
    else:
        if sidecar.get("file_sha256") != actual_sha256:
            problems.append(
                f"the file's SHA-256 {actual_sha256} differs from its seal's {sidecar.get('file_sha256')} "
                f"({seal.sidecar_path(path).name})"
            )
        if sidecar.get("chain_head") != head:
            problems.append(
                f"the chain head {head} differs from its seal's {sidecar.get('chain_head')} "
                f"({seal.sidecar_path(path).name})"
            )
    expected = None
    if expect_head is not None:
        expected = parse_head(expect_head)
        if expected == head and recorded_head == head:
            levels.append("agreement with a head kept elsewhere")
        else:
            problems.append(f"the chain head {head} is not the expected {expected}")
    signature: dict[str, Any] = {"in_file": final.get("signature"), "checked": False}
    if sidecar is not None:
        signature["sidecar"] = sidecar.get("signature")
    if public_key is not None:
        key = seal.load_public_key(public_key)
        key_hex = seal.public_key_hex(key)
        signature.update(checked=True, public_key=key_hex)
        in_file = final.get("signature")
        ok_file = (
            in_file is not None
            and recorded_head == head
            and seal.signature_valid(key, in_file, seal.head_statement(head))
        )
        signature["in_file_valid"] = ok_file
        if in_file is None:
            problems.append("the recording is not signed (no signature in its final /integrity record)")
        elif not ok_file:
            problems.append(
                f"the signature in the recording is not a valid signature of its chain head {head} "
                f"by the key {key_hex}"
            )
        if sidecar is not None and sidecar.get("signature") is not None:
            ok_side = (
                sidecar.get("chain_head") == head
                and sidecar.get("file_sha256") == actual_sha256
                and seal.signature_valid(key, sidecar["signature"], seal.seal_statement(head, actual_sha256))
            )
            signature["sidecar_valid"] = ok_side
            if not ok_side:
                problems.append(
                    f"the seal's signature is not the key {key_hex}'s signature of this file's "
                    f"chain head and SHA-256"
                )
        if ok_file and not problems:
            levels.append("signed by the station's key")
    elif final.get("signature") is not None:
        notes.append(
            f"the recording is signed by the key {final['signature'].get('public_key')}; "
            f"give --public-key to check it against the station's key"
        )
    return {
        "passed": not problems,
        "level": levels[-1],
        "levels": levels,
        "chain_head": head,
        "recorded_chain_head": recorded_head,
        "file_sha256": actual_sha256,
        "expected_head": expected,
        "sidecar": sidecar,
        "signature": signature,
        "problems": problems,
        "notes": notes,
    }


def audit(
    path: str | Path,
    pm: pluggy.PluginManager,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> AuditReport:
    """Run the checks on ``path`` (``RecordingError`` if it is not a crossfield recording).

    A calibration recording (``crossfield calibrate --record``) is audited by
    :func:`crossfield.camera.calib_audit.audit_calibration`: the same chain and seal,
    and the calibration solved again instead of a replay; a verification recording
    (``crossfield verify --record``) by :func:`crossfield.verification_audit.audit_verification`.

    expect_head: the chain head kept outside the file (printed by ``crossfield
    run``, in report.json and the seal); public_key: the station's Ed25519
    public key (PEM file or 64 hex digits). Both are checked before anything
    is replayed (a bad value is a :class:`ConfigError`).
    """
    path = Path(path)
    if expect_head is not None:
        parse_head(expect_head)
    if public_key is not None:
        seal.load_public_key(public_key)
    rec = open_recording(path)
    if rec.profile == L.CALIBRATION_PROFILE:  # a calibration session: re-solved, not replayed
        from crossfield.camera.calib_audit import audit_calibration

        return audit_calibration(path, reproduce=reproduce, expect_head=expect_head, public_key=public_key)
    if rec.profile == L.VERIFICATION_PROFILE:  # a verification session: evaluated again
        from crossfield.verification_audit import audit_verification

        return audit_verification(path, reproduce=reproduce, expect_head=expect_head, public_key=public_key)
    require_session(rec)
    integrity = verify(path)
    prov = provenance(path, pm)
    return _checked(
        path, rec, integrity, prov, (lambda p: reproduction(p, pm)) if reproduce else None,
        lambda: prov.get("result") is not None, incomplete_reason, "session", expect_head, public_key,
    )


def _checked(
    path: Path,
    rec: Any,
    integrity: Any,
    prov: dict[str, Any],
    reproduction_of: Callable[[Path], dict[str, Any]] | None,
    ended: Callable[[], bool],
    why_incomplete: Callable[[AuditReport], str],
    kind: str,
    expect_head: str | None,
    public_key: str | Path | None,
) -> AuditReport:
    """The report shared by every kind of audit, after the chain (``integrity``) and the
    provenance: the reproduction (None: not run, --no-replay), the file digest, the seal;
    complete when the file was finished, its chain is whole and ``ended()``; an
    incomplete one gets the note ``why_incomplete(report)``."""
    if reproduction_of is not None:
        repro = reproduction_of(path)
    else:
        repro = {"passed": False, "skipped": "not run (--no-replay)", "differences": []}
    digest = file_sha256(path)
    report = AuditReport(
        path=str(path),
        file_sha256=digest,
        complete=rec.complete and integrity.complete and ended(),
        integrity=integrity,
        provenance=prov,
        reproduction=repro,
        seal=seal_check(path, integrity, digest, expect_head=expect_head, public_key=public_key),
        kind=kind,
    )
    if not report.complete:
        report.notes.append(f"INCOMPLETE recording: {why_incomplete(report)}")
    return report


def audit_recording(
    path: str | Path,
    kind: str,
    profile: str,
    provenance_of: Callable[[Path], dict[str, Any]],
    reproduction_of: Callable[[Path], dict[str, Any]],
    result_topic: str,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> AuditReport:
    """The audit of a recording that is not a measurement session (a calibration, a
    verification: MCAP ``profile``): the chain, ``provenance_of(path)``,
    ``reproduction_of(path)`` unless not ``reproduce``, the seal; complete when the file
    was finished and holds a ``result_topic`` message. ``RecordingError`` if ``path``
    is not of ``profile``; ``expect_head`` / ``public_key`` as :func:`audit`."""
    path = Path(path)
    if expect_head is not None:
        parse_head(expect_head)
    if public_key is not None:
        seal.load_public_key(public_key)
    rec = open_recording(path)
    if rec.profile != profile:
        raise RecordingError(f"{path}: not a crossfield {kind} recording (profile {rec.profile!r})")
    integrity = verify(path)
    prov = provenance_of(path)

    def has_result() -> bool:
        try:
            return any(True for _ in rec.messages(result_topic, decode=False))
        except RecordingError:
            return False

    return _checked(
        path, rec, integrity, prov, reproduction_of if reproduce else None, has_result,
        lambda report: integrity.ends if not integrity.complete else f"no {result_topic} message",
        kind, expect_head, public_key,
    )


def incomplete_reason(report: AuditReport) -> str:
    """Why the audited session is incomplete: the file was cut short, or the
    session did not end normally (interrupted: no ``crossfield.result`` record)."""
    if not report.integrity.complete:
        return report.integrity.ends
    return (
        f"the session did not end normally: no {L.META_RESULT!r} record (interrupted, e.g. by Ctrl-C, "
        f"before its results were written)"
    )


def _section(title: str, ok: bool, text: str = "") -> str:
    return f"{title:<14} {'PASS' if ok else 'FAIL'}{('  ' + text) if text else ''}"


def format_report(report: AuditReport, *, limit: int = 40) -> str:
    """The audit as text for the terminal."""
    if report.kind == "calibration":
        from crossfield.camera.calib_audit import format_calibration_report

        return format_calibration_report(report, limit=limit)
    if report.kind == "verification":
        from crossfield.verification_audit import format_verification_report

        return format_verification_report(report, limit=limit)
    lines = [f"Audit of {report.path}", f"  file SHA-256 {report.file_sha256}"]
    prov = report.provenance
    session = prov.get("session") or {}
    lines.append(
        f"  session {session.get('session_id')}  started {session.get('start_time_utc')}  "
        f"crossfield {session.get('crossfield_version')}  {session.get('recording_format')}"
    )
    if session.get("parent"):
        parent = session["parent"]
        lines.append(f"  replay of {parent.get('path')} (SHA-256 {parent.get('sha256')})")
        changed = parent.get("changed") or {}
        for stage, c in (changed.get("plugins") or {}).items():
            lines.append(f"    changed {stage}: {c.get('from')} -> {c.get('to')}")
        for key, c in (changed.get("options") or {}).items():
            lines.append(f"    changed {key}: {c.get('from')!r} -> {c.get('to')!r}")
    if not report.complete:
        lines.append(f"  INCOMPLETE: {incomplete_reason(report)}")
    lines.append("")

    integ = report.integrity
    if integ.passed:
        text = (
            f"{integ.messages} messages and {integ.entries - integ.messages} other records chained "
            f"in {integ.records} {L.TOPIC_INTEGRITY} records, chain head {integ.chain_sha256}"
        )
    elif report.intact:
        text = (
            f"intact up to where the file ends: {integ.covered} of {integ.entries} records covered by "
            f"{integ.records} {L.TOPIC_INTEGRITY} records; incomplete"
        )
    else:
        text = f"{len([p for p in integ.problems if p.kind not in _TRUNCATION])} finding(s)"
    lines.append(_section("integrity", integ.passed, text))
    for p in integ.problems[:limit]:
        lines.append(f"  - {p.detail}")
    if len(integ.problems) > limit:
        lines.append(f"  ... and {len(integ.problems) - limit} more (see --json)")

    lines.append(_section("provenance", prov.get("passed", False)))
    plugins = prov.get("plugins") or {}
    for stage in STAGES:
        entry = plugins.get(stage) or {}
        lines.append(
            f"  {stage:<12} {entry.get('name', '-'):<14} "
            f"{entry.get('package', '')} {entry.get('version', '')}"
        )
    machine = prov.get("machine") or {}
    if machine:
        lines.append(
            f"  machine      {machine.get('hostname')}  {machine.get('platform')}  {machine.get('cpu')} "
            f"x{machine.get('cpu_count')}  {machine.get('python')}"
        )
    packages = prov.get("packages") or {}
    if packages:
        lines.append("  packages     " + ", ".join(f"{k} {v}" for k, v in packages.items()))
    plan, cal = prov.get("plan") or {}, prov.get("calibration") or {}
    lines.append(
        f"  plan         {plan.get('name')} ({plan.get('source')}) SHA-256 {plan.get('sha256')} "
        f"{'matches the record' if plan.get('ok') else 'MISMATCH'}"
    )
    if not cal.get("ok"):
        cal_state = "MISMATCH"
    elif cal.get("recorded_sha256"):
        cal_state = "matches the record"
    else:
        cal_state = "(no recorded digest)"
    lines.append(f"  calibration  {cal.get('source')} SHA-256 {cal.get('sha256')} {cal_state}")
    for p in prov.get("problems", []):
        lines.append(f"  - {p}")
    for n in prov.get("notes", []):
        lines.append(f"  note: {n}")

    repro = report.reproduction
    if repro.get("error") or repro.get("skipped"):
        lines.append(_section("reproduction", False, repro.get("error") or repro.get("skipped")))
    else:
        text = (
            f"{repro['messages_identical']} of {repro['messages_compared']} result messages identical "
            f"({repro['frames_replayed']} stereo pairs replayed with the recorded plugins)"
        )
        lines.append(_section("reproduction", repro["passed"], text))
        for d in repro["differences"][:limit]:
            lines.append(
                f"  - {name_message(d['topic'], d['sequence'], d['log_time_ns'])}: {d['path']}: "
                f"recorded {_short(d['recorded'])}, replayed {_short(d['replayed'])}"
            )
        if repro["differences_total"] > limit:
            lines.append(f"  ... and {repro['differences_total'] - limit} more (see --json)")
        for m in repro["only_recorded"][:limit]:
            lines.append(
                f"  - only in the recording: {name_message(m['topic'], m['sequence'], m['log_time_ns'])}"
            )
        for n in repro.get("log_differences", [])[:limit]:
            lines.append(
                f"  note: /log at {n['log_time_ns']} ns: recorded {n['recorded']!r}, "
                f"replayed {n['replayed']!r} (log lines are not results)"
            )
        if repro["only_replayed"] and repro.get("only_replayed_note"):
            lines.append(f"  - {len(repro['only_replayed'])} message(s) {repro['only_replayed_note']}")
        else:
            for m in repro["only_replayed"][:limit]:
                lines.append(
                    f"  - only in the replay (missing from the recording): "
                    f"{name_message(m['topic'], m['sequence'], m['log_time_ns'])}"
                )
    sealed = report.seal
    lines.append(
        _section(
            "seal",
            sealed.get("passed", False),
            f"chain head {sealed.get('chain_head')}; proves: {sealed.get('level')}",
        )
    )
    for p in sealed.get("problems", []):
        lines.append(f"  - {p}")
    for n in sealed.get("notes", []):
        lines.append(f"  note: {n}")
    lines.append("")
    lines.append(
        f"Audit: {'PASS' if report.passed else 'FAIL'}"
        + ("" if report.complete else " (incomplete recording)")
    )
    return "\n".join(lines)


def format_checks(
    report: AuditReport, header: list[str], summary: str, *, replayed: str = "replayed", limit: int = 40
) -> str:
    """The text of an audit of a recording that is not a measurement session (a calibration,
    a verification): ``header`` lines, then integrity, provenance, reproduction (``summary``:
    its one-line result; each difference named by message or attachment, with its tolerance;
    ``replayed`` names how the value was obtained again) and seal, then PASS/FAIL."""
    prov, integ, repro, sealed = report.provenance, report.integrity, report.reproduction, report.seal
    lines = [*header, *(f"  {n}" for n in report.notes), ""]
    if integ.passed:
        text = (
            f"{integ.messages} messages and {integ.entries - integ.messages} other records chained "
            f"in {integ.records} {L.TOPIC_INTEGRITY} records, chain head {integ.chain_sha256}"
        )
    else:
        text = f"{len(integ.problems)} finding(s)"
    lines.append(_section("integrity", integ.passed, text))
    lines += [f"  - {p.detail}" for p in integ.problems[:limit]]
    cal = prov.get("calibration") or {}
    lines.append(_section("provenance", prov.get("passed", False)))
    lines.append(
        f"  calibration  {cal.get('source')} SHA-256 {cal.get('sha256')} "
        f"{'matches the record' if cal.get('ok') else 'MISMATCH'}"
    )
    lines += [f"  - {p}" for p in prov.get("problems", [])]
    lines += [f"  note: {n}" for n in prov.get("notes", [])]
    if repro.get("error") or repro.get("skipped"):
        lines.append(_section("reproduction", False, repro.get("error") or repro.get("skipped")))
    else:
        lines.append(_section("reproduction", repro["passed"], summary))
        for d in repro["differences"][:limit]:
            where = (
                f"attachment {d['attachment']}"
                if "attachment" in d
                else name_message(d["topic"], d["sequence"], d["log_time_ns"])
            )
            lines.append(
                f"  - {where}: {d['path']}: recorded {_short(d['recorded'])}, "
                f"{replayed} {_short(d['replayed'])} (tolerance {_short(d['tolerance'])})"
            )
        if repro["differences_total"] > limit:
            lines.append(f"  ... and {repro['differences_total'] - limit} more (see --json)")
        lines += [f"  - missing from the recording: {m}" for m in repro.get("missing", [])]
        lines += [f"  - only in the recording: {m}" for m in repro.get("only_recorded", [])]
    lines.append(
        _section(
            "seal",
            sealed.get("passed", False),
            f"chain head {sealed.get('chain_head')}; proves: {sealed.get('level')}",
        )
    )
    lines += [f"  - {p}" for p in sealed.get("problems", [])]
    lines += [f"  note: {n}" for n in sealed.get("notes", [])]
    verdict = f"Audit: {'PASS' if report.passed else 'FAIL'}"
    lines += ["", verdict + ("" if report.complete else " (incomplete recording)")]
    return "\n".join(lines)


def _short(value: Any) -> str:
    text = (
        repr(value)
        if isinstance(value, float)
        else json.dumps(value)
        if not isinstance(value, str)
        else value
    )
    return text if len(text) <= 80 else text[:77] + "..."


def to_json(report: AuditReport) -> str:
    return json.dumps(report.to_json(), indent=2, default=str, allow_nan=False)
