"""The plan report: one HTML page with the sweep plots as inline SVG, and its JSON.

``write_report(out_dir, prediction, sweeps, recommendation)`` writes
``plan.html`` and ``plan.json``. Plots (matplotlib, Agg/SVG backend, imported
here only): per sweep the largest session standard uncertainty over the
characteristics against the parameter, Monte Carlo (solid, markers) and
analytic (dashed); hollow markers are layouts with points outside an image;
and the session TRE field over the measuring plane.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def _svg(fig, prefix: str) -> str:
    """The figure as inline SVG, its ids prefixed (several figures share one page)."""
    from crossfield.report.figures import svg

    return svg(fig, prefix)


def sweep_svgs(sweeps: dict[str, Any]) -> dict[str, str]:
    """name -> SVG text of one sweep's plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = {}
    for name, sweep in sweeps["sweeps"].items():
        fig, ax = plt.subplots(figsize=(4.6, 3.2))
        x = [p["value"] for p in sweep["points"]]
        names = [c["name"] for c in sweep["points"][0]["characteristics"]] if sweep["points"] else []
        for k, cname in enumerate(names):
            an = [p["characteristics"][k]["analytic_u_mm"] for p in sweep["points"]]
            mc = [p["characteristics"][k]["monte_carlo_u_mm"] for p in sweep["points"]]
            line = None
            if all(v is not None for v in mc):
                (line,) = ax.plot(x, [1000 * v for v in mc], "-", lw=1.2, label=cname)
                for xv, yv, p in zip(x, mc, sweep["points"]):
                    ax.plot(xv, 1000 * yv, "o", ms=4, color=line.get_color(),
                            mfc=line.get_color() if p["in_view"] else "none")
            if all(v is not None for v in an):
                ax.plot(x, [1000 * v for v in an], "--", lw=0.9, color=line.get_color() if line else None,
                        label=None if line else cname)
        ax.set_xlabel(sweep["label"])
        ax.set_ylabel("session u (µm, k = 1)")
        if name == "cmm_sigma_mm":
            ax.set_xscale("log")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        if len(names) <= 6:
            ax.legend(fontsize=7)
        out[name] = _svg(fig, f"sweep-{name}")
    return out


def tre_svg(tre: dict[str, Any]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.6, 3.2))
    im = ax.pcolormesh(tre["x_mm"], tre["y_mm"], [[1000 * v for v in row] for row in tre["tre_mm"]],
                       shading="auto", cmap="viridis")
    fig.colorbar(im, ax=ax, label="session TRE (µm)")
    ax.set_xlabel("x (mm, upper camera)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"z = {tre['z_mm']:.0f} mm", fontsize=9)
    ax.invert_yaxis()
    return _svg(fig, "tre")


def _value(value: Any) -> str:
    """A station parameter as table text (no Python reprs): numbers with %g, lists joined."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_value(v) for v in value)
    if isinstance(value, dict):
        return "; ".join(f"{k} {_value(v)}" for k, v in value.items())
    return "\u2014" if value is None else str(value)


def plan_header(prediction: dict[str, Any], recommendation: dict[str, Any] | None) -> Any:
    """The record header of the plan report: date, software, that a plan is a prediction
    (no recording, no seal, no decision), the coverage factor of its U."""
    from crossfield.chain.provenance import crossfield_version
    from crossfield.report.header import Fact, RecordHeader, now_utc, seal_facts
    from crossfield.report.vocabulary import DASH, expanded_heading

    st = prediction["station"]
    k = prediction["coverage_factor"]
    facts = [
        Fact("Date (UTC)", now_utc(), "record-date"),
        Fact("Software", f"crossfield {crossfield_version()}", "record-software"),
        *seal_facts(None, "none: a plan is a prediction from the station model, not a recorded session"),
        Fact("Decision rule", "none: a plan predicts U; each session decides under its plan's ISO 14253-1 rule",
             "decision-rule"),
        Fact("Expanded uncertainty", f"{expanded_heading(k)} = k u", "record-coverage"),
        Fact("Prediction route", str(prediction["route"]), "record-route"),
    ]
    worst = max((c["predicted_U_mm"] for c in prediction["characteristics"]), default=None)
    worst_text = DASH if worst is None else f"{worst:.4f}"
    return RecordHeader(
        title=f"Station plan: {st['name']}",
        subtitle=f"{len(prediction['characteristics'])} characteristics \u00b7 largest predicted "
        f"{expanded_heading(k)} = {worst_text} mm",
        verdict="target reached" if recommendation and recommendation.get("reached")
        else "target not reached" if recommendation else "prediction",
        verdict_class="pass" if recommendation and recommendation.get("reached")
        else "fail" if recommendation else "open",
        facts=tuple(facts),
    )


def render_html(prediction: dict[str, Any], sweeps: dict[str, Any] | None, recommendation: dict[str, Any] | None) -> str:
    """plan.html (``plan.html.j2``): the record header, the station as a table, the predicted
    uncertainties, the recommendation, the TRE field and the sweeps (inline SVG)."""
    from markupsafe import Markup

    from crossfield.report.pages import render_page
    from crossfield.report.vocabulary import expanded_heading

    def f(d: dict[str, Any], key: str) -> str:
        return f"{d[key]:.4f}" if d.get(key) is not None else "\u2013"

    rows = [
        (c["name"], c["kind"], f"{c['true_mm']:.3f}", f(c.get("analytic", {}), "u_mm"),
         f(c.get("monte_carlo", {}), "u_mm"), f"{c['predicted_U_mm']:.4f}",
         f(c.get("analytic", {}), "u_camera_frame_mm"), f(c.get("analytic", {}), "u_cmm_mm"),
         f(c.get("analytic", {}), "u_reference_line_mm"))
        for c in prediction["characteristics"]
    ]
    context = {
        "title": f"crossfield plan \u2014 {prediction['station']['name']}",
        "header": plan_header(prediction, recommendation),
        "prediction": prediction,
        "station": [(k.replace("_", " "), _value(v)) for k, v in prediction["station"].items() if k != "name"],
        "U_heading": expanded_heading(prediction["coverage_factor"]),
        "rows": rows,
        "recommendation": recommendation,
        "tre": Markup(tre_svg(prediction["tre_field"])) if "tre_field" in prediction else "",
        "sweeps": sweeps,
        "sweep_figures": [(n, Markup(svg)) for n, svg in sweep_svgs(sweeps).items()] if sweeps else [],
    }
    return render_page("plan.html.j2", context)


def write_report(out_dir: str | Path, prediction: dict[str, Any], sweeps: dict[str, Any] | None = None,
                 recommendation: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """Write plan.html and plan.json into out_dir (created); returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = {**prediction, "sweeps": sweeps, "recommendation": recommendation}
    json_path = out / "plan.json"
    json_path.write_text(json.dumps(doc, indent=2))
    html_path = out / "plan.html"
    html_path.write_text(render_html(prediction, sweeps, recommendation), encoding="utf-8")
    return html_path, json_path
