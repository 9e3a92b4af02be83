"""Matching camera points to CMM control points by rigid distances (crossfield.chain.correspondence)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.chain.correspondence import match_control_points
from crossfield.errors import CorrespondenceError

IDS = tuple(f"C{k + 1}" for k in range(8))


def scene(seed: int, n_controls: int = 8, n_extra: int = 10):
    """Controls (global, mm), their camera-frame positions, and extra camera points."""
    rng = np.random.default_rng(seed)
    camera_controls = np.column_stack(
        [
            rng.uniform(-80, 80, n_controls),
            rng.uniform(-20, 70, n_controls),
            rng.uniform(382, 418, n_controls),
        ]
    )
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-800, 800, 3)
    global_controls = camera_controls @ R.T + t
    extra = np.column_stack(
        [rng.uniform(-80, 80, n_extra), rng.uniform(-20, 70, n_extra), rng.uniform(380, 420, n_extra)]
    )
    return rng, global_controls, camera_controls, extra


def assemble(rng, camera_controls, extra, visible, noise_mm=0.0):
    """Shuffled camera points; returns them and the true camera index of each visible control."""
    points = np.vstack([camera_controls[visible], extra])
    points = points + rng.normal(0, noise_mm, points.shape)
    order = rng.permutation(len(points))
    shuffled = points[order]
    position = np.argsort(order)  # row r of `points` is row position[r] of `shuffled`
    truth = {IDS[k]: int(position[j]) for j, k in enumerate(np.flatnonzero(visible))}
    return shuffled, truth


def as_dict(corr):
    return dict(zip(corr.control_ids, corr.camera_index.tolist()))


@pytest.mark.parametrize("seed", range(20))
def test_shuffled_with_extra_and_missing_points_and_noise(seed):
    rng, G, camera_controls, extra = scene(seed)
    visible = np.ones(8, dtype=bool)
    visible[rng.choice(8, size=seed % 3, replace=False)] = False  # 0-2 controls not seen
    points, truth = assemble(rng, camera_controls, extra, visible, noise_mm=0.05)
    corr = match_control_points(points, G, IDS)
    assert as_dict(corr) == truth
    assert list(corr.control_ids) == [cid for cid in IDS if cid in truth]  # plan order
    assert set(corr.unmatched_control) == set(IDS) - set(truth)
    assert sorted(corr.unmatched_camera) == sorted(set(range(len(points))) - set(truth.values()))


def test_exact_data_only_controls():
    rng, G, camera_controls, _ = scene(100)
    order = rng.permutation(8)
    corr = match_control_points(camera_controls[order], G, IDS)
    assert as_dict(corr) == {IDS[k]: int(np.flatnonzero(order == k)[0]) for k in range(8)}
    assert corr.unmatched_camera == () and corr.unmatched_control == ()


def test_three_controls_are_enough():
    rng, G, camera_controls, extra = scene(101)
    visible = np.zeros(8, dtype=bool)
    visible[[1, 4, 6]] = True
    points, truth = assemble(rng, camera_controls, extra[:4], visible, noise_mm=0.02)
    assert as_dict(match_control_points(points, G, IDS)) == truth


def test_bumped_control_is_left_unmatched():
    """A target moved by 2 mm since it was probed no longer fits: reported, not used."""
    rng, G, camera_controls, extra = scene(102)
    moved = camera_controls.copy()
    moved[5] += np.array([2.0, 0.0, 0.0])
    points, truth = assemble(rng, moved, extra, np.ones(8, dtype=bool), noise_mm=0.02)
    corr = match_control_points(points, G, IDS)
    del truth["C6"]
    assert as_dict(corr) == truth
    assert corr.unmatched_control == ("C6",)


def test_noise_beyond_tolerance_is_reported_by_count():
    rng, G, camera_controls, extra = scene(103)
    points, truth = assemble(rng, camera_controls, extra, np.ones(8, dtype=bool), noise_mm=0.05)
    assert as_dict(match_control_points(points, G, IDS, tolerance_mm=0.5)) == truth
    with pytest.raises(CorrespondenceError, match="within 0.001 mm"):
        match_control_points(points, G, IDS, tolerance_mm=0.001)


def test_symmetric_layout_is_ambiguous():
    """Four controls on a rectangle: four rigid motions map it onto itself."""
    G = np.array([[0.0, 0, 0], [40, 0, 0], [40, 25, 0], [0, 25, 0]]) + [500.0, 20.0, -30.0]
    R = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
    camera = (G - G.mean(0)) @ R + [0.0, 20.0, 400.0]
    with pytest.raises(CorrespondenceError, match="ambiguous.*C1, C2, C3, C4"):
        match_control_points(camera, G, IDS[:4])


def test_isosceles_triangle_is_ambiguous():
    G = np.array([[-20.0, 0, 0], [20, 0, 0], [0, 30, 5]])
    with pytest.raises(CorrespondenceError, match="ambiguous.*C1, C2"):
        match_control_points(G + [1.0, 2.0, 400.0], G, IDS[:3])


def test_mirror_symmetric_layout_is_resolved_by_handedness():
    """Distances cannot tell a non-planar layout from its mirror image, the rigid fit can."""
    G = np.array([[-20.0, 0, 0], [20, 0, 0], [-15, 30, 10], [15, 30, 10], [0, 10, 25]])
    R = Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix()
    camera = G @ R + [3.0, 5.0, 400.0]
    order = np.array([3, 0, 4, 1, 2])
    corr = match_control_points(camera[order], G, IDS[:5])
    assert as_dict(corr) == {IDS[k]: int(np.flatnonzero(order == k)[0]) for k in range(5)}


def test_mirrored_camera_points_are_an_error():
    rng, G, camera_controls, extra = scene(104)
    mirrored = camera_controls * np.array([-1.0, 1.0, 1.0])
    with pytest.raises(CorrespondenceError, match="mirror image"):
        match_control_points(mirrored, G, IDS)


def test_stray_point_at_a_control_position_leaves_that_control_out():
    """Two camera points within the tolerance of C3: C3 is contested, the other 7 are certain."""
    rng, G, camera_controls, extra = scene(105)
    points = np.vstack([camera_controls, camera_controls[2] + [0.2, 0.0, 0.0], extra[:3]])
    corr = match_control_points(points, G, IDS)
    assert as_dict(corr) == {cid: k for k, cid in enumerate(IDS) if cid != "C3"}
    assert corr.unmatched_control == ("C3",)
    assert {2, 8} <= set(corr.unmatched_camera)


def test_stray_points_at_too_many_controls_is_an_error():
    """Only three controls, one contested: fewer than 3 certain pairs remain."""
    rng, G, camera_controls, extra = scene(108)
    points = np.vstack([camera_controls[:3], camera_controls[0] + [0.0, 0.15, 0.0]])
    with pytest.raises(CorrespondenceError, match="ambiguous.*C1"):
        match_control_points(points, G[:3], IDS[:3])


def test_unrelated_points_are_an_error():
    rng, G, _, extra = scene(106)
    with pytest.raises(CorrespondenceError, match="no 3 camera points"):
        match_control_points(extra * 3.0, G, IDS)


@pytest.mark.parametrize(
    "camera, control, ids, message",
    [
        (np.zeros((2, 3)), np.eye(3), IDS[:3], "at least 3"),
        (np.eye(3), np.eye(3), IDS[:2], "control ids"),
        (np.eye(3), np.eye(3), ("A", "A", "B"), "duplicate"),
        (np.full((3, 3), np.nan), np.eye(3), IDS[:3], "non-finite"),
    ],
)
def test_bad_input(camera, control, ids, message):
    with pytest.raises(CorrespondenceError, match=message):
        match_control_points(camera, control, ids)


def test_many_strays_with_loose_tolerance():
    """40 strays and a 1 mm tolerance: many chance distance coincidences, same answer."""
    rng, G, camera_controls, extra = scene(107, n_extra=40)
    points, truth = assemble(rng, camera_controls, extra, np.ones(8, dtype=bool), noise_mm=0.05)
    assert as_dict(match_control_points(points, G, IDS, tolerance_mm=1.0)) == truth
