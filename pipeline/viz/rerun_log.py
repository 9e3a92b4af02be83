"""The Rerun logger: an observer plugin that shows a session in the Rerun viewer.

A native Rerun recording (rerun-sdk 0.41, its own ``RecordingStream``, not
the global one) saved to ``session.rrd`` and/or streamed live to a viewer,
with the default blueprint of :mod:`crossfield.viz.blueprint`. What each
view shows: ``docs/visualisation.md``.

Entity tree (3-D positions in **metres**, as in the Foxglove messages of the
MCAP recording; values in labels and scalars in mm)::

    world                              the global (CMM) frame, Z up
      origin                           axes of the global frame (100 mm)
      camera                           upper camera frame; Transform3D = T_global_camera of each registered pair
        upper/image                    Pinhole (frustum to the working distance) + Image
          centroids, rings, rejected   2-D overlays: centroids labelled with their plan id, rejected blobs
        lower                          Transform3D: the lower camera's pose in the upper frame (static)
          image                        Pinhole + Image + the same overlays
        points                         triangulated camera points of the pair
      cmm/controls                     CMM control points (static)
      cmm/reference_points             out-of-view reference points (static, labelled)
      cmm/line_probes                  probes of the reference lines (static)
      cmm/axes/<line>                  the fitted axis of each reference line (static, labelled)
      registration/controls            camera-measured control points mapped by the pair's registration
      registration/residuals           residual vectors from each CMM control point, x residual_scale
      targets                          measured target points (labelled)
      characteristics/<name>           one segment per characteristic, labelled value (deviation)
    registration/rms_mm, registration/residual_mm/<control>       Scalars per pair
    measurement/{measured_mm,deviation_mm,error_mm}/<name>        Scalars per pair
    log                                TextLog
    session, report                    TextDocument (markdown)

Timelines: ``frame`` (the stereo pair's sequence number) and
``capture_time`` (its timestamp). Session-level data (calibration, CMM
points and fitted axes, session facts, report) is static. Everything of a
pair is logged when the pair is done (``on_frame_done``), its images when it
is acquired (``on_frame``); what a pair did not produce (a failed stage) is
cleared at that pair, so the viewer never shows an older pair's result as
if it were this one's.

Images: Rerun shows a 16-bit image over the full 0..65535 range, so a
12-bit image would look black; the logged copy is scaled by
2**(16 - bit_depth) (an exact bit shift: divide the values Rerun shows by
16 for 12-bit DN). The MCAP recording keeps the raw values. Images cost
about 45 ms of CPU per pair in Rerun's file sink (15 pairs/s, at the
station camera's 14 frames/s): ``image_every`` (or the session key
``rerun_image_every``, default 5: 60 pairs/s) logs every n-th pair's
images only (``bench/bench_rerun.py``; ``docs/visualisation.md``).

Pixels: Rerun puts the centre of the top-left pixel at (0.5, 0.5)
(rerun-io/rerun#3896), OpenCV at (0, 0); centroids and the pinholes'
principal points are shifted by +0.5 px so that everything lines up.
"""

from __future__ import annotations

import atexit
import math
import uuid
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from crossfield.config import SESSION_DEFAULTS
from crossfield.errors import ConfigError, RecordingError
from crossfield.geometry import AxisFit, element_probes, fit_reference_element
from crossfield.hookspecs import hookimpl
from crossfield.types import CAMERAS, CameraIntrinsics, StereoCalibration
from crossfield.viz import blueprint as bp
from crossfield.viz.labels import centroid_names

APPLICATION_ID = "crossfield"

WORLD = bp.WORLD
ORIGIN = "world/origin"
CAMERA = "world/camera"
IMAGE = bp.IMAGE
LOWER = "world/camera/lower"
CAMERA_POINTS = "world/camera/points"
CMM_CONTROLS = "world/cmm/controls"
CMM_REFERENCE_POINTS = "world/cmm/reference_points"
CMM_LINE_PROBES = "world/cmm/line_probes"
CMM_AXES = "world/cmm/axes"
CONTROLS = "world/registration/controls"
RESIDUAL_ARROWS = "world/registration/residuals"
TARGETS = "world/targets"
CHARACTERISTICS = "world/characteristics"
RMS = "registration/rms_mm"
RESIDUALS = "registration/residual_mm"
MEASUREMENT = bp.MEASUREMENT
LOG = bp.LOG
SESSION = bp.SESSION
REPORT = bp.REPORT

#: Rerun's pixel centres are at +0.5 from OpenCV's (rerun-io/rerun#3896).
PIXEL_OFFSET = 0.5
#: The residual vectors are drawn this many times longer than they are.
RESIDUAL_SCALE = 1000.0
#: The frusta reach this fraction of the working distance.
FRUSTUM_FRACTION = 1.0 / 3.0
#: Labels of targets and characteristics are shown in 3-D up to this many (else on hover).
MAX_3D_LABELS = 6
_M_PER_MM = 1e-3
_DEFAULT_IMAGE_PLANE_M = 0.05
_AXIS_AXES_M = 0.1

COLOURS: dict[str, tuple[int, int, int]] = {
    "control": (255, 170, 0),  # CMM control points and the centroids matched to them
    "camera_control": (80, 200, 255),  # the same controls as the cameras measured them
    "residual": (255, 80, 200),  # residual vectors (magnified)
    "target": (90, 220, 90),  # measured target points and their centroids
    "reference": (235, 235, 235),  # out-of-view reference points
    "probe": (150, 150, 150),  # probes of reference lines
    "axis": (255, 230, 80),  # fitted reference axes
    "camera_point": (140, 150, 255),  # triangulated points of a pair
    "centroid": (255, 60, 60),  # centroids not identified as a control or target
    "rejected": (160, 160, 160),  # rejected blobs
    "pass": (60, 230, 120),  # characteristic within tolerance
    "fail": (255, 70, 70),  # characteristic out of tolerance
}

_FRUSTUM = {"upper": (210, 210, 210), "lower": (120, 120, 120)}

_LOG_LEVELS = {
    "debug": "DEBUG",
    "info": "INFO",
    "warning": "WARN",
    "warn": "WARN",
    "error": "ERROR",
    "critical": "CRITICAL",
}


def default_blueprint(residual_scale: float = RESIDUAL_SCALE, eye: Any = None) -> Any:
    """The default layout (:func:`crossfield.viz.blueprint.default_blueprint`)."""
    return bp.default_blueprint(residual_scale=residual_scale, eye=eye)


def pinhole(
    intrinsics: CameraIntrinsics,
    image_plane_distance_m: float = _DEFAULT_IMAGE_PLANE_M,
    colour: tuple[int, int, int] | None = None,
) -> rr.Pinhole:
    """Rerun pinhole of an OpenCV camera (principal point shifted to Rerun's pixel convention).

    Distortion is not modelled by Rerun's pinhole; the images are raw.
    image_plane_distance_m: where the 3-D view draws the frustum's base (metres).
    colour: of the frustum lines.
    """
    K = np.array(intrinsics.camera_matrix, dtype=np.float64)
    K[0, 2] += PIXEL_OFFSET
    K[1, 2] += PIXEL_OFFSET
    return rr.Pinhole(
        image_from_camera=K,
        resolution=list(intrinsics.image_size),
        camera_xyz=rr.ViewCoordinates.RDF,  # OpenCV: x right, y down, z forward
        image_plane_distance=float(image_plane_distance_m),
        color=colour,
        line_width=rr.Radius.ui_points(0.5),
    )


def lower_in_upper(calibration: StereoCalibration) -> rr.Transform3D:
    """The lower camera's pose in the upper frame: ``p_upper = R.T @ p_lower - R.T @ t``
    (inverse of the calibration's ``p_lower = R @ p_upper + t``, Formula (4)); metres."""
    R = np.asarray(calibration.R_lower_upper, dtype=np.float64)
    t = np.asarray(calibration.t_lower_upper, dtype=np.float64)
    return rr.Transform3D(translation=(-R.T @ t) * _M_PER_MM, mat3x3=R.T)


def fit_reference_axes(plan: Any, reference: Any) -> dict[str, AxisFit]:
    """line id -> the axis fitted to its CMM probes (global frame, mm), for display.

    The measurement's own fit (:func:`crossfield.geometry.fit_reference_element`,
    also called by the measure plugin ``plan``), so the viewer draws the axis
    that was measured against; a line whose fit fails (too few probes, an
    undetermined cylinder) is left out, as the measurement refuses it.
    """
    axes: dict[str, AxisFit] = {}
    for spec in getattr(plan, "reference_lines", ()):
        try:
            axes[spec.id] = fit_reference_element(spec, reference.points)
        except ValueError:
            continue
    return axes


def foot_on_line(p: np.ndarray, point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The orthogonal projection (3,) of p onto the line through ``point`` along unit ``direction`` (mm)."""
    v = np.asarray(p, dtype=np.float64) - point
    return point + (v @ direction) * direction


def characteristic_segment(
    kind: str, a: np.ndarray, b: np.ndarray | None = None, line: Any = None
) -> np.ndarray | None:
    """The segment (2, 3), mm, global frame, that a characteristic measures.

    point_point: a -> b. point_line: a -> its foot on the line (``line`` a
    :class:`crossfield.types.Line3D`). depth (global Z of a): a -> (a_x, a_y, 0).
    None when an element is missing.
    """
    a = np.asarray(a, dtype=np.float64)
    if kind == "point_point" and b is not None:
        return np.array([a, np.asarray(b, dtype=np.float64)])
    if kind == "point_line" and line is not None:
        return np.array([a, foot_on_line(a, np.asarray(line.point), np.asarray(line.direction))])
    if kind == "depth":
        return np.array([a, [a[0], a[1], 0.0]])
    return None


def _finite_rows(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return np.isfinite(xyz).all(axis=1)


def _fmt(value: float | None, decimals: int = 4) -> str:
    if value is None or not math.isfinite(float(value)):
        return "-"
    return f"{float(value):.{decimals}f}"


def _entity_part(name: str) -> str:
    return rr.escape_entity_path_part(str(name))


class RerunLogger:
    """Observer plugin: logs the session into a Rerun recording.

    rrd_path: the ``.rrd`` file to write (None: none). viewer: the URL of a
    running viewer to stream to live (``rerun+http://127.0.0.1:9876/proxy``;
    None: none). At least one of the two.
    image_every: log the images of every n-th stereo pair (1 = all, 0 =
    none; the MCAP recording keeps every image regardless). None: the
    session config's ``[session] rerun_image_every`` (default 5); every
    image if no session start was seen.
    residual_scale: magnification of the residual vectors in the 3-D view.
    scale_images: shift images of ``bit_depth`` < 16 to the 16-bit range for display.
    application_id: the Rerun application id; every logger makes its own recording id.
    """

    def __init__(
        self,
        rrd_path: str | Path | None = None,
        *,
        viewer: str | None = None,
        image_every: int | None = None,
        residual_scale: float = RESIDUAL_SCALE,
        scale_images: bool = True,
        application_id: str = APPLICATION_ID,
    ):
        if rrd_path is None and not viewer:
            raise ValueError("RerunLogger needs an .rrd path, a viewer URL or both")
        if image_every is not None and int(image_every) < 0:
            raise ValueError(f"image_every must be >= 0, got {image_every}")
        if not (math.isfinite(residual_scale) and residual_scale > 0):
            raise ValueError(f"residual_scale must be > 0, got {residual_scale}")
        self.path = None if rrd_path is None else Path(rrd_path)
        self.viewer = viewer or None
        self.image_every = None if image_every is None else int(image_every)
        self.residual_scale = float(residual_scale)
        self.scale_images = bool(scale_images)
        self.rec = rr.RecordingStream(application_id, recording_id=uuid.uuid4())
        sinks: list[Any] = []
        try:
            if self.path is not None:
                sinks.append(rr.FileSink(str(self.path)))
            if self.viewer:
                sinks.append(rr.GrpcSink(self.viewer))
            self.rec.set_sinks(*sinks)
        except Exception as exc:  # noqa: BLE001 - rerun raises several types
            where = self.path if self.path is not None else self.viewer
            raise RecordingError(f"{where}: cannot write the Rerun recording: {exc}") from None
        self._closed = False
        atexit.register(self.close)
        self._frame_times: dict[int, int] = {}
        self._last_frame: int | None = None
        self._plan: Any = None
        self._calibration: StereoCalibration | None = None
        self._reference: Any = None
        self._axes: dict[str, AxisFit] = {}
        self._characteristics_shown: set[str] = set()
        self._eye_sent = False
        self._plane_set = False
        self.warnings: list[str] = []

    # ---- time ----------------------------------------------------------

    def _at_frame(self, sequence: int, timestamp_ns: int | None = None) -> None:
        sequence = int(sequence)
        if timestamp_ns is None:
            timestamp_ns = self._frame_times.get(sequence)
        self.rec.reset_time()
        self.rec.set_time("frame", sequence=sequence)
        if timestamp_ns:
            self.rec.set_time("capture_time", timestamp=np.datetime64(int(timestamp_ns), "ns"))

    def _remember_frame(self, sequence: int, timestamp_ns: int) -> None:
        self._frame_times[int(sequence)] = int(timestamp_ns)
        self._last_frame = int(sequence)
        if len(self._frame_times) > 256:
            self._frame_times.pop(next(iter(self._frame_times)))

    def wants_images(self, sequence: int) -> bool:
        """True when the images of pair ``sequence`` will be logged (``image_every``)."""
        every = 1 if self.image_every is None else self.image_every
        return bool(every) and int(sequence) % every == 0

    # ---- hooks: session ------------------------------------------------

    @hookimpl
    def on_session_start(self, session: Any) -> None:
        rec = self.rec
        if self.image_every is None:
            every = session.config.session.get("rerun_image_every", SESSION_DEFAULTS["rerun_image_every"])
            if isinstance(every, bool) or not isinstance(every, int) or every < 0:
                raise ConfigError(
                    f"{session.config.source}: [session] key 'rerun_image_every' must be an integer >= 0 "
                    f"(0 = no images), got {every!r}"
                )
            self.image_every = every
        rec.send_recording_name(str(session.session_id))
        if session.start_time_ns:
            rec.send_recording_start_time_nanos(int(session.start_time_ns))
        self._plan = session.plan
        self._calibration = session.calibration
        rec.send_blueprint(default_blueprint(self.residual_scale), make_active=True, make_default=True)
        rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(ORIGIN, rr.TransformAxes3D(_AXIS_AXES_M), static=True)
        for camera in CAMERAS:
            rec.log(
                IMAGE[camera],
                pinhole(session.calibration.camera(camera), colour=_FRUSTUM[camera]),
                static=True,
            )
        rec.log(LOWER, lower_in_upper(session.calibration), static=True)
        rec.log(RMS, rr.SeriesLines(names="RMS", widths=3.0, colors=(255, 255, 255)), static=True)
        rec.log(
            SESSION,
            rr.TextDocument(self._session_markdown(session), media_type=rr.MediaType.MARKDOWN),
            static=True,
        )

    @hookimpl
    def on_reference(self, reference: Any) -> None:
        self._reference = reference
        plan = self._plan
        controls = set(getattr(plan, "control_ids", ()))
        lines = {spec.id for spec in getattr(plan, "reference_lines", ())}
        groups: dict[str, list[Any]] = {"control": [], "reference": [], "probe": []}
        for p in reference.points:
            if not np.isfinite(p.xyz).all():
                continue
            if p.label in controls:
                groups["control"].append(p)
            elif p.label.split(".", 1)[0] in lines and "." in p.label:
                groups["probe"].append(p)
            else:  # the plan's reference points, and anything the plan does not name
                groups["reference"].append(p)
        for entity, key, show in (
            (CMM_CONTROLS, "control", False),  # the residual arrows carry the ids
            (CMM_REFERENCE_POINTS, "reference", True),
            (CMM_LINE_PROBES, "probe", False),
        ):
            points = groups[key]
            xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
            self.rec.log(
                entity,
                rr.Points3D(
                    xyz * _M_PER_MM,
                    labels=[p.label for p in points],
                    colors=COLOURS[key],
                    radii=rr.Radius.ui_points({"control": 3.5, "reference": 5.0, "probe": 3.0}[key]),
                    show_labels=show,
                ),
                static=True,
            )
        self._axes = fit_reference_axes(plan, reference) if plan is not None else {}
        for line_id, fit in self._axes.items():
            ends = self._axis_extent(line_id, fit, reference)
            radius = f", cylinder r {fit.radius_mm:.3f} mm" if fit.radius_mm is not None else ""
            self.rec.log(
                f"{CMM_AXES}/{_entity_part(line_id)}",
                rr.LineStrips3D(
                    [ends * _M_PER_MM],
                    labels=[f"{line_id} axis{radius}, fit rms {fit.rms_mm * 1000:.1f} µm"],
                    colors=COLOURS["axis"],
                    radii=rr.Radius.ui_points(2.0),
                    show_labels=True,
                ),
                static=True,
            )

    def _axis_extent(self, line_id: str, fit: AxisFit, reference: Any) -> np.ndarray:
        """Two points (2, 3), mm, on the fitted axis spanning its probes and the feet of
        the plan's targets measured against it, with a margin of 10 % (at least 20 mm)."""
        point, direction = np.asarray(fit.line.point), np.asarray(fit.line.direction)
        probes = element_probes(line_id, reference.points)
        along = [float((np.asarray(p.xyz) - point) @ direction) for p in probes]
        plan = self._plan
        nominal = {t.id: np.asarray(t.nominal) for t in getattr(plan, "targets", ())}
        by_label = reference.by_label()
        for spec in getattr(plan, "characteristics", ()):
            if spec.kind == "point_line" and spec.b == line_id:
                where = nominal.get(spec.a)
                if where is None and spec.a in by_label:
                    where = np.asarray(by_label[spec.a].xyz)
                if where is not None:
                    along.append(float((where - point) @ direction))
        lo, hi = (min(along), max(along)) if along else (-50.0, 50.0)
        margin = max(0.1 * (hi - lo), 20.0)
        return np.array([point + (lo - margin) * direction, point + (hi + margin) * direction])

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        # A log line belongs to the pair it names (same capture time), else to the
        # latest pair acquired (0 before the first): the frame timeline shows it there.
        sequence = next((s for s, t in self._frame_times.items() if t == timestamp_ns), self._last_frame)
        self.rec.reset_time()
        self.rec.set_time("frame", sequence=0 if sequence is None else sequence)
        if timestamp_ns:
            self.rec.set_time("capture_time", timestamp=np.datetime64(int(timestamp_ns), "ns"))
        self.rec.log(
            LOG, rr.TextLog(str(message), level=_LOG_LEVELS.get(str(level).lower(), str(level).upper()))
        )

    @hookimpl
    def on_session_end(self, summary: Any) -> None:
        if self._closed:
            return
        self.rec.log(
            REPORT,
            rr.TextDocument(self._report_markdown(summary), media_type=rr.MediaType.MARKDOWN),
            static=True,
        )
        self.close()

    def close(self) -> None:
        """Flush and finish the recording (the .rrd footer; the end of a live stream). Idempotent.

        A viewer that cannot be reached does not fail the session: the
        problem is kept in :attr:`warnings` (the .rrd file is complete).
        """
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        try:
            self.rec.flush(timeout_sec=10.0 if self.viewer else 1e38)
        except RuntimeError as exc:  # a live viewer that went away
            self.warnings.append(f"Rerun viewer {self.viewer}: {exc}")
        self.rec.disconnect()

    @property
    def closed(self) -> bool:
        return self._closed

    # ---- hooks: per stereo pair ----------------------------------------

    @hookimpl
    def on_frame(self, frame: Any) -> None:
        seq = int(frame.sequence)
        self._remember_frame(seq, frame.timestamp_ns)
        if not self.wants_images(seq):
            return
        self._at_frame(seq, frame.timestamp_ns)
        shift = 16 - int(frame.bit_depth)
        for camera in CAMERAS:
            image = frame.image(camera)
            if self.scale_images and image.dtype == np.uint16 and 0 < shift < 16:
                image = np.left_shift(image, shift)  # exact: DN * 2**shift
            self.rec.log(IMAGE[camera], rr.Image(image))

    @hookimpl
    def on_frame_done(self, result: Any) -> None:
        """Everything computed from one pair, at its frame and capture time."""
        seq = int(result.sequence)
        if seq not in self._frame_times:
            self._remember_frame(seq, result.timestamp_ns)
        self._at_frame(seq, result.timestamp_ns)
        names = centroid_names(result)
        for camera in CAMERAS:
            cs = None if result.centroids is None else getattr(result.centroids, camera)
            self._log_centroids(camera, cs, names.get(camera, {}))
        self._log_camera_points(result.points)
        self._log_registration(result.registration, result.points)
        self._log_measurement(result.measurement)

    # ---- per pair: pieces ----------------------------------------------

    def _clear(self, entity: str) -> None:
        self.rec.log(entity, rr.Clear(recursive=True))

    def _log_centroids(self, camera: str, cs: Any, names: Mapping[int, tuple[str, str]]) -> None:
        base = IMAGE[camera]
        if cs is None:
            for part in ("centroids", "rings", "rejected"):
                self._clear(f"{base}/{part}")
            return
        uv = np.asarray(cs.uv, dtype=np.float64).reshape(-1, 2)
        keep = np.flatnonzero(np.isfinite(uv).all(axis=1))
        labels = [names.get(int(i), (str(int(i)), "centroid"))[0] for i in keep]
        colours = [COLOURS[names.get(int(i), ("", "centroid"))[1]] for i in keep]
        centres = uv[keep] + PIXEL_OFFSET
        self.rec.log(
            f"{base}/centroids",
            rr.Points2D(
                centres, labels=labels, colors=colours, radii=rr.Radius.ui_points(1.5), show_labels=True
            ),
        )
        # A ring around each blob (twice its equivalent radius) that leaves the target visible.
        area = np.nan_to_num(np.asarray(cs.area_px, dtype=np.float64)[keep], nan=0.0)
        ring = np.maximum(2.0 * np.sqrt(np.maximum(area, 0.0) / np.pi), 6.0)
        self.rec.log(
            f"{base}/rings",
            rr.Ellipses2D(
                centers=centres,
                half_sizes=np.column_stack([ring, ring]),
                colors=colours,
                line_radii=rr.Radius.ui_points(1.0),
            ),
        )
        rejected = np.array([b.uv for b in cs.rejected], dtype=np.float64).reshape(-1, 2)
        keep_r = np.isfinite(rejected).all(axis=1)
        self.rec.log(
            f"{base}/rejected",
            rr.Points2D(
                rejected[keep_r] + PIXEL_OFFSET,
                labels=[f"rejected: {b.reason}" for b, k in zip(cs.rejected, keep_r) if k],
                colors=COLOURS["rejected"],
                radii=rr.Radius.ui_points(4.0),
                show_labels=True,
            ),
        )

    def _log_camera_points(self, points: Any) -> None:
        if points is None:
            self._clear(CAMERA_POINTS)
            return
        xyz = np.asarray(points.xyz, dtype=np.float64).reshape(-1, 3)
        keep = _finite_rows(xyz)
        self.rec.log(
            CAMERA_POINTS,
            rr.Points3D(
                xyz[keep] * _M_PER_MM,
                labels=[str(i) for i in np.flatnonzero(keep)],
                colors=COLOURS["camera_point"],
                radii=rr.Radius.ui_points(2.5),
                show_labels=False,
            ),
        )
        if not self._plane_set and keep.any() and self._calibration is not None:
            # Draw each frustum a third of the way to the working distance (median depth of
            # the points): long enough to show where the cameras look, short of the targets.
            depth_m = FRUSTUM_FRACTION * float(np.median(xyz[keep, 2])) * _M_PER_MM
            if depth_m > 0:
                for camera in CAMERAS:
                    intrinsics = self._calibration.camera(camera)
                    self.rec.log(IMAGE[camera], pinhole(intrinsics, depth_m, _FRUSTUM[camera]), static=True)
                self._plane_set = True

    def _log_registration(self, registration: Any, points: Any) -> None:
        if registration is None:
            self._clear("world/registration")
            return
        fit, corr = registration.fit, registration.correspondence
        # T_global_camera (Formulas (5)-(9)): the camera frame's pose in the global frame.
        self.rec.log(
            CAMERA,
            rr.Transform3D(
                translation=np.asarray(fit.t, dtype=np.float64) * _M_PER_MM,
                mat3x3=float(fit.scale) * np.asarray(fit.R, dtype=np.float64),
            ),
        )
        self.rec.log(RMS, rr.Scalars(float(fit.rms_mm)))
        residuals = np.asarray(fit.residuals, dtype=np.float64).reshape(-1, 3)
        norms = np.linalg.norm(residuals, axis=1)
        for cid, norm in zip(corr.control_ids, norms):
            self.rec.log(f"{RESIDUALS}/{_entity_part(cid)}", rr.Scalars(float(norm)))
        # Residual r_i = s R p_i + t - q_i (camera minus CMM), drawn from the CMM point q_i.
        by_label = self._reference.by_label() if self._reference is not None else {}
        rows = [k for k, cid in enumerate(corr.control_ids) if cid in by_label and k < len(residuals)]
        q = np.array([by_label[corr.control_ids[k]].xyz for k in rows], dtype=np.float64).reshape(-1, 3)
        r = residuals[rows].reshape(-1, 3)
        self.rec.log(
            RESIDUAL_ARROWS,
            rr.Arrows3D(
                origins=q * _M_PER_MM,
                vectors=r * self.residual_scale * _M_PER_MM,
                labels=[f"{corr.control_ids[k]} {norms[k] * 1000:.1f} µm" for k in rows],
                colors=COLOURS["residual"],
                radii=rr.Radius.ui_points(1.5),
                show_labels=False,  # on hover: the labels would cover each other
            ),
        )
        if points is not None and len(corr.camera_index):
            measured = fit.apply(points.xyz[np.asarray(corr.camera_index)])
            self.rec.log(
                CONTROLS,
                rr.Points3D(
                    measured * _M_PER_MM,
                    labels=[str(c) for c in corr.control_ids],
                    colors=COLOURS["camera_control"],
                    radii=rr.Radius.ui_points(2.0),  # inside the orange CMM point
                    show_labels=False,
                ),
            )
        else:
            self._clear(CONTROLS)
        if not self._eye_sent:
            self._send_eye(fit)

    def _send_eye(self, fit: Any) -> None:
        """Once the camera pose is known: the default blueprint again, with a 3-D eye
        that frames the station: the camera, the control points (their centroid),
        each reference point and each fitted axis (its ends), one element each."""
        elements: list[np.ndarray] = [np.asarray(fit.t, dtype=np.float64)]
        if self._reference is not None:
            by_label = self._reference.by_label()
            controls = [by_label[c].xyz for c in getattr(self._plan, "control_ids", ()) if c in by_label]
            if controls:
                elements.append(np.mean(np.asarray(controls, dtype=np.float64), axis=0))
            elements += [
                np.asarray(by_label[r].xyz)
                for r in getattr(self._plan, "reference_point_ids", ())
                if r in by_label
            ]
            for line_id, axis in self._axes.items():
                elements += list(self._axis_extent(line_id, axis, self._reference))
        scene = np.array(elements, dtype=np.float64).reshape(-1, 3) * _M_PER_MM
        self.rec.send_blueprint(
            default_blueprint(self.residual_scale, bp.station_eye(scene)), make_active=True, make_default=True
        )
        self._eye_sent = True

    def _log_measurement(self, measurement: Any) -> None:
        if measurement is None:
            self._clear(TARGETS)
            self._clear(CHARACTERISTICS)
            self._characteristics_shown.clear()
            return
        for c in measurement.characteristics:
            for field in ("measured_mm", "deviation_mm", "error_mm"):
                value = getattr(c, field)
                if value is not None and math.isfinite(float(value)):
                    self.rec.log(f"{MEASUREMENT}/{field}/{_entity_part(c.name)}", rr.Scalars(float(value)))
        ids = list(measurement.target_points)
        xyz = np.array([measurement.target_points[i] for i in ids], dtype=np.float64).reshape(-1, 3)
        keep = _finite_rows(xyz)
        self.rec.log(
            TARGETS,
            rr.Points3D(
                xyz[keep] * _M_PER_MM,
                labels=[i for i, k in zip(ids, keep) if k],
                colors=COLOURS["target"],
                radii=rr.Radius.ui_points(5.0),
                show_labels=len(ids) <= MAX_3D_LABELS,
            ),
        )
        shown = set()
        elements = self._elements(measurement)
        for c in measurement.characteristics:
            segment = self._segment(c, elements)
            entity = f"{CHARACTERISTICS}/{_entity_part(c.name)}"
            if segment is None or not np.isfinite(segment).all() or not math.isfinite(c.measured_mm):
                continue
            self.rec.log(
                entity,
                rr.LineStrips3D(
                    [segment * _M_PER_MM],
                    labels=[f"{c.name} {c.measured_mm:.4f} mm ({c.deviation_mm:+.4f})"],
                    colors=COLOURS["pass" if c.passed else "fail"],
                    radii=rr.Radius.ui_points(1.0 if c.kind == "depth" else 1.5),
                    show_labels=len(measurement.characteristics) <= MAX_3D_LABELS,
                ),
            )
            shown.add(c.name)
        for name in self._characteristics_shown - shown:
            self._clear(f"{CHARACTERISTICS}/{_entity_part(name)}")
        self._characteristics_shown = shown

    def _elements(self, measurement: Any) -> dict[str, np.ndarray]:
        """Point elements of a pair (global, mm): measured targets, CMM points by label."""
        out: dict[str, np.ndarray] = {}
        if self._reference is not None:
            for p in self._reference.points:
                out[p.label] = np.asarray(p.xyz, dtype=np.float64)
        for tid, xyz in measurement.target_points.items():
            out[str(tid)] = np.asarray(xyz, dtype=np.float64)
        return out

    def _segment(self, c: Any, elements: Mapping[str, np.ndarray]) -> np.ndarray | None:
        names = tuple(c.elements)
        if not names or names[0] not in elements:
            return None
        a = elements[names[0]]
        b = elements.get(names[1]) if len(names) > 1 else None
        line = self._axes[names[1]].line if len(names) > 1 and names[1] in self._axes else None
        return characteristic_segment(c.kind, a, b, line)

    # ---- text ----------------------------------------------------------

    def _session_markdown(self, session: Any) -> str:
        every = self.image_every
        images = "none" if every == 0 else ("every pair" if every == 1 else f"every {every}th pair")
        lines = [
            f"# Session {session.session_id}",
            "",
            f"* plan: **{session.plan.name}** ({session.plan.source or 'built in'})",
            f"* calibration: {session.calibration.source or '-'}",
            f"* config: {session.config.source}",
            f"* simulated: {'yes' if session.ground_truth is not None else 'no'}",
            f"* images shown: {images}",
            "",
            "| stage | implementation | package | version |",
            "| --- | --- | --- | --- |",
        ]
        for stage, entry in session.plugins.items():
            cells = [stage] + [str(entry.get(key, "")) for key in ("name", "package", "version")]
            lines.append("| " + " | ".join(cells) + " |")
        lines += [
            "",
            "## 3-D view",
            "",
            "Global (CMM) frame, metres, Z up; the axes at the origin are 100 mm long.",
            "",
            "| colour | what |",
            "| --- | --- |",
            "| orange | CMM control points (in the images: centroids matched to a control) |",
            "| light blue | the control points as the cameras measured them, mapped by the registration |",
            f"| magenta | residual vectors (camera - CMM) from each CMM control point, **x{self.residual_scale:g}** |",
            "| green | measured target points (in the images: their centroids) |",
            "| white | out-of-view reference points; grey: probes of reference lines |",
            "| yellow | fitted reference axes |",
            "| green / red lines | characteristics within / out of tolerance: value (deviation) in mm |",
            "| violet | the pair's triangulated camera points |",
            "| red (images) | centroids not identified; grey: rejected blobs with the reason |",
        ]
        return "\n".join(lines) + "\n"

    @staticmethod
    def _report_markdown(summary: Any) -> str:
        """The report panel: the session verdict and the characteristics table of
        :func:`crossfield.report.vocabulary.result_table` (the CLI's and ``print(summary)``'s)."""
        from crossfield.report.document import document_of
        from crossfield.report.vocabulary import result_table, rule_text, session_verdict

        report = document_of(summary)
        aggregate = summary.aggregate
        verdict = session_verdict(report["passed"], report["incomplete"], report.get("station_moved"))
        table = result_table(report)
        lines = [
            f"# {verdict}: session {summary.info.session_id}",
            "",
            f"{summary.frames_processed} stereo pairs, {summary.frames_failed} failed."
            + (f" Incomplete: {summary.incomplete}." if summary.incomplete else ""),
            "",
            f"Lengths in mm; decision rule: {rule_text(report['uncertainty']['decision_rule'])}.",
            "",
            "| " + " | ".join(table.headers) + " |",
            "|" + "".join(" ---: |" if r else " --- |" for r in table.right),
        ]
        for row in table.rows:
            lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |")
        lines += ["", ("u: standard uncertainty of the mean; U: expanded uncertainty; std (repeatability) and "
                       "more in the HTML report.")]
        rms = summary.rms_error_mm()
        if rms is not None:
            lines += ["", f"RMS error against the simulator's ground truth: {_fmt(rms)} mm"]
        registration = aggregate.registration
        if registration is not None:
            lines += [
                "",
                (
                    f"Registration RMS over {registration.n_frames} pairs: mean {_fmt(registration.rms_mean_mm)} mm, "
                    f"max {_fmt(registration.rms_max_mm)} mm."
                ),
            ]
        if aggregate.frame_errors:
            lines += ["", "## Failed frames", ""] + [f"* {e.error}" for e in aggregate.frame_errors]
            if aggregate.frame_errors_omitted:
                lines.append(f"* ... and {aggregate.frame_errors_omitted} more (see /frames in session.mcap)")
        if summary.report_files:
            lines += ["", "Report files: " + ", ".join(str(p) for p in summary.report_files)]
        return "\n".join(lines) + "\n"


def logged_entities() -> Iterable[str]:
    """The fixed entity paths (per-control, per-line and per-characteristic entities come in addition)."""
    return (
        WORLD,
        ORIGIN,
        CAMERA,
        IMAGE["upper"],
        IMAGE["lower"],
        LOWER,
        CAMERA_POINTS,
        CMM_CONTROLS,
        CMM_REFERENCE_POINTS,
        CMM_LINE_PROBES,
        CONTROLS,
        RESIDUAL_ARROWS,
        TARGETS,
        RMS,
        LOG,
        SESSION,
        REPORT,
    )
