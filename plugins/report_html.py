"""Report writers "html" (report.html + report.json) and "json" (report.json only).

report.json holds every number unrounded (see :mod:`crossfield.report.document`
and ``docs/report.md``). report.html is one self-contained page (inline CSS,
no scripts, no external assets) laid out like the paper's results: Table 1
the rotation ``R_global_camera``, Table 2 the translation ``t_global_camera``
(mm), Table 3 the cross-field lengths, then the registration residuals per
control point, problems and provenance. Every string from the session is
passed through :func:`html.escape`.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from markupsafe import Markup

from crossfield.plugin_api import (
    DASH,
    KIND_CONTROL,
    KIND_TARGET,
    REPORT_JSON,
    TEMPLATE_DIR,
    SessionSummary,
    common_coverage_factor,
    decision_class,
    decision_text,
    deviation_chart,
    document_of,
    dumps,
    expanded_cell,
    expanded_heading,
    fixed,
    hookimpl,
    render_page,
    report_text,
    residual_chart,
    rule_text,
    session_header,
    thumbnail_chart,
    tolerance_text,
    trend_chart,
)

KIND_LABELS = {
    "point_point": "point to point",
    "point_line": "point to line",
    "depth": "depth (global Z)",
}

#: crossfield's own report templates (Jinja2) and style sheet.
TEMPLATE_DIR = TEMPLATE_DIR


# --------------------------------------------------------------------------
# Formatting
# --------------------------------------------------------------------------


def esc(value: Any) -> str:
    """``value`` as text, escaped for HTML text and attribute values."""
    return html.escape("" if value is None else str(value), quote=True)


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` via a temporary file and rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8", newline="\n")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------



def _row(cells: Iterable[str]) -> str:
    return "<tr>" + "".join(cells) + "</tr>"


def _td(text: str, cls: str = "") -> str:
    """A cell; ``text`` must already be escaped."""
    return f'<td class="{cls}">{text}</td>' if cls else f"<td>{text}</td>"


def _num(value: float | None, decimals: int, signed: bool = False) -> str:
    return _td(esc(fixed(value, decimals, signed)), "num")


def _decision_cell(c: Mapping[str, Any]) -> str:
    """The ISO 14253-1 decision in the words of crossfield.report.vocabulary, marked and coloured."""
    cls = decision_class(c.get("decision"))
    mark = {"pass": "&#10003; ", "fail": "&#10007; "}.get(cls, "? ")
    return _td(f"{mark}{esc(decision_text(c.get('decision'), c['passed'], bool(c.get('partial'))))}", cls)


def _budget_table(report: Mapping[str, Any], decimals: int) -> str:
    """Per characteristic, each source's contribution u_mm (mm), u_c and U."""
    chars = report["characteristics"]
    sources = [s for s in report["uncertainty"]["sources"] if any(
        t["source"] == s for c in chars for t in c["budget"])]
    head = "".join(f"<th>{esc(s.replace('_', ' '))}</th>" for s in sources)
    k = common_coverage_factor(chars)
    rows = []
    for c in chars:
        by = {t["source"]: t for t in c["budget"]}
        cells = [_td(esc(c["name"]))]
        cells += [_num(by[s]["u_mm"] if s in by else None, decimals + 1) for s in sources]
        U_text = expanded_cell(c["expanded_uncertainty_mm"], c["coverage_factor"], k, decimals)
        cells += [_num(c["uncertainty_mm"], decimals + 1), _td(esc(U_text), "num")]
        rows.append(_row(cells))
    legend = "".join(
        f"<li><strong>{esc(s.replace('_', ' '))}</strong>: {esc(report['uncertainty']['sources'][s])}</li>"
        for s in sources
    )
    return (
        '<table id="budget" class="wide">'
        "<caption>Uncertainty budget: contribution of each source (mm, standard uncertainties)</caption>"
        f"<thead><tr><th>Characteristic</th>{head}<th>u<sub>c</sub></th><th>{esc(expanded_heading(k))}</th></tr></thead>"
        f"<tbody>{''.join(rows)}</tbody>"
        f'<tfoot><tr><td colspan="{len(sources) + 3}">u<sub>c</sub> = root sum of squares of the contributions '
        "(the shared registration's correlations are inside each source's contribution); "
        f"U = k u<sub>c</sub>. report.json holds each term's input u and sensitivity.</td></tr></tfoot></table>"
        f'<ul class="note">{legend}</ul>'
    )


def _table1(reg: Mapping[str, Any] | None, decimals: int) -> str:
    if reg is None:
        return '<p id="table1-rotation">No frame was registered: no rotation matrix.</p>'
    rows = "".join(_row(_num(v, decimals) for v in row) for row in reg["R_global_camera"])
    return (
        '<table id="table1-rotation" class="matrix">'
        "<caption>Table 1. Rotation matrix R<sub>global&#8592;camera</sub></caption>"
        f"<tbody>{rows}</tbody>"
        f'<tfoot><tr><td colspan="3">det R = {esc(fixed(reg["det_R"], 6))}; {_rotation_u(reg)}'
        f"{esc(_aggregate_note(reg))}</td></tr></tfoot></table>"
    )


def _rotation_u(reg: Mapping[str, Any]) -> str:
    cov = reg.get("covariance")
    if not cov:
        return ""
    urad = ", ".join(f"{v * 1e6:.1f}" for v in cov["rotation_u_rad"])
    return f"u of the rotation vector (x, y, z) = ({esc(urad)}) &#181;rad; "


def _aggregate_note(reg: Mapping[str, Any]) -> str:
    n = reg["n_frames"]
    return f"session mean over {n} registered frame{'s' if n != 1 else ''}"


def _table2(reg: Mapping[str, Any] | None, decimals: int) -> str:
    if reg is None:
        return '<p id="table2-translation">No frame was registered: no translation vector.</p>'
    cov = reg.get("covariance")
    t_u = cov["t_u_mm"] if cov else [None, None, None]
    rows = "".join(
        _row([f"<th>{axis}</th>", _num(v, decimals), _num(u, decimals), _num(s, decimals)])
        for axis, v, u, s in zip("xyz", reg["t_global_camera_mm"], t_u, reg["t_std_mm"])
    )
    return (
        '<table id="table2-translation" class="matrix">'
        "<caption>Table 2. Translation vector t<sub>global&#8592;camera</sub> (mm)</caption>"
        '<thead><tr><th></th><th>t (mm)</th><th>u (mm)</th><th>std over frames (mm)</th></tr></thead>'
        f"<tbody>{rows}</tbody>"
        f'<tfoot><tr><td colspan="4">p<sub>global</sub> = R p<sub>camera</sub> + t; u from the stated sigmas; '
        f"{esc(_aggregate_note(reg))}</td></tr></tfoot></table>"
    )


def _table3(report: Mapping[str, Any], decimals: int) -> str:
    chars = report["characteristics"]
    truth = report["ground_truth_known"]
    head = ["No.", "Characteristic", "Elements", "Frames", "Measured", "Std", "u"]
    if truth:
        head += ["Actual", "Error"]
    k = common_coverage_factor(chars)
    head += ["Nominal", "Tolerance", "Deviation", esc(expanded_heading(k)), "Decision"]
    rows = []
    for c in chars:
        kind = KIND_LABELS.get(c["kind"], c["kind"])
        cells = [
            _td(esc(c["no"]), "num"),
            _td(f'{esc(c["name"])}<br><span class="note">{esc(kind)}</span>'),
            _td(esc(" \u2192 ".join(c["elements"]))),
            _td(esc(c["n_frames"]), "num"),
            _num(c["measured_mm"], decimals),
            _num(c["std_mm"], decimals),
            _num(c["uncertainty_mm"], decimals),
        ]
        if truth:
            cells += [_num(c.get("actual_mm"), decimals), _num(c.get("error_mm"), decimals, signed=True)]
        cells += [
            _num(c["nominal_mm"], decimals),
            _td(esc(tolerance_text(c, decimals)), "num"),
            _num(c["deviation_mm"], decimals, signed=True),
            _td(esc(expanded_cell(c["expanded_uncertainty_mm"], c["coverage_factor"], k, decimals)), "num"),
            _decision_cell(c),
        ]
        rows.append(_row(cells))
    if not rows:
        rows.append(_row([_td("No characteristics were evaluated.")]))
    foot = (
        "Measured = mean over frames; Std = repeatability (sample standard deviation); "
        "u = standard uncertainty of the mean; Deviation = Measured &#8722; Nominal"
    )
    if truth:
        foot += "; Error = Measured &#8722; Actual (simulator ground truth)"
    header = "".join(f"<th>{h}</th>" for h in head)
    return (
        '<table id="table3-lengths" class="wide">'
        "<caption>Table 3. Cross-field length measurement results (mm)</caption>"
        f"<thead><tr>{header}</tr></thead><tbody>{''.join(rows)}</tbody>"
        f'<tfoot><tr><td colspan="{len(head)}">{foot}.</td></tr></tfoot></table>'
    )


def _consistency_html(report: Mapping[str, Any]) -> str:
    check = report["uncertainty"]["consistency"]
    if check is None:
        return '<p class="note">No registration residuals to test against the stated sigmas.</p>'
    text = (
        f"Chi-square test of the registration residuals against the stated sigmas: "
        f"chi2 = {check['chi2']:.1f} for {check['dof']} degrees of freedom, p = {check['p_value']:.3g}, "
        f"Birge ratio {check['birge_ratio']:.2f}."
    )
    if check["warning"]:
        return f'<p class="warning" id="consistency-warning"><strong>Warning:</strong> {esc(check["warning"])}.</p>'
    return f'<p class="note" id="consistency">{esc(text)} Consistent at alpha = {check["alpha"]:g}.</p>'


def _monte_carlo_html(report: Mapping[str, Any], decimals: int) -> str:
    mc = report.get("monte_carlo")
    if not mc:
        return ""
    rows = "".join(
        _row([
            _td(esc(c["name"])), _num(c["U_linear_mm"], decimals + 1), _num(c["U_mc_mm"], decimals + 1),
            _td(esc("[" + ", ".join(fixed(v, decimals + 1, True) for v in c["interval_mm"]) + "]"), "num"),
            _td(esc(DASH if c["agreement"] is None else f"{c['agreement']:+.1%}"
                    + ("" if c.get("agreement_u") is None else f" ± {c['agreement_u']:.1%}")), "num"),
            _td("agrees" if c["agreed"] else "differs", "pass" if c["agreed"] else "fail"),
        ])
        for c in mc["characteristics"]
    )
    return (
        '<table id="monte-carlo" class="wide">'
        f"<caption>GUM Supplement 1 check: Monte Carlo ({esc(mc['n_draws'])} draws) beside the linear U (mm)</caption>"
        "<thead><tr><th>Characteristic</th><th>U linear</th><th>U Monte Carlo</th><th>" + esc(f"{mc.get('coverage', 0.95):.2%}") + " interval about the mean</th>"
        "<th>U<sub>MC</sub> / U &#8722; 1</th><th>Within " + esc(f"{mc['tolerance']:.0%}") + "</th></tr></thead>"
        f"<tbody>{rows}</tbody>"
        f'<tfoot><tr><td colspan="6">{esc(mc["method"])}.</td></tr></tfoot></table>'
    )


def _residual_table(reg: Mapping[str, Any] | None, decimals: int) -> str:
    if reg is None:
        return "<p>No registration.</p>"
    rows = [
        _row(
            [
                _td(esc(cp["id"])),
                *(_num(v, decimals, signed=True) for v in cp["residual_mm"]),
                _num(cp["residual_norm_mm"], decimals),
                _num(cp["rms_norm_mm"], decimals),
                _num(cp["max_norm_mm"], decimals),
                _num(cp.get("expected_rms_mm"), decimals),
                _td(esc(cp["n_frames"]), "num"),
            ]
        )
        for cp in reg["control_points"]
    ]
    return (
        '<table id="residuals" class="wide">'
        "<caption>Per common control point: residual R p + t &#8722; q of the registration (mm)</caption>"
        "<thead><tr><th>Control</th><th>dx</th><th>dy</th><th>dz</th><th>|mean|</th>"
        "<th>RMS |r|</th><th>max |r|</th><th>expected RMS |r|</th><th>Frames</th></tr></thead>"
        f"<tbody>{''.join(rows)}</tbody>"
        '<tfoot><tr><td colspan="9">dx, dy, dz: mean over frames of each frame\'s own fit residual, '
        "global frame; RMS |r| and max |r| over frames; expected RMS |r|: what the stated camera and CMM "
        "sigmas predict, sqrt((1 - 2/n) tr S).</td></tr></tfoot></table>"
    )


def _frames_table(report: Mapping[str, Any], decimals: int) -> str:
    rows = [
        _row(
            [
                _td(esc(f["sequence"]), "num"),
                _td(esc(f["n_camera_points"] if f["n_camera_points"] is not None else DASH), "num"),
                _td(esc(f["n_controls"] if f["n_controls"] is not None else DASH), "num"),
                _num(f["registration_rms_mm"], decimals),
                _td(esc(", ".join(f["missing_targets"]) or DASH)),
                _td(f'<span class="fail-text">failed:</span> {esc(f["error"])}')
                if f["error"]
                else _td('<span class="ok">ok</span>'),
            ]
        )
        for f in report["frames"]
    ]
    note = report.get("frames_note")
    note_html = f'<p class="note" id="frames-note">{esc(note[0].upper() + note[1:])}.</p>' if note else ""
    return (
        f"{note_html}"
        '<table id="frames" class="wide">'
        "<thead><tr><th>Frame</th><th>Camera points</th><th>Controls used</th>"
        "<th>Registration RMS (mm)</th><th>Targets not found</th><th>Status</th></tr></thead>"
        f"<tbody>{''.join(rows)}</tbody></table>"
    )


def _dl(pairs: list[tuple[str, str]]) -> str:
    """A fact list; keys and values must already be escaped."""
    return '<dl class="facts">' + "".join(f"<dt>{k}</dt><dd>{v}</dd>" for k, v in pairs) + "</dl>"


def _provenance(report: Mapping[str, Any]) -> str:
    plugin_rows = "".join(
        _row(
            [
                _td(esc(stage)),
                _td(f"<code>{esc(p.get('name'))}</code>"),
                _td(esc(p.get("plugin"))),
                _td(esc(p.get("package"))),
                _td(esc(p.get("version"))),
            ]
        )
        for stage, p in report["plugins"].items()
    )
    package_rows = "".join(
        _row([_td(esc(name)), _td(esc(version))]) for name, version in sorted(report["packages"].items())
    )
    plan = report["plan"]
    parent = report["session"]["parent"]
    facts = _dl(
        [
            ("Session", esc(report["session"]["id"])),
            ("Started (UTC)", esc(report["session"]["start_time_utc"] or DASH)),
            ("Plan", esc(plan["name"])),
            ("Plan file", esc(plan["source"] or DASH)),
            ("Plan SHA-256", f"<code>{esc(plan['sha256'])}</code>"),
            ("Calibration", esc(report["calibration"]["source"] or DASH)),
            ("CMM reference", esc(report["reference"]["source"] or DASH)),
            ("Config file", esc(report["config_source"])),
            ("Output folder", esc(report["session"]["out_dir"])),
            ("Replay of", esc(json.dumps(parent) if parent else DASH)),
        ]
    )
    return (
        f"{facts}"
        '<table id="plugins"><caption>Plugins</caption>'
        "<thead><tr><th>Stage</th><th>Implementation</th><th>Plugin</th><th>Package</th><th>Version</th>"
        f"</tr></thead><tbody>{plugin_rows}</tbody></table>"
        '<table id="packages"><caption>Packages</caption>'
        f"<thead><tr><th>Package</th><th>Version</th></tr></thead><tbody>{package_rows}</tbody></table>"
        "<h3>Resolved config</h3>"
        f"<pre>{esc(json.dumps(report['config'], indent=2, ensure_ascii=False))}</pre>"
        "<h3>Acquisition</h3>"
        f"<pre>{esc(json.dumps(report['acquisition'], indent=2, ensure_ascii=False))}</pre>"
    )


def render_html(
    report: Mapping[str, Any],
    decimals: int = 4,
    *,
    figures: Mapping[str, str] | None = None,
    templates: str | Path | None = None,
    cameras: Sequence[Mapping[str, Any]] = (),
) -> str:
    """report.html for a :func:`crossfield.report.document.build_report` result.

    figures: name -> inline SVG (:func:`report_figures`; none drawn when None).
    cameras: the camera thumbnails (:func:`camera_figures`), the "Cameras" section.
    templates: a folder whose ``report.html.j2`` / ``report.css`` replace crossfield's
    (Jinja2; ``docs/report.md``, "Templates")."""
    reg = report["registration"]
    n_frames, n_failed = report["frames_processed"], report["frames_failed"]
    summary_facts = [
        ("Frames processed", esc(f"{n_frames} ({n_failed} failed)")),
        ("Frames registered", esc(reg["n_frames"] if reg else 0)),
        ("Registration RMS", esc(f"{fixed(reg['rms_mm'], decimals)} mm" if reg else DASH)),
        ("Control points", esc(len(reg["control_points"]) if reg else 0)),
        ("Characteristics", esc(f"{sum(c['passed'] for c in report['characteristics'])} of "
                                f"{len(report['characteristics'])} accepted ({rule_text(report['uncertainty']['decision_rule'])})")),
        ("CMM points", esc(report["reference"]["n_points"])),
    ]
    if report["rms_error_mm"] is not None:
        rms_error = fixed(report["rms_error_mm"], decimals)
        summary_facts.append(("RMS error vs ground truth", esc(f"{rms_error} mm")))
    if reg and reg["ground_truth"]:
        gt = reg["ground_truth"]
        angle_urad = gt["rotation_error_rad"] * 1e6
        shift = fixed(gt["translation_error_norm_mm"], decimals)
        summary_facts.append(("Pose error vs ground truth", esc(f"{angle_urad:.1f} \u00b5rad, {shift} mm")))
    if report["incomplete"]:
        reason = esc(report["incomplete_reason"])
        summary_facts.append(("Session", f'<span class="fail-text">INCOMPLETE: {reason}</span>'))
    if report.get("station_moved"):
        moved = esc(report["station_moved"])
        summary_facts.append(("Station", f'<span class="fail-text">MOVED: {moved}</span>'))

    problems = report["problems"]
    problem_html = (
        '<ul class="problems">' + "".join(f"<li>{esc(p)}</li>" for p in problems) + "</ul>"
        if problems
        else '<p class="ok">None.</p>'
    )
    rms_line = ""
    if report["rms_error_mm"] is not None:
        n_truth = sum("error_mm" in c for c in report["characteristics"])
        rms_line = (
            f'<p id="rms-error"><strong>RMS error</strong> (Measured &#8722; Actual over {n_truth} '
            f"characteristic{'s' if n_truth != 1 else ''}): "
            f"<strong>{esc(fixed(report['rms_error_mm'], decimals))} mm</strong></p>"
        )
    header = session_header(report)
    title = f"Cross-field measurement report {DASH} {report['plan']['name']}"
    context = {
        "report": report,
        "title": title,
        "decimals": decimals,
        "header": header,
        "verdict_class": header.verdict_class,
        "verdict_text": header.verdict,
        "summary_facts": Markup(_dl(summary_facts)),
        "table1": Markup(_table1(reg, decimals)),
        "table2": Markup(_table2(reg, decimals)),
        "table3": Markup(_table3(report, decimals)),
        "rms_line": Markup(rms_line),
        "budget": Markup(_budget_table(report, decimals)),
        "consistency": Markup(_consistency_html(report)),
        "monte_carlo": Markup(_monte_carlo_html(report, decimals)),
        "residuals": Markup(_residual_table(reg, decimals)),
        "frames": Markup(_frames_table(report, decimals)),
        "problems": Markup(problem_html),
        "provenance": Markup(_provenance(report)),
        "figures": {
            name: Markup((figures or {}).get(name, ""))
            for name in ("deviations", "residuals", "trends", *(figures or {}))
        },
        "cameras": [
            {"camera": c["camera"], "figure": Markup(c["svg"]), "caption": c["caption"]} for c in cameras
        ],
    }
    return render_page("report.html.j2", context, templates)


def report_figures(report: Mapping[str, Any], positions: Mapping[str, Any] | None = None) -> dict[str, str]:
    """The report's inline SVG pictures (:mod:`crossfield.report.figures`)."""

    return {
        "deviations": deviation_chart(report),
        "residuals": residual_chart(report, positions or {}),
        "trends": trend_chart(report),
    }


#: Which pair a thumbnail shows, by its ``status`` (crossfield.report.thumbnails.STATUS_RANK).
_PAIR_TEXT = {
    "measured": "the session's first measured pair",
    "registered": "no pair was measured: the first registered one",
    "centroids": "no pair was registered: the first with centroids",
    "image": "no pair had centroids: the first pair",
}


def camera_figures(thumbnails: Sequence[Any]) -> list[dict[str, Any]]:
    """The "Cameras" section: per :class:`~crossfield.report.thumbnails.CameraThumbnail`
    (``summary.thumbnails``) its ``camera``, ``svg`` (:func:`crossfield.report.thumbnail_chart`)
    and ``caption`` (plain text)."""

    out = []
    for t in thumbnails:
        height, width = t.full_size
        n_control, n_target = t.kinds.count(KIND_CONTROL), t.kinds.count(KIND_TARGET)
        caption = (
            f"{t.camera.capitalize()} camera, frame {t.sequence} ({_PAIR_TEXT.get(t.status, t.status)}): "
            f"{width} x {height} px shown at 1:{t.factor}; {len(t.uv)} centroids, "
            f"{n_control} control point{'s' if n_control != 1 else ''} (blue) and "
            f"{n_target} measured target{'s' if n_target != 1 else ''} (orange) labelled"
        )
        out.append({"camera": t.camera, "svg": thumbnail_chart(t), "caption": caption})
    return out


# --------------------------------------------------------------------------
# Terminal summary
# --------------------------------------------------------------------------


def summary_text(summary: SessionSummary, decimals: int = 4) -> str:
    """A few lines for the terminal: frames, registration, Table 3, RMS error, verdict
    (:func:`crossfield.tables.report_text`, the text ``print(summary)`` shows)."""
    return report_text(document_of(summary), decimals)


# --------------------------------------------------------------------------
# The implementations
# --------------------------------------------------------------------------


class JsonReport:
    """report.json only: every number unrounded, for audits and scripts. It renders the
    session's report document (``summary.report``, built once at the session end)."""

    def __init__(self, *, decimals: int = 4):
        if isinstance(decimals, bool) or not isinstance(decimals, int) or not 0 <= decimals <= 12:
            raise ValueError(f"option 'decimals' must be an integer 0..12, got {decimals!r}")
        self.decimals = decimals

    def report_files(self, out_dir: Path) -> list[Path]:
        """The files :meth:`write` writes into ``out_dir`` (the recording lists
        them: it is closed before they are written)."""
        return [Path(out_dir) / REPORT_JSON]

    def write(self, summary: SessionSummary, out_dir: Path) -> list[Path]:
        """Write report.json into ``out_dir`` (created if missing)."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / REPORT_JSON
        _write_atomic(path, dumps(document_of(summary)))
        return [path]

    def summary_text(self, summary: SessionSummary) -> str:
        return report_text(document_of(summary), self.decimals)


class HtmlReport(JsonReport):
    """report.json plus a self-contained report.html: the paper's Tables 1-3, the
    uncertainty budget, decisions, pictures (inline SVG), job header, provenance.

    decimals: decimals shown in the HTML tables and the terminal summary
    (the paper prints 4); report.json is never rounded.
    templates: a folder with the lab's ``report.html.j2`` and/or ``report.css``
    (Jinja2), used in place of crossfield's (``docs/report.md``, "Templates");
    "" = crossfield's.
    figures: draw the pictures (matplotlib; default true), the camera thumbnails included.
    """

    def __init__(self, *, decimals: int = 4, templates: str = "", figures: bool = True):
        super().__init__(decimals=decimals)
        if not isinstance(templates, str):
            raise ValueError(f"option 'templates' must be a folder path (string), got {templates!r}")
        if templates and not Path(templates).is_dir():
            raise ValueError(f"option 'templates': {templates!r} is not a folder")
        if not isinstance(figures, bool):
            raise ValueError(f"option 'figures' must be true or false, got {figures!r}")
        self.templates = templates
        self.figures = figures

    def report_files(self, out_dir: Path) -> list[Path]:
        return [*super().report_files(out_dir), Path(out_dir) / "report.html"]

    def write(self, summary: SessionSummary, out_dir: Path) -> list[Path]:
        """Write report.json and report.html into ``out_dir`` (created if missing)."""
        (json_path,) = super().write(summary, out_dir)
        report = document_of(summary)
        html_path = Path(out_dir) / "report.html"
        positions = {p.label: tuple(float(v) for v in p.xyz) for p in summary.reference.points}
        figures = report_figures(report, positions) if self.figures else None
        cameras = camera_figures(summary.thumbnails) if self.figures else []
        page = render_html(report, self.decimals, figures=figures, templates=self.templates or None, cameras=cameras)
        _write_atomic(html_path, page)
        return [json_path, html_path]


@hookimpl
def register_reports(register) -> None:
    register("html", HtmlReport, "report.html (paper's Tables 1-3, residuals, provenance) + report.json")
    register("json", JsonReport, "report.json only (every number unrounded)")
