"""The Rerun logger: an observer plugin writing the session to ``session.rrd``.

A native Rerun recording (rerun-sdk 0.41, its own ``RecordingStream``, not
the global one) with a default blueprint: the 3-D scene, both camera images
with their centroids, time series of the registration residuals and the
characteristics, the log and the report. Open it with ``rerun session.rrd``.

Entity tree (3-D positions in **metres**, like the Foxglove messages of the
MCAP recording; values in labels and scalars in mm)::

    world                          the global (CMM) frame
      camera                       upper camera frame; Transform3D = T_global_camera once registered
        upper/image                Pinhole + Image (16-bit) + centroids (Points2D), blobs (rings), rejected
        lower                      Transform3D: the lower camera's pose in the upper frame (static)
          image                    Pinhole + Image + centroids
        points                     triangulated camera points (Points3D)
      reference/points             the CMM arm's probed points (Points3D, labelled)
      registration/controls        the control points used by the registration, labelled with |residual|
      targets                      measured target points (Points3D, labelled)
    registration/rms_mm            Scalars; registration/residual_mm/<control id>: Scalars
    measurement/deviation_mm/<characteristic>   Scalars (measured - nominal); likewise
    measurement/error_mm/<characteristic>       (measured - simulator truth) and measured_mm
    log                            TextLog
    session, report                TextDocument (markdown)

Timelines: ``frame`` (the stereo pair's sequence number) and
``capture_time`` (its timestamp). Session-level data (calibration,
reference points, session facts, report) is static.

Images: Rerun shows a 16-bit image over the full 0..65535 range, so a
12-bit image would look black; the logged copy is scaled by
2**(16 - bit_depth) (an exact bit shift: divide the values Rerun shows by
16 for 12-bit DN). The MCAP recording keeps the raw values.

Pixels: Rerun puts the centre of the top-left pixel at (0.5, 0.5)
(rerun-io/rerun#3896), OpenCV at (0, 0); centroids and the pinholes'
principal points are shifted by +0.5 px so that everything lines up.
"""

from __future__ import annotations

import atexit
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from .errors import RecordingError
from .hookspecs import hookimpl
from .types import CAMERAS, CameraIntrinsics, StereoCalibration

APPLICATION_ID = "crossfield"

WORLD = "world"
CAMERA = "world/camera"
IMAGE = {"upper": "world/camera/upper/image", "lower": "world/camera/lower/image"}
LOWER = "world/camera/lower"
CAMERA_POINTS = "world/camera/points"
REFERENCE_POINTS = "world/reference/points"
CONTROLS = "world/registration/controls"
TARGETS = "world/targets"
RMS = "registration/rms_mm"
RESIDUALS = "registration/residual_mm"
MEASUREMENT = "measurement"
LOG = "log"
SESSION = "session"
REPORT = "report"

#: Rerun's pixel centres are at +0.5 from OpenCV's (rerun-io/rerun#3896).
PIXEL_OFFSET = 0.5
_M_PER_MM = 1e-3
_IMAGE_PLANE_DISTANCE_M = 0.05

_CONTROL_COLOUR = (255, 170, 0)
_CAMERA_POINT_COLOUR = (80, 180, 255)
_REFERENCE_COLOUR = (220, 220, 220)
_TARGET_COLOUR = (90, 220, 90)
_CENTROID_COLOUR = (255, 60, 60)
_REJECTED_COLOUR = (160, 160, 160)
_LOG_LEVELS = {
    "debug": "DEBUG",
    "info": "INFO",
    "warning": "WARN",
    "warn": "WARN",
    "error": "ERROR",
    "critical": "CRITICAL",
}


_REPORT_COLUMNS = (
    "characteristic",
    "n",
    "measured (mm)",
    "std (mm)",
    "u (mm)",
    "nominal (mm)",
    "tol (mm)",
    "deviation (mm)",
    "error (mm)",
    "result",
)


def default_blueprint() -> rrb.Blueprint:
    """3-D scene and both images on top; time series, log and report below."""
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=WORLD, name="Station (global frame, m)"),
                rrb.Vertical(
                    rrb.Spatial2DView(origin=IMAGE["upper"], name="Upper camera"),
                    rrb.Spatial2DView(origin=IMAGE["lower"], name="Lower camera"),
                ),
                column_shares=[3, 2],
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin=RMS.split("/")[0], name="Registration (mm)"),
                rrb.TimeSeriesView(
                    origin=MEASUREMENT,
                    contents=["$origin/deviation_mm/**", "$origin/error_mm/**"],
                    name="Characteristics: deviation, error (mm)",
                ),
                rrb.Tabs(
                    rrb.TextDocumentView(origin=REPORT, name="Report"),
                    rrb.TextDocumentView(origin=SESSION, name="Session"),
                    rrb.TextLogView(origin=LOG, name="Log"),
                ),
            ),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def pinhole(intrinsics: CameraIntrinsics) -> rr.Pinhole:
    """Rerun pinhole of an OpenCV camera (principal point shifted to Rerun's pixel convention).

    Distortion is not modelled by Rerun's pinhole; the images are raw.
    """
    K = np.array(intrinsics.camera_matrix, dtype=np.float64)
    K[0, 2] += PIXEL_OFFSET
    K[1, 2] += PIXEL_OFFSET
    return rr.Pinhole(
        image_from_camera=K,
        resolution=list(intrinsics.image_size),
        camera_xyz=rr.ViewCoordinates.RDF,  # OpenCV: x right, y down, z forward
        image_plane_distance=_IMAGE_PLANE_DISTANCE_M,
    )


def lower_in_upper(calibration: StereoCalibration) -> rr.Transform3D:
    """The lower camera's pose in the upper frame: ``p_upper = R.T @ p_lower - R.T @ t``
    (inverse of the calibration's ``p_lower = R @ p_upper + t``, Formula (4)); metres."""
    R = np.asarray(calibration.R_lower_upper, dtype=np.float64)
    t = np.asarray(calibration.t_lower_upper, dtype=np.float64)
    return rr.Transform3D(translation=(-R.T @ t) * _M_PER_MM, mat3x3=R.T)


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
    """Observer plugin: logs the session into a Rerun recording saved at ``rrd_path``.

    image_every: log the images of every n-th stereo pair (1 = all, 0 = none;
    the MCAP recording keeps every image regardless). scale_images: shift
    images of ``bit_depth`` < 16 to the 16-bit range for display.
    application_id: the Rerun application id.
    """

    def __init__(
        self,
        rrd_path: str | Path,
        *,
        image_every: int = 1,
        scale_images: bool = True,
        application_id: str = APPLICATION_ID,
    ):
        self.path = Path(rrd_path)
        if image_every < 0:
            raise ValueError(f"image_every must be >= 0, got {image_every}")
        self.image_every = int(image_every)
        self.scale_images = bool(scale_images)
        self.rec = rr.RecordingStream(application_id)
        try:
            self.rec.save(self.path, default_blueprint=default_blueprint())
        except Exception as exc:  # noqa: BLE001 - rerun raises several types
            raise RecordingError(f"{self.path}: cannot write the Rerun recording: {exc}") from None
        self._closed = False
        atexit.register(self.close)
        self._frame_times: dict[int, int] = {}
        self._reference: Any = None

    # ---- time ----------------------------------------------------------

    def _at_frame(self, sequence: int, timestamp_ns: int | None = None) -> None:
        sequence = int(sequence)
        if timestamp_ns is None:
            timestamp_ns = self._frame_times.get(sequence)
        self.rec.reset_time()
        self.rec.set_time("frame", sequence=sequence)
        if timestamp_ns:
            self.rec.set_time("capture_time", timestamp=np.datetime64(int(timestamp_ns), "ns"))

    def _at_time(self, timestamp_ns: int) -> None:
        self.rec.reset_time()
        if timestamp_ns:
            self.rec.set_time("capture_time", timestamp=np.datetime64(int(timestamp_ns), "ns"))

    # ---- hooks ---------------------------------------------------------

    @hookimpl
    def on_session_start(self, session: Any) -> None:
        rec = self.rec
        rec.send_recording_name(str(session.session_id))
        if session.start_time_ns:
            rec.send_recording_start_time_nanos(int(session.start_time_ns))
        calibration = session.calibration
        rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for camera in CAMERAS:
            rec.log(IMAGE[camera], pinhole(calibration.camera(camera)), static=True)
        rec.log(LOWER, lower_in_upper(calibration), static=True)
        rec.log(
            SESSION,
            rr.TextDocument(self._session_markdown(session), media_type=rr.MediaType.MARKDOWN),
            static=True,
        )

    @hookimpl
    def on_frame(self, frame: Any) -> None:
        seq = int(frame.sequence)
        self._frame_times[seq] = int(frame.timestamp_ns)
        if len(self._frame_times) > 256:
            self._frame_times.pop(next(iter(self._frame_times)))
        if self.image_every and seq % self.image_every == 0:
            self._at_frame(seq, frame.timestamp_ns)
            shift = 16 - int(frame.bit_depth)
            for camera in CAMERAS:
                image = frame.image(camera)
                if self.scale_images and image.dtype == np.uint16 and 0 < shift < 16:
                    image = np.left_shift(image, shift)  # exact: DN * 2**shift
                self.rec.log(IMAGE[camera], rr.Image(image))

    @hookimpl
    def on_reference(self, reference: Any) -> None:
        self._reference = reference
        ok = [p for p in reference.points if np.isfinite(p.xyz).all()]
        xyz = np.array([p.xyz for p in ok], dtype=np.float64).reshape(-1, 3)
        self.rec.log(
            REFERENCE_POINTS,
            rr.Points3D(xyz * _M_PER_MM, labels=[p.label for p in ok], colors=_REFERENCE_COLOUR, radii=0.002),
            static=True,
        )

    @hookimpl
    def on_centroids(self, centroids: Any) -> None:
        self._at_frame(centroids.sequence)
        for camera in CAMERAS:
            cs = getattr(centroids, camera)
            uv = np.asarray(cs.uv, dtype=np.float64).reshape(-1, 2)
            keep = np.isfinite(uv).all(axis=1)
            labels = [str(i) for i in np.flatnonzero(keep)]
            self.rec.log(
                f"{IMAGE[camera]}/centroids",
                rr.Points2D(
                    uv[keep] + PIXEL_OFFSET,
                    labels=labels,
                    colors=_CENTROID_COLOUR,
                    radii=rr.Radius.ui_points(1.5),
                ),
            )
            # A ring around each blob (twice its equivalent radius) that leaves the target visible.
            area = np.nan_to_num(np.asarray(cs.area_px, dtype=np.float64)[keep], nan=0.0)
            ring = np.maximum(2.0 * np.sqrt(np.maximum(area, 0.0) / np.pi), 6.0)
            self.rec.log(
                f"{IMAGE[camera]}/blobs",
                rr.Ellipses2D(
                    centers=uv[keep] + PIXEL_OFFSET,
                    half_sizes=np.column_stack([ring, ring]),
                    colors=_CENTROID_COLOUR,
                    line_radii=rr.Radius.ui_points(1.0),
                ),
            )
            rejected = np.array([b.uv for b in cs.rejected], dtype=np.float64).reshape(-1, 2)
            keep_r = np.isfinite(rejected).all(axis=1)
            self.rec.log(
                f"{IMAGE[camera]}/rejected",
                rr.Points2D(
                    rejected[keep_r] + PIXEL_OFFSET,
                    labels=[b.reason for b, k in zip(cs.rejected, keep_r) if k],
                    colors=_REJECTED_COLOUR,
                    radii=rr.Radius.ui_points(3.0),
                ),
            )

    @hookimpl
    def on_camera_points(self, points: Any) -> None:
        self._at_frame(points.sequence)
        xyz = np.asarray(points.xyz, dtype=np.float64).reshape(-1, 3)
        keep = _finite_rows(xyz)
        self.rec.log(
            CAMERA_POINTS,
            rr.Points3D(xyz[keep] * _M_PER_MM, colors=_CAMERA_POINT_COLOUR, radii=0.0015),
        )

    @hookimpl
    def on_registration(self, registration: Any) -> None:
        self._at_frame(registration.sequence)
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
        by_label = self._reference.by_label() if self._reference is not None else {}
        ids = [cid for cid in corr.control_ids if cid in by_label]
        if ids:
            xyz = np.array([by_label[cid].xyz for cid in ids], dtype=np.float64)
            norm_of = dict(zip(corr.control_ids, norms))
            self.rec.log(
                CONTROLS,
                rr.Points3D(
                    xyz * _M_PER_MM,
                    labels=[f"{cid} |r| {_fmt(norm_of[cid])} mm" for cid in ids],
                    colors=_CONTROL_COLOUR,
                    radii=0.003,
                ),
            )

    @hookimpl
    def on_measurement(self, measurement: Any) -> None:
        self._at_frame(measurement.sequence)
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
                colors=_TARGET_COLOUR,
                radii=0.003,
            ),
        )

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        self._at_time(timestamp_ns)
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
        """Flush and finish the .rrd file (writes its footer). Idempotent."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        self.rec.flush()
        self.rec.disconnect()

    @property
    def closed(self) -> bool:
        return self._closed

    # ---- text ----------------------------------------------------------

    @staticmethod
    def _session_markdown(session: Any) -> str:
        lines = [
            f"# Session {session.session_id}",
            "",
            f"* plan: **{session.plan.name}** ({session.plan.source or 'built in'})",
            f"* calibration: {session.calibration.source or '-'}",
            f"* config: {session.config.source}",
            f"* simulated: {'yes' if session.ground_truth is not None else 'no'}",
            "",
            "| stage | implementation | package | version |",
            "| --- | --- | --- | --- |",
        ]
        for stage, entry in session.plugins.items():
            cells = [stage] + [str(entry.get(key, "")) for key in ("name", "package", "version")]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"

    @staticmethod
    def _report_markdown(summary: Any) -> str:
        verdict = "PASS" if summary.passed else "FAIL"
        failed = [f for f in summary.frames if f.error]
        lines = [
            f"# {verdict}: session {summary.info.session_id}",
            "",
            f"{len(summary.frames)} stereo pairs, {len(failed)} failed."
            + (f" Incomplete: {summary.incomplete}." if summary.incomplete else ""),
            "",
            "| " + " | ".join(_REPORT_COLUMNS) + " |",
            "|" + " --- |" * len(_REPORT_COLUMNS),
        ]
        for c in summary.characteristics:
            numbers = (
                c.measured_mm,
                c.std_mm,
                c.uncertainty_mm,
                c.nominal_mm,
                c.tolerance_mm,
                c.deviation_mm,
                c.error_mm,
            )
            cells = [c.name, str(c.n)] + [_fmt(v) for v in numbers] + ["pass" if c.passed else "FAIL"]
            lines.append("| " + " | ".join(cells) + " |")
        rms = summary.rms_error_mm()
        if rms is not None:
            lines += ["", f"RMS error against the simulator's ground truth: {_fmt(rms)} mm"]
        if failed:
            lines += ["", "## Failed frames", ""] + [f"* {f.error}" for f in failed]
        if summary.report_files:
            lines += ["", "Report files: " + ", ".join(str(p) for p in summary.report_files)]
        return "\n".join(lines) + "\n"


def logged_entities() -> Iterable[str]:
    """The fixed entity paths (per-control and per-characteristic entities come in addition)."""
    return (
        WORLD,
        CAMERA,
        IMAGE["upper"],
        IMAGE["lower"],
        LOWER,
        CAMERA_POINTS,
        REFERENCE_POINTS,
        CONTROLS,
        TARGETS,
        RMS,
        LOG,
        SESSION,
        REPORT,
    )
