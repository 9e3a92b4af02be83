"""The calibration report: JSON (machine-readable) and HTML (with the coverage pictures).

Contents (``docs/calibration.md``, "Reading the report"): RMS reprojection
error per camera and stereo (px), per-view errors, dropped views with their
reasons, parameters with standard deviations, the coverage of each image by
board points, the epipolar error on held-out views (px), and the 3-D
uncertainty the calibration alone predicts in the working volume (mm),
for points and for lengths between them.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from crossfield.calibration.covariance import triangulation_sensitivity
from crossfield.calibration.coverage import COVERAGE_GRID, coverage_cells
from crossfield.calibration.quality import quality_dict, quality_html
from crossfield.calibration.solve import CalibrationResult
from crossfield.types import CAMERAS


def coverage_fraction(points: np.ndarray, image_size: tuple[int, int], grid: int = COVERAGE_GRID) -> float:
    """Fraction of the grid x grid image cells that hold at least one board point (points (N, 2) px)."""
    return float(np.mean(coverage_cells(points, image_size, grid) > 0))


def _used_points(result: CalibrationResult, camera: str) -> np.ndarray:
    views = result.cameras[camera].per_view_px
    pts = [result.detections[k][camera].image_points for k in views]
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def length_uncertainty(
    result: CalibrationResult, min_mm: float = 50.0, max_mm: float = 150.0
) -> dict[str, float]:
    """Predicted 1-sigma (mm) of lengths min_mm..max_mm between working-volume points, calibration only.

    sigma_L^2 = u^T (G_i - G_j) Sigma (G_i - G_j)^T u with u the unit vector
    from X_j to X_i (first order; :mod:`crossfield.calibration.covariance`).
    """
    c = result.calibration
    P = result.uncertainty_points
    if len(P) < 2:
        return {"pairs": 0}
    rvec = result.params[len(result.param_names) - 6 : len(result.param_names) - 3]
    G, _ = triangulation_sensitivity(
        P,
        np.asarray(c.upper.camera_matrix),
        np.asarray(c.upper.dist_coeffs),
        np.asarray(c.lower.camera_matrix),
        np.asarray(c.lower.dist_coeffs),
        rvec,
        np.asarray(c.t_lower_upper),
    )
    sig = []
    for i in range(len(P)):
        for j in range(i):
            d = P[i] - P[j]
            L = float(np.linalg.norm(d))
            if min_mm <= L <= max_mm:
                g = (d / L) @ (G[i] - G[j])
                sig.append(float(np.sqrt(g @ result.covariance @ g)))
    if not sig:
        return {"pairs": 0}
    return {
        "pairs": len(sig),
        "median_mm": float(np.median(sig)),
        "max_mm": float(np.max(sig)),
        "min_length_mm": min_mm,
        "max_length_mm": max_mm,
    }


def report_dict(result: CalibrationResult) -> dict[str, Any]:
    """The report as JSON-able data (see the module docstring)."""
    dropped_by_view: dict[int, list[str]] = {}
    for d in result.dropped:
        dropped_by_view.setdefault(d.view, []).append(f"{d.stage}: {d.reason}")
    views = []
    for k, name in enumerate(result.view_names):
        det = result.detections[k]
        status = (
            "held out" if k in result.held_out else "used" if k in result.per_view_stereo_px else "dropped"
        )
        views.append(
            {
                "index": k,
                "name": name,
                "status": status,
                "points": {cam: (0 if det[cam] is None else len(det[cam])) for cam in CAMERAS},
                "rms_px": {
                    **{cam: result.cameras[cam].per_view_px.get(k) for cam in CAMERAS},
                    "stereo": list(result.per_view_stereo_px[k]) if k in result.per_view_stereo_px else None,
                },
                "notes": dropped_by_view.get(k, []),
            }
        )
    cal = result.calibration
    sigma = result.uncertainty_sigma_mm
    return {
        "kind": "crossfield stereo calibration report",
        "board": result.board.to_dict(),
        "settings": {k: getattr(result.settings, k) for k in result.settings.__dataclass_fields__},
        "image_size": {cam: list(cal.camera(cam).image_size) for cam in CAMERAS},
        "rms_px": {
            "upper": result.cameras["upper"].rms_px,
            "lower": result.cameras["lower"].rms_px,
            "stereo": result.rms_stereo_px,
        },
        "sigma_px": result.sigma_px,
        "baseline_mm": result.baseline_mm,
        "baseline_std_mm": result.baseline_std_mm,
        "parameters": [
            {"name": n, "value": float(v), "std": float(s)}
            for n, v, s in zip(result.param_names, result.params, result.std)
        ],
        "per_camera_std": {cam: result.cameras[cam].std.tolist() for cam in CAMERAS},
        "views": views,
        "views_used": {
            "upper": len(result.cameras["upper"].per_view_px),
            "lower": len(result.cameras["lower"].per_view_px),
            "stereo": len(result.per_view_stereo_px),
        },
        "dropped": [
            {"view": d.view, "name": d.name, "stage": d.stage, "reason": d.reason} for d in result.dropped
        ],
        "held_out": [
            {"view": k, "name": result.view_names[k], "epipolar_rms_px": v[0], "epipolar_max_px": v[1]}
            for k, v in sorted(result.holdout_epipolar_px.items())
        ],
        "coverage": {
            cam: coverage_fraction(_used_points(result, cam), cal.camera(cam).image_size) for cam in CAMERAS
        },
        "uncertainty_3d": {
            "note": "1-sigma from the calibration parameters alone (pixels held fixed), upper camera frame",
            "points_mm": result.uncertainty_points.tolist(),
            "sigma_mm": sigma.tolist(),
            "median_sigma_mm": np.median(sigma, axis=0).tolist() if len(sigma) else [],
            "max_sigma_mm": sigma.max(axis=0).tolist() if len(sigma) else [],
            "length": length_uncertainty(result),
        },
        "quality": quality_dict(result),
    }


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def coverage_figures(result: CalibrationResult) -> dict[str, str]:
    """Per camera a PNG (base64) of where the board points fell: views used by that camera's solution
    in blue, dropped or held-out views in red, over the coverage grid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = {}
    for cam in CAMERAS:
        w, h = result.calibration.camera(cam).image_size
        fig, ax = plt.subplots(figsize=(6, 6 * h / w))
        used = result.cameras[cam].per_view_px
        for k, det in enumerate(result.detections):
            d = det[cam]
            if d is None:
                continue
            colour = "tab:blue" if k in used else "tab:red"
            ax.plot(d.image_points[:, 0], d.image_points[:, 1], ".", ms=3, color=colour)
        for g in range(1, COVERAGE_GRID):
            ax.axvline(g * w / COVERAGE_GRID, color="0.85", lw=0.5)
            ax.axhline(g * h / COVERAGE_GRID, color="0.85", lw=0.5)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        frac = coverage_fraction(_used_points(result, cam), (w, h))
        ax.set_title(
            f"{cam}: board points (blue used; red dropped or held out), {frac:.0%} of cells covered",
            fontsize=9,
        )
        out[cam] = _png(fig)
        plt.close(fig)
    return out


def _fmt(x: Any) -> str:
    """A px value (or list of them) with 3 decimals; empty for None."""
    if x is None:
        return ""
    return f"{x:.3f}" if isinstance(x, float) else ", ".join(f"{v:.3f}" for v in x)


def _setting(value: Any) -> str:
    """A board or solver setting as table text (no Python or JSON reprs)."""
    if value is None:
        return "\u2014"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_setting(v) for v in value)
    return str(value)


def calibration_header(
    data: dict[str, Any],
    *,
    calibration_path: str | None = None,
    calibration_sha256: str | None = None,
    seal: Any = None,
) -> Any:
    """The record header of the calibration report (:mod:`crossfield.report.header`):
    date, software, the recording's seal (``crossfield calibrate --record``), the calibration
    file written and its SHA-256, the instruments (the two cameras, the board)."""
    from crossfield.chain.provenance import crossfield_version
    from crossfield.report.header import Fact, RecordHeader, now_utc, seal_facts

    rms = data["rms_px"]
    board = data["board"]
    size = data["image_size"]
    facts = [
        Fact("Date (UTC)", now_utc(), "record-date"),
        Fact("Software", f"crossfield {crossfield_version()}", "record-software"),
        *seal_facts(None if seal is None else seal.to_json(), "not recorded (crossfield calibrate --record FILE)"),
        Fact("Calibration", calibration_path or "\u2014", "record-calibration", True),
        Fact("Calibration SHA-256", calibration_sha256 or "not recorded", "record-calibration-sha256", True),
        Fact("Distortion model", str(data["settings"]["distortion"]), "record-distortion"),
    ]
    instruments = (
        *((f"{cam} camera", f"{size[cam][0]} x {size[cam][1]} px", "\u2014", "\u2014") for cam in CAMERAS),
        (f"board ({board.get('type', '')})", board.get("source") or "stated in the command", "\u2014", "\u2014"),
    )
    return RecordHeader(
        title="Stereo calibration report",
        subtitle=f"RMS reprojection error {rms['stereo']:.4f} px (stereo) \u00b7 baseline {data['baseline_mm']:.3f} mm",
        verdict=f"{data['views_used']['stereo']} views used",
        verdict_class="open",
        facts=tuple(facts),
        instruments=instruments,
    )


def report_html(
    result: CalibrationResult,
    data: dict[str, Any] | None = None,
    *,
    calibration_path: str | None = None,
    calibration_sha256: str | None = None,
    seal: Any = None,
) -> str:
    """A self-contained HTML page of the report (``calibration.html.j2``, images inline)."""
    from markupsafe import Markup

    from crossfield.report.pages import render_page

    data = report_dict(result) if data is None else data
    figs = coverage_figures(result)
    u3 = data["uncertainty_3d"]
    length = u3["length"]
    length_text = (
        f"lengths {length['min_length_mm']:.0f}-{length['max_length_mm']:.0f} mm: median "
        f"{length['median_mm'] * 1000:.1f} um, max {length['max_mm'] * 1000:.1f} um ({length['pairs']} pairs)"
        if length.get("pairs")
        else "no point pairs"
    )
    context = {
        "title": "crossfield calibration report",
        "header": calibration_header(data, calibration_path=calibration_path,
                                     calibration_sha256=calibration_sha256, seal=seal),
        "data": data,
        "board": [(k.replace("_", " "), _setting(v)) for k, v in data["board"].items() if v is not None],
        "settings": [(k.replace("_", " "), _setting(v)) for k, v in data["settings"].items()],
        "parameters": [(p["name"], f"{p['value']:.6g}", f"{p['std']:.3g}") for p in data["parameters"]],
        "views": [
            (v["index"], v["name"], v["status"], v["points"]["upper"], v["points"]["lower"],
             _fmt(v["rms_px"]["upper"]), _fmt(v["rms_px"]["lower"]), _fmt(v["rms_px"]["stereo"]),
             "; ".join(v["notes"]))
            for v in data["views"]
        ],
        "held_out": [(h["name"], f"{h['epipolar_rms_px']:.3f}", f"{h['epipolar_max_px']:.3f}") for h in data["held_out"]],
        "grid": COVERAGE_GRID,
        "coverage": [(c, Markup(f'<img src="data:image/png;base64,{figs[c]}" alt="coverage {c}">')) for c in CAMERAS],
        "median_um": ", ".join(f"{v * 1000:.1f}" for v in u3["median_sigma_mm"]),
        "max_um": ", ".join(f"{v * 1000:.1f}" for v in u3["max_sigma_mm"]),
        "length_text": length_text,
        "quality": Markup(quality_html(result, data)),
    }
    return render_page("calibration.html.j2", context)


def write_report(
    result: CalibrationResult,
    stem: str | Path,
    *,
    calibration_path: str | Path | None = None,
    seal: Any = None,
) -> tuple[Path, Path]:
    """Write ``<stem>.json`` and ``<stem>.html``; returns both paths. calibration_path: the
    calibration file written (its SHA-256 goes into the header); seal: the recording's
    (``crossfield calibrate --record``), None when not recorded."""
    stem = Path(stem)
    data = report_dict(result)
    json_path = stem.with_suffix(".json")
    html_path = stem.with_suffix(".html")
    json_path.write_text(json.dumps(data, indent=2, allow_nan=False), encoding="utf-8")
    digest = hashlib.sha256(Path(calibration_path).read_bytes()).hexdigest() if calibration_path else None
    page = report_html(result, data, calibration_path=None if calibration_path is None else str(calibration_path),
                       calibration_sha256=digest, seal=seal)
    html_path.write_text(page, encoding="utf-8")
    return json_path, html_path
