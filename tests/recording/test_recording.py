"""The MCAP recorder and its reader, on synthetic stage outputs.

A session is driven through a plugin manager's observer hooks; the file is
then read back with the mcap reader (crossfield.recording.reader) and checked against
what was sent: bit-exact images and serial bytes, schemas, JSON Schema
validity, transforms, metadata and attachments. The real ``rerun`` CLI
converts the MCAP and verifies the .rrd; the converted recording is
opened with rerun's chunk reader to check what each Foxglove schema became.
The Rerun logger (session.rrd) is tested in tests/report/test_rerun.py.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import cv2
import jsonschema
import numpy as np
import pytest
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from scipy.spatial.transform import Rotation

from crossfield.camera.calibration_io import stereo_calibration_from_yaml
from crossfield.chain.aggregate import summary_of_frames
from crossfield.chain.registry import make_plugin_manager
from crossfield.config import load_config, parse_config
from crossfield.errors import RecordingError
from crossfield.plan import parse_plan
from crossfield.recording.codec import calibration_yaml, load_json_schema, raw_image_message, toml_text
from crossfield.recording.layout import JSON_SCHEMAS, recorded_topics
from crossfield.recording.reader import open_recording
from crossfield.recording.recorder import McapRecorder
from crossfield.session import FrameResult, SessionInfo, SessionSummary
from crossfield.types import (
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
    RejectedBlob,
    RigidFit,
    StereoCalibration,
    StereoCentroids,
    StereoFrame,
)

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_750_000_000_123_456_789  # session start, ns since the epoch
PERIOD_NS = 100_000_000
SIZE = (1626, 1236)  # the real sensor: each mono16 image (4 MB) is larger than a chunk

PLAN_TEXT = textwrap.dedent(
    """
    [plan]
    name = "synthetic"

    [[control]]
    id = "C1"
    [[control]]
    id = "C2"
    [[control]]
    id = "C3"
    [[control]]
    id = "C4"

    [[target]]
    id = "P1"
    nominal = [10.0, 20.0, 5.0]
    search_radius = 3.0

    [[reference_line]]
    id = "L3"
    probes = 5
    fit = "cylinder"

    [[characteristic]]
    name = "P1-L3"
    kind = "point_line"
    a = "P1"
    b = "L3"
    nominal = 308.35
    tolerance = 0.1
    """
)


# --------------------------------------------------------------------------
# Synthetic session
# --------------------------------------------------------------------------


def make_calibration() -> StereoCalibration:
    K1 = np.array([[3636.4, 0.0, 815.7], [0.0, 3637.1, 615.3], [0.0, 0.0, 1.0]])
    K2 = np.array([[3640.2, 0.0, 808.4], [0.0, 3641.0, 619.9], [0.0, 0.0, 1.0]])
    R = Rotation.from_rotvec([0.0021, -0.0015, 0.0009]).as_matrix()
    t = -R @ np.array([0.35, 50.0, -0.25])
    return StereoCalibration(
        CameraIntrinsics(K1, [-0.062, 0.14, 0.00021, -0.00013, 0.0], SIZE),
        CameraIntrinsics(K2, [-0.058, 0.12, -0.00017, 0.00009], SIZE),  # 4 coefficients: padded to 5
        R,
        t,
        source="synthetic calibration",
    )


class Synthetic:
    """Stage outputs of a 2-pair session with known numbers."""

    def __init__(self, out_dir: Path, seed: int = 7):
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.calibration = make_calibration()
        self.plan = parse_plan(PLAN_TEXT, "synthetic_plan.toml")
        self.R = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
        self.t = np.array([120.5, -340.25, 55.0])
        cam = np.array(
            [
                [-20.0, 10.0, 400.0],
                [25.0, 12.0, 405.0],
                [0.0, 40.0, 398.0],
                [5.0, -15.0, 402.0],
                [12.0, 3.0, 401.0],
            ]
        )
        self.camera_xyz = cam
        glob = cam @ self.R.T + self.t
        labels = self.plan.probing_order()
        self.reference = ReferenceData(
            points=tuple(
                ProbedPoint(
                    label,
                    glob[k] if k < 4 else np.array([300.0 + k, -20.0, 10.0 * k]),
                    0.012,
                    device_sequence=k,
                    device_time_s=float("nan") if k == 2 else 12.5 + k,
                    probe_vector=np.array([0.0, 0.0, 1.0]),
                    probe_diameter_mm=6.0,
                )
                for k, label in enumerate(labels)
            ),
            problems=("line 7: bad checksum 0x3f (expected 0x41)",),
            source="simulator tty",
        )
        truth_points = {f"C{k + 1}": glob[k] for k in range(4)} | {"P1": glob[4]}
        self.ground_truth = GroundTruth(
            truth_points,
            {"L3": Line3D(np.array([300.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))},
            self.R,
            self.t,
        )
        self.config = load_config()
        self.info = SessionInfo(
            session_id="synthetic-session",
            out_dir=out_dir,
            config=self.config,
            calibration=self.calibration,
            plan=self.plan,
            plugins={
                "acquire": {
                    "name": "synthetic",
                    "plugin": "tests",
                    "package": "crossfield",
                    "version": "0.1.0",
                },
                "register": {
                    "name": "svd",
                    "plugin": "crossfield.plugins.register_svd",
                    "package": "crossfield",
                    "version": "0.1.0",
                },
            },
            packages={"crossfield": "0.1.0", "numpy": np.__version__},
            acquisition={"source": "synthetic", "frames": 2, "period_s": 0.1, "seed": seed},
            ground_truth=self.ground_truth,
            start_time_ns=T0,
        )
        self.serial_chunks = [b"\x02C1,1.0,2.0\r\n", bytes(range(256)), b"", b"\xff\x00tail"]
        self.frames = [
            StereoFrame(
                seq,
                T0 + seq * PERIOD_NS,
                rng.integers(0, 4096, (SIZE[1], SIZE[0]), dtype=np.uint16),
                rng.integers(0, 4096, (SIZE[1], SIZE[0]), dtype=np.uint16),
                12,
            )
            for seq in range(2)
        ]
        self.results: list[FrameResult] = []

    def centroids(self, seq: int) -> StereoCentroids:
        def one(camera: str) -> CentroidSet:
            n = 5
            peak = self.rng.uniform(500, 3000, n)
            peak[1] = np.nan  # recorded as null
            return CentroidSet(
                camera,
                seq,
                self.rng.uniform(0, 1600, (n, 2)),
                np.full((n, 2), 0.02),
                self.rng.uniform(50, 90, n),
                self.rng.uniform(0.8, 1.0, n),
                peak,
                rejected=(RejectedBlob((12.5, 1000.25), "touches_border"),),
                method="weighted",
            )

        return StereoCentroids(seq, one("upper"), one("lower"))

    def camera_points(self, seq: int) -> CameraPoints:
        n = len(self.camera_xyz)
        return CameraPoints(
            seq,
            self.camera_xyz + 0.001 * seq,
            np.full((n, 3), [0.003, 0.003, 0.02]),
            np.arange(n),
            np.arange(n)[::-1],
            np.full(n, 0.04),
            rejected=("upper[5]: ambiguous (2 candidates)",),
            method="epipolar",
        )

    def registration(self, seq: int) -> Registration:
        residuals = np.array(
            [[0.001, -0.002, 0.0005], [0.0, 0.003, -0.001], [-0.002, 0.0, 0.0], [0.001, -0.001, 0.0005]]
        )
        fit = RigidFit(self.R, self.t, residuals, float(np.sqrt((residuals**2).sum(1).mean())), method="svd")
        corr = Correspondence(np.array([0, 1, 2, 3]), ("C1", "C2", "C3", "C4"), unmatched_camera=(4,))
        return Registration(seq, fit, corr)

    def measurement(self, seq: int) -> Measurement:
        c = CharacteristicResult(
            "P1-L3",
            "point_line",
            308.36,
            308.35,
            0.1,
            0.01,
            True,
            uncertainty_mm=0.004,
            actual_mm=308.352,
            error_mm=0.008,
            elements=("P1", "L3"),
        )
        return Measurement(
            seq, (c,), {"P1": tuple(self.camera_xyz[4] @ self.R.T + self.t)}, missing_targets=()
        )

    def drive(self, pm) -> SessionSummary:
        """Fire every observer hook in the runner's order."""
        hook = pm.hook
        hook.on_session_start(session=self.info)
        for k, chunk in enumerate(self.serial_chunks):
            hook.on_serial_bytes(data=chunk, timestamp_ns=T0 + 1000 + k, source="romer-serial")
        hook.on_log(level="warning", message="reference: line 7: bad checksum", timestamp_ns=T0 + 2000)
        hook.on_reference(reference=self.reference)
        for frame in self.frames:
            seq = frame.sequence
            hook.on_frame(frame=frame)
            centroids, points = self.centroids(seq), self.camera_points(seq)
            registration, measurement = self.registration(seq), self.measurement(seq)
            hook.on_centroids(centroids=centroids)
            hook.on_camera_points(points=points)
            hook.on_registration(registration=registration)
            hook.on_measurement(measurement=measurement)
            hook.on_log(level="info", message=f"frame {seq} done", timestamp_ns=frame.timestamp_ns)
            result = FrameResult(seq, frame.timestamp_ns, centroids, points, registration, measurement)
            hook.on_frame_done(result=result)
            self.results.append(result)
        summary = summary_of_frames(self.info, self.reference, self.results)
        hook.on_session_end(summary=summary)
        return summary


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A recorded synthetic session (MCAP), shared by the read-back tests."""
    out = tmp_path_factory.mktemp("session")
    synthetic = Synthetic(out)
    recorder = McapRecorder(out / "session.mcap")
    pm = make_plugin_manager(builtins=False, extra=[recorder])
    synthetic.summary = synthetic.drive(pm)
    assert recorder.closed
    return synthetic, out


def messages(path: Path, topic: str):
    with open_recording(path) as rec:
        return list(rec.messages(topic))


# --------------------------------------------------------------------------
# MCAP layout
# --------------------------------------------------------------------------

EXPECTED_SCHEMAS = {
    "/camera/upper/image": ("foxglove.RawImage", "protobuf", "protobuf", 2),
    "/camera/lower/image": ("foxglove.RawImage", "protobuf", "protobuf", 2),
    "/camera/upper/calibration": ("foxglove.CameraCalibration", "protobuf", "protobuf", 1),
    "/camera/lower/calibration": ("foxglove.CameraCalibration", "protobuf", "protobuf", 1),
    "/tf": ("foxglove.FrameTransforms", "protobuf", "protobuf", 3),
    "/points/camera": ("foxglove.PointCloud", "protobuf", "protobuf", 2),
    "/points/reference": ("foxglove.PointCloud", "protobuf", "protobuf", 1),
    "/points/global": ("foxglove.PointCloud", "protobuf", "protobuf", 2),
    "/points/camera/json": ("crossfield.CameraPoints", "jsonschema", "json", 2),
    "/points/reference/json": ("crossfield.ReferencePoints", "jsonschema", "json", 1),
    "/points/global/json": ("crossfield.GlobalPoints", "jsonschema", "json", 2),
    "/cmm/raw": (None, None, "application/octet-stream", 4),
    "/centroids/upper": ("crossfield.CentroidSet", "jsonschema", "json", 2),
    "/centroids/lower": ("crossfield.CentroidSet", "jsonschema", "json", 2),
    "/registration": ("crossfield.Registration", "jsonschema", "json", 2),
    "/measurement": ("crossfield.Measurement", "jsonschema", "json", 2),
    "/reference": ("crossfield.ReferenceData", "jsonschema", "json", 1),
    "/frames": ("crossfield.FrameStatus", "jsonschema", "json", 2),
    "/report": ("crossfield.Report", "jsonschema", "json", 1),
    "/log": ("foxglove.Log", "protobuf", "protobuf", 3),
    "/camera/upper/annotations": ("foxglove.ImageAnnotations", "protobuf", "protobuf", 2),
    "/camera/lower/annotations": ("foxglove.ImageAnnotations", "protobuf", "protobuf", 2),
    "/scene": ("foxglove.SceneUpdate", "protobuf", "protobuf", 3),  # the CMM elements + one per pair
    # one record per flushed chunk (frame ends, session start, reference, timed flushes) + the final one
    "/integrity": ("crossfield.Integrity", "jsonschema", "json", None),
}


def test_every_topic_has_its_schema_and_count(session):
    _, out = session
    with open_recording(out / "session.mcap") as rec:
        assert rec.complete and rec.damage is None
        topics = rec.topics()
    assert set(topics) == set(EXPECTED_SCHEMAS) == set(recorded_topics())
    for topic, (schema, schema_encoding, encoding, count) in EXPECTED_SCHEMAS.items():
        info = topics[topic]
        if count is None:
            assert info.message_count >= 2, topic
            count = info.message_count
        assert (info.schema_name, info.schema_encoding, info.message_encoding, info.message_count) == (
            schema,
            schema_encoding,
            encoding,
            count,
        ), topic


def test_images_are_bit_exact_with_capture_time(session):
    synthetic, out = session
    for camera in ("upper", "lower"):
        recorded = messages(out / "session.mcap", f"/camera/{camera}/image")
        assert [m.sequence for m in recorded] == [0, 1]
        for m, frame in zip(recorded, synthetic.frames):
            img = m.decoded
            assert (img.encoding, img.frame_id, img.width, img.height, img.step) == (
                "mono16",
                camera,
                SIZE[0],
                SIZE[1],
                2 * SIZE[0],
            )
            assert img.timestamp.ToNanoseconds() == frame.timestamp_ns == m.log_time_ns
            pixels = np.frombuffer(img.data, dtype="<u2").reshape(SIZE[1], SIZE[0])
            assert np.array_equal(pixels, frame.image(camera))
            assert m.channel_metadata == {"bit_depth": "12"}


def test_raw_image_message_equals_protobuf_serialisation():
    image = np.arange(12, dtype=np.uint16).reshape(3, 4) * 4000
    fast = RawImage.FromString(raw_image_message(image, "upper", 42))
    slow = RawImage(
        frame_id="upper", width=4, height=3, encoding="mono16", step=8, data=image.astype("<u2").tobytes()
    )
    slow.timestamp.FromNanoseconds(42)
    assert fast == slow
    # A big-endian or strided view records the same little-endian pixels.
    other = RawImage.FromString(raw_image_message(image.astype(">u2")[:, ::-1][:, ::-1], "upper", 42))
    assert other == slow
    with pytest.raises(RecordingError, match="float32"):
        raw_image_message(image.astype(np.float32), "upper", 0)


def test_serial_bytes_are_exact_and_in_read_order(session):
    synthetic, out = session
    recorded = messages(out / "session.mcap", "/cmm/raw")
    assert [m.data for m in recorded] == synthetic.serial_chunks
    assert [m.decoded for m in recorded] == synthetic.serial_chunks
    assert [m.sequence for m in recorded] == [0, 1, 2, 3]
    assert [m.log_time_ns for m in recorded] == [T0 + 1000 + k for k in range(4)]
    assert all(m.channel_metadata == {"source": "romer-serial"} for m in recorded)


def test_json_messages_validate_against_their_recorded_schema(session):
    _, out = session
    with open_recording(out / "session.mcap") as rec:
        topics = rec.topics()
        for topic, info in topics.items():
            if info.message_encoding != "json":
                continue
            schema = json.loads(rec.schema(topic))
            assert schema == load_json_schema(info.schema_name)  # the shipped file, verbatim
            jsonschema.Draft202012Validator.check_schema(schema)
            validator = jsonschema.Draft202012Validator(schema)
            for m in rec.messages(topic):
                validator.validate(m.decoded)
    # crossfield.SessionStop only in a session that stopped early (validated in tests/session/test_interrupted.py)
    assert set(JSON_SCHEMAS) - {"crossfield.SessionStop"} == {
        i.schema_name for i in topics.values() if i.message_encoding == "json"
    }


def test_stage_results_carry_the_numbers_sent(session):
    synthetic, out = session
    path = out / "session.mcap"
    centroids = messages(path, "/centroids/lower")[1].decoded
    sent = synthetic.results[1].centroids.lower
    assert centroids["uv"] == sent.uv.tolist()  # floats read back bit for bit
    assert centroids["peak"][1] is None and centroids["peak"][0] == sent.peak[0]
    assert centroids["rejected"] == [{"uv": [12.5, 1000.25], "reason": "touches_border"}]

    reg = messages(path, "/registration")[0].decoded
    assert np.array_equal(reg["R_global_camera"], synthetic.R) and np.array_equal(
        reg["t_global_camera_mm"], synthetic.t
    )
    residuals = synthetic.registration(0).fit.residuals
    assert [r["control_id"] for r in reg["residuals"]] == ["C1", "C2", "C3", "C4"]
    assert np.array_equal([r["residual_mm"] for r in reg["residuals"]], residuals)
    assert np.allclose([r["norm_mm"] for r in reg["residuals"]], np.linalg.norm(residuals, axis=1))
    assert reg["unmatched_camera"] == [4] and reg["unmatched_control"] == []
    assert np.allclose(Rotation.from_quat(reg["quaternion_xyzw"]).as_matrix(), synthetic.R)

    ref = messages(path, "/reference")[0].decoded
    assert [p["label"] for p in ref["points"]] == synthetic.plan.probing_order()
    assert ref["points"][2]["device_time_s"] is None  # NaN from the device
    assert ref["problems"] == list(synthetic.reference.problems)

    meas = messages(path, "/measurement")[1].decoded
    assert (
        meas["characteristics"][0]["measured_mm"] == 308.36
        and meas["characteristics"][0]["error_mm"] == 0.008
    )

    frames = [m.decoded for m in messages(path, "/frames")]
    assert [f["sequence"] for f in frames] == [0, 1] and all(f["error"] is None for f in frames)

    report = messages(path, "/report")[0].decoded
    assert report["session"]["id"] == "synthetic-session" and report["frames_processed"] == 2

    logs = messages(path, "/log")  # in log-time order: frame 0 was captured at T0, before the warning
    assert [(m.log_time_ns, m.decoded.level, m.decoded.message) for m in logs] == [
        (T0, 2, "frame 0 done"),  # INFO
        (T0 + 2000, 3, "reference: line 7: bad checksum"),  # WARNING
        (T0 + PERIOD_NS, 2, "frame 1 done"),
    ]


def test_point_clouds_are_metres_and_their_twins_mm(session):
    synthetic, out = session
    path = out / "session.mcap"
    cloud = messages(path, "/points/camera")[1].decoded
    assert [(f.name, f.offset, f.type) for f in cloud.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    assert cloud.point_stride == 12 and cloud.frame_id == "upper"
    xyz_m = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
    sent = synthetic.camera_points(1).xyz
    assert np.allclose(xyz_m * 1000.0, sent, atol=1e-4)
    twin = messages(path, "/points/camera/json")[1].decoded
    assert np.array_equal(twin["xyz_mm"], sent) and twin["lower_index"] == [4, 3, 2, 1, 0]

    glob = messages(path, "/points/global/json")[0].decoded
    expected = synthetic.camera_points(0).xyz @ synthetic.R.T + synthetic.t
    assert np.allclose(glob["xyz_mm"], expected, atol=1e-9)
    assert glob["ids"] == ["C1", "C2", "C3", "C4", None]
    # Per-axis sigma propagated through the rotation: var_g = R^2 @ var_c.
    var_c = np.array([0.003, 0.003, 0.02]) ** 2
    assert np.allclose(np.array(glob["sigma_xyz_mm"]) ** 2, np.tile((synthetic.R**2) @ var_c, (5, 1)))
    cloud_g = messages(path, "/points/global")[0].decoded
    assert cloud_g.frame_id == "global"
    assert np.allclose(np.frombuffer(cloud_g.data, "<f4").reshape(-1, 3) * 1000.0, expected, atol=1e-3)

    ref = messages(path, "/points/reference/json")[0].decoded
    assert ref["ids"] == synthetic.plan.probing_order() and ref["sigma_mm"] == [0.012] * 9


def _pose(tf) -> tuple[np.ndarray, np.ndarray]:
    q = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
    return Rotation.from_quat(q).as_matrix(), np.array([tf.translation.x, tf.translation.y, tf.translation.z])


def test_transforms_follow_the_foxglove_parent_child_convention(session):
    synthetic, out = session
    tfs = messages(out / "session.mcap", "/tf")
    static = tfs[0].decoded.transforms
    assert [(t.parent_frame_id, t.child_frame_id) for t in static] == [("upper", "lower")]
    # foxglove: p_parent = R p_child + t. A point in the lower frame maps to the
    # upper frame such that the calibration maps it back: p_lower = R_lu p_upper + t_lu.
    R, t_m = _pose(static[0])
    p_lower = np.array([3.0, -7.0, 390.0])
    p_upper = R @ p_lower + t_m * 1000.0
    cal = synthetic.calibration
    assert np.allclose(cal.R_lower_upper @ p_upper + cal.t_lower_upper, p_lower, atol=1e-9)

    registered = [m for m in tfs if m.decoded.transforms[0].parent_frame_id == "global"]
    assert [m.sequence for m in registered] == [0, 1]
    tf = registered[0].decoded.transforms[0]
    assert tf.child_frame_id == "upper"
    R, t_m = _pose(tf)
    assert np.allclose(R, synthetic.R, atol=1e-12) and np.allclose(t_m * 1000.0, synthetic.t, atol=1e-9)
    assert registered[0].log_time_ns == synthetic.frames[0].timestamp_ns


def test_calibration_messages(session):
    synthetic, out = session
    for camera in ("upper", "lower"):
        (m,) = messages(out / "session.mcap", f"/camera/{camera}/calibration")
        cal = m.decoded
        intr = synthetic.calibration.camera(camera)
        assert (cal.frame_id, cal.width, cal.height, cal.distortion_model) == (camera, *SIZE, "plumb_bob")
        assert np.array_equal(np.reshape(cal.K, (3, 3)), intr.camera_matrix)
        assert np.array_equal(cal.D, np.pad(intr.dist_coeffs, (0, 5 - len(intr.dist_coeffs))))
        assert np.array_equal(np.reshape(cal.P, (3, 4))[:, :3], intr.camera_matrix)
        assert m.log_time_ns == T0


def test_metadata_and_attachments(session):
    synthetic, out = session
    with open_recording(out / "session.mcap") as rec:
        meta = rec.metadata()
        assert {
            "crossfield.session",
            "crossfield.config",
            "crossfield.plugins",
            "crossfield.packages",
            "crossfield.acquisition",
            "crossfield.result",
        } <= set(meta)
        sess = rec.metadata_doc("crossfield.session")
        assert sess["session_id"] == "synthetic-session" and sess["start_time_ns"] == T0
        assert sess["crossfield_version"] == "0.1.0" and sess["simulated"] is True
        assert meta["crossfield.session"]["session_id"] == "synthetic-session"  # readable flat key
        config = synthetic.config.to_dict()
        assert json.loads(meta["crossfield.config"]["json"]) == config
        assert tomllib.loads(meta["crossfield.config"]["toml"]) == config
        assert parse_config(tomllib.loads(meta["crossfield.config"]["toml"])).to_dict() == config
        assert rec.metadata_doc("crossfield.plugins") == synthetic.info.plugins
        assert meta["crossfield.packages"] == synthetic.info.packages
        assert rec.metadata_doc("crossfield.acquisition") == synthetic.info.acquisition
        result = rec.metadata_doc("crossfield.result")
        assert result["frames"] == 2 and result["passed"] == synthetic.summary.passed

        attachments = rec.attachments()
        assert attachments["plan.toml"].text == PLAN_TEXT
        assert parse_plan(attachments["plan.toml"].text).sha256 == synthetic.plan.sha256
        truth = json.loads(attachments["simulator_ground_truth.json"].text)
        assert truth["note"].startswith("SIMULATOR GROUND TRUTH")
        assert np.array_equal(truth["R_global_camera"], synthetic.R)
        yaml_text = attachments["calibration.yml"].text
        assert attachments["calibration.yml"].media_type == "application/yaml"
    back = stereo_calibration_from_yaml(yaml_text, "calibration.yml")
    cal = synthetic.calibration
    for name in ("upper", "lower"):
        assert np.array_equal(back.camera(name).camera_matrix, cal.camera(name).camera_matrix)
        assert np.array_equal(back.camera(name).dist_coeffs, cal.camera(name).dist_coeffs)
        assert back.camera(name).image_size == SIZE
    assert np.array_equal(back.R_lower_upper, cal.R_lower_upper)
    assert np.array_equal(back.t_lower_upper, cal.t_lower_upper)
    fs = cv2.FileStorage(yaml_text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    assert all(not fs.getNode(k).empty() for k in ("M1", "D1", "M2", "D2", "R", "T"))  # stereo_calib's keys


def test_toml_text_round_trips():
    data = {
        "title": 'x "quoted" \\ \u00e9',
        "session": {"name": "", "record": True, "n": 3, "f": 0.1, "nan": float("nan"), "list": [1, 2.5, "a"]},
        "acquire": {"plugin": "simulator", "nested": {"a key": 1, "b": [True, False]}},
    }
    back = tomllib.loads(toml_text(data))
    assert np.isnan(back["session"].pop("nan")) and np.isnan(data["session"].pop("nan"))
    assert back == data


def test_calibration_yaml_reads_back_with_more_distortion_terms():
    cal = make_calibration()
    wide = StereoCalibration(
        cal.upper,
        CameraIntrinsics(cal.lower.camera_matrix, np.arange(8) * 0.01, SIZE),
        cal.R_lower_upper,
        cal.t_lower_upper,
    )
    back = stereo_calibration_from_yaml(calibration_yaml(wide))
    assert np.array_equal(back.lower.dist_coeffs, np.arange(8) * 0.01)


# --------------------------------------------------------------------------
# Writer behaviour
# --------------------------------------------------------------------------


def test_synchronous_writer_gives_the_same_messages(tmp_path):
    synthetic = Synthetic(tmp_path, seed=3)
    synthetic.frames = synthetic.frames[:1]
    threaded, direct = tmp_path / "threaded.mcap", tmp_path / "direct.mcap"
    for path, writer_thread in ((threaded, True), (direct, False)):
        synthetic.results = []
        synthetic.rng = np.random.default_rng(3)
        pm = make_plugin_manager(builtins=False, extra=[McapRecorder(path, writer_thread=writer_thread)])
        synthetic.drive(pm)
    with open_recording(threaded) as a, open_recording(direct) as b:
        ma = [(m.topic, m.log_time_ns, m.sequence, m.data) for m in a.messages(decode=False)]
        mb = [(m.topic, m.log_time_ns, m.sequence, m.data) for m in b.messages(decode=False)]
        assert ma == mb and len(ma) > 20
        assert a.metadata() == b.metadata()


def test_existing_file_is_not_overwritten(tmp_path):
    path = tmp_path / "session.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(RecordingError, match="already exists"):
        McapRecorder(path)
    assert path.read_bytes() == b"precious"
    McapRecorder(path, overwrite=True).close()
    assert open_recording(path).complete


def test_missing_directory_is_a_clear_error(tmp_path):
    with pytest.raises(RecordingError, match="cannot create"):
        McapRecorder(tmp_path / "no" / "such" / "dir" / "session.mcap")


def test_hooks_after_close_raise(tmp_path):
    recorder = McapRecorder(tmp_path / "s.mcap")
    recorder.close()
    recorder.close()  # idempotent
    with pytest.raises(RecordingError, match="closed"):
        recorder.on_log(level="info", message="late", timestamp_ns=1)


def test_writer_error_surfaces_at_the_next_hook(tmp_path):
    recorder = McapRecorder(tmp_path / "s.mcap")
    recorder.sink._stream.close()  # the disk goes away under the writer
    recorder.on_log(level="info", message="x", timestamp_ns=1)
    with pytest.raises(RecordingError, match="recording failed"):
        for _ in range(100):  # the writer thread reports asynchronously
            recorder.flush()
            recorder.on_log(level="info", message="y", timestamp_ns=2)
    with pytest.raises(RecordingError, match="recording failed"):
        recorder.close()


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty"),
        (b"not an mcap file at all", "not an MCAP file"),
        (b"\x89PNG\r\n\x1a\n0000", "not an MCAP file"),
    ],
)
def test_non_mcap_files_are_a_clear_error(tmp_path, content, message):
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=message) as err:
        open_recording(path)
    assert str(path) in str(err.value)
    with pytest.raises(RecordingError, match="cannot open"):
        open_recording(tmp_path / "missing.mcap")


CRASH_SCRIPT = """
import os, signal, sys
sys.path.insert(0, {root!r})
sys.path.insert(0, {tests!r})
sys.path.insert(0, {helpers!r})
from pathlib import Path
from test_recording import Synthetic
from crossfield.recording.recorder import McapRecorder
from crossfield.chain.registry import make_plugin_manager
from crossfield.session import FrameResult
out = Path({out!r})
s = Synthetic(out)
pm = make_plugin_manager(builtins=False, extra=[McapRecorder(out / "session.mcap")])
hook = pm.hook
hook.on_session_start(session=s.info)
for k, chunk in enumerate(s.serial_chunks):
    hook.on_serial_bytes(data=chunk, timestamp_ns=k, source="romer-serial")
hook.on_reference(reference=s.reference)
frame = s.frames[0]
hook.on_frame(frame=frame)
hook.on_centroids(centroids=s.centroids(0))
hook.on_frame_done(result=FrameResult(0, frame.timestamp_ns, error="centroid: synthetic failure"))
import time; time.sleep(0.5)  # let the writer thread hand the frame to the OS
hook.on_frame(frame=s.frames[1])  # the frame in progress when the process dies
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_session_keeps_everything_up_to_the_last_finished_frame(tmp_path):
    script = CRASH_SCRIPT.format(
        root=str(ROOT), tests=str(Path(__file__).parent), helpers=str(ROOT / "tests"), out=str(tmp_path)
    )
    proc = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    synthetic = Synthetic(tmp_path)
    with open_recording(tmp_path / "session.mcap") as rec:
        assert not rec.complete and rec.damage
        topics = rec.topics()
        assert rec.metadata_doc("crossfield.session")["session_id"] == "synthetic-session"
        assert rec.attachment("plan.toml").text == PLAN_TEXT
        images = list(rec.messages("/camera/upper/image"))
        assert images[0].sequence == 0
        pixels = np.frombuffer(images[0].decoded.data, "<u2").reshape(SIZE[1], SIZE[0])
        assert np.array_equal(pixels, synthetic.frames[0].upper)
        assert [m.data for m in rec.messages("/cmm/raw")] == synthetic.serial_chunks
        assert [m.decoded["error"] for m in rec.messages("/frames")] == ["centroid: synthetic failure"]
    assert topics["/centroids/upper"].message_count == 1
    # Rerun converts what survived too.
    converted = tmp_path / "recovered.rrd"
    proc = run_rerun(
        "mcap",
        "convert",
        "--recover",
        str(tmp_path / "session.mcap"),
        "-o",
        str(converted),
        "--application-id",
        "crossfield",
    )
    assert proc.returncode == 0, proc.stderr
    assert run_rerun("rrd", "verify", str(converted)).returncode == 0
    assert "Image:buffer" in archetype_columns(converted)["/camera/upper/image"]


def test_an_unclosed_recorder_is_finished_at_exit(tmp_path):
    script = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from crossfield.recording.recorder import McapRecorder
        recorder = McapRecorder({str(tmp_path / "s.mcap")!r})
        recorder.on_log(level="info", message="no close()", timestamp_ns=5)
        """
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=60)
    with open_recording(tmp_path / "s.mcap") as rec:
        assert rec.complete
        assert [m.decoded.message for m in rec.messages("/log")] == ["no close()"]


# --------------------------------------------------------------------------
# Rerun
# --------------------------------------------------------------------------


def rerun_cli() -> str:
    exe = Path(sys.executable).parent / "rerun"
    found = str(exe) if exe.exists() else shutil.which("rerun")
    if not found:
        pytest.skip("the rerun CLI (rerun-sdk) is not installed")
    return found


def run_rerun(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, RERUN_ANALYTICS="0")  # stay offline
    return subprocess.run(
        [rerun_cli(), *args], check=False, capture_output=True, text=True, timeout=300, env=env
    )


def archetype_columns(rrd: Path) -> dict[str, dict[str, object]]:
    """entity path -> {component column name: arrow column} over the temporal chunks of an .rrd."""
    import rerun.chunk as rrc

    out: dict[str, dict[str, object]] = {}
    for chunk in rrc.RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        cols = out.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            if ":" in name:
                cols.setdefault(name, []).extend(batch.column(name).to_pylist())
    return out


def test_rerun_converts_every_foxglove_schema(session, tmp_path):
    synthetic, out = session
    converted = tmp_path / "converted.rrd"
    proc = run_rerun(
        "mcap", "convert", str(out / "session.mcap"), "-o", str(converted), "--application-id", "crossfield"
    )
    assert proc.returncode == 0, proc.stderr
    verify = run_rerun("rrd", "verify", str(converted))
    assert verify.returncode == 0, verify.stdout + verify.stderr

    cols = archetype_columns(converted)
    for camera in ("upper", "lower"):
        image = cols[f"/camera/{camera}/image"]
        assert {"Image:buffer", "Image:format"} <= set(image)
        assert image["CoordinateFrame:frame"][0] == [f"{camera}_image_plane"]
        # The image survives the conversion bit for bit.
        buffer = np.array(image["Image:buffer"][0][0], dtype=np.uint8).view("<u2").reshape(SIZE[1], SIZE[0])
        assert np.array_equal(buffer, synthetic.frames[0].image(camera))

        pinhole = cols[f"/camera/{camera}/calibration"]
        K = np.array(pinhole["Pinhole:image_from_camera"][0][0]).reshape(3, 3).T  # column-major
        assert np.allclose(K, synthetic.calibration.camera(camera).camera_matrix, rtol=1e-6)
        assert pinhole["Pinhole:resolution"][0] == [list(map(float, SIZE))]
        assert pinhole["Pinhole:child_frame"][0] == [f"{camera}_image_plane"]
        assert pinhole["Pinhole:parent_frame"][0] == [camera]

    for topic in ("/points/camera", "/points/reference", "/points/global"):
        assert "Points3D:positions" in cols[topic], topic
    positions = np.array(cols["/points/camera"]["Points3D:positions"][0])
    assert np.allclose(positions * 1000.0, synthetic.camera_points(0).xyz, atol=1e-3)

    tf = cols["/tf"]
    assert {
        "Transform3D:translation",
        "Transform3D:quaternion",
        "Transform3D:parent_frame",
        "Transform3D:child_frame",
    } <= set(tf)
    pairs = [(p[0], c[0]) for p, c in zip(tf["Transform3D:parent_frame"], tf["Transform3D:child_frame"])]
    assert pairs == [("upper", "lower"), ("global", "upper"), ("global", "upper")]
    assert np.allclose(np.array(tf["Transform3D:translation"][1][0]) * 1000.0, synthetic.t, atol=1e-3)

    assert "TextLog:text" in cols["/log"]
    assert "McapMessage:data" in cols["/registration"]  # JSON: kept as raw message bytes


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_compressed_chunks_stay_lossless(tmp_path, compression):
    synthetic = Synthetic(tmp_path, seed=5)
    path = tmp_path / f"{compression}.mcap"
    recorder = McapRecorder(path, compression=compression)
    pm = make_plugin_manager(builtins=False, extra=[recorder])
    pm.hook.on_session_start(session=synthetic.info)
    pm.hook.on_frame(frame=synthetic.frames[0])
    recorder.close()
    (m,) = messages(path, "/camera/lower/image")
    assert np.array_equal(
        np.frombuffer(m.decoded.data, "<u2").reshape(SIZE[1], SIZE[0]), synthetic.frames[0].lower
    )
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert {c.compression for c in chunks} == {compression}
    with pytest.raises(ValueError, match="compression"):
        McapRecorder(tmp_path / "x.mcap", compression="gzip")


# --------------------------------------------------------------------------
# The recording wing's structure
# --------------------------------------------------------------------------

#: How a topic literal starts (every topic of docs/recording.md).
TOPIC_PREFIXES = (
    "/camera/",
    "/calibration/",
    "/verification/",
    "/points/",
    "/cmm/raw",
    "/tf",
    "/log",
    "/registration",
    "/measurement",
    "/centroids/",
    "/integrity",
    "/reference",
    "/frame",
    "/report",
)


def topic_literals(source: str) -> list[tuple[int, str]]:
    """(line, text) of every string literal in ``source`` that starts like a topic.

    The inner pieces of an f-string (after a ``{...}``) are not literals of their
    own: ``f"{base}/centroids"`` is a Rerun entity path, not a topic.
    """
    import ast

    tree = ast.parse(source)
    inner = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            inner.update(id(v) for v in node.values[1:])
    return [
        (node.lineno, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and id(node) not in inner
        and node.value.startswith(TOPIC_PREFIXES)
    ]


def test_the_topic_finder_finds_topic_literals():
    found = topic_literals('a = "/camera/upper/image"\nb = f"/log {x}"\nc = f"{base}/centroids"\nd = "/world"\n')
    assert found == [(1, "/camera/upper/image"), (2, "/log ")]


def test_no_topic_literal_outside_the_layout():
    offenders = []
    for folder in ("pipeline", "plugins"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path == ROOT / "pipeline" / "recording" / "layout.py":
                continue
            for line, text in topic_literals(path.read_text(encoding="utf-8")):
                offenders.append(f"{path.relative_to(ROOT)}:{line}: {text!r}")
    assert not offenders, "topic literals outside crossfield.recording.layout:\n" + "\n".join(offenders)


def test_the_layout_names_every_topic_written(session):
    synthetic, out = session
    with open_recording(out / "session.mcap") as rec:
        assert set(rec.topics()) <= set(recorded_topics())
    assert set(EXPECTED_SCHEMAS) == set(recorded_topics())


def test_a_memory_sink_receives_exactly_the_messages_the_file_holds(tmp_path):
    from crossfield.recording.layout import TOPIC_INTEGRITY
    from crossfield.recording.recorder import SessionRecorder
    from crossfield.recording.writer import MemorySink

    synthetic = Synthetic(tmp_path, seed=5)
    sink = MemorySink()
    memory = SessionRecorder(sink)
    pm = make_plugin_manager(builtins=False, extra=[McapRecorder(tmp_path / "s.mcap"), memory])
    synthetic.drive(pm)
    assert sink.closed
    with open_recording(tmp_path / "s.mcap") as rec:
        in_file = [
            (m.topic, m.log_time_ns, m.sequence, m.data)
            for m in rec.messages(decode=False, file_order=True)
            if m.topic != TOPIC_INTEGRITY
        ]
        assert sink.messages == in_file and len(in_file) > 30
        assert dict(sink.metadata_records) == rec.metadata()
        attachments = rec.attachments()
        assert [(a[0], a[2]) for a in sink.attachments] == [(n, a.data) for n, a in attachments.items()]
    with pytest.raises(RecordingError, match="closed"):
        memory.on_log(level="info", message="late", timestamp_ns=1)


def test_a_memory_sink_skips_the_topics_it_is_told_to(tmp_path):
    from crossfield.recording.layout import IMAGE_TOPICS, RAW_TOPICS, TOPIC_REGISTRATION
    from crossfield.recording.recorder import SessionRecorder
    from crossfield.recording.writer import MemorySink

    synthetic = Synthetic(tmp_path, seed=5)
    sink = MemorySink(skip_topics=RAW_TOPICS)
    synthetic.drive(make_plugin_manager(builtins=False, extra=[SessionRecorder(sink)]))
    topics = {m[0] for m in sink.messages}
    assert not topics & set(RAW_TOPICS) and set(IMAGE_TOPICS) <= set(RAW_TOPICS)
    assert TOPIC_REGISTRATION in topics and len(topics) > 10


def test_replay_and_the_viewer_load_the_same_facts_and_refuse_the_same_damage(session, tmp_path):
    """One loader (crossfield.recording.facts): the same facts for replay and the
    viewer, and the same one-line error naming the file and the record."""
    from mcap.records import Attachment
    from session_tools import rewrite_mcap

    from crossfield.recording.facts import load_session_facts
    from crossfield.replay import load_recorded_session
    from crossfield.viz.rerun_log import RerunLogger
    from crossfield.viz.rerun_mcap import log_recording, session_info

    synthetic, out = session
    good = out / "session.mcap"
    facts = load_session_facts(good)
    recorded = load_recorded_session(good)
    with open_recording(good) as rec:
        info = session_info(rec)
    assert facts.session_id == recorded.session_id == info.session_id == synthetic.info.session_id
    assert info.plan.text == recorded.plan.text == synthetic.plan.text
    assert np.array_equal(info.calibration.R_lower_upper, synthetic.calibration.R_lower_upper)
    assert info.calibration.source == recorded.calibration.source == "synthetic calibration"
    assert facts.result is not None and facts.result["frames"] == len(synthetic.frames)

    def garble(found):
        return [
            Attachment(a.create_time, a.log_time, a.name, a.media_type, b'{"points_global_mm": 3}')
            if a.name == "simulator_ground_truth.json"
            else a
            for a in found
        ]

    bad = tmp_path / "bad.mcap"
    rewrite_mcap(good, bad, attachments=garble)
    messages_seen = []
    for load in (
        load_recorded_session,
        lambda p: log_recording(p, RerunLogger(tmp_path / "x.rrd")),
    ):
        with pytest.raises(RecordingError) as err:
            load(bad)
        messages_seen.append(str(err.value))
    assert messages_seen[0] == messages_seen[1]
    assert str(bad) in messages_seen[0] and "simulator_ground_truth.json" in messages_seen[0]
    assert "\n" not in messages_seen[0]

    def no_plan(found):
        return [a for a in found if a.name != "plan.toml"]

    rewrite_mcap(good, bad, attachments=no_plan)
    with pytest.raises(RecordingError, match=r"attachment 'plan.toml' is missing"):
        load_session_facts(bad)


def test_file_order_reading_streams_one_chunk_at_a_time(tmp_path):
    """Replay and audit read in file order; the reader must hand out the first
    messages having read only the first chunks (the mcap library's own file-order
    iteration reads every chunk first: memory grew with the session), and give
    exactly the messages, in the order, of a plain sequential read."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    from crossfield.recording.reader import Recording

    synthetic = Synthetic(tmp_path, seed=2)
    path = tmp_path / "s.mcap"
    synthetic.drive(make_plugin_manager(builtins=False, extra=[McapRecorder(path)]))
    size = path.stat().st_size
    assert size > 6e6  # 2 pairs of 4 MB images per camera, lz4-compressed (~0.7): several chunks

    rec = open_recording(path)
    opened = []
    original_open = Recording._open

    def tracked_open(self):
        f = original_open(self)
        opened.append(f)
        return f

    rec._open = tracked_open.__get__(rec)
    stream = rec.messages(decode=False, file_order=True)
    first = next(stream)
    assert opened and opened[-1].tell() < 0.3 * size, (opened[-1].tell(), size)
    streamed = [first, *stream]

    topics: dict[int, str] = {}
    plain = []
    with open(path, "rb") as f:
        for r in StreamReader(f).records:
            if isinstance(r, Channel):
                topics.setdefault(r.id, r.topic)
            elif isinstance(r, Message):
                plain.append((topics[r.channel_id], r.sequence, r.log_time, bytes(r.data)))
    assert [(m.topic, m.sequence, m.log_time_ns, m.data) for m in streamed] == plain
    images = [m for m in rec.messages("/camera/lower/image", decode=False, file_order=True)]
    assert [(m.sequence, m.data) for m in images] == [(s, d) for t, s, _, d in plain if t == "/camera/lower/image"]
