"""Audit a recording (``crossfield audit FILE.mcap``): the profile dispatch.

A recording's MCAP profile says what it is, and so how it is audited:

* a measurement session: :func:`crossfield.audit.session.audit_session` (chain,
  provenance, reproduction by replay, seal);
* a calibration (``crossfield calibrate --record``):
  :func:`crossfield.audit.calibration.audit_calibration` (the same chain and seal,
  the calibration solved again instead of a replay);
* a verification (``crossfield verify --record``):
  :func:`crossfield.audit.verification.audit_verification` (evaluated again).

Every audit returns an :class:`~crossfield.audit.report.AuditReport`;
:func:`format_report` gives its text, :func:`to_json` its JSON.
"""

from __future__ import annotations

from pathlib import Path

import pluggy

from crossfield.audit.calibration import audit_calibration, format_calibration_report
from crossfield.audit.report import AuditReport, to_json
from crossfield.audit.session import audit_session, format_session_report
from crossfield.audit.verification import audit_verification, format_verification_report
from crossfield.recording import layout as L
from crossfield.recording.reader import open_recording

__all__ = ["AuditReport", "audit", "format_report", "to_json"]


def audit(
    path: str | Path,
    pm: pluggy.PluginManager,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> AuditReport:
    """Audit the recording ``path`` by its profile (``RecordingError`` if it is not a
    crossfield recording).

    reproduce: replay (or solve, or evaluate) again and compare; expect_head: the chain
    head kept outside the file (printed by ``crossfield run``, in report.json and the
    seal); public_key: the station's Ed25519 public key (PEM file or 64 hex digits).
    Each audit checks both before anything is replayed (a bad value is a ``ConfigError``).
    """
    path = Path(path)
    checks = dict(reproduce=reproduce, expect_head=expect_head, public_key=public_key)
    profile = open_recording(path).profile
    if profile == L.CALIBRATION_PROFILE:
        return audit_calibration(path, **checks)
    if profile == L.VERIFICATION_PROFILE:
        return audit_verification(path, **checks)
    return audit_session(path, pm, **checks)


def format_report(report: AuditReport, *, limit: int = 40) -> str:
    """The audit as text for the terminal, in the form of its kind."""
    by_kind = {"calibration": format_calibration_report, "verification": format_verification_report}
    return by_kind.get(report.kind, format_session_report)(report, limit=limit)
