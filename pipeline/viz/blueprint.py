"""The default Rerun blueprint of a crossfield session (``session.rrd``).

Layout (rerun-sdk 0.41 blueprint API, ``rerun.blueprint``)::

    +----------------------------------------+--------------------+
    | Station: 3-D, global (CMM) frame       | Upper camera (2-D) |
    |                                        +--------------------+
    |                                        | Lower camera (2-D) |
    +-------------------+--------------------+--------------------+
    | Registration      | Characteristics    | Report | Session   |
    | residuals (mm)    | deviation / error  | Log                |
    +-------------------+--------------------+--------------------+

The 3-D view shows the camera frusta but neither the images nor their 2-D
overlays (they belong to the camera views). Entity paths: :mod:`crossfield.viz.rerun_log`.
What each view shows: ``docs/visualisation.md``.
"""

from __future__ import annotations

import numpy as np
import rerun.blueprint as rrb

from crossfield.types import CAMERAS

WORLD = "world"
IMAGE = {camera: f"world/camera/{camera}/image" for camera in CAMERAS}
REGISTRATION = "registration"
MEASUREMENT = "measurement"
LOG = "log"
SESSION = "session"
REPORT = "report"

#: Names of the views, as the viewer lists them (tests look them up by these).
VIEW_3D = "Station: global (CMM) frame"
VIEW_CAMERA = {"upper": "Upper camera", "lower": "Lower camera"}
VIEW_RESIDUALS = "Registration residuals (mm)"
VIEW_DEVIATION = "Deviation from nominal (mm)"
VIEW_ERROR = "Error vs truth (mm)"
VIEW_REPORT = "Report"
VIEW_SESSION = "Session"
VIEW_LOG = "Log"

#: Elevation of the default 3-D eye above the scene's mean plane (radians).
_EYE_ELEVATION = np.radians(10.0)


def station_eye(
    points_m: np.ndarray, *, up: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> rrb.EyeControls3D:
    """A 3-D eye that shows all of ``points_m`` (N, 3), metres, global frame.

    It looks at the centre of their bounding box along the normal of their
    best-fit plane (the smallest principal axis, so the scene spreads out
    across the picture), tilted towards ``up`` by 10 degrees, from a
    distance of 0.85 times the bounding-box diagonal.
    """
    P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1)]
    if len(P) == 0:
        return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital)
    lo, hi = P.min(axis=0), P.max(axis=0)
    centre = (lo + hi) / 2.0
    diagonal = max(float(np.linalg.norm(hi - lo)), 0.1)
    up_v = np.asarray(up, dtype=np.float64)
    normal = up_v
    if len(P) >= 3:
        _, _, Vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
        normal = Vt[-1]
    # Look from the side of the plane the up axis points to; tilt the line of
    # sight by the elevation angle towards up (or, for a horizontal scene, away from it).
    if normal @ up_v < 0:
        normal = -normal
    horizontal = normal - (normal @ up_v) * up_v
    if np.linalg.norm(horizontal) < 1e-6:  # a horizontal scene: look down at it obliquely
        horizontal = np.cross(up_v, [1.0, 0.0, 0.0] if abs(up_v[0]) < 0.9 else [0.0, 1.0, 0.0])
    horizontal /= np.linalg.norm(horizontal)
    direction = np.cos(_EYE_ELEVATION) * horizontal + np.sin(_EYE_ELEVATION) * up_v
    position = centre + 0.85 * diagonal * direction
    return rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital,
        position=position.tolist(),
        look_target=centre.tolist(),
        eye_up=up_v.tolist(),
    )


def default_blueprint(
    *, residual_scale: float = 1000.0, eye: rrb.EyeControls3D | None = None
) -> rrb.Blueprint:
    """The session layout: 3-D station, both camera images, residual and
    characteristic plots, report / session / log tabs.

    residual_scale: the magnification of the residual arrows, stated in the 3-D
    view's name. eye: the 3-D view's initial eye (:func:`station_eye`);
    None lets the viewer frame the scene.
    """
    hide_2d = [f"- {IMAGE[c]}/**" for c in CAMERAS] + [f"+ {IMAGE[c]}" for c in CAMERAS]
    station = rrb.Spatial3DView(
        origin=WORLD,
        contents=["+ $origin/**", *hide_2d],
        # Only the frustum of each camera in 3-D: no image texture, no 2-D overlays.
        overrides={IMAGE[c]: [rrb.Visualizer("Cameras")] for c in CAMERAS},
        name=f"{VIEW_3D}; residual arrows x{residual_scale:g}",
        eye_controls=eye,
        background=rrb.BackgroundKind.GradientDark,
    )
    cameras = rrb.Vertical(
        *(rrb.Spatial2DView(origin=IMAGE[c], name=VIEW_CAMERA[c]) for c in CAMERAS),
    )
    residuals = rrb.TimeSeriesView(
        origin=REGISTRATION,
        name=VIEW_RESIDUALS,
        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True),
    )
    deviation = rrb.TimeSeriesView(
        origin=f"{MEASUREMENT}/deviation_mm",
        name=VIEW_DEVIATION,
        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True),
    )
    error = rrb.TimeSeriesView(
        origin=f"{MEASUREMENT}/error_mm",
        name=VIEW_ERROR,
        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True),
    )
    text = rrb.Tabs(
        rrb.TextDocumentView(origin=REPORT, name=VIEW_REPORT),
        rrb.TextDocumentView(origin=SESSION, name=VIEW_SESSION),
        rrb.TextLogView(origin=LOG, name=VIEW_LOG),
    )
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(station, cameras, column_shares=[3, 2]),
            rrb.Horizontal(residuals, rrb.Tabs(deviation, error), text, column_shares=[2, 2, 3]),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )
