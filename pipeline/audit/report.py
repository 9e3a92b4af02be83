"""What every audit shares: the report, the seal check and its text.

:class:`AuditReport` is the result of every kind of audit (a measurement session,
:mod:`crossfield.audit.session`; a calibration, :mod:`crossfield.audit.calibration`;
a verification, :mod:`crossfield.audit.verification`). :func:`checked_report` builds
it after the chain and provenance checks (the reproduction, the file digest and the
seal: :func:`seal_check`); :func:`audit_recording` is the whole audit of a recording
that is not a measurement session; :func:`format_checks` its text.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from crossfield.audit.chain import IntegrityResult, name_message, verify
from crossfield.chain.provenance import package_versions
from crossfield.errors import ConfigError, RecordingError
from crossfield.recording import layout as L
from crossfield.recording import seal
from crossfield.recording.integrity import file_sha256
from crossfield.recording.reader import open_recording

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
TRUNCATION = {"truncated", "uncovered"}


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
    #: "session", "calibration" (:mod:`crossfield.audit.calibration`) or "verification"
    #: (:mod:`crossfield.audit.verification`).
    kind: str = "session"

    @property
    def intact(self) -> bool:
        """No finding but truncation: what is in the file is as it was written."""
        return self.integrity.has_chain and all(p.kind in TRUNCATION for p in self.integrity.problems)

    @property
    def passed(self) -> bool:
        return (
            self.complete
            and self.integrity.passed
            and self.provenance.get("passed", False)
            and (self.reproduction.get("passed", False) or not_run(self.reproduction))
            and self.seal.get("passed", False)
        )

    @property
    def not_run(self) -> list[str]:
        """The checks not run (``--no-replay``: ``["reproduction"]``): neither passed nor
        failed; :attr:`passed` goes by the checks that were run."""
        return ["reproduction"] if not_run(self.reproduction) else []

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "path": self.path,
            "file_sha256": self.file_sha256,
            "passed": self.passed,
            "not_run": self.not_run,
            "complete": self.complete,
            "intact": self.intact,
            "integrity": self.integrity.to_json(),
            "provenance": self.provenance,
            "reproduction": self.reproduction,
            "seal": self.seal,
            "notes": self.notes,
        }


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


def parse_head(text: str) -> str:
    """A chain head given by the user (``--expect-head``): 64 hex digits."""
    head = str(text).strip().lower()
    if not seal.is_digest(head):
        raise ConfigError(f"--expect-head: {text!r} is not a chain head (64 hex digits)")
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
    checked: list[str] = []
    not_checked: list[str] = []
    head = integrity.chain_sha256
    final = integrity.final_record_doc or {}
    recorded_head = final.get("chain_sha256")
    side_name = seal.sidecar_path(path).name
    levels = ["self-consistency"] if integrity.passed else []
    if not integrity.passed:
        checked.append("self-consistency: FAILED (see integrity)")
    elif integrity.coverage_note:
        checked.append(f"self-consistency of the messages only ({integrity.coverage_note})")
    else:
        checked.append("self-consistency (the chain head the file's own records give)")
    try:
        sidecar = seal.read_sidecar(path)
    except seal.SealError as exc:
        sidecar = None
        problems.append(str(exc))
    if sidecar is None:
        not_checked.append(f"the seal file ({side_name}: none next to the recording)")
    else:
        checked.append(f"the file's SHA-256 and chain head against the seal file ({side_name})")
        if sidecar.get("file_sha256") != actual_sha256:
            problems.append(
                f"the file's SHA-256 {actual_sha256} differs from its seal's {sidecar.get('file_sha256')} "
                f"({side_name})"
            )
        if sidecar.get("chain_head") != head:
            problems.append(
                f"the chain head {head} differs from its seal's {sidecar.get('chain_head')} "
                f"({side_name})"
            )
    expected = None
    if expect_head is not None:
        expected = parse_head(expect_head)
        checked.append("the chain head against the head kept elsewhere (--expect-head)")
        if expected == head and recorded_head == head and levels:
            levels.append("agreement with a head kept elsewhere")
        else:
            problems.append(f"the chain head {head} is not the expected {expected}")
    else:
        not_checked.append("a chain head kept elsewhere (no --expect-head)")
    signature = signature_check(path, final, head, actual_sha256, sidecar, public_key, problems, notes)
    if public_key is not None:
        checked.append(f"the station's signature (key {signature['public_key']})")
        if signature.get("in_file_valid") and not problems and levels:
            levels.append("signed by the station's key")
    else:
        not_checked.append("the station's signature (no --public-key)")
    return {
        "passed": not problems,
        "level": levels[-1] if levels and not problems else "nothing",
        "levels": levels,
        "checked": checked,
        "not_checked": not_checked,
        "chain_head": head,
        "recorded_chain_head": recorded_head,
        "file_sha256": actual_sha256,
        "expected_head": expected,
        "sidecar": sidecar,
        "signature": signature,
        "problems": problems,
        "notes": notes,
    }


def signature_check(
    path: Path,
    final: Mapping[str, Any],
    head: str,
    actual_sha256: str,
    sidecar: Mapping[str, Any] | None,
    public_key: str | Path | None,
    problems: list[str],
    notes: list[str],
) -> dict[str, Any]:
    """The station's signatures (in the final /integrity record and in the seal file)
    against ``public_key`` (None: not checked, a note if the file is signed); findings
    are appended to ``problems``."""
    recorded_head = final.get("chain_sha256")
    signature: dict[str, Any] = {"in_file": final.get("signature"), "checked": False}
    if sidecar is not None:
        signature["sidecar"] = sidecar.get("signature")
    if public_key is None:
        if final.get("signature") is not None:
            notes.append(
                f"the recording is signed by the key {final['signature'].get('public_key')}; "
                f"give --public-key to check it against the station's key"
            )
        return signature
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
    return signature


def seal_lines(sealed: Mapping[str, Any]) -> list[str]:
    """The seal section of an audit's text: the verdict with what it proves, then
    exactly what was checked and what was not (``seal_check``), problems and notes."""
    lines = [
        section(
            "seal",
            sealed.get("passed", False),
            f"chain head {sealed.get('chain_head')}; proves: {sealed.get('level')}",
        )
    ]
    lines += [f"  checked: {c}" for c in sealed.get("checked", [])]
    lines += [f"  not checked: {c}" for c in sealed.get("not_checked", [])]
    lines += [f"  - {p}" for p in sealed.get("problems", [])]
    lines += [f"  note: {n}" for n in sealed.get("notes", [])]
    return lines


def checked_report(
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
        repro = {"passed": None, "run": False, "skipped": "not run (--no-replay)", "differences": []}
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

    return checked_report(
        path, rec, integrity, prov, reproduction_of if reproduce else None, has_result,
        lambda report: integrity.ends if not integrity.complete else f"no {result_topic} message",
        kind, expect_head, public_key,
    )


def section(title: str, ok: bool, text: str = "") -> str:
    return f"{title:<14} {'PASS' if ok else 'FAIL'}{('  ' + text) if text else ''}"


def not_run(check: dict[str, Any]) -> bool:
    """True for a check that was not run (``run: False``, e.g. the reproduction under
    ``--no-replay``), as opposed to one that ran and failed or broke (``error``)."""
    return check.get("run", True) is False and not check.get("error")


def reproduction_line(repro: dict[str, Any], summary: str) -> str:
    """The reproduction's section line: ``not run (--no-replay)``, its error (FAIL), or
    PASS/FAIL with ``summary``."""
    if not_run(repro):
        return f"{'reproduction':<14} {repro.get('skipped') or 'not run'}"
    if repro.get("error") or repro.get("skipped"):
        return section("reproduction", False, repro.get("error") or repro.get("skipped"))
    return section("reproduction", repro["passed"], summary)


def verdict_line(report: AuditReport) -> str:
    """``Audit: PASS`` or ``FAIL`` by the checks run, naming those not run and an
    incomplete recording: ``Audit: PASS (reproduction not run)``."""
    notes = [f"{', '.join(report.not_run)} not run"] if report.not_run else []
    notes += [] if report.complete else ["incomplete recording"]
    return f"Audit: {'PASS' if report.passed else 'FAIL'}" + (f" ({'; '.join(notes)})" if notes else "")


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
            f"{integ.chained_text(L.TOPIC_INTEGRITY)}, chain head {integ.chain_sha256}"
        )
    else:
        text = f"{len(integ.problems)} finding(s)"
    lines.append(section("integrity", integ.passed, text))
    lines += [f"  note: {integ.coverage_note}"] if integ.coverage_note else []
    lines += [f"  - {p.detail}" for p in integ.problems[:limit]]
    cal = prov.get("calibration") or {}
    lines.append(section("provenance", prov.get("passed", False)))
    lines.append(
        f"  calibration  {cal.get('source')} SHA-256 {cal.get('sha256')} "
        f"{'matches the record' if cal.get('ok') else 'MISMATCH'}"
    )
    lines += [f"  - {p}" for p in prov.get("problems", [])]
    lines += [f"  note: {n}" for n in prov.get("notes", [])]
    lines.append(reproduction_line(repro, summary))
    if not (repro.get("error") or repro.get("skipped")):
        for d in repro["differences"][:limit]:
            where = (
                f"attachment {d['attachment']}"
                if "attachment" in d
                else name_message(d["topic"], d["sequence"], d["log_time_ns"])
            )
            lines.append(
                f"  - {where}: {d['path']}: recorded {short(d['recorded'])}, "
                f"{replayed} {short(d['replayed'])} (tolerance {short(d['tolerance'])})"
            )
        if repro["differences_total"] > limit:
            lines.append(f"  ... and {repro['differences_total'] - limit} more (see --json)")
        lines += [f"  - missing from the recording: {m}" for m in repro.get("missing", [])]
        lines += [f"  - only in the recording: {m}" for m in repro.get("only_recorded", [])]
    lines += seal_lines(sealed)
    lines += ["", verdict_line(report)]
    return "\n".join(lines)


def short(value: Any) -> str:
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
