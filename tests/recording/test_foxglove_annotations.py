"""The Foxglove overlays of a recording (/camera/*/annotations, /scene), decoded with the official
foxglove-schemas-protobuf classes and checked against the recorded results and the simulator's truth;
the Foxglove layout in docs/ names only recorded topics."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from scipy.spatial.transform import Rotation

from crossfield.recording import foxglove_overlay as fo
from crossfield.recording import layout as L
from crossfield.recording.facts import load_session_facts
from crossfield.recording.reader import open_recording
from crossfield.simulator.scenarios import CYLINDER_RADIUS_MM
from crossfield.types import CAMERAS, CentroidSet, RejectedBlob

from session_tools import record_session

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 2-pair station session: raw message bytes per topic (decoded here, not by crossfield)."""
    out = tmp_path_factory.mktemp("fox")
    record_session(out, "s", scenario="station", frames=2, seed=4, report={"plugin": "json"})
    path = out / "s" / "session.mcap"
    facts = load_session_facts(path)
    by_topic: dict[str, list] = {}
    with open_recording(path) as rec:
        for m in rec.messages(decode=False):
            by_topic.setdefault(m.topic, []).append(m)
    return facts, by_topic


def json_by_sequence(by_topic, topic):
    return {m.sequence: json.loads(m.data) for m in by_topic[topic]}


def test_annotations_sit_on_the_centroids_and_name_them(recorded):
    facts, by_topic = recorded
    truth = facts.ground_truth
    registrations = json_by_sequence(by_topic, L.TOPIC_REGISTRATION)
    camera_points = json_by_sequence(by_topic, L.TOPIC_POINTS_CAMERA_JSON)
    for camera in CAMERAS:
        centroids = json_by_sequence(by_topic, L.centroids_topic(camera))
        messages = by_topic[L.annotations_topic(camera)]
        assert [m.sequence for m in messages] == sorted(centroids)
        intrinsics = facts.calibration.camera(camera)
        for m in messages:
            ann = ImageAnnotations.FromString(m.data)  # the official class
            assert ann.timestamp.ToNanoseconds() == m.log_time_ns
            uv = np.array(centroids[m.sequence]["uv"], dtype=float).reshape(-1, 2)
            circles = np.array([[c.position.x, c.position.y] for c in ann.circles])
            points = np.array([[p.x, p.y] for p in ann.points[0].points])
            assert len(circles) == len(points) == len(uv) > 0
            # Foxglove's origin is the top-left pixel's corner: centre + 0.5 px
            assert np.abs(circles - 0.5 - uv).max() < 0.01
            assert np.abs(points - 0.5 - uv).max() < 0.01
            assert all(c.diameter >= 12.0 for c in ann.circles)
            labels = [t.text for t in ann.texts]
            # every matched control is labelled at its centroid, which lies on the true projection
            reg = registrations[m.sequence]
            index_key = f"{camera}_index"
            R_c = np.asarray(truth.R_global_camera).T  # camera <- global (upper)
            t_c = -R_c @ np.asarray(truth.t_global_camera)
            if camera == "lower":
                R_lu = np.asarray(facts.calibration.R_lower_upper)
                R_c, t_c = R_lu @ R_c, R_lu @ t_c + np.asarray(facts.calibration.t_lower_upper)
            for r in reg["residuals"]:
                k = camera_points[m.sequence][index_key][r["camera_index"]]
                assert labels[k] == r["control_id"]
                p_cam = R_c @ truth.points_global[r["control_id"]] + t_c
                true_uv, _ = cv2.projectPoints(p_cam.reshape(1, 3), np.zeros(3), np.zeros(3),
                                               np.asarray(intrinsics.camera_matrix),
                                               np.asarray(intrinsics.dist_coeffs))
                assert np.linalg.norm(circles[k] - 0.5 - true_uv.reshape(2)) < 0.5, r["control_id"]
            assert {"P1", "P2"} <= set(labels)


def test_rejected_blobs_in_their_own_colour():
    cs = CentroidSet(camera="upper", sequence=3, uv=np.array([[10.25, 20.5], [np.nan, np.nan]]),
                     sigma_uv=np.full((2, 2), 0.01), area_px=np.array([50.0, 0.0]), roundness=np.ones(2),
                     peak=np.ones(2), rejected=(RejectedBlob((100.0, 200.0), "not_round"),))
    ann = ImageAnnotations.FromString(fo.image_annotations(cs, {0: ("C4", "control")}, 7))
    assert len(ann.circles) == 1 and (ann.circles[0].position.x, ann.circles[0].position.y) == (10.75, 21.0)
    found, rejected = ann.points
    grey = fo.COLOURS["rejected"]
    assert (rejected.points[0].x, rejected.points[0].y) == (100.5, 200.5)
    assert [round(255 * c) for c in (rejected.outline_color.r, rejected.outline_color.g,
                                     rejected.outline_color.b)] == list(grey)
    orange = [round(255 * c) for c in (found.outline_colors[0].r, found.outline_colors[0].g,
                                       found.outline_colors[0].b)]
    assert orange == list(fo.COLOURS["control"]) != list(grey)
    assert [t.text for t in ann.texts] == ["C4", "rejected: not_round"]
    assert ImageAnnotations.FromString(fo.image_annotations(None, {}, 7)).circles == []


def _entities(data: bytes) -> dict[str, object]:
    return {e.id: e for e in SceneUpdate.FromString(data).entities}


def _xyz_mm(primitive) -> np.ndarray:
    p = primitive.pose.position
    return 1e3 * np.array([p.x, p.y, p.z])


def test_scene_entities_sit_on_the_measured_coordinates(recorded):
    facts, by_topic = recorded
    truth = facts.ground_truth
    scene = by_topic[L.TOPIC_SCENE]
    cmm = _entities(scene[0].data)  # at the CMM import
    reference = json.loads(by_topic[L.TOPIC_REFERENCE][0].data)
    probed = {p["label"]: np.array(p["xyz_mm"]) for p in reference["points"]}
    controls = cmm[fo.ENTITY_CONTROLS]
    assert controls.frame_id == L.FRAME_GLOBAL == "global"
    assert [t.text for t in controls.texts] == list(facts.plan.control_ids)
    for sphere, cid in zip(controls.spheres, facts.plan.control_ids):
        assert np.abs(_xyz_mm(sphere) - probed[cid]).max() < 1e-9
    assert [t.text for t in cmm[fo.ENTITY_REFERENCE_POINTS].texts] == ["R1"]
    cylinder = cmm[fo.ENTITY_LINE.format(id="L3")].cylinders[0]
    axis = truth.lines_global["L3"]
    q = cylinder.pose.orientation
    direction = Rotation.from_quat([q.x, q.y, q.z, q.w]).apply([0.0, 0.0, 1.0])
    true_dir = np.asarray(axis.direction) / np.linalg.norm(axis.direction)
    assert np.degrees(np.arccos(min(1.0, abs(direction @ true_dir)))) < 0.05  # the cylinder lies on the axis
    centre = _xyz_mm(cylinder) - np.asarray(axis.point)
    assert np.linalg.norm(centre - (centre @ true_dir) * true_dir) < 0.05
    assert 1e3 * cylinder.size.x == pytest.approx(2 * CYLINDER_RADIUS_MM, abs=0.05)

    measurements = json_by_sequence(by_topic, L.TOPIC_MEASUREMENT)
    camera_points = json_by_sequence(by_topic, L.TOPIC_POINTS_CAMERA_JSON)
    registrations = json_by_sequence(by_topic, L.TOPIC_REGISTRATION)
    tfs = {m.sequence: FrameTransforms.FromString(m.data) for m in by_topic[L.TOPIC_TF] if m.sequence in registrations}
    per_pair = [m for m in scene[1:]]
    assert [m.sequence for m in per_pair] == sorted(measurements)
    for m in per_pair:
        entities = _entities(m.data)
        measured = measurements[m.sequence]
        targets = entities[fo.ENTITY_TARGETS]
        assert targets.frame_id == "global"
        for sphere, text in zip(targets.spheres, targets.texts):
            xyz = _xyz_mm(sphere)
            assert np.abs(xyz - measured["target_points_mm"][text.text]).max() < 1e-9
            assert np.linalg.norm(xyz - truth.points_global[text.text]) < 0.05
        # the camera-measured controls, in the upper camera's frame, land on the CMM's through /tf
        own = entities[fo.ENTITY_CAMERA_CONTROLS]
        assert own.frame_id == L.FRAME_CAMERA == "upper"
        tf = next(t for t in tfs[m.sequence].transforms if t.parent_frame_id == "global")
        assert tf.child_frame_id == "upper"
        R = Rotation.from_quat([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]).as_matrix()
        t = 1e3 * np.array([tf.translation.x, tf.translation.y, tf.translation.z])
        xyz_c = np.array(camera_points[m.sequence]["xyz_mm"])
        for r, sphere, text in zip(registrations[m.sequence]["residuals"], own.spheres, own.texts):
            assert text.text == r["control_id"]
            assert np.abs(_xyz_mm(sphere) - xyz_c[r["camera_index"]]).max() < 1e-9
            assert np.linalg.norm(R @ _xyz_mm(sphere) + t - probed[r["control_id"]]) < 0.1
        # one segment per characteristic, as long as its measured value
        lines = entities[fo.ENTITY_CHARACTERISTICS]
        texts = [t.text.split()[0] for t in lines.texts]
        assert texts == [c["name"] for c in measured["characteristics"]]
        for line, c in zip(lines.lines, measured["characteristics"]):
            a, b = (1e3 * np.array([p.x, p.y, p.z]) for p in line.points)
            assert np.linalg.norm(b - a) == pytest.approx(c["measured_mm"], abs=1e-6), c["name"]


def test_a_pair_without_results_deletes_the_per_pair_entities():
    class Failed:
        measurement = registration = points = centroids = None

    overlay = fo.FoxgloveOverlay()
    update = SceneUpdate.FromString(overlay.frame(Failed(), 5))
    assert not update.entities
    assert {d.id for d in update.deletions} == {fo.ENTITY_TARGETS, fo.ENTITY_CHARACTERISTICS,
                                                fo.ENTITY_CAMERA_CONTROLS}
    assert all(d.type == SceneEntityDeletion.MATCHING_ID for d in update.deletions)
    assert all(ImageAnnotations.FromString(v).circles == [] for v in overlay.annotations(Failed(), 5).values())


def test_the_layout_opens_recorded_topics_side_by_side():
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    topics = set(L.recorded_topics())
    panels = layout["configById"]
    named = set()
    for config in panels.values():
        mode = config.get("imageMode", {})
        named |= {mode.get("imageTopic"), mode.get("calibrationTopic"), *mode.get("annotations", {})}
        named |= set(config.get("topics", {})) | {config.get("topicToRender")}
    named.discard(None)
    assert named <= topics, named - topics
    assert {L.annotations_topic(c) for c in CAMERAS} | {L.TOPIC_SCENE} <= named

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
