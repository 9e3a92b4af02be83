"""Exports of a session's results for SPC and QMS software: one row per characteristic.

Columns (:data:`COLUMNS`; lengths in mm, as in report.json, unrounded):
``session, part, serial, no, name, kind, nominal_mm, measured_mm, deviation_mm,
upper_tol_mm, lower_tol_mm, u_mm, U_mm, k, decision_rule, decision, accepted, n_frames``.
``crossfield export SESSION --csv FILE`` writes it from a session's report.json;
:func:`characteristic_rows` gives the same rows from a :class:`~crossfield.session.SessionSummary`
or a report.json document (``crossfield.export.characteristic_rows(summary)``).
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from crossfield.errors import ConfigError

__all__ = ["COLUMNS", "characteristic_rows", "load_report", "to_csv", "write_csv"]

COLUMNS = (
    "session", "part", "serial", "no", "name", "kind", "nominal_mm", "measured_mm", "deviation_mm",
    "upper_tol_mm", "lower_tol_mm", "u_mm", "U_mm", "k", "decision_rule", "decision", "accepted", "n_frames",
)


def load_report(session: str | Path) -> dict[str, Any]:
    """report.json of ``session``: a session folder, or the report.json file itself."""
    path = Path(session)
    if path.is_dir():
        path = path / "report.json"
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the session report: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a session report: a binary file, not UTF-8 JSON") from None
    try:
        report = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not valid JSON: line {exc.lineno}: {exc.msg}") from None
    if not isinstance(report, dict) or not str(report.get("format", "")).startswith("crossfield-report/"):
        raise ConfigError(f"{path}: not a crossfield report.json (key 'format' missing or unknown)")
    if report["format"] != "crossfield-report/2":
        raise ConfigError(f"{path}: report format {report['format']!r} has no uncertainty budget; "
                          "replay the session with this version (crossfield replay) to export it")
    return report


def characteristic_rows(source: Any) -> list[dict[str, Any]]:
    """One dict per characteristic (keys :data:`COLUMNS`) from a SessionSummary or a
    report.json document (dict)."""
    if not isinstance(source, Mapping):
        from crossfield.report.document import build_report

        source = build_report(source)
    job = source.get("job") or {}
    rows = []
    for c in source["characteristics"]:
        rows.append({
            "session": source["session"]["id"],
            "part": job.get("part", ""),
            "serial": job.get("serial", ""),
            "no": c["no"],
            "name": c["name"],
            "kind": c["kind"],
            "nominal_mm": c["nominal_mm"],
            "measured_mm": c["measured_mm"],
            "deviation_mm": c["deviation_mm"],
            "upper_tol_mm": c["upper_tol_mm"],
            "lower_tol_mm": c["lower_tol_mm"],
            "u_mm": c["uncertainty_mm"],
            "U_mm": c["expanded_uncertainty_mm"],
            "k": c["coverage_factor"],
            "decision_rule": c["decision_rule"],
            "decision": c["decision"],
            "accepted": c["passed"],
            "n_frames": c["n_frames"],
        })
    return rows


def to_csv(rows: list[dict[str, Any]]) -> str:
    """CSV text (RFC 4180, comma, header row); floats by repr (they read back exactly),
    unknown values empty."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(COLUMNS), lineterminator="\r\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row[k] is None else (repr(row[k]) if isinstance(row[k], float) else row[k])
                         for k in COLUMNS})
    return out.getvalue()


def write_csv(source: Any, path: str | Path) -> Path:
    """Write the rows of ``source`` (SessionSummary, report.json dict, or a session folder /
    report.json path) to the CSV file ``path``."""
    if isinstance(source, (str, Path)):
        source = load_report(source)
    path = Path(path)
    try:
        path.write_text(to_csv(characteristic_rows(source)), encoding="utf-8", newline="")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write the CSV file: {exc.strerror}") from None
    return path
