"""Summaries as readable tables: plain text for ``print`` and the terminal, HTML for notebooks.

``print(summary)``, ``crossfield run``'s summary and a notebook's display of a
summary (``_repr_html_``) are one rendering of the session's report document
(``summary.report``, built once at the session end by the runner): the headline (frames,
registration RMS, the decision rule), the characteristics table of
:func:`crossfield.report.vocabulary.result_table` (lengths in mm; u, U (k = 2),
the ISO 14253-1 decision), the RMS error, the Monte Carlo check, the problems
and the session verdict, all in the words of :mod:`crossfield.report.vocabulary`.

The cells are the reported values, rounded for reading (``decimals``, 4 as
the paper prints); the summary's own fields and report.json hold the unrounded numbers.
"""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from typing import Any

from crossfield.report.vocabulary import (
    expanded_heading,
    fixed,
    guard_band_text,
    printable,
    result_table,
    rule_text,
    session_verdict,
)

__all__ = [
    "SummaryTables",
    "format_table",
    "html_table",
    "printable",
    "report_html",
    "report_text",
    "session_html",
    "session_text",
]

#: How many problems the terminal lists (report.json has them all).
PROBLEMS_SHOWN = 5


def format_table(headers: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool]) -> str:
    """Columns padded to their widest cell, two spaces apart (``right[k]``: right-align column k)."""
    widths = [max([len(h)] + [len(row[k]) for row in rows]) for k, h in enumerate(headers)]

    def line(cells: Sequence[str]) -> str:
        padded = (c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right))
        return "  ".join(padded).rstrip()

    return "\n".join([line(headers), line(["-" * w for w in widths]), *(line(r) for r in rows)])


def html_table(
    headers: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool], cls: str = ""
) -> str:
    """The same table as HTML, every cell escaped."""

    def cells(tag: str, values: Sequence[str]) -> str:
        return "".join(
            f'<{tag} style="text-align:{"right" if r else "left"}">{html.escape(v)}</{tag}>'
            for v, r in zip(values, right)
        )

    body = "".join(f"<tr>{cells('td', row)}</tr>" for row in rows)
    attr = f' class="{html.escape(cls)}"' if cls else ""
    return f"<table{attr}><thead><tr>{cells('th', headers)}</tr></thead><tbody>{body}</tbody></table>"


def _headline(report: Mapping[str, Any], decimals: int) -> list[str]:
    session = report["session"]
    lines = [
        f"Session {printable(session['id'])}  plan {printable(report['plan']['name'])}  ({session['out_dir']})",
        f"Frames: {report['frames_processed']} processed, {report['frames_failed']} failed",
    ]
    reg = report["registration"]
    if reg:
        lines.append(
            f"Registration: RMS {fixed(reg['rms_mm'], decimals)} mm over {len(reg['control_points'])} "
            f"control points (session mean of {reg['n_frames']} frames)"
        )
    else:
        lines.append("Registration: none")
    rule = report["uncertainty"]["decision_rule"]
    lines.append(f"Decision rule: {rule_text(rule)}, guard band {guard_band_text(rule)}")
    return lines


def _caption(report: Mapping[str, Any]) -> str:
    k = result_table(report).k
    return (
        f"Characteristics (mm; u: standard uncertainty of the mean; {expanded_heading(k)}: expanded "
        "uncertainty; Decision: ISO 14253-1):"
    )


def _footer(report: Mapping[str, Any], decimals: int) -> list[str]:
    lines = []
    if report["rms_error_mm"] is not None:
        lines.append(f"RMS error vs ground truth: {fixed(report['rms_error_mm'], decimals)} mm")
    mc = report.get("monte_carlo")
    if mc:
        agreed = sum(c["agreed"] for c in mc["characteristics"])
        worst = max((abs(c["agreement"]) for c in mc["characteristics"] if c["agreement"] is not None), default=0.0)
        lines.append(
            f"Monte Carlo (GUM-S1, {mc['n_draws']} draws): U_MC within {mc['tolerance']:.0%} of U for "
            f"{agreed} of {len(mc['characteristics'])} characteristics (largest difference {worst:.1%})"
        )
    problems = report["problems"]
    lines += [f"! {printable(p)}" for p in problems[:PROBLEMS_SHOWN]]
    if len(problems) > PROBLEMS_SHOWN:
        lines.append(f"! ... and {len(problems) - PROBLEMS_SHOWN} more problems (see report.json)")
    verdict = session_verdict(report["passed"], report.get("incomplete_reason") or report["incomplete"], report.get("station_moved"))
    lines.append(f"Result: {verdict}")
    return lines


def report_text(report: Mapping[str, Any], decimals: int = 4) -> str:
    """A report document as text: headline, characteristics table (mm), RMS error, verdict."""
    table = result_table(report, decimals)
    return "\n".join([
        *_headline(report, decimals), _caption(report), format_table(table.headers, table.rows, table.right),
        *_footer(report, decimals),
    ])


def report_html(report: Mapping[str, Any], decimals: int = 4) -> str:
    """A report document as an HTML fragment (a notebook's rich display), the same lines as :func:`report_text`."""
    table = result_table(report, decimals)
    head = "".join(f"<div>{html.escape(line)}</div>" for line in _headline(report, decimals))
    foot = "".join(f"<div>{html.escape(line)}</div>" for line in _footer(report, decimals))
    caption = f"<div>{html.escape(_caption(report))}</div>"
    return f"<div>{head}{caption}{html_table(table.headers, table.rows, table.right)}{foot}</div>"


def _no_document(summary: Any) -> str:
    """What a summary without its report document prints (one made outside the runner,
    which builds the document at the session end)."""
    return (
        f"Session {printable(summary.info.session_id)}: {summary.frames_processed} frames; no report document "
        "yet (crossfield.report.document.document_of(summary) builds it; report_text(document) prints it)"
    )


def session_text(summary: Any, decimals: int = 4) -> str:
    """The session as text: :func:`report_text` of its report document (``summary.report``,
    built at the session end)."""
    return _no_document(summary) if summary.report is None else report_text(summary.report, decimals)


def session_html(summary: Any, decimals: int = 4) -> str:
    """The session as an HTML fragment: :func:`report_html` of its report document."""
    if summary.report is None:
        return f"<div>{html.escape(_no_document(summary))}</div>"
    return report_html(summary.report, decimals)


class SummaryTables:
    """Mixin: ``str(summary)`` and a notebook's display show the session as a table."""

    def __str__(self) -> str:
        return session_text(self)

    def _repr_html_(self) -> str:
        return session_html(self)
