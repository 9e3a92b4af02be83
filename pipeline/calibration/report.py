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
import html
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


def report_html(result: CalibrationResult, data: dict[str, Any] | None = None) -> str:
    """A self-contained HTML page of the report (images inline)."""
    data = report_dict(result) if data is None else data
    e = html.escape
    figs = coverage_figures(result)
    rms = data["rms_px"]
    rows = "".join(
        f"<tr><td>{e(p['name'])}</td><td>{p['value']:.6g}</td><td>{p['std']:.3g}</td></tr>"
        for p in data["parameters"]
    )

    def fmt(x):
        return "" if x is None else (f"{x:.3f}" if isinstance(x, float) else ", ".join(f"{v:.3f}" for v in x))

    views = "".join(
        f"<tr><td>{v['index']}</td><td>{e(v['name'])}</td><td>{e(v['status'])}</td>"
        f"<td>{v['points']['upper']}</td><td>{v['points']['lower']}</td>"
        f"<td>{fmt(v['rms_px']['upper'])}</td><td>{fmt(v['rms_px']['lower'])}</td><td>{fmt(v['rms_px']['stereo'])}</td>"
        f"<td>{e('; '.join(v['notes']))}</td></tr>"
        for v in data["views"]
    )
    dropped = (
        "".join(f"<li>{e(d['name'])} ({e(d['stage'])}): {e(d['reason'])}</li>" for d in data["dropped"])
        or "<li>none</li>"
    )
    held = (
        "".join(
            f"<li>{e(h['name'])}: epipolar RMS {h['epipolar_rms_px']:.3f} px, max {h['epipolar_max_px']:.3f} px</li>"
            for h in data["held_out"]
        )
        or "<li>none held out</li>"
    )
    u3 = data["uncertainty_3d"]
    length = u3["length"]
    length_text = (
        f"lengths {length['min_length_mm']:.0f}-{length['max_length_mm']:.0f} mm: median "
        f"{length['median_mm'] * 1000:.1f} um, max {length['max_mm'] * 1000:.1f} um ({length['pairs']} pairs)"
        if length.get("pairs")
        else "no point pairs"
    )
    med = ", ".join(f"{v * 1000:.1f}" for v in u3["median_sigma_mm"])
    mx = ", ".join(f"{v * 1000:.1f}" for v in u3["max_sigma_mm"])
    images = "".join(
        f'<figure><img src="data:image/png;base64,{figs[c]}" alt="coverage {c}"></figure>' for c in CAMERAS
    )
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>crossfield calibration report</title>
<style>body{{font-family:sans-serif;max-width:70em;margin:auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}figure{{display:inline-block;margin:4px}}</style></head>
<body><h1>Stereo calibration report</h1>
<p>Board: {e(json.dumps(data["board"]))}. Distortion model: {e(data["settings"]["distortion"])}.</p>
<h2>Reprojection error</h2>
<p>RMS upper {rms["upper"]:.4f} px, lower {rms["lower"]:.4f} px, stereo {rms["stereo"]:.4f} px;
corner noise estimated from the residuals {data["sigma_px"]:.4f} px.
Views used: upper {data["views_used"]["upper"]}, lower {data["views_used"]["lower"]}, stereo {data["views_used"]["stereo"]}.</p>
<p>Baseline |T| = {data["baseline_mm"]:.4f} mm &plusmn; {data["baseline_std_mm"] * 1000:.1f} um (1 sigma).</p>
<h2>Coverage</h2>{images}
<p>Coverage (cells of an {COVERAGE_GRID}x{COVERAGE_GRID} grid holding a point): upper {data["coverage"]["upper"]:.0%},
lower {data["coverage"]["lower"]:.0%}.</p>
<h2>Dropped views</h2><ul>{dropped}</ul>
<h2>Held-out views (epipolar error)</h2><ul>{held}</ul>
<h2>Predicted 3-D uncertainty (calibration only, 1 sigma)</h2>
<p>Points in the working volume (x, y, z): median {med} um, max {mx} um. {e(length_text)}.
A common shift of every point (from the principal points) cancels in the registration; lengths do not.</p>
{quality_html(result, data)}
<h2>Parameters</h2><table><tr><th>name</th><th>value</th><th>std</th></tr>{rows}</table>
<h2>Views</h2><table><tr><th>#</th><th>name</th><th>status</th><th>pts upper</th><th>pts lower</th>
<th>RMS upper</th><th>RMS lower</th><th>RMS stereo</th><th>notes</th></tr>{views}</table>
</body></html>
"""


def write_report(result: CalibrationResult, stem: str | Path) -> tuple[Path, Path]:
    """Write ``<stem>.json`` and ``<stem>.html``; returns both paths."""
    stem = Path(stem)
    data = report_dict(result)
    json_path = stem.with_suffix(".json")
    html_path = stem.with_suffix(".html")
    json_path.write_text(json.dumps(data, indent=2, allow_nan=False), encoding="utf-8")
    html_path.write_text(report_html(result, data), encoding="utf-8")
    return json_path, html_path
