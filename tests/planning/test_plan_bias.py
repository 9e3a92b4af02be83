"""The planner's fixed centroid bias (crossfield.planning.image_bias) against the simulator and the
pipeline: on a noise-free session the pipeline's actual errors are the planner's predicted biases."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from crossfield.config import parse_config
from crossfield.planning.routes import analytic, camera_model, centroid_bias, simulate_sessions
from crossfield.planning.station import PLANNED_STAGES, station_from_scenario
from crossfield.plugins.acquire_simulator import SimulatorSource
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.chain.runner import run_session
from crossfield.types import StereoFrame


class NoiseFreeSimulator(SimulatorSource):
    """The simulator's scene, every pair its clean image (rounded to DN): no sensor noise."""

    def frames(self):
        clean = self.scene.clean_images
        pair = {cam: np.rint(clean[cam]).astype(np.uint16) for cam in ("upper", "lower")}
        for k in range(self.n_frames):
            yield StereoFrame(k, 1_700_000_000_000_000_000 + k, pair["upper"], pair["lower"], self.scene.sensor.bit_depth)


@pytest.fixture(scope="module")
def station():
    # The arm exact; its stated sigma (the runner's weights) romer-serial's default.
    return dataclasses.replace(station_from_scenario("station", arm_sigma_mm=0.0), weight_cmm_sigma_mm=0.01)


@pytest.fixture(scope="module")
def model(station):
    return camera_model(station)


@pytest.fixture(scope="module")
def scene():
    from crossfield.simulator.scenarios import build_scene

    return build_scene("station", arm_sigma_mm=0.0)


@pytest.fixture(scope="module")
def noise_free(station, model):
    """The camera model with the bias of the noise-free rendering (rendered_bias noise="none")."""
    return dataclasses.replace(model, bias_uv=centroid_bias(station, model.uv, noise="none"))


def test_rendered_bias_is_the_centroid_on_the_simulators_own_images(station, model, noise_free, scene):
    """The simulator's own scene images (Scene.clean_images) through the weighted centroid: the
    planner's noise-free rendered bias to 1e-5 px; the session bias (antithetic pair: the detector at
    the session's noise level) within 0.0005 px of it; the eccentricity model alone misses ~0.003 px."""
    centroid = implementations(make_plugin_manager(), "centroid")["weighted"].create({}, "<test>")
    ecc = camera_model(dataclasses.replace(station, bias_model="eccentricity")).bias_uv
    for j, cam in enumerate(("upper", "lower")):
        found = np.asarray(centroid.extract(np.rint(scene.clean_images[cam]).astype(np.uint16), cam, 0).uv)
        expected = model.uv[:, 2 * j : 2 * j + 2]
        nearest = np.array([found[np.argmin(np.linalg.norm(found - e, axis=1))] for e in expected])
        actual = nearest - expected
        assert np.all(np.abs(actual) < 0.06)  # the bias itself: ~0.02 px RMS
        np.testing.assert_allclose(noise_free.bias_uv[:, 2 * j : 2 * j + 2], actual, atol=1e-5)
        assert np.sqrt(np.mean((model.bias_uv[:, 2 * j : 2 * j + 2] - actual) ** 2)) < 0.0005
        assert np.sqrt(np.mean((ecc[:, 2 * j : 2 * j + 2] - actual) ** 2)) > 0.0015


def test_planner_bias_is_the_pipelines_error_on_a_noise_free_session(station, noise_free, scene, tmp_path):
    """A session of noise-free images and an exact arm through the whole pipeline (weighted centroid,
    epipolar triangulation, weighted SVD registration, measurement): its errors are the fixed
    biases. The planner's rendered bias, propagated linearly (analytic) and through the Monte Carlo's
    kernels without noise, predicts every one to 0.0001 mm; the eccentricity model alone is off by
    up to ~0.0007 mm (P2-depth: the weighted centroid's own bias, 0.002-0.003 px RMS)."""
    data = {
        "session": {"output_dir": str(tmp_path), "name": "noise-free", "record": False, "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": "station", "frames": 2, "seed": 1, "arm_sigma_mm": 0.0},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
        # the pipeline the planner models (docs/planning.md): not the defaults since issue 11
        **{stage: {"plugin": plugin} for stage, plugin in PLANNED_STAGES.items()},
    }
    source = NoiseFreeSimulator(scenario="station", frames=2, seed=1, arm_sigma_mm=0.0)
    source.scene = scene  # the same scene (its images rendered once for both tests)
    summary = run_session(parse_config(data, "<test>"), make_plugin_manager(), source=source)
    actual = {c.name: c.error_mm for c in summary.characteristics}
    predicted = {c["name"]: c["bias_mm"] for c in analytic(station, noise_free)["characteristics"]}
    quiet = dataclasses.replace(noise_free, sigma_uv=noise_free.sigma_uv * 1e-6)  # the kernels, no noise
    mc = simulate_sessions(station, 2, np.random.default_rng(0), quiet, triangulation="full").mean(axis=0)
    eccentric = {c["name"]: c["bias_mm"]
                 for c in analytic(dataclasses.replace(station, bias_model="eccentricity"))["characteristics"]}
    assert set(actual) == set(predicted)
    assert max(abs(v) for v in actual.values()) > 0.001  # P1-P2, P2-L3, P1-depth: 0.0012-0.0017 mm
    for k, c in enumerate(station.characteristics):
        assert predicted[c.name] == pytest.approx(actual[c.name], abs=1e-4), c.name
        assert mc[k] == pytest.approx(actual[c.name], abs=1e-4), c.name
    assert max(abs(eccentric[n] - actual[n]) for n in actual) > 5e-4


def test_planner_bias_with_modelfit_is_the_corrected_pipelines_error(station, model, scene, tmp_path):
    """The default centroid (modelfit, with conics) and the epipolar eccentricity correction: the
    planner's rendered bias less the eccentricity model's offset (what the correction takes off)
    is each characteristic's actual error on a noise-free session to 0.0001 mm, and that error is a
    fraction of the uncorrected weighted pipeline's (test above: up to 0.0017 mm)."""
    fit = dataclasses.replace(station, centroid="modelfit")
    corrected = dataclasses.replace(model, bias_uv=centroid_bias(fit, model.uv, noise="none"))
    data = {
        "session": {"output_dir": str(tmp_path), "name": "noise-free-modelfit", "record": False, "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": "station", "frames": 2, "seed": 1, "arm_sigma_mm": 0.0},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
        "centroid": {"plugin": "modelfit"},
        "register": {"plugin": "svd"},  # the planner's registration model
    }
    source = NoiseFreeSimulator(scenario="station", frames=2, seed=1, arm_sigma_mm=0.0)
    source.scene = scene
    summary = run_session(parse_config(data, "<test>"), make_plugin_manager(), source=source)
    actual = {c.name: c.error_mm for c in summary.characteristics}
    predicted = {c["name"]: c["bias_mm"] for c in analytic(fit, corrected)["characteristics"]}
    assert set(actual) == set(predicted)
    assert np.sqrt(np.mean(np.square(corrected.bias_uv))) < 0.001  # px: the eccentricity (~0.02 px) is gone
    for name in actual:
        assert predicted[name] == pytest.approx(actual[name], abs=1e-4), name
    assert max(abs(v) for v in actual.values()) < 0.0005
