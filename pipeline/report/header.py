"""The record header every crossfield report page carries (``templates/_header.html.j2``).

One header for report.html, the verification record (VDI/VDE 2634-1), the
calibration, plan and batch reports: what the page is, its verdict, and the facts
that tie it to its recording and its conditions, each stated or said to be absent:

* the date (UTC) and the crossfield version that wrote the results;
* the seal (:mod:`crossfield.recording.seal`): the recording, its chain head, the
  file's SHA-256 and the signature status (signed with Ed25519 by which public key,
  or not signed);
* the ISO 14253-1 decision rule and its guard band (:mod:`crossfield.report.vocabulary`);
* the calibration (source, SHA-256), the operator and the instrument list, where the
  record has them.

Builders return a :class:`RecordHeader`; values are plain text (the template escapes them).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from crossfield.report.vocabulary import DASH, guard_band_text, rule_text, session_verdict, verdict_class

__all__ = [
    "Fact",
    "RecordHeader",
    "now_utc",
    "seal_facts",
    "session_header",
    "signature_text",
]

#: How a page says that a fact is not part of its record.
NOT_RECORDED = "not recorded"


@dataclass(frozen=True)
class Fact:
    """One header line: ``label``, ``value`` (plain text), ``id`` (the HTML id of its value),
    ``mono`` (a digest or path, set in a monospace font)."""

    label: str
    value: str
    id: str
    mono: bool = False


@dataclass(frozen=True)
class RecordHeader:
    """A report page's header: ``title``, ``subtitle``, the ``verdict`` text and its CSS class
    (``pass``, ``fail``, ``open``), the ``facts``, and ``instruments``: rows of
    (id, kind, calibrated, due) (empty: none stated; ``instruments_note`` says so)."""

    title: str
    subtitle: str
    verdict: str
    verdict_class: str
    facts: tuple[Fact, ...]
    instruments: tuple[tuple[str, str, str, str], ...] = field(default_factory=tuple)
    instruments_note: str = ""


def now_utc() -> str:
    """The present time, ISO 8601 UTC to the second (when a page is written)."""
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()


def signature_text(integrity: Mapping[str, Any] | None) -> str:
    """The signature status of a seal (report.json's ``integrity``): ``signed (Ed25519,
    public key 1a2b…)``, ``not signed (no station key, [session] signing_key)``, or that
    there is no seal."""
    if not integrity:
        return "no seal (nothing recorded)"
    if integrity.get("signed"):
        signature = integrity.get("signature") or {}
        key = str(signature.get("public_key", ""))
        return f"signed ({signature.get('algorithm', 'Ed25519')}, public key {key})"
    return "not signed (no station key: [session] signing_key, crossfield keygen)"


def seal_facts(integrity: Mapping[str, Any] | None, absent: str = NOT_RECORDED) -> list[Fact]:
    """Recording, chain head, file SHA-256 and signature of a seal (``Seal.to_json()``);
    ``absent`` names why there is none."""
    if not integrity:
        return [
            Fact("Recording", absent, "seal-recording"),
            Fact("Chain head", DASH, "seal-chain-head", True),
            Fact("File SHA-256", DASH, "seal-file-sha256", True),
            Fact("Signature", signature_text(None), "seal-signature"),
        ]
    return [
        Fact("Recording", str(integrity.get("recording", "")), "seal-recording", True),
        Fact("Chain head", str(integrity.get("chain_head", "")), "seal-chain-head", True),
        Fact("File SHA-256", str(integrity.get("file_sha256", "")), "seal-file-sha256", True),
        Fact("Signature", signature_text(integrity), "seal-signature"),
    ]


def rule_facts(rule: str | None) -> list[Fact]:
    """The ISO 14253-1 decision rule and its guard band."""
    return [
        Fact("Decision rule", rule_text(rule), "decision-rule"),
        Fact("Guard band", guard_band_text(rule), "guard-band"),
    ]


def instrument_rows(instruments: Sequence[Mapping[str, Any]]) -> tuple[tuple[str, str, str, str], ...]:
    """(id, kind, calibrated, due) per instrument, a dash for what is not stated."""
    return tuple(
        tuple(str(i.get(key) or DASH) for key in ("id", "kind", "calibrated", "due"))  # type: ignore[misc]
        for i in instruments
    )


def session_header(report: Mapping[str, Any]) -> RecordHeader:
    """The header of report.html, from the report document (report.json, with its ``integrity``)."""
    session = report["session"]
    job = report.get("job") or {}
    packages = report.get("packages") or {}
    calibration = report.get("calibration") or {}
    cal_text = str(calibration.get("source") or DASH)
    recorded = (report.get("config") or {}).get("session", {}).get("record", True)
    absent = f"{NOT_RECORDED} (session.record = false)" if not recorded else "no seal in the report document"
    facts = [
        Fact("Date (UTC)", str(session.get("start_time_utc") or NOT_RECORDED), "record-date"),
        Fact("Software", f"crossfield {packages.get('crossfield', NOT_RECORDED)}", "record-software"),
        *seal_facts(report.get("integrity"), absent),
        *rule_facts(report["uncertainty"]["decision_rule"]),
        Fact("Calibration", cal_text, "record-calibration"),
        Fact("Calibration SHA-256", str(calibration.get("sha256") or NOT_RECORDED), "record-calibration-sha256",
             True),
        Fact("Operator", str(job.get("operator") or "not stated"), "record-operator"),
        Fact("Part / serial", f"{job.get('part') or DASH} / {job.get('serial') or DASH}", "record-part"),
    ]
    passed = bool(report["passed"])
    verdict = session_verdict(passed, report.get("incomplete_reason") or report["incomplete"], report.get("station_moved"))
    return RecordHeader(
        title="Cross-field measurement report",
        subtitle=f"Plan {report['plan']['name']} \u00b7 session {session['id']}",
        verdict=("\u2713 " if passed else "\u2717 ") + verdict,
        verdict_class=verdict_class(passed),
        facts=tuple(facts),
        instruments=instrument_rows(job.get("instruments") or ()),
        instruments_note="" if job.get("instruments") else "No instruments stated in the plan ([[job.instrument]]).",
    )
