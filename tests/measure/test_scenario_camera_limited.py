"""The camera-limited scenario is what docs/simulator.md says it is."""

import cv2
import numpy as np

from crossfield.simulator.optics import pixel_rays, project
from crossfield.simulator.scenarios import (
    CL_LENGTHS_MM,
    CL_MAX_TILT_DEG,
    CL_TOE_IN_DEG,
    build_scene,
)


def test_geometry_as_documented():
    scene = build_scene("camera-limited")
    assert scene.arm_sigma_mm == 0.001
    assert build_scene("camera-limited", arm_sigma_mm=0.004).arm_sigma_mm == 0.004
    cal = scene.calibration
    # toe-in: the lower optical axis, in the upper frame, is tilted towards -y by ~2 degrees
    axis = cal.R_lower_upper.T @ np.array([0.0, 0.0, 1.0])
    toe = np.degrees(np.arctan2(-axis[1], axis[2]))
    assert abs(toe - CL_TOE_IN_DEG) < 0.2
    assert cal.upper.dist_coeffs[0] < -0.1 and cal.lower.dist_coeffs[0] < -0.1
    tilts, depths = [], []
    for t in scene.targets:
        assert t.radius_mm == 1.5
        sight = -t.centre_camera / np.linalg.norm(t.centre_camera)
        tilts.append(np.degrees(np.arccos(np.clip(sight @ t.normal_camera, -1, 1))))
        depths.append(t.centre_camera[2])
    assert max(tilts) <= CL_MAX_TILT_DEG + 1e-9 and min(tilts) >= 0.4 * CL_MAX_TILT_DEG - 1e-9
    assert 340 < min(depths) and max(depths) < 410
    # every target in both images; the measured points on their shells around L3
    for cam in ("upper", "lower"):
        assert len(scene.true_blob_centres(cam)) == len(scene.targets)
    truth = scene.ground_truth
    for k, length in enumerate(CL_LENGTHS_MM):
        assert abs(truth.lines_global["L3"].distance(truth.points_global[f"P{k + 1}"]) - length) < 1e-9
    assert len(scene.plan.control_ids) == 8


def test_strong_distortion_still_inverted_and_matches_opencv():
    cal = build_scene("camera-limited").calibration
    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-90, 90, 60), rng.uniform(-70, 70, 60), np.full(60, 380.0)])
    for intr in (cal.upper, cal.lower):
        uv = project(P, intr)
        ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), intr.camera_matrix, intr.dist_coeffs)
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
        x, y = pixel_rays(uv[:, 0], uv[:, 1], intr)
        np.testing.assert_allclose(np.column_stack([x, y]), P[:, :2] / 380.0, atol=1e-10)


def test_eccentricity_is_of_the_order_of_the_noise():
    """The blob centres differ from the projected circle centres by 0.005-0.03 px."""
    scene = build_scene("camera-limited")
    shifts = []
    for cam in ("upper", "lower"):
        blobs = scene.true_blob_centres(cam)
        for t in scene.targets:
            uv = project(scene.to_camera(cam, t.centre_camera[None]), scene.calibration.camera(cam))[0]
            shifts.append(np.linalg.norm(blobs[t.id] - uv))
    assert 0.003 < min(shifts) and 0.015 < max(shifts) < 0.04
