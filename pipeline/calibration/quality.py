"""The report's quality sections: the two standard deviations, the board's bow, residual maps, cross-validation.

``quality_dict`` is the JSON part (``report_dict`` merges it), ``quality_html``
the HTML part with its pictures (matplotlib, PNG inline): per camera the
binned residual vectors over the image (arrows scaled so that the largest
bin mean is 1/20 of the image width), and the cross-validation's projection
difference over each image (arrows) with the ratio to its predicted 1-sigma
(colour). How to read them: ``docs/calibration.md``.
"""

from __future__ import annotations

import base64
import html
import io
from typing import Any

import numpy as np

from crossfield.types import CAMERAS


def _num(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def quality_dict(result) -> dict[str, Any]:
    """std (stated), std_jacobian, std_jackknife per parameter; the bow; residual maps; cross-validation."""
    names = result.param_names
    jac = result.std_jacobian if result.std_jacobian is not None else np.full(len(names), np.nan)
    jk = result.std_jackknife if result.std_jackknife is not None else np.full(len(names), np.nan)
    out: dict[str, Any] = {
        "std_sources": {
            "note": "stated std = max(Jacobian, jackknife over views); None: not computed",
            "parameters": [
                {"name": n, "std": float(s), "std_jacobian": _num(a), "std_jackknife": _num(b)}
                for n, s, a, b in zip(names, result.std, jac, jk)
            ],
        },
        "board_warp": None,
        "residual_maps": {cam: m.as_dict() for cam, m in result.residual_maps.items()},
        "cross_validation": None if result.cross_validation is None else result.cross_validation.as_dict(),
    }
    if result.warp_mm is not None and np.all(np.isfinite(result.warp_mm)):
        out["board_warp"] = {
            "note": "bow of the board, mrcal's calobject_warp form: z = wx (1 - xn^2) + wy (1 - yn^2)",
            "warp_mm": [float(v) for v in result.warp_mm],
            "std_mm": [_num(v) for v in result.warp_std_mm],
        }
    return out


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def residual_figures(result) -> dict[str, str]:
    """Per camera a PNG (base64) of the binned mean residual vectors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = {}
    for cam, m in result.residual_maps.items():
        w, h = m.image_size
        ok = m.count >= 3
        fig, ax = plt.subplots(figsize=(6, 6 * h / w))
        longest = np.nanmax(np.linalg.norm(m.mean_px[ok], axis=1)) if ok.any() else 1.0
        scale = longest / (w / 20) if longest > 0 else 1.0
        ax.quiver(
            m.centres_px[ok][:, 0],
            m.centres_px[ok][:, 1],
            m.mean_px[ok][:, 0],
            m.mean_px[ok][:, 1],
            angles="xy",
            scale_units="xy",
            scale=scale,
            color="tab:purple",
        )
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_title(
            f"{cam}: mean residual per bin, longest {longest:.3f} px; amplitude {m.amplitude_px:.3f} px "
            f"(noise alone {m.noise_amplitude_px:.3f} px)",
            fontsize=8,
        )
        out[cam] = _png(fig)
        plt.close(fig)
    return out


def cross_validation_figure(cv) -> str:
    """PNG (base64): per camera the projection difference (arrows) coloured by |diff| / sigma."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    for ax, cam in zip(axes, CAMERAS):
        g, d = cv.grid_px[cam], cv.diff_px[cam]
        ratio = cv.projection_ratio(cam)
        longest = float(np.max(np.linalg.norm(d, axis=1)))
        w = g[:, 0].max() - g[:, 0].min()
        scale = longest / (w / 12) if longest > 0 else 1.0
        q = ax.quiver(
            g[:, 0],
            g[:, 1],
            d[:, 0],
            d[:, 1],
            ratio,
            angles="xy",
            scale_units="xy",
            scale=scale,
            cmap="RdYlGn_r",
            clim=(0, 3),
        )
        ax.invert_yaxis()
        ax.set_aspect("equal")
        ax.set_title(
            f"{cam}: half A vs half B at {cv.depth_mm:.0f} mm, longest {longest:.3f} px, "
            f"max {ratio.max():.2f} sigma",
            fontsize=8,
        )
        fig.colorbar(q, ax=ax, label="|difference| / predicted sigma")
    out = _png(fig)
    plt.close(fig)
    return out


def quality_html(result, data: dict[str, Any]) -> str:
    """The HTML sections (residual maps, bow, std sources, cross-validation)."""
    e = html.escape
    q = data["quality"]
    parts = ["<h2>Residual maps</h2>"]
    if result.residual_maps:
        figs = residual_figures(result)
        parts.append(
            "".join(
                f'<figure><img src="data:image/png;base64,{figs[c]}" alt="residuals {c}"></figure>'
                for c in figs
            )
        )
        parts.append(
            "<p>A good calibration's map is noise (amplitude near the 'noise alone' figure); a "
            "pattern (a swirl, arrows pointing out at the corners) is what the model does not fit.</p>"
        )
    else:
        parts.append("<p>not computed (joint refinement off)</p>")
    bow = q["board_warp"]
    parts.append("<h2>Board flatness</h2>")
    if bow:
        parts.append(
            f"<p>Bow wx {bow['warp_mm'][0] * 1000:.1f} um, wy {bow['warp_mm'][1] * 1000:.1f} um "
            f"(1 sigma {', '.join('-' if s is None else f'{s * 1000:.1f}' for s in bow['std_mm'])} um).</p>"
        )
    else:
        parts.append("<p>not estimated (too few views, or estimate_warp = false)</p>")
    rows = "".join(
        f"<tr><td>{e(p['name'])}</td><td>{p['std']:.3g}</td>"
        f"<td>{'-' if p['std_jacobian'] is None else format(p['std_jacobian'], '.3g')}</td>"
        f"<td>{'-' if p['std_jackknife'] is None else format(p['std_jackknife'], '.3g')}</td></tr>"
        for p in q["std_sources"]["parameters"]
    )
    parts.append(
        "<h2>Standard deviations: Jacobian and jackknife</h2><table><tr><th>name</th><th>stated</th>"
        f"<th>Jacobian</th><th>jackknife</th></tr>{rows}</table>"
    )
    cv = result.cross_validation
    parts.append("<h2>Cross-validation</h2>")
    if cv is None:
        parts.append("<p>not run (crossfield calibrate --cross-validate)</p>")
    else:
        within = cv.within(2.0)
        d = q["cross_validation"]
        parts.append(
            f'<figure><img src="data:image/png;base64,{cross_validation_figure(cv)}" alt="cross-validation"></figure>'
        )
        parts.append(
            f"<p>Halves of {len(cv.halves[0])} and {len(cv.halves[1])} views. Within 2 predicted sigma: upper "
            f"{within['upper']:.0%}, lower {within['lower']:.0%} of the image; 3-D points at {cv.depth_mm:.0f} mm "
            f"{within['points']:.0%} (max difference {d['points']['max_diff_mm'] * 1000:.1f} um, "
            f"{d['points']['max_ratio']:.2f} sigma).</p>"
        )
    return "".join(parts)
