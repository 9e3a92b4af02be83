"""Audit a recorded session (``crossfield audit SESSION.mcap``).

Three checks, each with its findings named:

* **integrity**: the hash chain (BLAKE3, format 3) written while recording
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
  Every difference is listed (for JSON results down to the field). The replay
  computes the session end and writes no report file (no figure is drawn:
  ``replay_session(reports=False)``).
  Provenance labels that name the run rather than its results are not
  compared: see :data:`IGNORED`.

The audit passes when all three pass; an incomplete recording never passes.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import pluggy

from crossfield.audit.chain import name_message, verify
from crossfield.audit.report import (
    IGNORED,
    LOG_TOPIC,
    RAW_TOPICS,
    TRUNCATION,
    AuditReport,
    attachment_check,
    checked_report,
    json_differences,
    package_notes,
    parse_head,
    reproduction_line,
    seal_lines,
    section,
    short,
    verdict_line,
)
from crossfield.chain.registry import STAGES, implementations
from crossfield.errors import CrossfieldError, RecordingError
from crossfield.progress import Progress
from crossfield.recording import layout as L
from crossfield.recording import seal
from crossfield.recording.calibration_files import copy_problems, disk_notes, no_copy_note, recorded_calibration_files
from crossfield.recording.codec import decode_log
from crossfield.recording.facts import load_session_facts, require_session
from crossfield.recording.reader import open_recording
from crossfield.recording.recorder import SessionRecorder
from crossfield.recording.writer import MemorySink
from crossfield.replay import replay_session

# --------------------------------------------------------------------------
# Provenance
# --------------------------------------------------------------------------


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
    calibration["files"] = _calibration_files(path, session, attachments, problems, notes)

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


def _calibration_files(
    path: Path, session: dict[str, Any], attachments: dict[str, Any], problems: list[str], notes: list[str]
) -> list[dict[str, Any]]:
    """The recorded copies of the calibration file(s): each against its recorded SHA-256
    (a mismatch or a missing copy is a problem), and against the file on disk at the
    recorded path (differs or gone: a note, not a failure; the replay uses the copy)."""
    try:
        files = recorded_calibration_files(session, attachments, str(path))
    except RecordingError as exc:
        problems.append(str(exc))
        return []
    if files is None:
        note = no_copy_note(str(session.get("calibration_source") or ""))
        if note is not None:
            notes.append(note)
        return []
    problems.extend(copy_problems(session, files))
    notes.extend(disk_notes(files))
    return [f.entry() for f in files]


# --------------------------------------------------------------------------
# Reproduction
# --------------------------------------------------------------------------


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

    # CRCs are not validated here: the integrity check names every damaged
    # chunk and message; the reproduction compares what the file holds.
    try:
        recorded = load_session_facts(open_recording(path, validate_crcs=False))
    except RecordingError as exc:
        return {"passed": False, "error": f"the session cannot be replayed: {exc}", "differences": []}
    sink = MemorySink(skip_topics=RAW_TOPICS)
    capture = SessionRecorder(sink)
    images = recorded.recording.topics().get(L.IMAGE_TOPICS[0]) if recorded.complete else None
    shown = Progress(total=images.message_count if images else None, desc="audit: replaying", log=False)
    with tempfile.TemporaryDirectory(prefix="crossfield-audit-") as tmp:
        try:
            summary = replay_session(
                path, pm, output_dir=tmp, record=False, rerun=False, reports=False, observers=[capture, shown],
                recorded=recorded,
            )
        except CrossfieldError as exc:
            return {"passed": False, "error": f"the replay failed: {exc}", "differences": []}
        finally:
            if not capture.closed:
                capture.close()
            shown.on_session_end(summary=None)  # the bar closed even if the replay failed
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
    # Topics the recording has no channel for at all were added to the recorder after it was
    # made (e.g. /scene and the image annotations): noted, not a difference of its results.
    recorded_topics = {k[0] for k in a} | set(rec.topics())
    newer_topics = sorted({k[0] for k in b if k not in a and k[0] not in recorded_topics})
    only_replayed = [k for k in b if k not in a and k[0] in recorded_topics]
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
        "topics_not_recorded": newer_topics,
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


def audit_session(
    path: str | Path,
    pm: pluggy.PluginManager,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> AuditReport:
    """Run the checks on the measurement session ``path`` (``RecordingError`` if it is not one).

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
    require_session(rec)
    integrity = verify(path)
    prov = provenance(path, pm)
    report = checked_report(
        path, rec, integrity, prov, (lambda p: reproduction(p, pm)) if reproduce else None,
        lambda: prov.get("result") is not None, incomplete_reason, "session", expect_head, public_key,
    )
    stopped = recorded_incomplete(report)
    if stopped and report.complete:  # ended INCOMPLETE (Ctrl-C, a source error), the recording finished
        report.notes.append(f"the recorded session is INCOMPLETE: {stopped}")
    return report


def recorded_incomplete(report: AuditReport) -> str | None:
    """The ``incomplete`` reason of the recorded ``crossfield.result`` (a session that
    stopped early but whose recording was finished: Ctrl-C, a source error), else None."""
    result = report.provenance.get("result")
    reason = result.get("incomplete") if isinstance(result, dict) else None
    return str(reason) if reason else None


def incomplete_reason(report: AuditReport) -> str:
    """Why the audited session is incomplete: the file was cut short, or the
    session did not end normally (interrupted: no ``crossfield.result`` record)."""
    if not report.integrity.complete:
        return report.integrity.ends
    return (
        f"the session did not end normally: no {L.META_RESULT!r} record (interrupted, e.g. by Ctrl-C, "
        f"before its results were written)"
    )


def format_session_report(report: AuditReport, *, limit: int = 40) -> str:
    """The audit of a measurement session as text for the terminal."""
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
    elif recorded_incomplete(report):
        lines.append(f"  session INCOMPLETE (as its report says): {recorded_incomplete(report)}")
    lines.append("")

    integ = report.integrity
    if integ.passed:
        text = (
            f"{integ.chained_text(L.TOPIC_INTEGRITY)}, chain head {integ.chain_sha256}"
        )
    elif report.intact:
        text = (
            f"intact up to where the file ends: {integ.covered} of {integ.entries} records covered by "
            f"{integ.records} {L.TOPIC_INTEGRITY} records; incomplete"
        )
    else:
        text = f"{len([p for p in integ.problems if p.kind not in TRUNCATION])} finding(s)"
    lines.append(section("integrity", integ.passed, text))
    if integ.coverage_note:
        lines.append(f"  note: {integ.coverage_note}")
    for p in integ.problems[:limit]:
        lines.append(f"  - {p.detail}")
    if len(integ.problems) > limit:
        lines.append(f"  ... and {len(integ.problems) - limit} more (see --json)")

    lines.append(section("provenance", prov.get("passed", False)))
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
    for copy in cal.get("files") or []:
        lines.append(
            f"  calibration file {copy.get('path')}: recorded copy {copy.get('attachment')} "
            f"SHA-256 {copy.get('sha256')} (the budget reads this copy)"
        )
    for p in prov.get("problems", []):
        lines.append(f"  - {p}")
    for n in prov.get("notes", []):
        lines.append(f"  note: {n}")

    repro = report.reproduction
    ran = not (repro.get("error") or repro.get("skipped"))
    text = (
        f"{repro['messages_identical']} of {repro['messages_compared']} result messages identical "
        f"({repro['frames_replayed']} stereo pairs replayed with the recorded plugins)"
    ) if ran else ""
    lines.append(reproduction_line(repro, text))
    if ran:
        for d in repro["differences"][:limit]:
            lines.append(
                f"  - {name_message(d['topic'], d['sequence'], d['log_time_ns'])}: {d['path']}: "
                f"recorded {short(d['recorded'])}, replayed {short(d['replayed'])}"
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
        if repro.get("topics_not_recorded"):
            lines.append(
                f"  note: topics the recording has no channel for (written by a newer recorder), not "
                f"compared: {', '.join(repro['topics_not_recorded'])}"
            )
        if repro["only_replayed"] and repro.get("only_replayed_note"):
            lines.append(f"  - {len(repro['only_replayed'])} message(s) {repro['only_replayed_note']}")
        else:
            for m in repro["only_replayed"][:limit]:
                lines.append(
                    f"  - only in the replay (missing from the recording): "
                    f"{name_message(m['topic'], m['sequence'], m['log_time_ns'])}"
                )
    lines += seal_lines(report.seal)
    lines.append("")
    verdict = verdict_line(report)
    if report.complete and recorded_incomplete(report):  # the record is sound; the session is not complete
        verdict += " (the recording and its partial results; the session is INCOMPLETE)"
    lines.append(verdict)
    return "\n".join(lines)


