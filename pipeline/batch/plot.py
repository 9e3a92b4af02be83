"""The plot of the archive report: the distribution of the shifts a plugin swap causes.

One panel per characteristic: a histogram over the archive's sessions of
``shift / U`` (the shift of the measured value, replayed - original, over that
session's expanded uncertainty U), with the band |shift| <= U shaded. Rendered by
matplotlib (Agg, no display) to SVG text for inlining in the HTML page.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["shift_values", "shift_histogram_svg"]


def shift_values(entries: Sequence[Mapping[str, Any]]) -> dict[str, list[float]]:
    """characteristic name -> the ``shift_over_U`` of every session that has one (ratio)."""
    values: dict[str, list[float]] = {}
    for entry in entries:
        for row in entry.get("characteristics") or ():
            ratio = row.get("shift_over_U")
            if ratio is not None:
                values.setdefault(row["name"], []).append(float(ratio))
    return values


def shift_histogram_svg(entries: Sequence[Mapping[str, Any]]) -> str | None:
    """The SVG text of the histograms (None when no session has a shift to plot)."""
    values = shift_values(entries)
    if not values:
        return None
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    names = sorted(values)
    fig = Figure(figsize=(6.4, 1.9 * len(names) + 0.6), layout="constrained")
    axes = fig.subplots(len(names), 1, squeeze=False)[:, 0]
    for ax, name in zip(axes, names):
        data = values[name]
        span = max(1.0, max(abs(v) for v in data)) * 1.1
        ax.axvspan(-1.0, 1.0, color="#d8ecd8", label="|shift| <= U")
        ax.hist(data, bins=min(40, max(5, len(data))), range=(-span, span), color="#3b6ea8")
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_title(f"{name}: {len(data)} session(s)", fontsize=9, loc="left")
        ax.set_ylabel("sessions", fontsize=8)
        ax.tick_params(labelsize=8)
    axes[-1].set_xlabel("shift of the measured value / U of the session", fontsize=8)
    axes[0].legend(fontsize=7, loc="upper right")
    out = io.StringIO()
    fig.savefig(out, format="svg")
    text = out.getvalue()
    return text[text.index("<svg"):]  # inline: without the XML declaration and doctype
