"""``crossfield catalog report -o trends.html`` and ``crossfield catalog check``: per
characteristic an individuals / moving-range chart with limits from a stated baseline,
the Nelson tests that fire marked on it, Cp / Cpk with their intervals against the
tolerance, and the station-health figures over time.

The page is rendered with the report's Jinja2 templates (``trends.html.j2`` next to
``report.html.j2`` in ``crossfield/report/templates``, the same ``report.css``); the
charts are matplotlib SVG inline (:func:`crossfield.report.figures.svg`), so the page is
one file.

Baseline: the sessions whose start is in [``baseline_since``, ``baseline_until``), or,
when no period is given, the first ``baseline_n`` sessions (default 20) of the period
shown. The limits (:func:`crossfield.catalog.spc.individuals_limits`) come from the
baseline only; the tests run over every point shown; the capability is of the baseline
(the period the process is judged on), against [nominal - lower_tol, nominal + upper_tol]
of the newest row.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crossfield.catalog import spc
from crossfield.catalog.ingest import HEALTH
from crossfield.catalog.query import Catalog, parse_time

#: Sessions in the default baseline (the first of the period).
BASELINE_N = 20


@dataclass(frozen=True)
class Baseline:
    """Which points set the limits: a period [since, until) or the first ``n``."""

    since: _dt.datetime | None = None
    until: _dt.datetime | None = None
    n: int = BASELINE_N

    def mask(self, times: Sequence[Any]) -> np.ndarray:
        t = np.asarray([np.datetime64(x, "us") for x in times])
        if self.since is None and self.until is None:
            m = np.zeros(len(t), dtype=bool)
            m[: self.n] = True
            return m
        m = np.ones(len(t), dtype=bool)
        if self.since is not None:
            m &= t >= np.datetime64(self.since, "us")
        if self.until is not None:
            m &= t < np.datetime64(self.until, "us")
        return m

    def text(self) -> str:
        if self.since is None and self.until is None:
            return f"the first {self.n} sessions shown"
        a = self.since.isoformat(sep=" ") if self.since else "the first session"
        b = self.until.isoformat(sep=" ") if self.until else "the last session"
        return f"sessions from {a} to {b} (UTC, end excluded)"


@dataclass(frozen=True)
class Firing:
    """A Nelson test that fired: on characteristic ``name`` at the point of session
    ``session_id`` (``start_utc``), test ``rule``."""

    name: str
    rule: int
    session_id: str
    start_utc: str
    value_mm: float

    def text(self) -> str:
        return (f"{self.name}: Nelson test {self.rule} ({spc.NELSON_RULES[self.rule]}) at session "
                f"{self.session_id} ({self.start_utc}, {self.value_mm:.4f} mm)")


@dataclass(frozen=True)
class CharacteristicTrend:
    """One characteristic's chart data (mm)."""

    name: str
    session_ids: tuple[str, ...]
    times: tuple[str, ...]
    values: np.ndarray
    in_baseline: np.ndarray
    nominal: float | None
    lsl: float | None
    usl: float | None
    limits: spc.IndividualsLimits | None
    rules: Mapping[int, list[int]]
    capability: spc.Capability | None
    note: str = ""
    firings: tuple[Firing, ...] = field(default_factory=tuple)


def trend_of(name: str, df: Any, baseline: Baseline) -> CharacteristicTrend:
    """The chart data of one characteristic's rows (``df``: rows of
    :meth:`Catalog.characteristics` for ``name``, in session order, measured_mm not null)."""
    df = df[df["measured_mm"].notna()]
    values = df["measured_mm"].to_numpy(dtype=float)
    times = tuple(str(t) for t in df["start_utc"])
    ids = tuple(str(s) for s in df["session_id"])
    base = baseline.mask(list(df["start_utc"]))
    import pandas as pd

    last = df.iloc[-1] if len(df) else None
    nominal = float(last["nominal_mm"]) if last is not None and pd.notna(last["nominal_mm"]) else None
    lsl = usl = None
    if nominal is not None and pd.notna(last["upper_tol_mm"]) and pd.notna(last["lower_tol_mm"]):
        lsl, usl = nominal - float(last["lower_tol_mm"]), nominal + float(last["upper_tol_mm"])
    limits, rules, cap, note = None, {r: [] for r in spc.NELSON_RULES}, None, ""
    if base.sum() >= 2:
        limits = spc.individuals_limits(values[base])
        if limits.sigma > 0:
            rules = spc.nelson_rules(values, limits.centre, limits.sigma)
        else:
            note = "the baseline does not vary (MR̄ = 0): no tests"
    else:
        note = f"{int(base.sum())} baseline point(s): no limits (at least 2)"
    if lsl is not None and base.sum() >= 3:
        try:
            cap = spc.capability(values[base], lsl, usl)
        except ValueError as exc:
            note = (note + "; " if note else "") + f"no capability: {exc}"
    firings = tuple(
        Firing(name, rule, ids[i], times[i], float(values[i])) for rule, idx in rules.items() for i in idx
    )
    return CharacteristicTrend(name, ids, times, values, base, nominal, lsl, usl, limits, rules, cap, note, firings)


def trends(
    catalog: Catalog, *, station: str | None = None, since: Any = None, until: Any = None,
    names: Sequence[str] = (), baseline: Baseline = Baseline(),
) -> list[CharacteristicTrend]:
    """Every characteristic's trend over the sessions selected (``names``: only those)."""
    if names:  # each name filtered in SQL (the name index), not the whole table read
        import pandas as pd

        df = pd.concat([catalog.characteristics(name=n, station=station, since=since, until=until)
                        for n in dict.fromkeys(names)], ignore_index=True)
    else:
        df = catalog.characteristics(station=station, since=since, until=until)
    out = []
    for name in sorted(set(df["name"])) if len(df) else []:
        if names and name not in names:
            continue
        out.append(trend_of(name, df[df["name"] == name], baseline))
    return out


# --------------------------------------------------------------------------
# Charts
# --------------------------------------------------------------------------


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)  # as crossfield.report.figures: no display
    import matplotlib.pyplot as plt

    return plt


def _ticks(ax, times: Sequence[str]) -> None:
    n = len(times)
    step = max(1, n // 6)
    idx = list(range(0, n, step))
    ax.set_xticks(idx, [times[i][:10] for i in idx], fontsize=7)


def control_chart(t: CharacteristicTrend, prefix: str) -> str:
    """Individuals (top) and moving-range (bottom) chart of ``t``: baseline points shaded,
    limits dashed, the tolerance zone's limits in green, points where a test fires red with
    the test numbers."""
    from crossfield.report.figures import svg

    plt = _pyplot()
    x = np.arange(len(t.values))
    fig, (ax, axm) = plt.subplots(2, 1, figsize=(7.4, 4.2), sharex=True, height_ratios=[2.2, 1])
    if t.in_baseline.any():
        b = np.nonzero(t.in_baseline)[0]
        for a in (ax, axm):
            a.axvspan(b[0] - 0.5, b[-1] + 0.5, color="#eef2f7", zorder=0)
    ax.plot(x, t.values, "-o", ms=3, lw=0.8, color="#234e77")
    if t.limits is not None:
        L = t.limits
        ax.axhline(L.centre, color="#5b6b7b", lw=0.8)
        for y in (L.ucl, L.lcl):
            ax.axhline(y, color="#b3261e", lw=0.8, ls="--")
        ax.text(len(x) - 0.5, L.ucl, " UCL", va="center", fontsize=7, color="#b3261e")
        ax.text(len(x) - 0.5, L.lcl, " LCL", va="center", fontsize=7, color="#b3261e")
    for y in (t.lsl, t.usl):
        if y is not None:
            ax.axhline(y, color="#1b7a3a", lw=0.8, ls=":")
    fired: dict[int, list[int]] = {}
    for rule, idx in t.rules.items():
        for i in idx:
            fired.setdefault(i, []).append(rule)
    for i, rules in sorted(fired.items()):
        ax.plot(i, t.values[i], "o", ms=6, mfc="none", mec="#b3261e", mew=1.4)
        ax.annotate(",".join(map(str, rules)), (i, t.values[i]), textcoords="offset points", xytext=(0, 6),
                    ha="center", fontsize=7, color="#b3261e")
    ax.set_ylabel(f"{t.name} (mm)")
    ax.ticklabel_format(axis="y", useOffset=False)
    mr = spc.moving_ranges(t.values)
    axm.plot(x[1:], mr, "-o", ms=2.5, lw=0.8, color="#234e77")
    if t.limits is not None:
        axm.axhline(t.limits.mr_bar, color="#5b6b7b", lw=0.8)
        axm.axhline(t.limits.mr_ucl, color="#b3261e", lw=0.8, ls="--")
    axm.set_ylabel("MR (mm)")
    _ticks(axm, t.times)
    for a in (ax, axm):
        a.grid(color="#c9d2dc", lw=0.5)
        a.set_axisbelow(True)
    return svg(fig, prefix)


def health_chart(df: Any, figure: str, prefix: str) -> str:
    """One station-health figure over the sessions (per station a line)."""
    from crossfield.report.figures import svg

    rows = df[df["figure"] == figure]
    if rows.empty:
        return ""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.4, 1.9))
    for station, g in rows.groupby("station"):
        ax.plot(g["start_utc"], g["value"], "-o", ms=2.5, lw=0.8, label=str(station))
    unit = HEALTH.get(figure, ("", ""))[0]
    ax.set_ylabel(f"{unit}", fontsize=8)
    ax.set_title(figure, fontsize=9, loc="left")
    ax.tick_params(labelsize=7)
    if rows["station"].nunique() > 1:
        ax.legend(fontsize=7)
    ax.grid(color="#c9d2dc", lw=0.5)
    fig.autofmt_xdate()
    return svg(fig, prefix)


# --------------------------------------------------------------------------
# The page
# --------------------------------------------------------------------------


def _cap_text(c: spc.Capability | None) -> dict[str, str]:
    if c is None:
        return {"cp": "–", "cpk": "–"}
    pct = f"{100 * (1 - c.alpha):g} %"
    return {
        "cp": f"{c.cp:.2f} ({pct}: {c.cp_low:.2f} – {c.cp_high:.2f})",
        "cpk": f"{c.cpk:.2f} ({pct}: {c.cpk_low:.2f} – {c.cpk_high:.2f})",
    }


def render(
    catalog: Catalog, *, station: str | None = None, since: Any = None, until: Any = None,
    names: Sequence[str] = (), baseline: Baseline = Baseline(), templates: str | Path | None = None,
) -> tuple[str, list[CharacteristicTrend]]:
    """The page (HTML text) and the trends it shows."""
    from markupsafe import Markup  # the SVG is matplotlib's (no script), inlined as is

    from crossfield.report.pages import render_page

    found = trends(catalog, station=station, since=since, until=until, names=names, baseline=baseline)
    health = catalog.health(station=station, since=since, until=until)
    sessions = catalog.sessions(station=station, since=since, until=until)
    charts = []
    for i, t in enumerate(found):
        L = t.limits
        charts.append({
            "name": t.name,
            "n": len(t.values),
            "n_baseline": int(t.in_baseline.sum()),
            "figure": Markup(control_chart(t, f"spc{i}")) if len(t.values) else "",
            "centre": f"{L.centre:.4f}" if L else "–",
            "limits": f"{L.lcl:.4f} – {L.ucl:.4f}" if L else "–",
            "sigma": f"{L.sigma:.4f}" if L else "–",
            "mr_ucl": f"{L.mr_ucl:.4f}" if L else "–",
            "tolerance": f"{t.lsl:.4f} – {t.usl:.4f}" if t.lsl is not None else "–",
            **_cap_text(t.capability),
            "firings": [f.text() for f in t.firings],
            "note": t.note,
        })
    health_figures = [
        {"name": f, "unit": HEALTH[f][0], "source": HEALTH[f][1], "figure": Markup(health_chart(health, f, f"health{j}"))}
        for j, f in enumerate(HEALTH) if not health.empty and (health["figure"] == f).any()
    ]
    period = " – ".join(
        x.isoformat(sep=" ") if x else "…" for x in (parse_time(since), parse_time(until, "--until"))
    ) if (since or until) else "every catalogued session"
    n_firings = sum(len(t.firings) for t in found)
    page = render_page("trends.html.j2", dict(
        title=f"crossfield trends: {catalog.url}",
        header=_header(catalog.url, station or "every station", period, len(sessions), n_firings),
        catalog=catalog.url,
        station=station or "every station",
        period=period,
        n_sessions=len(sessions),
        baseline=baseline.text(),
        charts=charts,
        health=health_figures,
        rules=spc.NELSON_RULES,
        n_firings=n_firings,
        generated=_dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    ), templates)
    return page, found


def _header(url: str, station: str, period: str, n_sessions: int, n_firings: int) -> Any:
    """The record header of the trends page (:mod:`crossfield.report.header`): when, by what,
    over which sessions; each session's seal and decision rule are its own (the catalog keeps them)."""
    from crossfield.chain.provenance import crossfield_version
    from crossfield.report.header import Fact, RecordHeader, now_utc

    facts = (
        Fact("Date (UTC)", now_utc(), "record-date"),
        Fact("Software", f"crossfield {crossfield_version()}", "record-software"),
        Fact("Catalog", url, "record-catalog", True),
        Fact("Sessions", f"{n_sessions} ({station}, {period})", "record-sessions"),
        Fact("Seal", "per session: its chain head, file SHA-256 and signature, kept by the catalog "
             "(crossfield audit --catalog)", "seal-recording"),
        Fact("Decision rule", "per session: the ISO 14253-1 rule of its plan", "decision-rule"),
    )
    return RecordHeader(
        title="Trends and process control",
        subtitle=f"Catalog {url} \u00b7 {station} \u00b7 {period} \u00b7 {n_sessions} session(s)",
        verdict=f"{n_firings} test(s) fired" if n_firings else "in control",
        verdict_class="fail" if n_firings else "pass",
        facts=facts,
    )


