"""The report's pictures as inline SVG (matplotlib, Agg, no files): the page stays one file.

Each function takes the report.json document (:func:`crossfield.report.document.build_report`)
and returns an ``<svg>`` element as text, or ``""`` when there is nothing to draw:

* :func:`deviation_chart`: each characteristic's deviation (mm) against its
  tolerance zone, with the expanded uncertainty U as error bars and, for a
  guarded rule, the acceptance zone;
* :func:`residual_chart`: the control points' registration residual vectors
  (global frame, mean over frames, drawn magnified) in the plane of the two
  largest spreads of the controls, with circles of the expected RMS;
* :func:`trend_chart`: per frame (the kept rows) the registration RMS and each
  characteristic's difference from its session mean;
* :func:`thumbnail_chart`: one camera's image (a
  :class:`~crossfield.report.thumbnails.CameraThumbnail`, not the report
  document) in grey with each centroid marked and labelled with its target id.

SVG text stays text (``svg.fonttype = none``), so the page remains searchable;
matplotlib's SVG carries no script. A raster image is embedded in the SVG as a
PNG data URI (``<image xlink:href="data:image/png;base64,...">``), at its own
resolution.
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from crossfield.report.thumbnails import KIND_CONTROL, KIND_TARGET

__all__ = [
    "LABEL_OFFSET", "RESIDUAL_ARROW_FRACTION", "THUMBNAIL_GID", "deviation_chart", "residual_chart", "residual_gain", "svg",
    "thumbnail_chart", "trend_chart",
]

#: SVG group ids of a thumbnail's parts (:func:`thumbnail_chart`), formatted
#: with the camera name and a centroid's label: the image; the markers of the
#: control points, of the measured targets and of the unidentified centroids
#: (one ``<use>`` each, in centroid order); each label's ``<text>``.
THUMBNAIL_GID = {
    "image": "thumbnail-{camera}-image",
    KIND_CONTROL: "thumbnail-{camera}-controls",
    KIND_TARGET: "thumbnail-{camera}-targets",
    "": "thumbnail-{camera}-unlabelled",
    "label": "thumbnail-{camera}-label-{label}",
}

#: Where a thumbnail label's text starts from its centroid (points, x right, y up).
LABEL_OFFSET = (5.0, -6.0)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


_SVG_ID = re.compile(r'\bid="([^"]+)"')
_SVG_ID_OR_REF = re.compile(r'(\bid="|#)([^"#)\s]+)(?=[")])')  # id="x", href="#x", url(#x)
_OWN_ID = "thumbnail-"  # the THUMBNAIL_GID ids, set by crossfield and unique already


def svg(fig, prefix: str, tight: bool = True) -> str:
    """The figure as an inline ``<svg>`` element (no XML prolog, no DOCTYPE);
    ``tight``: cropped to what is drawn (matplotlib draws the figure twice then).

    matplotlib numbers its element ids per file (``figure_1``, ``patch_1``, a
    marker's hash ...), so two figures inlined in one page would repeat them,
    and a ``<use>`` or ``clip-path`` could resolve to the other figure's
    element: every id (and every ``#id`` reference to it) gets ``prefix`` + ``-``,
    except the ids crossfield sets itself (``THUMBNAIL_GID``, already unique).
    """
    plt = _pyplot()
    out = io.StringIO()
    with plt.rc_context({"svg.fonttype": "none", "svg.hashsalt": "crossfield"}):
        fig.savefig(out, format="svg", bbox_inches="tight" if tight else None, metadata={"Date": None, "Creator": None})
    plt.close(fig)
    text = out.getvalue()
    text = text[text.index("<svg"):]
    renamed = {i for i in _SVG_ID.findall(text) if not i.startswith(_OWN_ID)}
    return _SVG_ID_OR_REF.sub(lambda m: f"{m[1]}{prefix}-{m[2]}" if m[2] in renamed else m[0], text)


def deviation_chart(report: Mapping[str, Any]) -> str:
    """Deviations (mm) with U bars against the zone [-lower_tol, +upper_tol]."""
    chars = [c for c in report["characteristics"] if c["deviation_mm"] is not None]
    if not chars:
        return ""
    plt = _pyplot()
    n = len(chars)
    fig, ax = plt.subplots(figsize=(7.2, 0.42 * n + 1.1))
    y = np.arange(n)[::-1]
    rule = report["uncertainty"]["decision_rule"]
    colours = {"conforms": "#1b7a3a", "does_not_conform": "#b3261e", "not_proven": "#c07a00"}
    for yi, c in zip(y, chars):
        lo, hi = -c["lower_tol_mm"], c["upper_tol_mm"]
        ax.barh(yi, hi - lo, left=lo, height=0.6, color="#e3f4e8", edgecolor="#9cc9a9", linewidth=0.6)
        U = c["expanded_uncertainty_mm"]
        if U is not None and rule == "guarded_acceptance" and hi - U > lo + U:
            ax.barh(yi, (hi - U) - (lo + U), left=lo + U, height=0.6, color="#c3e6cd", linewidth=0)
        ax.errorbar(
            c["deviation_mm"], yi, xerr=U if U is not None else None, fmt="o", ms=4, capsize=3,
            color=colours.get(c["decision"], "#234e77"), ecolor="#1d2733", elinewidth=1,
        )
    ax.axvline(0.0, color="#5b6b7b", linewidth=0.8)
    ax.set_yticks(y, [c["name"] for c in chars])
    k = chars[0]["coverage_factor"]
    ax.set_xlabel(f"deviation from nominal (mm); bars: U (k = {k:g}); band: tolerance zone")
    ax.grid(axis="x", color="#c9d2dc", linewidth=0.5)
    ax.set_axisbelow(True)
    return svg(fig, "deviation")


#: The residual figure's drawn length of the largest residual, as a fraction of the
#: controls' spread: long enough to read its direction at print size.
RESIDUAL_ARROW_FRACTION = 0.25


def _step_below(value: float) -> float:
    """The largest 1-2-5 step number (..., 0.1, 0.2, 0.5, 1, 2, 5, 10, ...) not above ``value`` > 0."""
    decade = 10.0 ** np.floor(np.log10(value))
    return float(max(step * decade for step in (1.0, 2.0, 5.0) if step * decade <= value * (1 + 1e-12)))


def residual_gain(spread_mm: float, largest_mm: float, fraction: float = RESIDUAL_ARROW_FRACTION) -> float:
    """The magnification of the residual figure: the largest 1-2-5 step number
    (1, 2, 5, 10, 20, ...) that draws the largest residual ``largest_mm`` no longer than
    ``fraction`` of the controls' spread ``spread_mm`` (so between 0.4 and 1 times that)."""
    if not largest_mm > 0 or not spread_mm > 0:
        return 1.0
    return _step_below(fraction * spread_mm / largest_mm)


def residual_chart(report: Mapping[str, Any], positions: Mapping[str, Any]) -> str:
    """Control residual vectors (global mm) at the controls' CMM positions ``positions``
    (id -> (3,) mm), magnified (:func:`residual_gain`) so that the largest is a quarter
    of the controls' spread, with a scale arrow in the corner; the figure is as wide as
    the report's text at print size (7.2 in, fonts >= 9 pt)."""
    reg = report["registration"]
    if reg is None:
        return ""
    controls = [c for c in reg["control_points"] if c["id"] in positions]
    if len(controls) < 2:
        return ""
    P = np.array([positions[c["id"]] for c in controls], dtype=float)
    r = np.array([c["residual_mm"] for c in controls], dtype=float)
    # the plane of the two largest spreads of the controls (principal axes)
    centred = P - P.mean(axis=0)
    _, _, Vt = np.linalg.svd(centred, full_matrices=False)
    axes = Vt[:2]
    xy, rxy = centred @ axes.T, r @ axes.T
    spread = float(np.ptp(xy, axis=0).max()) or 1.0
    largest = float(np.linalg.norm(rxy, axis=1).max()) or 1.0
    gain = residual_gain(spread, largest)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.2, 5.0))
    ax.scatter(xy[:, 0], xy[:, 1], s=30, color="#234e77", zorder=3)
    for (x, yv), (dx, dy), c in zip(xy, rxy, controls):
        ax.annotate("", (x + gain * dx, yv + gain * dy), (x, yv),
                    arrowprops={"arrowstyle": "-|>", "color": "#b3261e", "lw": 1.8, "mutation_scale": 14})
        if c.get("expected_rms_mm"):
            ax.add_patch(plt.Circle((x, yv), gain * c["expected_rms_mm"], fill=False, ls=":", lw=1.2,
                                    color="#5b6b7b"))
        ax.annotate(c["id"], (x, yv), textcoords="offset points", xytext=(5, 5), fontsize=10, fontweight="bold")
    # scale arrow: a round residual length, drawn with the same magnification
    key_mm = _step_below(largest)
    x0 = float(xy[:, 0].min())
    y0 = float(xy[:, 1].min()) - 0.15 * spread
    ax.plot([x0, x0], [y0 - 0.06 * spread, y0], alpha=0.0)  # room for the key inside the axes
    ax.annotate("", (x0 + gain * key_mm, y0), (x0, y0),
                arrowprops={"arrowstyle": "-|>", "color": "#b3261e", "lw": 1.8, "mutation_scale": 14})
    ax.annotate(f"{key_mm * 1000:g} \u00b5m", (x0 + gain * key_mm, y0), textcoords="offset points",
                xytext=(6, -4), fontsize=10, va="baseline")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("principal axis 1 of the controls (mm)", fontsize=10)
    ax.set_ylabel("principal axis 2 (mm)", fontsize=10)
    ax.tick_params(labelsize=9)
    ax.set_title(f"residual R p + t \u2212 q, magnified {gain:g}x; dotted circles: expected RMS", fontsize=10)
    ax.grid(color="#c9d2dc", linewidth=0.5)
    return svg(fig, "residuals")


def trend_chart(report: Mapping[str, Any]) -> str:
    """Per kept frame: registration RMS (mm) and each characteristic minus its mean (mm)."""
    frames = [f for f in report["frames"] if f["registration_rms_mm"] is not None]
    if len(frames) < 2:
        return ""
    plt = _pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.2, 4.6), sharex=True)
    seq = [f["sequence"] for f in frames]
    top.plot(seq, [f["registration_rms_mm"] for f in frames], "o-", ms=3, color="#234e77")
    top.set_ylabel("registration\nRMS (mm)")
    names = [c["name"] for c in report["characteristics"]]
    for name in names:
        values = [
            next((c["measured_mm"] for c in f["characteristics"] if c["name"] == name), None) for f in frames
        ]
        pts = [(s, v) for s, v in zip(seq, values) if v is not None]
        if len(pts) < 2:
            continue
        mean = float(np.mean([v for _, v in pts]))
        bottom.plot([s for s, _ in pts], [v - mean for _, v in pts], ".-", lw=0.8, ms=3, label=name)
    bottom.set_ylabel("value - session\nmean (mm)")
    bottom.set_xlabel("frame")
    if len(names) <= 12:
        bottom.legend(fontsize=7, ncol=min(5, len(names)), loc="upper center", bbox_to_anchor=(0.5, -0.3))
    for ax in (top, bottom):
        ax.grid(color="#c9d2dc", linewidth=0.5)
    return svg(fig, "trends")



#: Marker colours of the thumbnail: control points, measured targets, the rest.
#: Blank space right of and below a thumbnail (SVG units = thumbnail px), for labels.
_THUMB_MARGIN = (24, 10)

_THUMB_COLOURS = {KIND_CONTROL: "#2f7fd6", KIND_TARGET: "#f28e1c", "": "#b0b8c0"}


def thumbnail_chart(thumb) -> str:
    """One camera's image in grey (``thumb.image``, uint8, drawn pixel for pixel,
    one thumbnail pixel = one SVG unit) with its centroids at ``thumb.thumbnail_uv()``
    (thumbnail px; pixel centres at integer coordinates, OpenCV convention),
    labelled with their target ids: control points (correspondence) and measured
    targets in two colours, unidentified centroids as small grey crosses.

    The SVG's parts carry the group ids of :data:`THUMBNAIL_GID`."""
    plt = _pyplot()
    h, w = thumb.image.shape
    camera = thumb.camera
    # 72 SVG units per inch: one unit per thumbnail pixel, and a margin right and
    # below for the labels of targets at the edge (not cropped: one draw, not two)
    W, H = w + _THUMB_MARGIN[0], h + _THUMB_MARGIN[1]
    fig = plt.figure(figsize=(W / 72.0, H / 72.0))
    ax = fig.add_axes((0.0, 1.0 - h / H, w / W, h / H))
    image = ax.imshow(thumb.image, cmap="gray", vmin=0, vmax=255, interpolation="none")
    image.set_gid(THUMBNAIL_GID["image"].format(camera=camera))
    uv = thumb.thumbnail_uv()
    for kind, marker, size in (("", "x", 4), (KIND_CONTROL, "o", 7), (KIND_TARGET, "o", 7)):
        index = [i for i, k in enumerate(thumb.kinds) if k == kind]
        if index:  # one artist per kind: its marker is defined once in the SVG
            (line,) = ax.plot(uv[index, 0], uv[index, 1], marker, ms=size, mfc="none",
                              mec=_THUMB_COLOURS[kind], mew=1.4 if kind else 1.0, linestyle="none")
            line.set_gid(THUMBNAIL_GID[kind].format(camera=camera))
    for (u, v), label, kind in zip(uv, thumb.labels, thumb.kinds):
        if label:
            text = ax.annotate(label, (u, v), textcoords="offset points", xytext=LABEL_OFFSET, fontsize=8,
                               color=_THUMB_COLOURS.get(kind, _THUMB_COLOURS[KIND_TARGET]),
                               fontweight="bold", annotation_clip=False)
            text.set_gid(THUMBNAIL_GID["label"].format(camera=camera, label=label))
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_axis_off()
    return svg(fig, f"thumbnail-{camera}-figure", tight=False)
