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
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from crossfield.report.figure_pool import reused_figure
from crossfield.report.thumbnails import KIND_CONTROL, KIND_TARGET

__all__ = [
    "LABEL_OFFSET", "RESIDUAL_ARROW_FRACTION", "THUMBNAIL_GID", "TREND_MARKERS_UP_TO", "deviation_chart", "residual_chart", "residual_gain", "svg",
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


def _figure(width_in: float, height_in: float):
    """A bare matplotlib ``Figure`` (``width_in`` x ``height_in`` inches) outside pyplot:
    no figure manager to register and close; :func:`svg` draws it once on the SVG canvas."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in))


def _pooled(kind: str, width_in: float, height_in: float, add_axes: Callable[[Any], Any]):
    """This thread's figure of chart ``kind`` (:func:`crossfield.report.figure_pool.reused_figure`),
    ``width_in`` x ``height_in`` inches; ``add_axes(fig)`` makes its axes the first time."""
    fig = reused_figure(kind, lambda: _made(_figure(width_in, height_in), add_axes))
    fig.set_size_inches(width_in, height_in)
    return fig


def _made(fig, add_axes: Callable[[Any], Any]):
    add_axes(fig)
    return fig


def _text_width_in(texts, fontsize_pt: float, weight: str = "normal") -> float:
    """The widest of ``texts`` set in the default font at ``fontsize_pt`` (inches), as the
    SVG backend measures it (``matplotlib.textpath.TextToPath``): the margin a fixed
    layout leaves for tick labels, instead of a second draw to crop to what is drawn."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import text_to_path

    prop = FontProperties(size=fontsize_pt, weight=weight)
    return max((text_to_path.get_text_width_height_descent(str(t), prop, False)[0] for t in texts), default=0.0) / 72.0


def _margins(fig, left_in: float, right_in: float, bottom_in: float, top_in: float, **kw) -> None:
    """Place the axes with fixed margins (inches) on all four sides (``Figure.subplots_adjust``)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=left_in / w, right=1.0 - right_in / w, bottom=bottom_in / h, top=1.0 - top_in / h, **kw)


_SVG_ID = re.compile(r'\bid="([^"]+)"')
_SVG_ID_OR_REF = re.compile(r'(\bid="|#)([^"#)\s]+)(?=[")])')  # id="x", href="#x", url(#x)
_OWN_ID = "thumbnail-"  # the THUMBNAIL_GID ids, set by crossfield and unique already


def svg(fig, prefix: str, tight: bool = True) -> str:
    """The figure as an inline ``<svg>`` element (no XML prolog, no DOCTYPE);
    ``tight``: cropped to what is drawn (matplotlib draws the figure twice then;
    the session report's figures lay themselves out and are drawn once).

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
    """Deviations (mm) with U bars against the zone [-lower_tol, +upper_tol].

    One artist per kind of mark (the zones, the guarded acceptance zones, the points
    with U bars of one decision colour), laid out with fixed margins and drawn once."""
    chars = [c for c in report["characteristics"] if c["deviation_mm"] is not None]
    if not chars:
        return ""
    n = len(chars)
    names = [c["name"] for c in chars]
    fig = _pooled("deviation", 7.2, 0.42 * n + 1.1, lambda f: f.add_subplot())
    # left: the widest name (10 pt) + tick and pad; bottom: tick labels + the x label
    _margins(fig, _text_width_in(names, 10.0) + 0.2, 0.25, 0.58, 0.08)
    (ax,) = fig.axes
    y = np.arange(n)[::-1].astype(float)
    rule = report["uncertainty"]["decision_rule"]
    colours = {"conforms": "#1b7a3a", "does_not_conform": "#b3261e", "not_proven": "#c07a00"}
    lo = np.array([-c["lower_tol_mm"] for c in chars], dtype=float)
    hi = np.array([c["upper_tol_mm"] for c in chars], dtype=float)
    ax.barh(y, hi - lo, left=lo, height=0.6, color="#e3f4e8", edgecolor="#9cc9a9", linewidth=0.6)
    U = [c["expanded_uncertainty_mm"] for c in chars]
    guarded = [i for i in range(n) if U[i] is not None and rule == "guarded_acceptance" and hi[i] - U[i] > lo[i] + U[i]]
    if guarded:
        g = np.array(guarded)
        Ug = np.array([U[i] for i in guarded], dtype=float)
        ax.barh(y[g], (hi[g] - Ug) - (lo[g] + Ug), left=lo[g] + Ug, height=0.6, color="#c3e6cd", linewidth=0)
    groups: dict[tuple[str, bool], list[int]] = {}
    for i, c in enumerate(chars):
        groups.setdefault((colours.get(c["decision"], "#234e77"), U[i] is not None), []).append(i)
    for (colour, with_u), index in groups.items():
        ax.errorbar(
            [chars[i]["deviation_mm"] for i in index], y[index],
            xerr=[U[i] for i in index] if with_u else None, fmt="o", ms=4, capsize=3,
            color=colour, ecolor="#1d2733", elinewidth=1,
        )
    ax.axvline(0.0, color="#5b6b7b", linewidth=0.8)
    ax.set_yticks(y, names)
    k = chars[0]["coverage_factor"]
    ax.set_xlabel(f"deviation from nominal (mm); bars: U (k = {k:g}); band: tolerance zone")
    ax.grid(axis="x", color="#c9d2dc", linewidth=0.5)
    ax.set_axisbelow(True)
    return svg(fig, "deviation", tight=False)


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


def _tick_labels_width_in(axis, fontsize_pt: float | str | None = None) -> float:
    """The widest major tick label of ``axis`` (inches) as it will be drawn at the current
    limits: formatted from its locator and formatter, measured as :func:`_text_width_in`
    does; no draw. ``fontsize_pt``: the tick labels' size (default: the rc value)."""
    import matplotlib

    size = fontsize_pt or matplotlib.rcParams[f"{axis.axis_name}tick.labelsize"]
    locs = axis.get_majorticklocs()
    from matplotlib.font_manager import FontProperties

    points = FontProperties(size=size).get_size_in_points()
    return _text_width_in(axis.get_major_formatter().format_ticks(locs), points)


#: The room left of the y tick labels for an ``n``-line y label of ``fontsize`` pt
#: (line spacing 1.2, label pad 4 pt, tick 3.5 pt and its pad 3.5 pt, 4 pt to the edge), inches.
def _ylabel_room_in(lines: int, fontsize_pt: float = 10.0) -> float:
    return (lines * 1.2 * fontsize_pt + 4.0 + 3.5 + 3.5 + 4.0) / 72.0


def residual_chart(report: Mapping[str, Any], positions: Mapping[str, Any]) -> str:
    """Control residual vectors (global mm) at the controls' CMM positions ``positions``
    (id -> (3,) mm), magnified (:func:`residual_gain`) so that the largest is a quarter
    of the controls' spread, with a scale arrow in the corner; the figure is as wide as
    the report's text at print size (7.2 in, fonts >= 9 pt).

    The residuals and the scale arrow are one ``quiver`` (arrow length = gain x residual,
    in data units), the expected-RMS circles one ``PatchCollection``; fixed margins, one draw."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

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
    fig = _pooled("residuals", 7.2, 5.0, lambda f: f.add_subplot())
    (ax,) = fig.axes
    ax.scatter(xy[:, 0], xy[:, 1], s=30, color="#234e77", zorder=3)
    circles = [Circle((x, yv), gain * c["expected_rms_mm"]) for (x, yv), c in zip(xy, controls)
               if c.get("expected_rms_mm")]
    if circles:
        ax.add_collection(PatchCollection(circles, facecolors="none", edgecolors="#5b6b7b", linestyles=":",
                                          linewidths=1.2))
    for (x, yv), c in zip(xy, controls):
        ax.annotate(c["id"], (x, yv), textcoords="offset points", xytext=(5, 5), fontsize=10, fontweight="bold")
    # scale arrow: a round residual length, drawn with the same magnification
    key_mm = _step_below(largest)
    x0 = float(xy[:, 0].min())
    y0 = float(xy[:, 1].min()) - 0.15 * spread
    ax.plot([x0, x0], [y0 - 0.06 * spread, y0], alpha=0.0)  # room for the key inside the axes
    # every residual and the key: tail at the point, tip at point + gain * vector (data units)
    tails = np.vstack([xy, [[x0, y0]]])
    vectors = np.vstack([rxy, [[key_mm, 0.0]]])
    ax.quiver(tails[:, 0], tails[:, 1], vectors[:, 0], vectors[:, 1], angles="xy", scale_units="xy",
              scale=1.0 / gain, color="#b3261e", units="inches", width=0.025, headwidth=3.6,
              headlength=5.0, headaxislength=4.5, zorder=2)
    ax.annotate(f"{key_mm * 1000:g} \u00b5m", (x0 + gain * key_mm, y0), textcoords="offset points",
                xytext=(6, -4), fontsize=10, va="baseline")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("principal axis 1 of the controls (mm)", fontsize=10)
    ax.set_ylabel("principal axis 2 (mm)", fontsize=10)
    ax.tick_params(labelsize=9)
    ax.set_title(f"residual R p + t \u2212 q, magnified {gain:g}x; dotted circles: expected RMS", fontsize=10)
    ax.grid(color="#c9d2dc", linewidth=0.5)
    _margins(fig, _ylabel_room_in(1) + _tick_labels_width_in(ax.yaxis, 9.0), 0.3, 0.55, 0.3)
    return svg(fig, "residuals", tight=False)


#: The trend chart marks each frame on its lines up to this many frames (on 7.2 in, ~7 pt apart).
TREND_MARKERS_UP_TO = 60


def trend_chart(report: Mapping[str, Any]) -> str:
    """Per kept frame: registration RMS (mm) and each characteristic minus its mean (mm);
    the legend (at most 12 characteristics, 5 a row) under the axes. Fixed margins, one draw."""
    frames = [f for f in report["frames"] if f["registration_rms_mm"] is not None]
    if len(frames) < 2:
        return ""
    names = [c["name"] for c in report["characteristics"]]
    ncol = min(5, len(names))
    legend_rows = -(-len(names) // ncol) if 0 < len(names) <= 12 else 0
    legend_in = 0.12 + 0.155 * legend_rows if legend_rows else 0.0  # 7 pt rows, the frame's pad
    fig = _pooled("trends", 7.2, 4.6 + legend_in, lambda f: f.subplots(2, 1, sharex=True))
    top, bottom = fig.axes
    seq = [f["sequence"] for f in frames]
    # a marker on every frame while they stand apart; denser, the line's vertices are the
    # frames (SVG draws a marker as one <use> element each: 700 of them at 100 frames)
    marked = len(frames) <= TREND_MARKERS_UP_TO
    top.plot(seq, [f["registration_rms_mm"] for f in frames], "o-" if marked else "-", ms=3, color="#234e77")
    top.set_ylabel("registration\nRMS (mm)")
    for name in names:
        values = [
            next((c["measured_mm"] for c in f["characteristics"] if c["name"] == name), None) for f in frames
        ]
        pts = [(s, v) for s, v in zip(seq, values) if v is not None]
        if len(pts) < 2:
            continue
        mean = float(np.mean([v for _, v in pts]))
        bottom.plot([s for s, _ in pts], [v - mean for _, v in pts], ".-" if marked else "-", lw=0.8, ms=3,
                    label=name)
    bottom.set_ylabel("value - session\nmean (mm)")
    bottom.set_xlabel("frame")
    if legend_rows and bottom.lines:
        fig.legend(handles=bottom.lines, fontsize=7, ncol=ncol, loc="lower center", bbox_to_anchor=(0.5, 0.0))
    for ax in (top, bottom):
        ax.grid(color="#c9d2dc", linewidth=0.5)
    left = _ylabel_room_in(2) + max(_tick_labels_width_in(ax.yaxis) for ax in (top, bottom))
    _margins(fig, left, 0.25, 0.5 + legend_in, 0.1, hspace=0.25)
    return svg(fig, "trends", tight=False)



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
    h, w = thumb.image.shape
    camera = thumb.camera
    # 72 SVG units per inch: one unit per thumbnail pixel, and a margin right and
    # below for the labels of targets at the edge (not cropped: one draw, not two)
    W, H = w + _THUMB_MARGIN[0], h + _THUMB_MARGIN[1]
    fig = _pooled("thumbnail", W / 72.0, H / 72.0, lambda f: f.add_axes((0.0, 0.0, 1.0, 1.0)))
    (ax,) = fig.axes
    ax.set_position((0.0, 1.0 - h / H, w / W, h / H))
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
