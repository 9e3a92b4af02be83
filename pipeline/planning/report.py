"""The plan report: one HTML page with the sweep plots as inline SVG, and its JSON.

``write_report(out_dir, prediction, sweeps, recommendation)`` writes
``plan.html`` and ``plan.json``. Plots (matplotlib, Agg/SVG backend, imported
here only): per sweep the largest session standard uncertainty over the
characteristics against the parameter, Monte Carlo (solid, markers) and
analytic (dashed); hollow markers are layouts with points outside an image;
and the session TRE field over the measuring plane.
"""

from __future__ import annotations

import html
import io
import json
from pathlib import Path
from typing import Any


def _svg(fig) -> str:
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    return text[text.index("<svg"):]


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
        out[name] = _svg(fig)
        plt.close(fig)
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
    svg = _svg(fig)
    plt.close(fig)
    return svg


def render_html(prediction: dict[str, Any], sweeps: dict[str, Any] | None, recommendation: dict[str, Any] | None) -> str:
    e = html.escape
    st = prediction["station"]
    k = prediction["coverage_factor"]
    rows = []
    for c in prediction["characteristics"]:
        an, mc = c.get("analytic", {}), c.get("monte_carlo", {})

        def f(d, key, scale=1.0):
            return f"{scale * d[key]:.4f}" if key in d and d[key] is not None else "–"

        rows.append(
            f"<tr><td>{e(c['name'])}</td><td>{e(c['kind'])}</td><td>{c['true_mm']:.3f}</td>"
            f"<td>{f(an, 'u_mm')}</td><td>{f(mc, 'u_mm')}</td><td>{c['predicted_U_mm']:.4f}</td>"
            f"<td>{f(an, 'u_camera_frame_mm')}</td><td>{f(an, 'u_cmm_mm')}</td><td>{f(an, 'u_reference_line_mm')}</td></tr>"
        )
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>crossfield plan</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:1em auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}.plots{display:flex;flex-wrap:wrap}"
        ".plots div{margin:4px}</style></head><body>",
        f"<h1>Station plan: {e(str(st['name']))}</h1>",
        "<p>" + ", ".join(f"{e(str(key))} = {e(str(v))}" for key, v in st.items() if key != "name") + "</p>",
        f"<p>Centroid sigma {prediction['centroid_sigma_px']:.5f} px (Cramér-Rao bound "
        f"{prediction['centroid_crb_px']:.5f} px); route for the prediction: {e(prediction['route'])}.</p>",
        f"<h2>Predicted session uncertainty (mm)</h2><table><tr><th>characteristic</th><th>kind</th><th>true</th>"
        f"<th>u analytic</th><th>u Monte Carlo</th><th>U (k = {k:g})</th><th>camera part per frame</th>"
        f"<th>CMM part</th><th>of it: reference line</th></tr>",
        *rows, "</table>",
    ]
    if recommendation:
        parts.append(f"<h2>Recommendation</h2><p id='recommendation'>{e(recommendation['reason'])}</p>")
    if "tre_field" in prediction:
        parts.append("<h2>Target registration error over the measuring plane</h2>" + tre_svg(prediction["tre_field"]))
    if sweeps:
        parts.append(f"<h2>Sweeps</h2><p>Monte Carlo ({sweeps['sessions']} sessions per point): solid; analytic: "
                     f"dashed; hollow markers: some point leaves an image.</p><div class='plots'>")
        parts += [f"<div id='sweep-{e(n)}'>{svg}</div>" for n, svg in sweep_svgs(sweeps).items()]
        parts.append("</div>")
    parts.append("</body></html>")
    return "\n".join(parts)


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
