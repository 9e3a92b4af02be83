"""The verification record (VDI/VDE 2634-1 length test): ``<stem>.json`` and ``<stem>.html``.

The page is the template ``verification.html.j2`` with the record header every
crossfield report carries (:mod:`crossfield.report.header`): date, software,
the recording's seal (chain head, file SHA-256, signature) when the verification
was recorded, the acceptance rule (every |E| <= MPE: simple acceptance, ISO
14253-1, no guard band), the calibration under test with its SHA-256, the
operator and the instruments (the scale bar with its certified length and u, the
stereo camera pair); then the length errors E per position (table, and a chart of E
against +-MPE as inline SVG). ``<stem>.json`` holds the same, unrounded:
:meth:`crossfield.verification.procedure.VerificationResult.to_dict` and ``record``.
Lengths in mm, E in the table in um.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from markupsafe import Markup

from crossfield.report.header import Fact, RecordHeader, now_utc, seal_facts
from crossfield.report.vocabulary import DASH, verdict_class, verdict_word
from crossfield.verification.procedure import MIN_POSITIONS, VerificationResult

__all__ = ["ACCEPTANCE_RULE", "record_facts", "verification_chart", "verification_header", "write_verification"]

#: How the verification decides (VDI/VDE 2634-1; simple acceptance, ISO 14253-1).
ACCEPTANCE_RULE = (
    f"VDI/VDE 2634-1: every |E| \u2264 MPE at \u2265 {MIN_POSITIONS} positions (ISO 14253-1 simple acceptance)"
)


def record_facts(
    result: VerificationResult,
    *,
    calibration_sha256: str | None,
    seal: Any = None,
    operator: str | None = None,
    date_utc: str | None = None,
    software: str | None = None,
) -> dict[str, Any]:
    """The ``record`` section of ``<stem>.json``: when, by what and whom, under which
    calibration, and the recording's seal (``Seal.to_json()``, None when not recorded)."""
    from crossfield.chain.provenance import crossfield_version

    return {
        "date_utc": date_utc or now_utc(),
        "crossfield_version": software or crossfield_version(),
        "operator": operator or None,
        "calibration_source": result.calibration_source,
        "calibration_sha256": calibration_sha256,
        "acceptance_rule": ACCEPTANCE_RULE,
        "instruments": [
            {"id": "scale bar", "kind": f"certified length {result.certified_mm:g} mm, "
             f"u = {result.certified_u_mm * 1000:g} \u00b5m", "calibrated": None, "due": None},
            {"id": "stereo camera pair", "kind": f"calibration under test: {result.calibration_source}",
             "calibrated": None, "due": None},
        ],
        "integrity": None if seal is None else seal.to_json(),
    }


def verification_header(result: VerificationResult, record: Mapping[str, Any]) -> RecordHeader:
    """The record header of the verification page (``record``: :func:`record_facts`)."""
    facts = [
        Fact("Date (UTC)", record["date_utc"], "record-date"),
        Fact("Software", f"crossfield {record['crossfield_version']}", "record-software"),
        *seal_facts(record["integrity"], "not recorded (crossfield verify --record VERIFY.mcap)"),
        Fact("Decision rule", record["acceptance_rule"], "decision-rule"),
        Fact("Guard band", "none (w = 0)", "guard-band"),
        Fact("Calibration", record["calibration_source"] or DASH, "record-calibration"),
        Fact("Calibration SHA-256", record["calibration_sha256"] or "not recorded", "record-calibration-sha256",
             True),
        Fact("Operator", record["operator"] or "not stated (crossfield verify --operator NAME)", "record-operator"),
        Fact("MPE", f"{result.mpe_mm * 1000:g} \u00b5m", "record-mpe"),
    ]
    rows = tuple(
        tuple(str(i.get(key) or DASH) for key in ("id", "kind", "calibrated", "due")) for i in record["instruments"]
    )
    return RecordHeader(
        title="Length verification (VDI/VDE 2634-1)",
        subtitle=f"Scale bar L = {result.certified_mm:g} mm \u00b7 {len(result.positions)} positions \u00b7 "
        f"max |E| = {result.max_abs_error_mm * 1000:.1f} \u00b5m",
        verdict=("\u2713 " if result.passed else "\u2717 ") + verdict_word(result.passed),
        verdict_class=verdict_class(result.passed),
        facts=tuple(facts),
        instruments=rows,  # type: ignore[arg-type]
    )


def verification_chart(result: VerificationResult) -> str:
    """E (um) per position as bars (green within the MPE, red outside) against +-MPE (dashed), inline SVG."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from crossfield.report.figures import svg

    fig, ax = plt.subplots(figsize=(7.2, 3.6))
    names = [p.name for p in result.positions]
    errors = [p.error_mm * 1000 for p in result.positions]
    ax.bar(range(len(names)), errors, color=["#1b7a3a" if p.passed else "#b3261e" for p in result.positions])
    for sign in (-1, 1):
        ax.axhline(sign * result.mpe_mm * 1000, color="#1d2733", ls="--", lw=1)
    ax.axhline(0.0, color="#5b6b7b", lw=0.8)
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=9)
    ax.tick_params(axis="y", labelsize=9)
    ax.set_ylabel("E (\u00b5m)", fontsize=10)
    ax.set_title(f"length error E, L = {result.certified_mm:g} mm, MPE = {result.mpe_mm * 1000:g} \u00b5m (dashed)",
                 fontsize=10)
    ax.grid(axis="y", color="#c9d2dc", linewidth=0.5)
    ax.set_axisbelow(True)
    return svg(fig, "verification")


def render_verification(result: VerificationResult, record: Mapping[str, Any]) -> str:
    """The verification page (``verification.html.j2``)."""
    from crossfield.report.pages import render_page

    positions = [
        {
            "name": p.name,
            "pairs": len(p.lengths_mm),
            "length": f"{p.length_mm:.4f}",
            "error_um": f"{p.error_mm * 1000:+.1f}",
            "passed": p.passed,
            "verdict": verdict_word(p.passed),
            "cls": verdict_class(p.passed),
        }
        for p in result.positions
    ]
    return render_page("verification.html.j2", {
        "title": f"crossfield length verification \u2014 {verdict_word(result.passed)}",
        "header": verification_header(result, record),
        "result": result,
        "positions": positions,
        "min_positions": MIN_POSITIONS,
        "chart": Markup(verification_chart(result)),
    })


def write_verification(
    result: VerificationResult,
    stem: str | Path,
    *,
    calibration_sha256: str | None = None,
    seal: Any = None,
    operator: str | None = None,
) -> tuple[Path, Path]:
    """``<stem>.json`` (the result and its ``record``) and ``<stem>.html`` (header, table, chart)."""
    stem = Path(stem)
    record = record_facts(result, calibration_sha256=calibration_sha256, seal=seal, operator=operator)
    json_path, html_path = stem.with_suffix(".json"), stem.with_suffix(".html")
    json_path.write_text(json.dumps({**result.to_dict(), "record": record}, indent=2, allow_nan=False),
                         encoding="utf-8")
    html_path.write_text(render_verification(result, record), encoding="utf-8")
    return json_path, html_path
