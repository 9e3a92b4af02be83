"""Summaries as readable tables: plain text for ``print`` and HTML for notebooks.

``print(summary)`` shows a session's headline (frames, registration RMS) and its
characteristics as a table (lengths in mm); in Jupyter the same table renders
as HTML (``_repr_html_``). :class:`SummaryTables` gives a summary class both.

The cells are the reported values, rounded for reading (``decimals``, 4 as
the paper prints); the summary's own fields hold the unrounded numbers.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

__all__ = [
    "SummaryTables", "format_table", "html_table", "printable", "session_html", "session_rows", "session_text"
]

#: The numeric columns of the characteristics table: (header, summary field, signed).
_COLUMNS: tuple[tuple[str, str, bool], ...] = (
    ("Measured", "measured_mm", False),
    ("u", "uncertainty_mm", False),
    ("Actual", "actual_mm", False),
    ("Error", "error_mm", True),
    ("Nominal", "nominal_mm", False),
    ("Tol", "tolerance_mm", False),
    ("Dev", "deviation_mm", True),
)


def _number(value: float | None, decimals: int, signed: bool) -> str:
    """``value`` with ``decimals`` decimals (``+`` when ``signed``); ``-`` for None or NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:+.{decimals}f}" if signed else f"{value:.{decimals}f}"


def printable(text: Any) -> str:
    """``text`` with control characters (ANSI escapes, newlines) made visible."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(text))


def format_table(headers: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool]) -> str:
    """Columns padded to their widest cell, two spaces apart (``right[k]``: right-align column k)."""
    widths = [max([len(h)] + [len(row[k]) for row in rows]) for k, h in enumerate(headers)]

    def line(cells: Sequence[str]) -> str:
        padded = (c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right))
        return "  ".join(padded).rstrip()

    return "\n".join([line(headers), line(["-" * w for w in widths]), *(line(r) for r in rows)])


def html_table(headers: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool]) -> str:
    """The same table as HTML, every cell escaped."""

    def cells(tag: str, values: Sequence[str]) -> str:
        return "".join(
            f'<{tag} style="text-align:{"right" if r else "left"}">{html.escape(v)}</{tag}>'
            for v, r in zip(values, right)
        )

    body = "".join(f"<tr>{cells('td', row)}</tr>" for row in rows)
    return f"<table><thead><tr>{cells('th', headers)}</tr></thead><tbody>{body}</tbody></table>"


def session_rows(summary: Any, decimals: int = 4) -> tuple[list[str], list[list[str]], list[bool]]:
    """Headers, rows and alignment of a session's characteristics table (mm).

    Columns: number, name, frames measured (n), measured value, its standard
    uncertainty u, the simulator's actual value and the error against it (when
    the ground truth is known), nominal, tolerance, deviation, PASS/FAIL.
    """
    chars = tuple(summary.characteristics)
    truth = any(getattr(c, "actual_mm", None) is not None for c in chars)
    columns = [c for c in _COLUMNS if truth or c[1] not in ("actual_mm", "error_mm")]
    headers = ["No.", "Characteristic", "n", *(h for h, _, _ in columns), "Result"]
    right = [True, False, True, *(True for _ in columns), False]
    rows = [
        [
            str(k),
            printable(c.name),
            str(c.n),
            *(_number(getattr(c, field, None), decimals, signed) for _, field, signed in columns),
            "PASS" if c.passed else "FAIL",
        ]
        for k, c in enumerate(chars, start=1)
    ]
    return headers, rows, right


_CAPTION = "Characteristics (mm; u: standard uncertainty of the mean):"


def _headline(summary: Any, decimals: int) -> list[str]:
    info = summary.info
    lines = [
        f"Session {printable(info.session_id)}  plan {printable(info.plan.name)}  ({info.out_dir})",
        f"Frames: {summary.frames_processed} processed, {summary.frames_failed} failed",
    ]
    reg = summary.aggregate.registration
    if reg is not None:
        lines.append(
            f"Registration: RMS {_number(reg.rms_mm, decimals, False)} mm over {len(reg.controls)} "
            f"control points ({reg.n_frames} frames)"
        )
    else:
        lines.append("Registration: none")
    return lines


def _footer(summary: Any, decimals: int) -> list[str]:
    lines = []
    rms = summary.rms_error_mm()
    if rms is not None:
        lines.append(f"RMS error vs ground truth: {_number(rms, decimals, False)} mm")
    if summary.incomplete:
        lines.append(f"Incomplete: {printable(summary.incomplete)}")
    lines.append(f"Result: {'PASS' if summary.passed else 'FAIL'}")
    return lines


def session_text(summary: Any, decimals: int = 4) -> str:
    """The session as text: headline, characteristics table (mm), RMS error, verdict."""
    table = format_table(*session_rows(summary, decimals))
    return "\n".join([*_headline(summary, decimals), _CAPTION, table, *_footer(summary, decimals)])


def session_html(summary: Any, decimals: int = 4) -> str:
    """The session as an HTML fragment (a notebook's rich display)."""
    head = "".join(f"<div>{html.escape(line)}</div>" for line in _headline(summary, decimals))
    foot = "".join(f"<div>{html.escape(line)}</div>" for line in _footer(summary, decimals))
    caption = f"<div>{html.escape(_CAPTION)}</div>"
    return f"<div>{head}{caption}{html_table(*session_rows(summary, decimals))}{foot}</div>"


class SummaryTables:
    """Mixin: ``str(summary)`` and a notebook's display show the session as a table."""

    def __str__(self) -> str:
        return session_text(self)

    def _repr_html_(self) -> str:
        return session_html(self)
