"""Foxglove overlays of a session: what the Rerun view shows, as Foxglove's own schemas.

Two kinds of message, built here and written by :class:`crossfield.recording.writer.SessionWriter`
(``docs/recording.md``, ``docs/visualisation.md``):

- ``/camera/<camera>/annotations`` (``foxglove.ImageAnnotations``), one per camera and stereo
  pair, at the pair's capture time: every centroid as a circle (diameter: four times the
  blob's equivalent radius, at least 12 px, so the target stays visible) and a point at its
  centre, labelled with its plan id (control or target) or its index; the rejected blobs in
  grey with their reason. Foxglove puts the origin at the top-left corner of the top-left
  pixel, OpenCV (crossfield) at its centre: every position is ``uv + 0.5`` px.
- ``/scene`` (``foxglove.SceneUpdate``), in the frames of ``/tf``: when the CMM points are
  imported, the control points, reference points and the fitted reference lines (a cylinder
  of the shaft's diameter for a cylinder fit, a line list for a line fit), frame ``global``;
  per pair, the measured targets (``global``), the controls as the cameras measured them
  (frame ``upper``: Foxglove maps them with the pair's ``global -> upper`` transform onto
  the CMM's) and one segment per characteristic with its value. A pair that produced no
  measurement deletes the per-pair entities, as the Rerun view clears them.

Positions in the scene are in **metres** (the Foxglove convention, as the point clouds);
labels carry mm. Colours are the Rerun view's (:data:`COLOURS`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from crossfield.recording.layout import FRAME_CAMERA, FRAME_GLOBAL
from crossfield.types import CAMERAS
from crossfield.viz.labels import centroid_names

__all__ = [
    "COLOURS",
    "ENTITY_CAMERA_CONTROLS",
    "ENTITY_CHARACTERISTICS",
    "ENTITY_CONTROLS",
    "ENTITY_LINE",
    "ENTITY_REFERENCE_POINTS",
    "ENTITY_TARGETS",
    "PIXEL_OFFSET",
    "FoxgloveOverlay",
    "image_annotations",
]

#: Foxglove's pixel origin is the top-left pixel's corner, OpenCV's its centre.
PIXEL_OFFSET = 0.5
_M_PER_MM = 1e-3
#: Sphere diameters in the scene (m).
_SPHERE_M = {"control": 0.004, "reference": 0.006, "target": 0.004, "camera_control": 0.003}

#: RGB of each kind of thing (the Rerun view's, crossfield.viz.rerun_log.COLOURS).
COLOURS: dict[str, tuple[int, int, int]] = {
    "control": (255, 170, 0),
    "camera_control": (80, 200, 255),
    "target": (90, 220, 90),
    "reference": (235, 235, 235),
    "axis": (255, 230, 80),
    "centroid": (255, 60, 60),
    "rejected": (160, 160, 160),
    "pass": (60, 230, 120),
    "fail": (255, 70, 70),
}

ENTITY_CONTROLS = "cmm/controls"
ENTITY_REFERENCE_POINTS = "cmm/reference_points"
ENTITY_LINE = "cmm/lines/{id}"
ENTITY_TARGETS = "measurement/targets"
ENTITY_CHARACTERISTICS = "measurement/characteristics"
ENTITY_CAMERA_CONTROLS = "registration/camera_controls"
_PER_PAIR = (ENTITY_TARGETS, ENTITY_CHARACTERISTICS, ENTITY_CAMERA_CONTROLS)


def _colour(message: Color, key: str, alpha: float = 1.0) -> None:
    r, g, b = COLOURS[key]
    message.r, message.g, message.b, message.a = r / 255.0, g / 255.0, b / 255.0, alpha


def image_annotations(centroids: Any, names: Mapping[int, tuple[str, str]], timestamp_ns: int) -> bytes:
    """A serialized foxglove.ImageAnnotations of one camera's :class:`~crossfield.types.CentroidSet`
    (None: an empty message, which clears the overlay). Positions: OpenCV px + :data:`PIXEL_OFFSET`."""
    message = ImageAnnotations()
    message.timestamp.FromNanoseconds(int(timestamp_ns))
    if centroids is None:
        return message.SerializeToString()
    uv = np.asarray(centroids.uv, dtype=np.float64).reshape(-1, 2)
    area = np.nan_to_num(np.asarray(centroids.area_px, dtype=np.float64).reshape(-1), nan=0.0)
    keep = np.flatnonzero(np.isfinite(uv).all(axis=1))
    found = PointsAnnotation(type=PointsAnnotation.POINTS, thickness=3.0)
    found.timestamp.FromNanoseconds(int(timestamp_ns))
    for i in keep:
        name, role = names.get(int(i), (str(int(i)), "centroid"))
        u, v = float(uv[i, 0]) + PIXEL_OFFSET, float(uv[i, 1]) + PIXEL_OFFSET
        radius = max(2.0 * math.sqrt(max(float(area[i]), 0.0) / math.pi), 6.0)
        circle = message.circles.add(diameter=2.0 * radius, thickness=1.5)
        circle.timestamp.FromNanoseconds(int(timestamp_ns))
        circle.position.x, circle.position.y = u, v
        _colour(circle.outline_color, role)
        _colour(circle.fill_color, role, 0.0)
        point = found.points.add()
        point.x, point.y = u, v
        _colour(found.outline_colors.add(), role)
        text = message.texts.add(text=name, font_size=14.0)
        text.timestamp.FromNanoseconds(int(timestamp_ns))
        text.position.x, text.position.y = u + radius, v - radius
        _colour(text.text_color, role)
        _colour(text.background_color, "centroid", 0.0)
    if len(found.points):
        message.points.append(found)
    rejected = [b for b in centroids.rejected if all(math.isfinite(float(x)) for x in b.uv)]
    if rejected:
        grey = PointsAnnotation(type=PointsAnnotation.POINTS, thickness=6.0)
        grey.timestamp.FromNanoseconds(int(timestamp_ns))
        _colour(grey.outline_color, "rejected")
        for blob in rejected:
            point = grey.points.add()
            point.x, point.y = float(blob.uv[0]) + PIXEL_OFFSET, float(blob.uv[1]) + PIXEL_OFFSET
            text = message.texts.add(text=f"rejected: {blob.reason}", font_size=12.0)
            text.timestamp.FromNanoseconds(int(timestamp_ns))
            text.position.x, text.position.y = point.x + 8.0, point.y + 8.0
            _colour(text.text_color, "rejected")
            _colour(text.background_color, "rejected", 0.0)
        message.points.append(grey)
    return message.SerializeToString()


def _set_xyz(target: Any, xyz_mm: Sequence[float]) -> None:
    target.x, target.y, target.z = (float(c) * _M_PER_MM for c in xyz_mm)


def _entity(update: SceneUpdate, entity_id: str, frame_id: str, timestamp_ns: int) -> Any:
    entity = update.entities.add(id=entity_id, frame_id=frame_id)
    entity.timestamp.FromNanoseconds(int(timestamp_ns))
    return entity


def _spheres(entity: Any, labelled: Sequence[tuple[str, np.ndarray]], key: str, size_key: str) -> None:
    """One sphere and one text per (label, xyz mm)."""
    d = _SPHERE_M[size_key]
    for label, xyz in labelled:
        sphere = entity.spheres.add()
        _set_xyz(sphere.pose.position, xyz)
        sphere.pose.orientation.w = 1.0
        sphere.size.x = sphere.size.y = sphere.size.z = d
        _colour(sphere.color, key)
        text = entity.texts.add(text=str(label), billboard=True, font_size=12.0, scale_invariant=True)
        _set_xyz(text.pose.position, np.asarray(xyz, dtype=np.float64) + [0.0, 0.0, 1e3 * d])
        text.pose.orientation.w = 1.0
        _colour(text.color, key)


def _quaternion_z_to(direction: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) rotating +Z onto the unit ``direction`` (shortest arc)."""
    z = np.array([0.0, 0.0, 1.0])
    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    c = float(z @ d)
    if c < -1.0 + 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    axis = np.cross(z, d)
    w = math.sqrt((1.0 + c) / 2.0)
    x, y, zz = axis / (2.0 * w)
    return (float(x), float(y), float(zz), w)


class FoxgloveOverlay:
    """Builds the overlay messages of one session; keeps the plan, the CMM points and the
    fitted reference lines between the reference import and the pairs."""

    def __init__(self, plan: Any = None) -> None:
        self.plan = plan
        self._cmm: dict[str, np.ndarray] = {}
        self._axes: dict[str, Any] = {}

    def reference(self, reference: Any, timestamp_ns: int) -> bytes:
        """The SceneUpdate of the CMM points and the fitted reference lines (frame ``global``)."""
        from crossfield.geometry import element_probes, fit_reference_element

        plan = self.plan
        controls = set(getattr(plan, "control_ids", ()))
        lines = {spec.id for spec in getattr(plan, "reference_lines", ())}
        control_points, reference_points = [], []
        for p in reference.points:
            if not np.isfinite(p.xyz).all():
                continue
            self._cmm[p.label] = np.asarray(p.xyz, dtype=np.float64)
            if p.label in controls:
                control_points.append((p.label, p.xyz))
            elif not ("." in p.label and p.label.split(".", 1)[0] in lines):
                reference_points.append((p.label, p.xyz))
        update = SceneUpdate()
        _spheres(_entity(update, ENTITY_CONTROLS, FRAME_GLOBAL, timestamp_ns), control_points, "control", "control")
        _spheres(_entity(update, ENTITY_REFERENCE_POINTS, FRAME_GLOBAL, timestamp_ns), reference_points,
                 "reference", "reference")
        for spec in getattr(plan, "reference_lines", ()):
            try:
                fit = fit_reference_element(spec, reference.points)
            except ValueError:
                continue
            self._axes[spec.id] = fit
            point, direction = np.asarray(fit.line.point), np.asarray(fit.line.direction)
            probes = element_probes(spec.id, reference.points)
            along = [float((np.asarray(p.xyz) - point) @ direction) for p in probes]
            lo, hi = (min(along), max(along)) if along else (-50.0, 50.0)
            margin = max(0.1 * (hi - lo), 20.0)
            a, b = point + (lo - margin) * direction, point + (hi + margin) * direction
            entity = _entity(update, ENTITY_LINE.format(id=spec.id), FRAME_GLOBAL, timestamp_ns)
            if fit.radius_mm is not None:
                balls = [float(p.probe_diameter_mm) for p in probes if math.isfinite(float(p.probe_diameter_mm))]
                diameter = 2.0 * float(fit.radius_mm) - (float(np.mean(balls)) if balls else 0.0)
                cylinder = entity.cylinders.add(bottom_scale=1.0, top_scale=1.0)
                _set_xyz(cylinder.pose.position, (a + b) / 2.0)
                q = _quaternion_z_to(direction)
                o = cylinder.pose.orientation
                o.x, o.y, o.z, o.w = q
                cylinder.size.x = cylinder.size.y = diameter * _M_PER_MM
                cylinder.size.z = float(np.linalg.norm(b - a)) * _M_PER_MM
                _colour(cylinder.color, "axis", 0.35)
                label = f"{spec.id} cylinder d {diameter:.3f} mm"
            else:
                label = f"{spec.id} line"
            line = entity.lines.add(type=LinePrimitive.LINE_LIST, thickness=2.0, scale_invariant=True)
            line.pose.orientation.w = 1.0
            for end in (a, b):
                _set_xyz(line.points.add(), end)
            _colour(line.color, "axis")
            text = entity.texts.add(text=f"{label}, fit rms {fit.rms_mm * 1000:.1f} µm", billboard=True,
                                    font_size=12.0, scale_invariant=True)
            _set_xyz(text.pose.position, b)
            text.pose.orientation.w = 1.0
            _colour(text.color, "axis")
        return update.SerializeToString()

    def segment(self, spec_kind: str, a: np.ndarray, b: np.ndarray | None = None,
                line_id: str | None = None) -> np.ndarray | None:
        """The segment (2, 3), mm, global frame, a characteristic measures: point_point a -> b;
        point_line a -> its foot on the fitted axis; depth (global Z of a) a -> (a_x, a_y, 0)."""
        a = np.asarray(a, dtype=np.float64)
        if spec_kind == "point_point" and b is not None:
            return np.array([a, np.asarray(b, dtype=np.float64)])
        if spec_kind == "point_line" and line_id in self._axes:
            point = np.asarray(self._axes[line_id].line.point)
            direction = np.asarray(self._axes[line_id].line.direction)
            return np.array([a, point + ((a - point) @ direction) * direction])
        if spec_kind == "depth":
            return np.array([a, [a[0], a[1], 0.0]])
        return None

    def annotations(self, result: Any, timestamp_ns: int) -> dict[str, bytes]:
        """camera -> the serialized ImageAnnotations of a finished pair (:func:`image_annotations`)."""
        names = centroid_names(result)
        return {
            camera: image_annotations(
                None if result.centroids is None else getattr(result.centroids, camera),
                names.get(camera, {}), timestamp_ns,
            )
            for camera in CAMERAS
        }

    def frame(self, result: Any, timestamp_ns: int) -> bytes:
        """The SceneUpdate of a finished pair: targets, the camera-measured controls, the characteristics."""
        update = SceneUpdate()
        measurement, registration, points = result.measurement, result.registration, result.points
        if measurement is None or registration is None or points is None:
            for entity_id in _PER_PAIR:
                deletion = update.deletions.add(type=SceneEntityDeletion.MATCHING_ID, id=entity_id)
                deletion.timestamp.FromNanoseconds(int(timestamp_ns))
            return update.SerializeToString()
        targets = {str(k): np.asarray(v, dtype=np.float64) for k, v in measurement.target_points.items()}
        _spheres(_entity(update, ENTITY_TARGETS, FRAME_GLOBAL, timestamp_ns),
                 [(k, v) for k, v in targets.items() if np.isfinite(v).all()], "target", "target")
        corr = registration.correspondence
        camera_xyz = np.asarray(points.xyz, dtype=np.float64).reshape(-1, 3)
        _spheres(_entity(update, ENTITY_CAMERA_CONTROLS, FRAME_CAMERA, timestamp_ns),
                 [(str(cid), camera_xyz[int(i)]) for cid, i in zip(corr.control_ids, corr.camera_index)
                  if 0 <= int(i) < len(camera_xyz)], "camera_control", "camera_control")
        entity = _entity(update, ENTITY_CHARACTERISTICS, FRAME_GLOBAL, timestamp_ns)
        known = {**self._cmm, **targets}
        for c in measurement.characteristics:
            elements = list(c.elements)
            if not elements or elements[0] not in known or not math.isfinite(float(c.measured_mm)):
                continue
            second = elements[1] if len(elements) > 1 else None
            segment = self.segment(c.kind, known[elements[0]], known.get(second) if second else None,
                                   second if c.kind == "point_line" else None)
            if segment is None:
                continue
            key = "pass" if c.passed else "fail"
            line = entity.lines.add(type=LinePrimitive.LINE_LIST, thickness=2.0, scale_invariant=True)
            line.pose.orientation.w = 1.0
            for end in segment:
                _set_xyz(line.points.add(), end)
            _colour(line.color, key)
            text = entity.texts.add(text=f"{c.name} {float(c.measured_mm):.4f} mm ({float(c.deviation_mm):+.4f})",
                                    billboard=True, font_size=12.0, scale_invariant=True)
            _set_xyz(text.pose.position, segment.mean(axis=0))
            text.pose.orientation.w = 1.0
            _colour(text.color, key)
        return update.SerializeToString()
