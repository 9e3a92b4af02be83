"""One result vocabulary: the words and numbers every surface prints for a session's results.

The CLI table (``crossfield run``), ``print(summary)``, the notebook view
(``_repr_html_``), the Rerun report panel, ``crossfield compare``, report.html
and the other reports call these functions, so one session reads the same
everywhere (docs/report.md, "One vocabulary"):

* the expanded uncertainty as ``U (k = 2) = 0.0123 mm`` (GUM 6.2.1: U = k u_c);
* the ISO 14253-1 decision of a characteristic: ``conforms``, ``does not conform``,
  ``not proven``, with ``(accepted)`` when the rule accepts a characteristic whose
  conformance is not proven (guarded rejection);
* the decision rule and its guard band (ISO 14253-1:2017 5.2/5.3, ILAC-G8 4.2);
* the session verdict: ``PASS``, ``FAIL`` or ``INCOMPLETE (<reason>)`` (a run
  stopped early), with ``(the station moved)`` when it moved.

Everything here works on plain values or on the report document
(:func:`crossfield.report.document.build_report`); it imports nothing of crossfield.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "DASH",
    "DECISION_WORDS",
    "GUARD_BAND_WORDS",
    "RULE_WORDS",
    "ResultTable",
    "common_coverage_factor",
    "decision_class",
    "decision_text",
    "expanded_cell",
    "expanded_heading",
    "expanded_text",
    "fixed",
    "guard_band_text",
    "printable",
    "result_table",
    "rule_text",
    "session_verdict",
    "tolerance_text",
    "verdict_class",
    "verdict_word",
]

DASH = "\u2014"

#: The ISO 14253-1 decisions (crossfield.uncertainty.decision.DECISIONS) as printed.
DECISION_WORDS = {"conforms": "conforms", "does_not_conform": "does not conform", "not_proven": "not proven"}

#: The decision rules (crossfield.uncertainty.decision.RULES) as printed.
RULE_WORDS = {
    "simple": "simple acceptance",
    "guarded_acceptance": "guarded acceptance",
    "guarded_rejection": "guarded rejection",
}

#: Each rule's guard band w (ISO 14253-1:2017 5.2, 5.3; ILAC-G8:09/2019 4.2).
GUARD_BAND_WORDS = {
    "simple": "none (w = 0)",
    "guarded_acceptance": "w = U inside the tolerance zone",
    "guarded_rejection": "w = U outside the tolerance zone",
}


def fixed(value: float | None, decimals: int, signed: bool = False) -> str:
    """``value`` with ``decimals`` decimals (``+`` sign if ``signed``); a dash when unknown (None, NaN)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return DASH
    return f"{value:+.{decimals}f}" if signed else f"{value:.{decimals}f}"


def _k(k: float | None) -> str:
    """k as printed: two decimals at most (``2``, ``2.13``); report.json keeps it whole."""
    return f"{round(2.0 if k is None else float(k), 2):g}"


def expanded_heading(k: float | None) -> str:
    """``U (k = 2)``: the column heading of the expanded uncertainty; ``U (k per row)``
    when ``k`` is None (the characteristics' coverage factors differ, see
    :func:`common_coverage_factor`)."""
    return "U (k per row)" if k is None else f"U (k = {_k(k)})"


def common_coverage_factor(chars: Sequence[Mapping[str, Any]]) -> float | None:
    """The coverage factor all of a report's characteristics share (2.0 when there are
    none), or None when they differ: k is then each characteristic's own, a Student-t
    factor at its effective degrees of freedom (GUM G.3, G.4;
    :mod:`crossfield.uncertainty.dof`)."""
    ks = {round(float(c["coverage_factor"]), 2) for c in chars}
    if not ks:
        return 2.0
    return float(chars[0]["coverage_factor"]) if len(ks) == 1 else None


def expanded_cell(U_mm: float | None, k: float, common_k: float | None, decimals: int = 4) -> str:
    """A U cell: the value (mm), with ``(k = 2.13)`` after it when the table has no
    common k (:func:`common_coverage_factor`)."""
    value = fixed(U_mm, decimals)
    return value if common_k is not None else f"{value} (k = {float(k):.2f})"


def expanded_text(U_mm: float | None, k: float | None, decimals: int = 4) -> str:
    """``U (k = 2) = 0.0123 mm`` (U = k u_c, GUM 6.2.1); ``U (k = 2) = —`` when unknown."""
    value = fixed(U_mm, decimals)
    return f"{expanded_heading(k)} = {value}" + (" mm" if value != DASH else "")


def decision_text(decision: str | None, passed: bool | None = None, partial: bool = False) -> str:
    """The ISO 14253-1 decision as printed; ``(accepted)`` when ``passed`` although
    conformance is not proven (guarded rejection); ``(partial)`` when the session
    stopped early (only part of its frames measured). None (no decision recorded):
    from ``passed`` alone."""
    if decision is None:
        decision = "conforms" if passed else "does_not_conform"
    words = DECISION_WORDS.get(decision, str(decision))
    if passed and decision != "conforms":
        words += " (accepted)"
    if partial:
        words += " (partial)"
    return words


def decision_class(decision: str | None) -> str:
    """CSS class of a decision cell: ``pass``, ``fail`` or ``open`` (not proven)."""
    return {"conforms": "pass", "does_not_conform": "fail"}.get(decision or "", "open")


def rule_text(rule: str | None) -> str:
    """``ISO 14253-1 simple acceptance`` (the rule as printed)."""
    return f"ISO 14253-1 {RULE_WORDS.get(rule or 'simple', str(rule))}"


def guard_band_text(rule: str | None) -> str:
    """The rule's guard band w, in words."""
    return GUARD_BAND_WORDS.get(rule or "simple", "not stated")


def verdict_word(passed: bool) -> str:
    """``PASS`` or ``FAIL``."""
    return "PASS" if passed else "FAIL"


def verdict_class(passed: bool) -> str:
    return "pass" if passed else "fail"


def session_verdict(passed: bool, incomplete: bool | str | None = None, station_moved: str | None = None) -> str:
    """The session verdict: ``PASS``, ``FAIL``, ``INCOMPLETE (<reason>)`` (never
    PASS: a part of a session proves nothing about the rest), each with
    ``(the station moved)`` when it moved."""
    if incomplete:
        reason = incomplete if isinstance(incomplete, str) else "session incomplete"
        text = f"INCOMPLETE ({printable(reason)})"
    else:
        text = verdict_word(passed)
    if station_moved:
        text += " (the station moved)"
    return text


def tolerance_text(c: Mapping[str, Any], decimals: int) -> str:
    """``±0.1000`` for a symmetric zone, ``+0.1000/-0.0500`` otherwise (mm; a report characteristic)."""
    upper, lower = c.get("upper_tol_mm"), c.get("lower_tol_mm")
    if upper is None or lower is None:
        return "\u00b1" + fixed(c.get("tolerance_mm"), decimals)
    if upper == lower:
        return "\u00b1" + fixed(upper, decimals)
    return f"{fixed(upper, decimals, True)}/{fixed(-lower, decimals, True)}"


@dataclass(frozen=True)
class ResultTable:
    """The characteristics table of a session (lengths in mm): ``headers``, ``rows``
    (text cells), ``right`` (right-aligned columns), ``decisions`` (per row the
    decision key, for colouring) and ``k`` (the coverage factor of the U column)."""

    headers: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    right: tuple[bool, ...]
    decisions: tuple[str, ...]
    k: float | None


def result_table(report: Mapping[str, Any], decimals: int = 4) -> ResultTable:
    """The one characteristics table of a report document: No., Characteristic, n,
    Measured, u (standard uncertainty of the mean), U (k = ..), Actual and Error (when the
    simulator's truth is known), Nominal, Tol, Dev, Decision (mm)."""
    chars: Sequence[Mapping[str, Any]] = report["characteristics"]
    truth = bool(report.get("ground_truth_known"))
    k = common_coverage_factor(chars)
    headers = ["No.", "Characteristic", "n", "Measured", "u", expanded_heading(k)]
    headers += ["Actual", "Error"] if truth else []
    headers += ["Nominal", "Tol", "Dev", "Decision"]
    rows = []
    for c in chars:
        row = [
            str(c["no"]),
            printable(c["name"]),
            str(c["n_frames"]),
            fixed(c["measured_mm"], decimals),
            fixed(c["uncertainty_mm"], decimals),
            expanded_cell(c["expanded_uncertainty_mm"], c["coverage_factor"], k, decimals),
        ]
        if truth:
            row += [fixed(c.get("actual_mm"), decimals), fixed(c.get("error_mm"), decimals, True)]
        row += [
            fixed(c["nominal_mm"], decimals),
            tolerance_text(c, decimals),
            fixed(c["deviation_mm"], decimals, True),
            decision_text(c.get("decision"), c.get("passed"), bool(c.get("partial"))),
        ]
        rows.append(tuple(row))
    right = tuple(h not in ("Characteristic", "Decision") for h in headers)
    decisions = tuple(str(c.get("decision")) for c in chars)
    return ResultTable(tuple(headers), tuple(rows), right, decisions, k)


def printable(text: Any) -> str:
    """``text`` with control characters (ANSI escapes, newlines) made visible."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(text))
