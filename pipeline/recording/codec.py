"""Encoders and decoders of every message and document of a session recording.

Encoders (writing): the Foxglove protobuf messages (``foxglove.RawImage``,
``CameraCalibration``, ``FrameTransforms``, ``PointCloud``, ``Log``), the
JSON documents of the stage outputs (``*_doc``), the metadata records and
the attachments' contents. Decoders (reading): the same, back into the
pipeline's data types (:mod:`crossfield.types`), with a
:class:`RecordingError` naming the message at fault. Names of topics and
schemas: :mod:`crossfield.recording.layout`.

Units: the JSON documents carry the project's units (mm, radians,
pixels); ``foxglove.PointCloud`` and ``foxglove.FrameTransforms`` carry
**metres** (the Foxglove convention), converted from mm on encoding.
JSON floats are written by ``repr`` so that they read back bit for bit;
a non-finite value is written as null (:mod:`crossfield.jsonable`) and
read back as NaN.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import math
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Any

import cv2
import numpy as np
import tomli_w
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap_protobuf.schema import build_file_descriptor_set
from scipy.spatial.transform import Rotation

from crossfield.errors import RecordingError
from crossfield.jsonable import ints, plain, real, reals
from crossfield.recording.layout import FRAME_CAMERA, FRAME_GLOBAL, JSON_SCHEMAS, META_JSON
from crossfield.stages import LinkEvent
from crossfield.types import (
    BudgetTerm,
    CameraIntrinsics,
    CameraPoints,
    CentroidSet,
    CharacteristicResult,
    Correspondence,
    GroundTruth,
    Line3D,
    Measurement,
    ProbedPoint,
    ReferenceData,
    Registration,
    RegistrationConsistency,
    RejectedBlob,
    RigidFit,
    StereoCalibration,
)

_MM_PER_M = 1000.0
_LOG_LEVELS = {
    "debug": Log.DEBUG,
    "info": Log.INFO,
    "warning": Log.WARNING,
    "warn": Log.WARNING,
    "error": Log.ERROR,
    "critical": Log.FATAL,
    "fatal": Log.FATAL,
}
#: foxglove.Log levels (enum values) -> the pipeline's level names.
FOXGLOVE_LEVELS = {0: "info", 1: "debug", 2: "info", 3: "warning", 4: "error", 5: "critical"}
_RAW_IMAGE_DATA_TAG = bytes([(RawImage.DESCRIPTOR.fields_by_name["data"].number << 3) | 2])
#: foxglove.RawImage encodings crossfield writes -> pixel dtype.
IMAGE_DTYPES = {"mono16": np.dtype("<u2"), "mono8": np.dtype("u1")}


# --------------------------------------------------------------------------
# Schemas (hashable; a writer registers each once)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class SchemaSpec:
    """An MCAP schema: name, encoding (``protobuf`` / ``jsonschema``) and data."""

    name: str
    encoding: str
    data: bytes


@functools.cache
def protobuf_schema(message_class: Any) -> SchemaSpec:
    """The MCAP schema of a protobuf message class (a FileDescriptorSet)."""
    fds = build_file_descriptor_set(message_class)
    return SchemaSpec(message_class.DESCRIPTOR.full_name, "protobuf", fds.SerializeToString())


def load_json_schema(name: str) -> dict[str, Any]:
    """The JSON Schema (as data) of the JSON schema ``name`` (e.g. ``crossfield.Registration``)."""
    return json.loads(_json_schema_text(name))


@functools.cache
def _json_schema_text(name: str) -> str:
    try:
        filename = JSON_SCHEMAS[name]
    except KeyError:
        raise KeyError(f"unknown JSON schema {name!r}; known: {', '.join(JSON_SCHEMAS)}") from None
    return resources.files("crossfield.recording").joinpath("schemas", filename).read_text(encoding="utf-8")


@functools.cache
def json_schema(name: str) -> SchemaSpec:
    """The MCAP schema (``jsonschema``) of the JSON schema ``name``."""
    return SchemaSpec(name, "jsonschema", _json_schema_text(name).encode("utf-8"))


# --------------------------------------------------------------------------
# JSON (no NaN: non-finite -> null; see crossfield.jsonable)
# --------------------------------------------------------------------------


def dump_json(doc: Any) -> bytes:
    """Compact strict JSON (floats by repr, so they read back bit for bit)."""
    return json.dumps(doc, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode("utf-8")


def utc_text(timestamp_ns: int) -> str:
    seconds, nanos = divmod(int(timestamp_ns), 1_000_000_000)
    moment = _dt.datetime.fromtimestamp(seconds, tz=_dt.UTC)
    return moment.strftime("%Y-%m-%dT%H:%M:%S") + f".{nanos:09d}Z"


def toml_text(data: Mapping[str, Any]) -> str:
    """``data`` (a mapping of tables, as ``Config.to_dict()``) as TOML text
    (tomli-w); ``tomllib.loads`` of the result gives ``data`` back."""
    try:
        return tomli_w.dumps(data)
    except TypeError as exc:
        raise TypeError(f"cannot write the config as TOML: {exc}") from None


# --------------------------------------------------------------------------
# Foxglove protobuf messages
# --------------------------------------------------------------------------


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        low, n = n & 0x7F, n >> 7
        if n:
            out.append(low | 0x80)
        else:
            out.append(low)
            return bytes(out)


def image_encoding(image: np.ndarray) -> str:
    """The foxglove.RawImage encoding of a 2-D image array (mono8 / mono16)."""
    if image.ndim != 2:
        raise RecordingError(f"cannot record a {image.ndim}-D image; expected (height, width)")
    if image.dtype.kind == "u" and image.dtype.itemsize == 2:
        return "mono16"
    if image.dtype.kind == "u" and image.dtype.itemsize == 1:
        return "mono8"
    raise RecordingError(f"cannot record an image of dtype {image.dtype}; expected uint16 or uint8")


def raw_image_message(image: np.ndarray, frame_id: str, timestamp_ns: int) -> bytes:
    """A serialized foxglove.RawImage holding ``image`` (H, W) losslessly.

    uint16 -> ``mono16`` (16-bit little-endian words, as foxglove specifies),
    uint8 -> ``mono8``; ``step`` = bytes per row, no padding. The header
    fields are serialized by protobuf and the pixel bytes appended as the
    ``data`` field (protobuf allows fields in any order), so the image is
    copied once, not three times.
    """
    encoding = image_encoding(image)
    if image.dtype.byteorder == ">" or (image.dtype.byteorder == "=" and sys.byteorder == "big"):
        image = image.astype(image.dtype.newbyteorder("<"))
    if not image.flags.c_contiguous:
        image = np.ascontiguousarray(image)
    height, width = image.shape
    header = RawImage(
        frame_id=frame_id, width=width, height=height, encoding=encoding, step=width * image.itemsize
    )
    header.timestamp.FromNanoseconds(int(timestamp_ns))
    return b"".join(
        (header.SerializeToString(), _RAW_IMAGE_DATA_TAG, _varint(image.nbytes), memoryview(image).cast("B"))
    )


def distortion_model(dist_coeffs: np.ndarray) -> tuple[str, list[float]]:
    """Foxglove distortion model name and parameters for OpenCV coefficients.

    4 or 5 coefficients -> ``plumb_bob`` (k1 k2 p1 p2 k3), 8 ->
    ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6). Longer OpenCV models
    (thin prism, tilt) have no Foxglove equivalent: their first 8 are given
    as ``rational_polynomial``; the exact calibration is attached in full
    (``calibration.yml``).
    """
    d = [float(v) for v in np.asarray(dist_coeffs, dtype=np.float64).ravel()]
    if len(d) <= 5:
        return "plumb_bob", d + [0.0] * (5 - len(d))
    return "rational_polynomial", (d + [0.0] * 8)[:8]


def camera_calibration_message(intrinsics: CameraIntrinsics, frame_id: str, timestamp_ns: int) -> bytes:
    """A serialized foxglove.CameraCalibration of one (unrectified) camera.

    K = camera_matrix (pixels), D = distortion, R = identity and P = [K | 0]:
    the images are recorded raw (distorted, unrectified), each camera in its
    own frame; the stereo geometry is on ``/tf`` (upper -> lower).
    """
    K = np.asarray(intrinsics.camera_matrix, dtype=np.float64)
    model, D = distortion_model(intrinsics.dist_coeffs)
    P = np.hstack([K, np.zeros((3, 1))])
    width, height = intrinsics.image_size
    message = CameraCalibration(
        frame_id=frame_id,
        width=int(width),
        height=int(height),
        distortion_model=model,
        D=D,
        K=K.ravel().tolist(),
        R=np.eye(3).ravel().tolist(),
        P=P.ravel().tolist(),
    )
    message.timestamp.FromNanoseconds(int(timestamp_ns))
    return message.SerializeToString()


@dataclass(frozen=True)
class FramePose:
    """The pose of ``child`` in ``parent``: ``p_parent = R @ p_child + t`` (t in mm)."""

    parent: str
    child: str
    R: np.ndarray
    t_mm: np.ndarray


def frame_transforms_message(poses: Iterable[FramePose], timestamp_ns: int) -> bytes:
    """A serialized foxglove.FrameTransforms; translations converted mm -> m.

    Foxglove's FrameTransform gives the child frame's origin (translation)
    and orientation (rotation) in the parent frame, i.e. it maps child
    coordinates into the parent: ``p_parent = R @ p_child + t``.
    """
    message = FrameTransforms()
    for pose in poses:
        tf = message.transforms.add(parent_frame_id=pose.parent, child_frame_id=pose.child)
        tf.timestamp.FromNanoseconds(int(timestamp_ns))
        x, y, z = (np.asarray(pose.t_mm, dtype=np.float64) / _MM_PER_M).tolist()
        tf.translation.x, tf.translation.y, tf.translation.z = x, y, z
        qx, qy, qz, qw = quaternion_xyzw(pose.R)
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = qx, qy, qz, qw
    return message.SerializeToString()


def quaternion_xyzw(R: np.ndarray) -> list[float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix, w >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return (-q if q[3] < 0 else q).tolist()


def upper_to_lower_pose(calibration: StereoCalibration) -> FramePose:
    """The lower camera's pose in the upper camera frame.

    The calibration maps upper into lower, ``p_lower = R @ p_upper + t``
    (paper Formula (4)); the pose of child ``lower`` in parent ``upper`` is
    the inverse: ``p_upper = R.T @ p_lower - R.T @ t``.
    """
    R = np.asarray(calibration.R_lower_upper, dtype=np.float64)
    t = np.asarray(calibration.t_lower_upper, dtype=np.float64)
    return FramePose("upper", "lower", R.T, -R.T @ t)


_XYZ_FIELDS = [
    PackedElementField(name=n, offset=4 * i, type=PackedElementField.FLOAT32) for i, n in enumerate("xyz")
]


def point_cloud_message(xyz_mm: np.ndarray, frame_id: str, timestamp_ns: int) -> bytes:
    """A serialized foxglove.PointCloud: float32 x, y, z in **metres** (from mm).

    The pose is set to identity explicitly: ``rerun mcap convert`` turns it
    into InstancePoses3D and writes null (failing ``rerun rrd verify``) when
    it is absent.
    """
    xyz_m = (np.asarray(xyz_mm, dtype=np.float64).reshape(-1, 3) / _MM_PER_M).astype("<f4")
    message = PointCloud(frame_id=frame_id, point_stride=12, fields=_XYZ_FIELDS, data=xyz_m.tobytes())
    message.timestamp.FromNanoseconds(int(timestamp_ns))
    message.pose.position.x = 0.0
    message.pose.position.SetInParent()
    message.pose.orientation.w = 1.0
    return message.SerializeToString()


def log_message(level: str, text: str, timestamp_ns: int, name: str = "crossfield") -> bytes:
    message = Log(level=_LOG_LEVELS.get(str(level).lower(), Log.UNKNOWN), message=str(text), name=name)
    message.timestamp.FromNanoseconds(int(timestamp_ns))
    return message.SerializeToString()


# --------------------------------------------------------------------------
# JSON documents of the stage outputs
# --------------------------------------------------------------------------


def centroids_doc(centroids: CentroidSet) -> dict[str, Any]:
    return {
        "sequence": int(centroids.sequence),
        "camera": centroids.camera,
        "method": centroids.method,
        "count": len(centroids),
        "uv": reals(centroids.uv),
        "sigma_uv": reals(centroids.sigma_uv),
        "area_px": reals(centroids.area_px),
        "roundness": reals(centroids.roundness),
        "peak": reals(centroids.peak),
        "rejected": [{"uv": reals(b.uv), "reason": str(b.reason)} for b in centroids.rejected],
    }


def camera_points_doc(points: CameraPoints) -> dict[str, Any]:
    return {
        "sequence": int(points.sequence),
        "method": points.method,
        "frame": FRAME_CAMERA,
        "units": "mm",
        "count": len(points),
        "xyz_mm": reals(points.xyz),
        "sigma_xyz_mm": reals(points.sigma_xyz),
        "upper_index": ints(points.upper_index),
        "lower_index": ints(points.lower_index),
        "residual_px": reals(points.residual_px),
        "rejected": [str(r) for r in points.rejected],
    }


def registration_doc(registration: Any) -> dict[str, Any]:
    fit, corr = registration.fit, registration.correspondence
    residuals = np.asarray(fit.residuals, dtype=np.float64).reshape(-1, 3)
    norms = np.linalg.norm(residuals, axis=1)
    return {
        "sequence": int(registration.sequence),
        "method": fit.method,
        "R_global_camera": reals(fit.R),
        "t_global_camera_mm": reals(fit.t),
        "quaternion_xyzw": reals(quaternion_xyzw(fit.R)),
        "scale": real(fit.scale),
        "rms_mm": real(fit.rms_mm),
        "residuals": [
            {
                "control_id": str(cid),
                "camera_index": int(ci),
                "residual_mm": reals(residuals[k]) if k < len(residuals) else [None, None, None],
                "norm_mm": real(norms[k]) if k < len(norms) else None,
            }
            for k, (cid, ci) in enumerate(zip(corr.control_ids, corr.camera_index))
        ],
        "unmatched_camera": ints(corr.unmatched_camera),
        "unmatched_control": [str(c) for c in corr.unmatched_control],
    }


def measurement_doc(measurement: Any) -> dict[str, Any]:
    return {
        "sequence": int(measurement.sequence),
        "characteristics": [
            {
                "name": c.name,
                "kind": c.kind,
                "elements": [str(e) for e in c.elements],
                "measured_mm": real(c.measured_mm),
                "nominal_mm": real(c.nominal_mm),
                "tolerance_mm": real(c.tolerance_mm),
                "deviation_mm": real(c.deviation_mm),
                "passed": bool(c.passed),
                "uncertainty_mm": real(c.uncertainty_mm),
                "actual_mm": real(c.actual_mm),
                "error_mm": real(c.error_mm),
                "budget": [
                    {"source": t.source, "u": real(t.u), "unit": t.unit, "sensitivity": real(t.sensitivity),
                     "u_mm": real(t.u_mm),
                     **({"dof": float(t.dof)} if math.isfinite(getattr(t, "dof", math.inf)) else {})}
                    for t in c.budget
                ],
            }
            for c in measurement.characteristics
        ],
        "target_points_mm": {str(k): reals(v) for k, v in measurement.target_points.items()},
        "missing_targets": [str(t) for t in measurement.missing_targets],
        "consistency": consistency_doc(measurement.consistency),
    }


def consistency_doc(c: RegistrationConsistency | None) -> dict[str, Any] | None:
    """A pair's :class:`RegistrationConsistency` as plain data (None stays None)."""
    if c is None:
        return None
    return {
        "observed_ss_mm2": real(c.observed_ss_mm2),
        "expected_camera_ss_mm2": real(c.expected_camera_ss_mm2),
        "expected_cmm_ss_mm2": real(c.expected_cmm_ss_mm2),
        "dof": int(c.dof),
        "expected_residual_mm": {str(k): real(v) for k, v in c.expected_residual_mm.items()},
        "pose_cov_camera": None if c.pose_cov_camera is None else reals(c.pose_cov_camera),
        "pose_cov_cmm": None if c.pose_cov_cmm is None else reals(c.pose_cov_cmm),
        "epipolar_chi2": real(c.epipolar_chi2),
        "epipolar_count": int(c.epipolar_count),
    }


def consistency(doc: Mapping[str, Any] | None) -> RegistrationConsistency | None:
    """A recorded ``consistency`` document (:func:`consistency_doc`), or None."""
    if not doc:
        return None

    def matrix(value: Any) -> np.ndarray | None:
        return None if value is None else _array(value, (6, 6))

    return RegistrationConsistency(
        observed_ss_mm2=_nan(doc["observed_ss_mm2"]),
        expected_camera_ss_mm2=_nan(doc["expected_camera_ss_mm2"]),
        expected_cmm_ss_mm2=_nan(doc["expected_cmm_ss_mm2"]),
        dof=int(doc["dof"]),
        expected_residual_mm={str(k): _nan(v) for k, v in doc.get("expected_residual_mm", {}).items()},
        pose_cov_camera=matrix(doc.get("pose_cov_camera")),
        pose_cov_cmm=matrix(doc.get("pose_cov_cmm")),
        epipolar_chi2=_nan(doc.get("epipolar_chi2", 0.0)),
        epipolar_count=int(doc.get("epipolar_count", 0)),
    )


def reference_doc(reference: Any) -> dict[str, Any]:
    return {
        "source": str(reference.source),
        "count": len(reference.points),
        "points": [
            {
                "label": p.label,
                "xyz_mm": reals(p.xyz),
                "sigma_mm": real(p.sigma_mm),
                "device_sequence": int(p.device_sequence),
                "device_time_s": real(p.device_time_s),
                "probe_vector": reals(p.probe_vector),
                "probe_diameter_mm": real(p.probe_diameter_mm),
            }
            for p in reference.points
        ],
        "problems": [str(p) for p in reference.problems],
    }


def frame_status_doc(result: Any) -> dict[str, Any]:
    return {
        "sequence": int(result.sequence),
        "timestamp_ns": int(result.timestamp_ns),
        "error": None if result.error is None else str(result.error),
        "stages": {
            "centroids": result.centroids is not None,
            "points": result.points is not None,
            "registration": result.registration is not None,
            "measurement": result.measurement is not None,
        },
    }


def calibration_yaml(calibration: StereoCalibration) -> str:
    """The stereo calibration as OpenCV FileStorage YAML (the ``calibration.yml``
    attachment), written by :mod:`crossfield.camera.calibration_io`: the keys OpenCV's
    ``stereo_calib`` sample writes (M1 D1 M2 D2 R T, 1 = upper, 2 = lower,
    plus R1 R2 P1 P2 Q from ``cv2.stereoRectify``) and the image size;
    :func:`crossfield.camera.calibration_io.stereo_calibration_from_yaml` reads it back."""
    from crossfield.camera.calibration_io import stereo_calibration_to_yaml

    try:
        return stereo_calibration_to_yaml(calibration)
    except cv2.error:  # a calibration stereoRectify cannot handle: record it without R1..Q
        return stereo_calibration_to_yaml(calibration, rectification=False)


def ground_truth_doc(truth: GroundTruth) -> dict[str, Any]:
    return {
        "note": "SIMULATOR GROUND TRUTH: the true geometry the simulator rendered and probed. "
        "It is not a measurement; it exists only for simulated sessions.",
        "units": "mm",
        "frame": FRAME_GLOBAL,
        "points_global_mm": {str(k): reals(v) for k, v in truth.points_global.items()},
        "lines_global": {
            str(k): {"point_mm": reals(line.point), "direction": reals(line.direction)}
            for k, line in truth.lines_global.items()
        },
        "R_global_camera": reals(truth.R_global_camera),
        "t_global_camera_mm": reals(truth.t_global_camera),
    }


def metadata_record(doc: Mapping[str, Any], flat: Mapping[str, Any] | None = None) -> dict[str, str]:
    """An MCAP metadata record (str -> str): readable flat keys plus ``json``,
    the exact document (what :meth:`crossfield.recording.reader.Recording.metadata_doc` returns)."""
    record = {}
    for k, v in (flat if flat is not None else doc).items():
        record[str(k)] = v if isinstance(v, str) else json.dumps(plain(v), ensure_ascii=False)
    record[META_JSON] = json.dumps(plain(doc), ensure_ascii=False, allow_nan=False)
    return record


# ==========================================================================
# Decoders
# ==========================================================================


def raw_image_pixels(message: Any, where: str) -> np.ndarray:
    """(H, W) pixels of a decoded foxglove.RawImage (mono16 little-endian or
    mono8), in native byte order; ``where`` names the message in errors."""
    dtype = IMAGE_DTYPES.get(message.encoding)
    if dtype is None:
        raise RecordingError(f"{where}: image encoding {message.encoding!r}; crossfield reads mono16 and mono8")
    width, height = int(message.width), int(message.height)
    if message.step != width * dtype.itemsize or len(message.data) != height * message.step:
        raise RecordingError(
            f"{where}: {len(message.data)} bytes of pixel data for {width} x {height} {message.encoding} "
            f"with step {message.step}"
        )
    pixels = np.frombuffer(message.data, dtype=dtype).reshape(height, width)
    return pixels.astype(pixels.dtype.newbyteorder("="), copy=False)


def decode_image(data: bytes, where: str) -> tuple[np.ndarray, int]:
    """(H, W) pixels and capture time (ns) of a serialized foxglove.RawImage."""
    try:
        message = RawImage.FromString(data)
    except Exception as exc:  # noqa: BLE001 - protobuf raises several types
        raise RecordingError(f"{where}: not a foxglove.RawImage: {exc}") from None
    return raw_image_pixels(message, where), message.timestamp.ToNanoseconds()


def decode_log(data: bytes, where: str) -> tuple[str, str]:
    """(level name, text) of a serialized foxglove.Log."""
    try:
        message = Log.FromString(data)
    except Exception as exc:  # noqa: BLE001 - protobuf raises several types
        raise RecordingError(f"{where}: not a foxglove.Log: {exc}") from None
    return FOXGLOVE_LEVELS.get(int(message.level), "info"), message.message


def decode_json(data: bytes, where: str) -> Any:
    """The JSON document of a JSON message; :class:`RecordingError` naming ``where``."""
    try:
        return json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{where}: not valid JSON: {exc}") from None


def _nan(value: Any) -> float:
    """JSON null (not finite when recorded) -> NaN."""
    return math.nan if value is None else float(value)


def _array(values: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    out = np.array(
        [[_nan(v) for v in row] if isinstance(row, list) else _nan(row) for row in values], dtype=np.float64
    )
    return out.reshape(shape) if shape is not None else out


def centroid_set(doc: Mapping[str, Any]) -> CentroidSet:
    """A ``/centroids/<camera>`` document (``crossfield.CentroidSet``) as a :class:`CentroidSet`."""
    n = len(doc["uv"])
    return CentroidSet(
        camera=str(doc["camera"]),
        sequence=int(doc["sequence"]),
        uv=_array(doc["uv"], (n, 2)),
        sigma_uv=_array(doc["sigma_uv"], (n, 2)),
        area_px=_array(doc["area_px"], (n,)),
        roundness=_array(doc["roundness"], (n,)),
        peak=_array(doc["peak"], (n,)),
        rejected=tuple(
            RejectedBlob((_nan(b["uv"][0]), _nan(b["uv"][1])), str(b["reason"]))
            for b in doc.get("rejected", ())
        ),
        method=str(doc.get("method", "")),
    )


def camera_points(doc: Mapping[str, Any]) -> CameraPoints:
    """A ``/points/camera/json`` document (``crossfield.CameraPoints``)."""
    n = len(doc["xyz_mm"])
    return CameraPoints(
        sequence=int(doc["sequence"]),
        xyz=_array(doc["xyz_mm"], (n, 3)),
        sigma_xyz=_array(doc["sigma_xyz_mm"], (n, 3)),
        upper_index=np.array(doc["upper_index"], dtype=np.int64),
        lower_index=np.array(doc["lower_index"], dtype=np.int64),
        residual_px=_array(doc["residual_px"], (n,)),
        rejected=tuple(str(r) for r in doc.get("rejected", ())),
        method=str(doc.get("method", "")),
    )


def registration(doc: Mapping[str, Any]) -> Registration:
    """A ``/registration`` document (``crossfield.Registration``)."""
    rows = doc["residuals"]
    fit = RigidFit(
        R=_array(doc["R_global_camera"], (3, 3)),
        t=_array(doc["t_global_camera_mm"], (3,)),
        residuals=_array([r["residual_mm"] for r in rows], (len(rows), 3)),
        rms_mm=_nan(doc["rms_mm"]),
        method=str(doc.get("method", "")),
        scale=1.0 if doc.get("scale") is None else float(doc["scale"]),
    )
    correspondence = Correspondence(
        camera_index=np.array([int(r["camera_index"]) for r in rows], dtype=np.int64),
        control_ids=tuple(str(r["control_id"]) for r in rows),
        unmatched_camera=tuple(int(i) for i in doc.get("unmatched_camera", ())),
        unmatched_control=tuple(str(c) for c in doc.get("unmatched_control", ())),
    )
    return Registration(int(doc["sequence"]), fit, correspondence)


def measurement(doc: Mapping[str, Any]) -> Measurement:
    """A ``/measurement`` document (``crossfield.Measurement``)."""

    def optional(value: Any) -> float | None:
        return None if value is None else float(value)

    return Measurement(
        sequence=int(doc["sequence"]),
        characteristics=tuple(
            CharacteristicResult(
                name=str(c["name"]),
                kind=str(c["kind"]),
                measured_mm=_nan(c["measured_mm"]),
                nominal_mm=_nan(c["nominal_mm"]),
                tolerance_mm=_nan(c["tolerance_mm"]),
                deviation_mm=_nan(c["deviation_mm"]),
                passed=bool(c["passed"]),
                uncertainty_mm=optional(c.get("uncertainty_mm")),
                actual_mm=optional(c.get("actual_mm")),
                error_mm=optional(c.get("error_mm")),
                elements=tuple(str(e) for e in c.get("elements", ())),
                budget=tuple(  # absent in recordings made before budgets were recorded
                    BudgetTerm(str(t["source"]), _nan(t["u"]), str(t["unit"]), _nan(t["sensitivity"]),
                               _nan(t["u_mm"]), float(t["dof"]) if "dof" in t else math.inf)
                    for t in c.get("budget", ())
                ),
            )
            for c in doc["characteristics"]
        ),
        target_points={str(k): tuple(_nan(v) for v in xyz) for k, xyz in doc["target_points_mm"].items()},
        missing_targets=tuple(str(t) for t in doc.get("missing_targets", ())),
        consistency=consistency(doc.get("consistency")),
    )


def reference_data(doc: Mapping[str, Any]) -> ReferenceData:
    """A ``/reference`` document (``crossfield.ReferenceData``)."""
    return ReferenceData(
        points=tuple(
            ProbedPoint(
                label=str(p["label"]),
                xyz=_array(p["xyz_mm"], (3,)),
                sigma_mm=_nan(p["sigma_mm"]),
                device_sequence=int(p.get("device_sequence", -1)),
                device_time_s=_nan(p.get("device_time_s")),
                probe_vector=_array(p.get("probe_vector") or [0.0, 0.0, 0.0], (3,)),
                probe_diameter_mm=_nan(p.get("probe_diameter_mm")),
            )
            for p in doc["points"]
        ),
        problems=tuple(str(p) for p in doc.get("problems", ())),
        source=str(doc.get("source", "")),
    )


def ground_truth_from_doc(doc: Mapping[str, Any]) -> GroundTruth:
    """The :class:`GroundTruth` of a ``simulator_ground_truth.json`` attachment (exact floats)."""
    return GroundTruth(
        points_global={k: np.array(v, dtype=np.float64) for k, v in doc["points_global_mm"].items()},
        lines_global={
            k: Line3D(np.array(v["point_mm"], dtype=np.float64), np.array(v["direction"], dtype=np.float64))
            for k, v in doc["lines_global"].items()
        },
        R_global_camera=np.array(doc["R_global_camera"], dtype=np.float64),
        t_global_camera=np.array(doc["t_global_camera_mm"], dtype=np.float64),
    )


def decode_link_event(data: bytes, where: str) -> LinkEvent:
    """A recorded link event of the CMM line (``{"event": "down"|"up", "detail": str}``,
    UTF-8 JSON on the ``/cmm/raw`` link-events channel), or a RecordingError naming ``where``."""
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError):
        doc = None
    if not (isinstance(doc, dict) and doc.get("event") in ("down", "up") and isinstance(doc.get("detail"), str)):
        raise RecordingError(f'{where}: not a link event ({{"event": "down"|"up", "detail": ...}})')
    return LinkEvent(doc["event"], doc["detail"])
