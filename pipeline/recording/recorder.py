"""The MCAP session recorder: an observer plugin writing one ``session.mcap``.

Layout (``docs/recording.md``): raw inputs (both camera images, the exact
serial bytes), every stage output, the log, and the session's facts
(config, plugins, packages, plan, calibration) in one MCAP file. Where a
Foxglove schema exists it is used with protobuf encoding, so Foxglove and
Rerun (``rerun session.mcap``, ``rerun mcap convert``) display the data
without code of ours; the stage results are JSON with a JSON Schema
(``pipeline/schemas/*.schema.json``).

Units: the JSON messages carry the project's units (mm, radians, pixels);
the Foxglove geometry messages (``foxglove.PointCloud``,
``foxglove.FrameTransforms``) carry **metres**, the Foxglove convention,
converted from mm on writing.

Speed and crash safety: images are written uncompressed (lossless
``mono16``, little-endian) with one copy into the protobuf message; the
MCAP writer runs in a background thread so that its copies, CRCs and the
file write overlap with the pipeline. Each image closes its chunk, and
the open chunk is flushed to the file at the end of every frame and at
least every ``flush_interval_s``, so a killed session loses at most the
frame in progress (and the messages still queued for the writer, at most
``queue_size``).
"""

from __future__ import annotations

import atexit
import datetime as _dt
import functools
import hashlib
import json
import queue
import sys
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata, resources
from pathlib import Path
from typing import Any, Self

import cv2
import numpy as np
import tomli_w
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
from scipy.spatial.transform import Rotation

from crossfield.errors import RecordingError
from crossfield.hookspecs import hookimpl
from crossfield.recording.integrity import TOPIC_INTEGRITY, IntegrityChain
from crossfield.jsonable import ints, plain, real, reals
from crossfield.types import CAMERAS, CameraIntrinsics, CameraPoints, CentroidSet, GroundTruth, StereoCalibration

#: Identifies this layout; written into the ``crossfield.session`` metadata.
RECORDING_FORMAT = "crossfield-mcap/1"

# ---- topics ---------------------------------------------------------------

TOPIC_IMAGE = "/camera/{camera}/image"
TOPIC_CALIBRATION = "/camera/{camera}/calibration"
TOPIC_TF = "/tf"
TOPIC_POINTS_CAMERA = "/points/camera"
TOPIC_POINTS_REFERENCE = "/points/reference"
TOPIC_POINTS_GLOBAL = "/points/global"
#: Suffix of the JSON twin of each point cloud topic (ids and uncertainties, mm).
JSON_TWIN = "/json"
TOPIC_CMM_RAW = "/cmm/raw"
TOPIC_CENTROIDS = "/centroids/{camera}"
TOPIC_REGISTRATION = "/registration"
TOPIC_MEASUREMENT = "/measurement"
TOPIC_REFERENCE = "/reference"
TOPIC_FRAMES = "/frames"
TOPIC_REPORT = "/report"
TOPIC_LOG = "/log"

#: Coordinate frame ids (foxglove ``frame_id`` / ``parent_frame_id`` / ``child_frame_id``).
FRAME_GLOBAL = "global"

#: JSON schema name -> file in ``pipeline/schemas``.
JSON_SCHEMAS: dict[str, str] = {
    "crossfield.CentroidSet": "centroids.schema.json",
    "crossfield.CameraPoints": "camera_points.schema.json",
    "crossfield.ReferencePoints": "reference_points.schema.json",
    "crossfield.GlobalPoints": "global_points.schema.json",
    "crossfield.Registration": "registration.schema.json",
    "crossfield.Measurement": "measurement.schema.json",
    "crossfield.ReferenceData": "reference.schema.json",
    "crossfield.FrameStatus": "frame_status.schema.json",
    "crossfield.Report": "report.schema.json",
    "crossfield.Integrity": "integrity.schema.json",
}

#: Message encoding of ``/cmm/raw`` (schema-less: the bytes as read).
RAW_ENCODING = "application/octet-stream"
#: Channel metadata ``content`` of the ``/cmm/raw`` channel that holds the
#: line's link events (UTF-8 JSON ``{"event": "down"|"up", "detail": ...}``).
LINK_EVENTS = "link-events"

#: Chunk compression by name. "none" is the default: lz4 costs ~9 ms and zstd
#: ~11 ms of CPU per 4 MB image (ratio 0.68 and 0.44 on simulated 12-bit
#: images), more than a 2-core station can spare at 60 pairs/s; compression
#: pays only where the disk, not the CPU, is the limit.
COMPRESSIONS = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}

#: Each image (4 MB for 1626 x 1236 mono16) is larger than this, so it closes
#: its chunk: chunks stay small (crash safety) and the writer never re-grows a
#: multi-image buffer (measured: 16 MiB chunks cost 2x the CPU of 1 MiB ones).
DEFAULT_CHUNK_SIZE = 1 << 20

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
_RAW_IMAGE_DATA_TAG = bytes([(RawImage.DESCRIPTOR.fields_by_name["data"].number << 3) | 2])


# --------------------------------------------------------------------------
# Channel and schema specs (hashable; registered lazily by the writer)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class SchemaSpec:
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelSpec:
    topic: str
    message_encoding: str
    schema: SchemaSpec | None
    metadata: tuple[tuple[str, str], ...] = ()


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
    return SchemaSpec(name, "jsonschema", _json_schema_text(name).encode("utf-8"))


@functools.lru_cache(maxsize=256)
def _protobuf_channel(
    topic: str, message_class: Any, metadata_: tuple[tuple[str, str], ...] = ()
) -> ChannelSpec:
    return ChannelSpec(topic, "protobuf", protobuf_schema(message_class), metadata_)


@functools.lru_cache(maxsize=256)
def _json_channel(topic: str, schema_name: str) -> ChannelSpec:
    return ChannelSpec(topic, "json", json_schema(schema_name))


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
        "frame": "upper",
        "units": "mm",
        "count": len(points),
        "xyz_mm": reals(points.xyz),
        "sigma_xyz_mm": reals(points.sigma_xyz),
        "upper_index": ints(points.upper_index),
        "lower_index": ints(points.lower_index),
        "residual_px": reals(points.residual_px),
        "rejected": [str(r) for r in points.rejected],
    }


def global_points(points: CameraPoints, registration: Any) -> tuple[np.ndarray, np.ndarray]:
    """Camera points of a frame in the global frame, with propagated sigmas (mm).

    ``p_g = scale * R @ p_c + t`` (the registration, Formulas (5)-(9));
    ``var_g = (scale R)^2 @ var_c`` per axis (axes taken as independent; the
    registration's own uncertainty is not included).
    """
    fit = registration.fit
    xyz = fit.apply(points.xyz).reshape(-1, 3)
    A = float(fit.scale) * np.asarray(fit.R, dtype=np.float64)
    sigma = np.sqrt((np.asarray(points.sigma_xyz, dtype=np.float64) ** 2) @ (A**2).T).reshape(-1, 3)
    return xyz, sigma


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
            }
            for c in measurement.characteristics
        ],
        "target_points_mm": {str(k): reals(v) for k, v in measurement.target_points.items()},
        "missing_targets": [str(t) for t in measurement.missing_targets],
    }


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


def machine_info() -> dict[str, Any]:
    """The machine a session runs on (the ``crossfield.machine`` metadata record)."""
    import os
    import platform
    import socket

    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "hostname": socket.gethostname(),
        "platform": platform.platform(),
        "system": platform.system(),
        "release": platform.release(),
        "machine": platform.machine(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
    }


def _crossfield_version(packages: Mapping[str, str]) -> str:
    if packages.get("crossfield"):
        return str(packages["crossfield"])
    try:
        return metadata.version("crossfield")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def _metadata_record(doc: Mapping[str, Any], flat: Mapping[str, Any] | None = None) -> dict[str, str]:
    """An MCAP metadata record (str -> str): readable flat keys plus ``json``,
    the exact document (what :mod:`crossfield.recording.reader` returns)."""
    record = {}
    for k, v in (flat if flat is not None else doc).items():
        record[str(k)] = v if isinstance(v, str) else json.dumps(plain(v), ensure_ascii=False)
    record["json"] = json.dumps(plain(doc), ensure_ascii=False, allow_nan=False)
    return record


# --------------------------------------------------------------------------
# The writer (one thread owns the mcap Writer)
# --------------------------------------------------------------------------


class _McapSink:
    """Owns the ``mcap`` Writer; every method is called from one thread."""

    def __init__(
        self,
        stream: Any,
        chunk_size: int,
        flush_interval_s: float,
        library: str,
        compression: CompressionType,
    ):
        self.stream = stream
        self.writer = Writer(stream, chunk_size=chunk_size, compression=compression)
        self.writer.start(profile="", library=library)
        self.schemas: dict[SchemaSpec, int] = {}
        self.channels: dict[ChannelSpec, int] = {}
        self.flush_interval_s = flush_interval_s
        self.last_flush = time.monotonic()
        self.chain = IntegrityChain()

    def _channel_id(self, spec: ChannelSpec) -> int:
        channel_id = self.channels.get(spec)
        if channel_id is None:
            schema_id = 0
            if spec.schema is not None:
                schema_id = self.schemas.get(spec.schema, 0)
                if not schema_id:
                    schema_id = self.writer.register_schema(
                        spec.schema.name, spec.schema.encoding, spec.schema.data
                    )
                    self.schemas[spec.schema] = schema_id
            channel_id = self.writer.register_channel(
                spec.topic, spec.message_encoding, schema_id, dict(spec.metadata)
            )
            self.channels[spec] = channel_id
        return channel_id

    def message(self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int) -> None:
        sequence = int(sequence) & 0xFFFFFFFF
        self.writer.add_message(self._channel_id(spec), int(log_time), data, int(log_time), sequence)
        self.chain.add_message(spec.topic, int(log_time), sequence, data)
        if time.monotonic() - self.last_flush > self.flush_interval_s:
            self.flush()

    def metadata(self, name: str, record: dict[str, str]) -> None:
        self.writer.add_metadata(name, record)
        self.chain.add_metadata(name, record)

    def attachment(self, name: str, media_type: str, data: bytes, log_time: int) -> None:
        self.writer.add_attachment(int(log_time), int(log_time), name, media_type, data)
        self.chain.add_attachment(name, media_type, data)

    def _integrity_record(self, final: bool) -> None:
        """Write the next /integrity record into the open chunk (pipeline/recording/integrity.py)."""
        t = self.chain.latest_time_ns or time.time_ns()
        index = self.chain.index
        data = self.chain.record(final)
        self.writer.add_message(self._channel_id(_INTEGRITY_CHANNEL), t, data, t, index & 0xFFFFFFFF)

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (no fsync). The
        chunk ends with an /integrity record covering everything written so far."""
        if self.chain.pending:
            self._integrity_record(final=False)
        self.writer.flush()
        self.last_flush = time.monotonic()

    def finish(self) -> None:
        self._integrity_record(final=True)
        self.writer.finish()
        self.stream.flush()


_CLOSE = object()
_INTEGRITY_CHANNEL = _json_channel(TOPIC_INTEGRITY, "crossfield.Integrity")


class McapRecorder:
    """Observer plugin: records one session into ``path`` (``session.mcap``).

    Register an instance with the session's plugin manager; it writes as
    the hooks fire and closes the file on ``on_session_end`` (or
    :meth:`close`; also at interpreter exit if neither ran).

    path: the MCAP file to create; an existing file is an error unless
    ``overwrite``. chunk_size: MCAP chunk size in bytes. writer_thread: run
    the MCAP writer in a background thread (the hooks only build message
    bytes and queue them). queue_size: messages the queue holds before the
    hooks wait for the writer. flush_interval_s: longest time a message
    stays in the open chunk. compression: chunk compression, one of
    :data:`COMPRESSIONS` (lossless in every case).

    An error writing the file is raised as :class:`RecordingError` from the
    next hook call (and from :meth:`close`).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        overwrite: bool = False,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        writer_thread: bool = True,
        queue_size: int = 8,
        flush_interval_s: float = 1.0,
        compression: str = "none",
    ):
        self.path = Path(path)
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        try:
            self._stream = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115 - held until close()
        except FileExistsError:
            raise RecordingError(f"{self.path}: a recording already exists there (not overwritten)") from None
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create the recording: {exc.strerror}") from None
        library = (
            f"crossfield/{_crossfield_version({})} {RECORDING_FORMAT} mcap-python/{metadata.version('mcap')}"
        )
        self._sink = _McapSink(self._stream, chunk_size, flush_interval_s, library, COMPRESSIONS[compression])
        self._closed = False
        self._error: BaseException | None = None
        self._lock = threading.Lock()
        self._frame_times: dict[int, int] = {}
        self._camera_points: dict[int, CameraPoints] = {}
        self._latest_time_ns = 0
        self._static_time_ns: int | None = None
        self._session: Any = None
        self._serial_counts: dict[str, int] = {}
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if writer_thread:
            self._queue = queue.Queue(maxsize=max(1, int(queue_size)))
            self._thread = threading.Thread(
                target=self._run_writer, name=f"mcap-writer {self.path.name}", daemon=True
            )
            self._thread.start()
        atexit.register(self.close)

    # ---- plumbing -------------------------------------------------------

    def _run_writer(self) -> None:
        assert self._queue is not None
        while True:
            item = self._queue.get()
            if item is _CLOSE:
                return
            if self._error is None:
                try:
                    method, args = item
                    getattr(self._sink, method)(*args)
                except BaseException as exc:  # noqa: BLE001 - reported to the producer
                    self._error = exc

    def _submit(self, method: str, *args: Any) -> None:
        if self._error is not None:
            raise RecordingError(f"{self.path}: recording failed: {self._error}") from self._error
        if self._closed:
            raise RecordingError(f"{self.path}: the recording is closed")
        if self._queue is not None:
            self._queue.put((method, args))
        else:
            try:
                getattr(self._sink, method)(*args)
            except Exception as exc:
                self._error = exc
                raise RecordingError(f"{self.path}: recording failed: {exc}") from exc

    def _message(self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int = 0, *, advances_clock: bool = True) -> None:
        log_time = int(log_time)
        if advances_clock:
            self._latest_time_ns = max(self._latest_time_ns, log_time)
        self._submit("message", spec, log_time, data, sequence)

    def _json(self, topic: str, schema_name: str, doc: Any, log_time: int, sequence: int = 0) -> None:
        self._message(_json_channel(topic, schema_name), log_time, dump_json(doc), sequence)

    def _now(self) -> int:
        """Time for a session-level result with no timestamp of its own: the
        latest time recorded so far (it sorts after the data it derives
        from), or the wall clock before anything was recorded."""
        return self._latest_time_ns or time.time_ns()

    def _frame_time(self, sequence: int) -> int:
        return self._frame_times.get(int(sequence)) or self._now()

    def flush(self) -> None:
        """Hand everything recorded so far to the OS (closes the open chunk)."""
        self._submit("flush")

    def close(self) -> None:
        """Finish the MCAP file (summary, indexes, footer) and close it. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        atexit.unregister(self.close)
        if self._thread is not None and self._queue is not None:
            self._queue.put(_CLOSE)
            self._thread.join()
        try:
            if self._error is None:
                self._sink.finish()
        except Exception as exc:  # noqa: BLE001 - reported below as RecordingError
            self._error = exc
        finally:
            self._stream.close()
        if self._error is not None:
            raise RecordingError(f"{self.path}: recording failed: {self._error}") from self._error

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- session start: facts, attachments, static data ----------------

    @hookimpl
    def on_session_start(self, session: Any) -> None:
        self._session = session
        start = int(session.start_time_ns or time.time_ns())
        self._latest_time_ns = max(self._latest_time_ns, start)
        version = _crossfield_version(session.packages)
        calibration_text = calibration_yaml(session.calibration).encode()
        session_doc = {
            "session_id": session.session_id,
            "start_time_ns": start,
            "start_time_utc": utc_text(start),
            "crossfield_version": version,
            "recording_format": RECORDING_FORMAT,
            "out_dir": str(session.out_dir),
            "config_source": session.config.source,
            "plan_name": session.plan.name,
            "plan_source": session.plan.source,
            "plan_sha256": session.plan.sha256,
            "calibration_source": session.calibration.source,
            "calibration_sha256": hashlib.sha256(calibration_text).hexdigest(),
            "simulated": session.ground_truth is not None,
            "parent": plain(session.parent),
            "units": "JSON messages: mm, rad, px; foxglove PointCloud and FrameTransforms: m",
        }
        self._submit("metadata", "crossfield.session", _metadata_record(session_doc))
        config = session.config.to_dict()
        config_record = {"source": session.config.source, "json": json.dumps(plain(config), allow_nan=False)}
        try:
            config_record["toml"] = toml_text(config)
        except TypeError as exc:  # a value TOML cannot hold: the JSON stays exact
            config_record["toml_error"] = str(exc)
        self._submit("metadata", "crossfield.config", config_record)
        self._submit("metadata", "crossfield.plugins", _metadata_record(session.plugins))
        self._submit("metadata", "crossfield.packages", {str(k): str(v) for k, v in session.packages.items()})
        self._submit("metadata", "crossfield.acquisition", _metadata_record(session.acquisition))
        self._submit("metadata", "crossfield.machine", _metadata_record(machine_info()))

        self._submit("attachment", "plan.toml", "application/toml", session.plan.text.encode("utf-8"), start)
        self._submit("attachment", "calibration.yml", "application/yaml", calibration_text, start)
        if session.ground_truth is not None:
            self._submit(
                "attachment",
                "simulator_ground_truth.json",
                "application/json",
                json.dumps(ground_truth_doc(session.ground_truth), indent=1, allow_nan=False).encode(),
                start,
            )
        self._write_static(start)
        self.flush()

    def _write_static(self, timestamp_ns: int) -> None:
        """Calibrations and the upper -> lower transform, at ``timestamp_ns``."""
        calibration = self._session.calibration
        self._static_time_ns = int(timestamp_ns)
        for camera in CAMERAS:
            self._message(
                _protobuf_channel(TOPIC_CALIBRATION.format(camera=camera), CameraCalibration),
                timestamp_ns,
                camera_calibration_message(calibration.camera(camera), camera, timestamp_ns),
            )
        self._message(
            _protobuf_channel(TOPIC_TF, FrameTransforms),
            timestamp_ns,
            frame_transforms_message([upper_to_lower_pose(calibration)], timestamp_ns),
        )

    # ---- raw inputs -----------------------------------------------------

    @hookimpl
    def on_frame(self, frame: Any) -> None:
        t = int(frame.timestamp_ns)
        seq = int(frame.sequence)
        self._frame_times[seq] = t
        if len(self._frame_times) > 256:
            self._frame_times.pop(next(iter(self._frame_times)))
        if self._session is not None and self._static_time_ns is not None and t < self._static_time_ns:
            # A source stamping frames with its own clock, earlier than the
            # session start: repeat the static data so that viewers find the
            # calibration at every frame.
            self._write_static(t)
        for camera in CAMERAS:
            image = frame.image(camera)
            spec = _protobuf_channel(
                TOPIC_IMAGE.format(camera=camera), RawImage, (("bit_depth", str(int(frame.bit_depth))),)
            )
            self._message(spec, t, raw_image_message(image, camera, t), seq)

    @hookimpl
    def on_serial_bytes(self, data: bytes, timestamp_ns: int, source: str) -> None:
        source = str(source)
        count = self._serial_counts.get(source, 0)
        self._serial_counts[source] = count + 1
        spec = ChannelSpec(TOPIC_CMM_RAW, RAW_ENCODING, None, (("source", source),))
        self._message(spec, timestamp_ns, bytes(data), count)

    @hookimpl
    def on_serial_event(self, kind: str, detail: str, timestamp_ns: int, source: str) -> None:
        # A channel of its own on /cmm/raw (file order = the order of the link's
        # bytes and events), so that no byte sequence on the line can pass for one.
        source = str(source)
        key = f"{source}\n{LINK_EVENTS}"
        count = self._serial_counts.get(key, 0)
        self._serial_counts[key] = count + 1
        spec = ChannelSpec(TOPIC_CMM_RAW, RAW_ENCODING, None, (("source", source), ("content", LINK_EVENTS)))
        self._message(spec, timestamp_ns, dump_json({"event": str(kind), "detail": str(detail)}), count)

    # ---- stage outputs --------------------------------------------------

    @hookimpl
    def on_reference(self, reference: Any) -> None:
        t = self._now()
        xyz = np.array([p.xyz for p in reference.points], dtype=np.float64).reshape(-1, 3)
        self._message(
            _protobuf_channel(TOPIC_POINTS_REFERENCE, PointCloud),
            t,
            point_cloud_message(xyz, FRAME_GLOBAL, t),
        )
        twin = {
            "frame": FRAME_GLOBAL,
            "units": "mm",
            "count": len(reference.points),
            "ids": [p.label for p in reference.points],
            "xyz_mm": reals(xyz),
            "sigma_mm": [real(p.sigma_mm) for p in reference.points],
        }
        self._json(TOPIC_POINTS_REFERENCE + JSON_TWIN, "crossfield.ReferencePoints", twin, t)
        self._json(TOPIC_REFERENCE, "crossfield.ReferenceData", reference_doc(reference), t)
        self.flush()

    @hookimpl
    def on_centroids(self, centroids: Any) -> None:
        t = self._frame_time(centroids.sequence)
        for camera in CAMERAS:
            cs = getattr(centroids, camera)
            self._json(
                TOPIC_CENTROIDS.format(camera=camera),
                "crossfield.CentroidSet",
                centroids_doc(cs),
                t,
                cs.sequence,
            )

    @hookimpl
    def on_camera_points(self, points: Any) -> None:
        seq = int(points.sequence)
        t = self._frame_time(seq)
        self._camera_points[seq] = points
        while len(self._camera_points) > 8:
            self._camera_points.pop(next(iter(self._camera_points)))
        self._message(
            _protobuf_channel(TOPIC_POINTS_CAMERA, PointCloud),
            t,
            point_cloud_message(points.xyz, "upper", t),
            seq,
        )
        self._json(
            TOPIC_POINTS_CAMERA + JSON_TWIN, "crossfield.CameraPoints", camera_points_doc(points), t, seq
        )

    @hookimpl
    def on_registration(self, registration: Any) -> None:
        seq = int(registration.sequence)
        t = self._frame_time(seq)
        fit = registration.fit
        pose = FramePose(FRAME_GLOBAL, "upper", np.asarray(fit.R), np.asarray(fit.t))
        self._message(
            _protobuf_channel(TOPIC_TF, FrameTransforms), t, frame_transforms_message([pose], t), seq
        )
        self._json(TOPIC_REGISTRATION, "crossfield.Registration", registration_doc(registration), t, seq)
        points = self._camera_points.get(seq)
        if points is not None:
            xyz, sigma = global_points(points, registration)
            ids: list[str | None] = [None] * len(points)
            for index, cid in zip(
                registration.correspondence.camera_index, registration.correspondence.control_ids
            ):
                if 0 <= int(index) < len(ids):
                    ids[int(index)] = str(cid)
            self._message(
                _protobuf_channel(TOPIC_POINTS_GLOBAL, PointCloud),
                t,
                point_cloud_message(xyz, FRAME_GLOBAL, t),
                seq,
            )
            twin = {
                "sequence": seq,
                "frame": FRAME_GLOBAL,
                "units": "mm",
                "count": len(points),
                "ids": ids,
                "camera_index": list(range(len(points))),
                "xyz_mm": reals(xyz),
                "sigma_xyz_mm": reals(sigma),
            }
            self._json(TOPIC_POINTS_GLOBAL + JSON_TWIN, "crossfield.GlobalPoints", twin, t, seq)

    @hookimpl
    def on_measurement(self, measurement: Any) -> None:
        seq = int(measurement.sequence)
        self._json(
            TOPIC_MEASUREMENT,
            "crossfield.Measurement",
            measurement_doc(measurement),
            self._frame_time(seq),
            seq,
        )

    @hookimpl
    def on_frame_done(self, result: Any) -> None:
        seq = int(result.sequence)
        t = int(result.timestamp_ns) or self._frame_time(seq)
        self._json(TOPIC_FRAMES, "crossfield.FrameStatus", frame_status_doc(result), t, seq)
        self._camera_points.pop(seq, None)
        self.flush()

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        t = int(timestamp_ns) or self._now()
        # Device events (link down, dropped frame) are logged at wall-clock
        # times a replay cannot know: they must not move the time stamps of
        # the results, which a replay reproduces from the data's own times.
        self._message(_protobuf_channel(TOPIC_LOG, Log), t, log_message(level, message, t), advances_clock=False)

    @hookimpl
    def on_session_end(self, summary: Any) -> None:
        if self._closed:
            return
        t = self._now()
        try:
            from crossfield.report.document import build_report

            report = build_report(summary)
        except Exception as exc:  # noqa: BLE001 - the recording must still be finished
            self._message(
                _protobuf_channel(TOPIC_LOG, Log), t, log_message("error", f"recorder: no /report: {exc}", t)
            )
        else:
            self._json(TOPIC_REPORT, "crossfield.Report", report, t)
        result = {
            "passed": bool(summary.passed),
            "incomplete": summary.incomplete,
            "frames": summary.frames_processed,
            "frames_failed": summary.frames_failed,
            "rms_error_mm": real(summary.rms_error_mm()),
            "report_files": [str(p) for p in summary.report_files],
        }
        self._submit("metadata", "crossfield.result", _metadata_record(result))
        self.close()


def recorded_topics(cameras: Sequence[str] = CAMERAS) -> list[str]:
    """Every topic a complete session writes (``/cmm/raw`` only if bytes were read)."""
    topics = []
    for camera in cameras:
        topics += [TOPIC_IMAGE.format(camera=camera), TOPIC_CALIBRATION.format(camera=camera)]
        topics.append(TOPIC_CENTROIDS.format(camera=camera))
    topics += [TOPIC_TF, TOPIC_LOG, TOPIC_CMM_RAW, TOPIC_REFERENCE, TOPIC_REGISTRATION, TOPIC_MEASUREMENT]
    topics += [TOPIC_FRAMES, TOPIC_REPORT, TOPIC_INTEGRITY]
    for cloud in (TOPIC_POINTS_CAMERA, TOPIC_POINTS_REFERENCE, TOPIC_POINTS_GLOBAL):
        topics += [cloud, cloud + JSON_TWIN]
    return topics


class MessageCapture(McapRecorder):
    """An observer that builds every message exactly as :class:`McapRecorder`
    would and keeps them in memory instead of writing a file.

    ``messages``: ``(topic, log_time_ns, sequence, data)`` in write order,
    topics in ``skip_topics`` left out (the audit skips the raw images).
    Metadata and attachments are not kept. Used by ``crossfield audit`` to
    recompute a session's recorded results without writing a second file.
    """

    def __init__(self, skip_topics: Iterable[str] = ()) -> None:
        import os

        super().__init__(os.devnull, overwrite=True, writer_thread=False)
        self.messages: list[tuple[str, int, int, bytes]] = []
        self._skip = frozenset(skip_topics)

    def _submit(self, method: str, *args: Any) -> None:
        if self._closed:
            raise RecordingError("the message capture is closed")
        if method == "message":
            spec, log_time, data, sequence = args
            if spec.topic not in self._skip:
                self.messages.append((spec.topic, int(log_time), int(sequence) & 0xFFFFFFFF, bytes(data)))
