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
from typing import Any, Iterable, Mapping

from crossfield.hookspecs import hookimpl
from crossfield.session import SessionSummary

from crossfield.report import document as doc

KIND_LABELS = {
    "point_point": "point to point",
    "point_line": "point to line",
    "depth": "depth (global Z)",
}

DASH = "\u2014"


# --------------------------------------------------------------------------
# Formatting
# --------------------------------------------------------------------------


def esc(value: Any) -> str:
    """``value`` as text, escaped for HTML text and attribute values."""
    return html.escape("" if value is None else str(value), quote=True)


def fixed(value: float | None, decimals: int, signed: bool = False) -> str:
    """``value`` with ``decimals`` decimals (``+`` sign if ``signed``); a dash when unknown."""
    if value is None:
        return DASH
    return f"{value:+.{decimals}f}" if signed else f"{value:.{decimals}f}"


def verdict(passed: bool) -> str:
    return "PASS" if passed else "FAIL"


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

CSS = """
:root { --ink:#1d2733; --muted:#5b6b7b; --rule:#c9d2dc; --band:#f3f6f9; --pass:#1b7a3a; --pass-bg:#e3f4e8;
        --fail:#b3261e; --fail-bg:#fbe5e3; --accent:#234e77; }
* { box-sizing: border-box; }
body { margin: 0; color: var(--ink); background: #fff;
       font: 14px/1.45 "Segoe UI", "Helvetica Neue", Helvetica, Arial, sans-serif; }
main { max-width: 1120px; margin: 0 auto; padding: 28px 32px 48px; }
header.report { border-bottom: 3px solid var(--accent); padding-bottom: 14px; margin-bottom: 18px;
                display: flex; justify-content: space-between; align-items: flex-start; gap: 24px; }
h1 { font-size: 22px; margin: 0 0 4px; letter-spacing: .01em; }
h2 { font-size: 16px; margin: 30px 0 8px; color: var(--accent); border-bottom: 1px solid var(--rule);
     padding-bottom: 4px; }
.subtitle { color: var(--muted); margin: 0; }
.verdict { font-weight: 700; font-size: 20px; padding: 8px 18px; border-radius: 6px; border: 2px solid;
           white-space: nowrap; }
.verdict.pass, td.pass { color: var(--pass); background: var(--pass-bg); border-color: var(--pass); }
.verdict.fail, td.fail { color: var(--fail); background: var(--fail-bg); border-color: var(--fail); }
td.pass, td.fail { font-weight: 700; text-align: center; white-space: nowrap; }
.fail-text { color: var(--fail); font-weight: 700; }
dl.facts { display: grid; grid-template-columns: max-content 1fr max-content 1fr; gap: 4px 18px; margin: 0; }
dl.facts dt { color: var(--muted); }
dl.facts dd { margin: 0; font-variant-numeric: tabular-nums; }
table { border-collapse: collapse; margin: 6px 0 4px; font-variant-numeric: tabular-nums; }
caption { caption-side: top; text-align: left; font-weight: 600; padding: 0 0 6px; }
th, td { padding: 4px 10px; border-bottom: 1px solid var(--rule); vertical-align: top; }
thead th { background: var(--band); border-top: 2px solid var(--ink); border-bottom: 1px solid var(--ink);
           font-weight: 600; text-align: center; }
tbody tr:last-child td, tbody tr:last-child th { border-bottom: 2px solid var(--ink); }
td.num, th.num { text-align: right; font-family: "DejaVu Sans Mono", Consolas, Menlo, monospace; }
table.matrix td { min-width: 90px; }
#table1-rotation tbody tr:first-child td { border-top: 2px solid var(--ink); }
thead th { white-space: nowrap; }
table.wide th, table.wide td { padding: 4px 7px; }
table.wide { width: 100%; }
tfoot td { border: none; color: var(--muted); font-size: 12.5px; }
.note { color: var(--muted); font-size: 12.5px; margin: 4px 0 0; }
ul.problems li { margin: 2px 0; }
.ok { color: var(--pass); }
pre { background: var(--band); border: 1px solid var(--rule); padding: 10px; overflow-x: auto;
      font-size: 12px; }
code { font-family: "DejaVu Sans Mono", Consolas, Menlo, monospace; font-size: 12.5px; }
footer { margin-top: 36px; color: var(--muted); font-size: 12px; border-top: 1px solid var(--rule);
         padding-top: 8px; }
@media print { main { padding: 0; } h2 { break-after: avoid; } table { break-inside: avoid; } }
"""


def _row(cells: Iterable[str]) -> str:
    return "<tr>" + "".join(cells) + "</tr>"


def _td(text: str, cls: str = "") -> str:
    """A cell; ``text`` must already be escaped."""
    return f'<td class="{cls}">{text}</td>' if cls else f"<td>{text}</td>"


def _num(value: float | None, decimals: int, signed: bool = False) -> str:
    return _td(esc(fixed(value, decimals, signed)), "num")


def _result_cell(passed: bool) -> str:
    return _td("&#10003; PASS" if passed else "&#10007; FAIL", "pass" if passed else "fail")


def _table1(reg: Mapping[str, Any] | None, decimals: int) -> str:
    if reg is None:
        return '<p id="table1-rotation">No frame was registered: no rotation matrix.</p>'
    rows = "".join(_row(_num(v, decimals) for v in row) for row in reg["R_global_camera"])
    return (
        '<table id="table1-rotation" class="matrix">'
        "<caption>Table 1. Rotation matrix R<sub>global&#8592;camera</sub></caption>"
        f"<tbody>{rows}</tbody>"
        f'<tfoot><tr><td colspan="3">det R = {esc(fixed(reg["det_R"], 6))}; '
        f"{esc(_aggregate_note(reg))}</td></tr></tfoot></table>"
    )


def _aggregate_note(reg: Mapping[str, Any]) -> str:
    n = reg["n_frames"]
    return f"session mean over {n} registered frame{'s' if n != 1 else ''}"


def _table2(reg: Mapping[str, Any] | None, decimals: int) -> str:
    if reg is None:
        return '<p id="table2-translation">No frame was registered: no translation vector.</p>'
    rows = "".join(
        _row([f"<th>{axis}</th>", _num(v, decimals), _num(s, decimals)])
        for axis, v, s in zip("xyz", reg["t_global_camera_mm"], reg["t_std_mm"])
    )
    return (
        '<table id="table2-translation" class="matrix">'
        "<caption>Table 2. Translation vector t<sub>global&#8592;camera</sub> (mm)</caption>"
        '<thead><tr><th></th><th>t (mm)</th><th>std over frames (mm)</th></tr></thead>'
        f"<tbody>{rows}</tbody>"
        f'<tfoot><tr><td colspan="3">p<sub>global</sub> = R p<sub>camera</sub> + t; '
        f"{esc(_aggregate_note(reg))}</td></tr></tfoot></table>"
    )


def _table3(report: Mapping[str, Any], decimals: int) -> str:
    chars = report["characteristics"]
    truth = report["ground_truth_known"]
    head = ["No.", "Characteristic", "Elements", "Frames", "Measured", "Std", "u"]
    if truth:
        head += ["Actual", "Error"]
    head += ["Nominal", "Tol. &#177;", "Deviation", "Result"]
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
            _num(c["tolerance_mm"], decimals),
            _num(c["deviation_mm"], decimals, signed=True),
            _result_cell(c["passed"]),
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
                _td(esc(cp["n_frames"]), "num"),
            ]
        )
        for cp in reg["control_points"]
    ]
    return (
        '<table id="residuals" class="wide">'
        "<caption>Per common control point: residual R p + t &#8722; q of the registration (mm)</caption>"
        "<thead><tr><th>Control</th><th>dx</th><th>dy</th><th>dz</th><th>|mean|</th>"
        "<th>RMS |r|</th><th>max |r|</th><th>Frames</th></tr></thead>"
        f"<tbody>{''.join(rows)}</tbody>"
        '<tfoot><tr><td colspan="8">dx, dy, dz: mean over frames of each frame\'s own fit residual, '
        "global frame; RMS |r| and max |r| over frames.</td></tr></tfoot></table>"
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


def render_html(report: Mapping[str, Any], decimals: int = 4) -> str:
    """report.html for a :func:`crossfield.report.document.build_report` result."""
    reg = report["registration"]
    passed = report["passed"]
    n_frames, n_failed = report["frames_processed"], report["frames_failed"]
    summary_facts = [
        ("Frames processed", esc(f"{n_frames} ({n_failed} failed)")),
        ("Frames registered", esc(reg["n_frames"] if reg else 0)),
        ("Registration RMS", esc(f"{fixed(reg['rms_mm'], decimals)} mm" if reg else DASH)),
        ("Control points", esc(len(reg["control_points"]) if reg else 0)),
        ("Characteristics", esc(f"{sum(c['passed'] for c in report['characteristics'])} of "
                                f"{len(report['characteristics'])} in tolerance")),
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
    cls = "pass" if passed else "fail"
    title = f"Cross-field measurement report {DASH} {report['plan']['name']}"
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{esc(title)}</title>
<style>{CSS}</style>
</head>
<body>
<main>
<header class="report">
<div>
<h1>Cross-field measurement report</h1>
<p class="subtitle">Plan <strong>{esc(report["plan"]["name"])}</strong>
&middot; session <code>{esc(report["session"]["id"])}</code>
&middot; {esc(report["session"]["start_time_utc"] or "start time not recorded")}</p>
</div>
<div class="verdict {cls}" id="verdict">{"&#10003;" if passed else "&#10007;"} {verdict(passed)}</div>
</header>
<section>
{_dl(summary_facts)}
</section>
<section>
<h2>Registration: camera to global (CMM) frame</h2>
{_table1(reg, decimals)}
{_table2(reg, decimals)}
</section>
<section>
<h2>Cross-field characteristics</h2>
{_table3(report, decimals)}
{rms_line}
</section>
<section>
<h2>Registration residuals</h2>
{_residual_table(reg, decimals)}
</section>
<section>
<h2>Frames</h2>
{_frames_table(report, decimals)}
</section>
<section>
<h2>Problems</h2>
{problem_html}
</section>
<section>
<h2>Provenance</h2>
{_provenance(report)}
</section>
<footer>Written by crossfield. Lengths in mm, rotation unitless; tables rounded to {decimals} decimals,
report.json beside this file holds every number unrounded.</footer>
</main>
</body>
</html>
"""


# --------------------------------------------------------------------------
# Terminal summary
# --------------------------------------------------------------------------


def _printable(text: Any) -> str:
    """``text`` with control characters (ANSI escapes, newlines) made visible."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(text))


def summary_text(summary: SessionSummary, decimals: int = 4) -> str:
    """A few lines for the terminal: frames, registration, Table 3, RMS error, verdict."""
    report = doc.build_report(summary)
    return render_text(report, decimals)


def render_text(report: Mapping[str, Any], decimals: int = 4) -> str:
    reg = report["registration"]
    lines = [
        f"Session {_printable(report['session']['id'])}  plan {_printable(report['plan']['name'])}",
        f"Frames: {report['frames_processed']} processed, {report['frames_failed']} failed",
    ]
    if reg:
        lines.append(
            f"Registration: RMS {fixed(reg['rms_mm'], decimals)} mm over {len(reg['control_points'])} "
            f"control points (session mean of {reg['n_frames']} frames)"
        )
    else:
        lines.append("Registration: none")
    chars = report["characteristics"]
    width = max([len("Characteristic")] + [len(_printable(c["name"])) for c in chars])
    truth = report["ground_truth_known"]
    header = f"{'No.':>3}  {'Characteristic':<{width}}  {'Measured':>10}"
    if truth:
        header += f"  {'Actual':>10}  {'Error':>8}"
    header += f"  {'Nominal':>10}  {'Dev':>8}  Result"
    lines.append(header)
    for c in chars:
        line = f"{c['no']:>3}  {_printable(c['name']):<{width}}  {fixed(c['measured_mm'], decimals):>10}"
        if truth:
            actual, error = fixed(c.get("actual_mm"), decimals), fixed(c.get("error_mm"), decimals, True)
            line += f"  {actual:>10}  {error:>8}"
        line += f"  {fixed(c['nominal_mm'], decimals):>10}  {fixed(c['deviation_mm'], decimals, True):>8}"
        line += f"  {verdict(c['passed'])}"
        lines.append(line)
    if report["rms_error_mm"] is not None:
        lines.append(f"RMS error vs ground truth: {fixed(report['rms_error_mm'], decimals)} mm")
    for problem in report["problems"][:5]:
        lines.append(f"! {_printable(problem)}")
    if len(report["problems"]) > 5:
        lines.append(f"! ... and {len(report['problems']) - 5} more problems (see report.json)")
    incomplete = " (session incomplete)" if report["incomplete"] else ""
    lines.append(f"Result: {verdict(report['passed'])}{incomplete}")
    return "\n".join(lines)


# --------------------------------------------------------------------------
# The implementations
# --------------------------------------------------------------------------


class JsonReport:
    """report.json only: every number unrounded, for audits and scripts."""

    def __init__(self, *, decimals: int = 4):
        if isinstance(decimals, bool) or not isinstance(decimals, int) or not 0 <= decimals <= 12:
            raise ValueError(f"option 'decimals' must be an integer 0..12, got {decimals!r}")
        self.decimals = decimals

    def _write_json(self, report: Mapping[str, Any], out_dir: Path) -> Path:
        path = out_dir / "report.json"
        _write_atomic(path, doc.dumps(report))
        return path

    def report_files(self, out_dir: Path) -> list[Path]:
        """The files :meth:`write` writes into ``out_dir`` (the recording lists
        them: it is closed before they are written)."""
        return [Path(out_dir) / "report.json"]

    def write(self, summary: SessionSummary, out_dir: Path) -> list[Path]:
        """Write report.json into ``out_dir`` (created if missing)."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        return [self._write_json(doc.build_report(summary), out_dir)]

    def summary_text(self, summary: SessionSummary) -> str:
        return summary_text(summary, self.decimals)


class HtmlReport(JsonReport):
    """report.json plus a self-contained report.html with the paper's Tables 1-3.

    decimals: decimals shown in the HTML tables and the terminal summary
    (the paper prints 4); report.json is never rounded.
    """

    def report_files(self, out_dir: Path) -> list[Path]:
        return [*super().report_files(out_dir), Path(out_dir) / "report.html"]

    def write(self, summary: SessionSummary, out_dir: Path) -> list[Path]:
        """Write report.json and report.html into ``out_dir`` (created if missing)."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        report = doc.build_report(summary)
        json_path = self._write_json(report, out_dir)
        html_path = out_dir / "report.html"
        _write_atomic(html_path, render_html(report, self.decimals))
        return [json_path, html_path]


@hookimpl
def register_reports(register) -> None:
    register("html", HtmlReport, "report.html (paper's Tables 1-3, residuals, provenance) + report.json")
    register("json", JsonReport, "report.json only (every number unrounded)")
