"""Conformance of every "centroid" implementation against SIMULATOR ground truth.

Each implementation registered with a fresh plugin manager must pass the same
tests on the station simulator's rendered images (pipeline/simulator): every
target's blob found once, its centre within the stated tolerance of the true
centre of the imaged ellipse (Scene.true_blob_centres, which includes the
perspective shift of a tilted disc), the error consistent with the stated
sigma; and all implementations agree with each other on the same image.
tests/centroid/test_centroid.py tests the same implementations on synthetic images.
"""

from __future__ import annotations

import itertools
import os

import numpy as np
import pytest

from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.simulator.scenarios import build_scene
from crossfield.types import CAMERAS, CentroidSet

#: CROSSFIELD_CONFORMANCE_ENTRY_POINTS=1 also tests installed third-party plugins (docs/plugins.md).
IMPLEMENTATIONS = implementations(
    make_plugin_manager(entry_points=os.environ.get("CROSSFIELD_CONFORMANCE_ENTRY_POINTS") == "1"), "centroid"
)
NAMES = sorted(IMPLEMENTATIONS)

#: Stated tolerances (pixels) on simulator images (12-bit, blur 0.9 px, photon + read noise).
RMS_PX = 0.01  # RMS radial error over the targets of one image
MAX_PX = 0.02  # largest radial error of any target
MAX_Z = 5.0  # largest |error / sigma| per axis
AGREEMENT_PX = 0.02  # any two implementations, same target, same image
MATCH_RADIUS_PX = 1.0


@pytest.fixture(scope="module", params=["station", "table3"])
def scene_and_frames(request):
    scene = build_scene(request.param)
    frames = [scene.render_pair(k, np.random.default_rng([seed, 1])) for k, seed in enumerate((1, 2))]
    return scene, frames


def matched(result: CentroidSet, truth: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray]:
    """Target ids and the index of the centroid of each (one-to-one within the radius)."""
    ids = list(truth)
    T = np.array([truth[i] for i in ids])
    d = np.linalg.norm(result.uv[:, None, :] - T[None, :, :], axis=2)
    index = d.argmin(axis=0)
    assert np.all(d[index, np.arange(len(ids))] < MATCH_RADIUS_PX), "a target was not found"
    assert len(set(index.tolist())) == len(ids) == len(result), (
        f"{len(result)} centroids for {len(ids)} targets"
    )
    return ids, index


@pytest.mark.parametrize("name", NAMES)
def test_every_target_within_tolerance_of_truth(name, scene_and_frames):
    scene, frames = scene_and_frames
    extractor = IMPLEMENTATIONS[name].create({})
    for frame in frames:
        for camera in CAMERAS:
            result = extractor.extract(frame.image(camera), camera, frame.sequence)
            assert isinstance(result, CentroidSet)
            assert (result.camera, result.sequence, result.method) == (camera, frame.sequence, name)
            assert result.uv.shape == result.sigma_uv.shape == (len(result), 2)
            truth = scene.true_blob_centres(camera)
            ids, index = matched(result, truth)
            error = result.uv[index] - np.array([truth[i] for i in ids])
            radial = np.linalg.norm(error, axis=1)
            assert np.sqrt(np.mean(radial**2)) < RMS_PX, (camera, radial)
            assert radial.max() < MAX_PX, (camera, radial)
            assert np.all(result.sigma_uv > 0)
            assert np.abs(error / result.sigma_uv[index]).max() < MAX_Z


@pytest.mark.skipif(len(NAMES) < 2, reason="needs two implementations")
def test_all_implementations_agree(scene_and_frames):
    scene, frames = scene_and_frames
    frame = frames[0]
    for camera in CAMERAS:
        truth = scene.true_blob_centres(camera)
        positions = {}
        for name in NAMES:
            result = IMPLEMENTATIONS[name].create({}).extract(frame.image(camera), camera, 0)
            _, index = matched(result, truth)
            positions[name] = result.uv[index]
        for a, b in itertools.combinations(NAMES, 2):
            gap = np.linalg.norm(positions[a] - positions[b], axis=1)
            assert gap.max() < AGREEMENT_PX, (camera, a, b, gap.max())
