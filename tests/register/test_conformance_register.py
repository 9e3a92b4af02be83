"""Conformance of every "register" implementation against SIMULATOR ground truth.

The simulator's true control-point positions in the camera frame
(GroundTruth.camera_points) and in the global frame, then the simulated
ROMER arm's noisy probes (Scene.arm_probes) against camera points with
triangulation-like noise: every implementation registered with a fresh
plugin manager must recover the true T_global_camera within the stated
tolerances, refuse a mirror image, and agree with the others.
tests/register/test_register.py tests the same implementations on synthetic layouts.
"""

from __future__ import annotations

import itertools
import math
import os

import numpy as np
import pytest

from crossfield.errors import RegistrationError
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.simulator.scenarios import build_scene

#: CROSSFIELD_CONFORMANCE_ENTRY_POINTS=1 also tests installed third-party plugins (docs/plugins.md).
IMPLEMENTATIONS = implementations(
    make_plugin_manager(entry_points=os.environ.get("CROSSFIELD_CONFORMANCE_ENTRY_POINTS") == "1"), "register"
)
NAMES = sorted(IMPLEMENTATIONS)

#: Stated tolerances.
EXACT_MM = 1e-9  # noise-free: residuals and the pose (mm, rad)
CAMERA_SIGMA_MM = 0.01  # noise added to the true camera points, per axis
ANGLE_RAD = 1e-3  # rotation error with the arm's and the camera's noise
CENTRE_MM = 0.02  # error of the pose at the controls' centroid
AGREE_R = 1e-9  # implementations agree: rotation elements ...
AGREE_T_MM = 1e-6  # ... and translation (mm)


@pytest.fixture(scope="module", params=["station", "table3"])
def scene(request):
    return build_scene(request.param)


def controls(scene, seed: int | None):
    """(N, 3) camera-frame and (N, 3) global control points (mm): exact when seed is None,
    else the arm's probes and camera points with CAMERA_SIGMA_MM noise."""
    truth = scene.ground_truth
    ids = list(scene.plan.control_ids)
    camera = truth.camera_points(ids)
    if seed is None:
        return camera, np.array([truth.points_global[i] for i in ids])
    probes = {p.label: p.xyz for p in scene.arm_probes(np.random.default_rng([seed, 2]))}
    camera = camera + np.random.default_rng([seed, 3]).normal(0.0, CAMERA_SIGMA_MM, camera.shape)
    return camera, np.array([probes[i] for i in ids])


def rotation_error(R, truth):
    return math.acos(min(1.0, max(-1.0, (np.trace(R @ truth.R_global_camera.T) - 1) / 2)))


@pytest.mark.parametrize("name", NAMES)
def test_exact_data_gives_the_true_pose(name, scene):
    camera, global_ = controls(scene, None)
    fit = IMPLEMENTATIONS[name].create({}).fit(camera, global_)
    truth = scene.ground_truth
    assert np.abs(fit.R - truth.R_global_camera).max() < EXACT_MM  # (acos near 1 resolves only ~3e-8 rad)
    assert np.abs(fit.t - truth.t_global_camera).max() < 1e-6
    assert fit.rms_mm < EXACT_MM and np.abs(fit.residuals).max() < EXACT_MM
    assert np.linalg.det(fit.R) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noisy_data_within_tolerance(name, scene, seed):
    camera, global_ = controls(scene, seed)
    fit = IMPLEMENTATIONS[name].create({}).fit(camera, global_)
    truth = scene.ground_truth
    assert fit.method == name
    assert rotation_error(fit.R, truth) < ANGLE_RAD
    centre = camera.mean(axis=0)
    true_centre = truth.R_global_camera @ centre + truth.t_global_camera
    assert np.linalg.norm(fit.R @ centre + fit.t - true_centre) < CENTRE_MM
    # residuals as documented, RMS consistent with the noise (arm sigma and camera sigma)
    np.testing.assert_allclose(fit.residuals, fit.apply(camera) - global_, atol=1e-12)
    n = len(camera)
    expected = math.sqrt(3 * (CAMERA_SIGMA_MM**2 + scene.arm_sigma_mm**2) * (1 - 2 / n))
    assert 0.3 * expected < fit.rms_mm < 2.0 * expected


@pytest.mark.parametrize("name", NAMES)
def test_mirror_image_is_refused(name, scene):
    camera, global_ = controls(scene, 1)
    with pytest.raises(RegistrationError):
        IMPLEMENTATIONS[name].create({}).fit(camera * np.array([1.0, 1.0, -1.0]), global_)


@pytest.mark.skipif(len(NAMES) < 2, reason="needs two implementations")
@pytest.mark.parametrize("seed", [1, 2])
def test_all_implementations_agree(scene, seed):
    camera, global_ = controls(scene, seed)
    fits = {name: IMPLEMENTATIONS[name].create({}).fit(camera, global_) for name in NAMES}
    for a, b in itertools.combinations(NAMES, 2):
        assert np.abs(fits[a].R - fits[b].R).max() < AGREE_R, (a, b)
        assert np.abs(fits[a].t - fits[b].t).max() < AGREE_T_MM, (a, b)
        assert fits[a].rms_mm == pytest.approx(fits[b].rms_mm, abs=1e-9)
