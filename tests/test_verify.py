"""`crossfield verify`: the VDI/VDE 2634-1 style length test against the simulated scale bar."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from crossfield.camera.calibration_io import write_stereo_calibration
from crossfield.cli import main
from crossfield.config import load_config
from crossfield.errors import CrossfieldError
from crossfield.registry import get_implementation, make_plugin_manager
from crossfield.simulator.scale_bar import bar_scene, scale_bar_positions
from crossfield.simulator.scenarios import station_calibration
from crossfield.verification import MIN_POSITIONS, evaluate, simulate_positions


@pytest.fixture(scope="module")
def stages():
    config, pm = load_config(None), make_plugin_manager()
    return tuple(
        get_implementation(pm, s, config.stages[s].plugin).create(dict(config.stages[s].options), s)
        for s in ("centroid", "triangulate")
    )


@pytest.fixture(scope="module")
def bar_frames():
    return simulate_positions(station_calibration(), 100.0, 1, seed=4)


def test_positions_span_the_volume():
    positions = scale_bar_positions()
    assert len(positions) >= MIN_POSITIONS
    directions = np.array([p.direction for p in positions])
    assert np.linalg.matrix_rank(directions) == 3  # orientations in all three dimensions
    for p in positions:
        a, b = p.targets(100.0)
        assert np.linalg.norm(a - b) == pytest.approx(100.0)
        assert len(bar_scene(p, 100.0).targets) == 2  # in both views (else ValueError)


def test_true_calibration_passes(bar_frames, stages):
    result = evaluate(
        bar_frames, station_calibration(), *stages, certified_mm=100.0, certified_u_mm=0.002, mpe_mm=0.05
    )
    assert result.passed and result.max_abs_error_mm < 0.02


def test_wrong_baseline_fails_by_the_scale_error(bar_frames, stages):
    """T 0.3 % too long scales every length by 1.003: E = +0.3 mm at every position, and the test fails."""
    truth = station_calibration()
    wrong = dataclasses.replace(truth, t_lower_upper=np.asarray(truth.t_lower_upper) * 1.003)
    result = evaluate(bar_frames, wrong, *stages, certified_mm=100.0, certified_u_mm=0.002, mpe_mm=0.1)
    assert not result.passed
    np.testing.assert_allclose([p.error_mm for p in result.positions], 0.3, atol=0.03)


def test_too_few_positions_refused(bar_frames, stages):
    with pytest.raises(CrossfieldError, match="needs at least 7"):
        evaluate(
            bar_frames[:6],
            station_calibration(),
            *stages,
            certified_mm=100.0,
            certified_u_mm=0.002,
            mpe_mm=0.1,
        )


def test_verify_cli_fails_a_bad_calibration(tmp_path, capsys):
    truth = station_calibration()
    bad = dataclasses.replace(truth, t_lower_upper=np.asarray(truth.t_lower_upper) * 1.003)
    path = write_stereo_calibration(tmp_path / "bad.yml", bad)
    out = tmp_path / "v"
    assert main(["verify", "--calibration", str(path), "--frames", "1", "-o", str(out)]) == 1
    assert "FAIL" in capsys.readouterr().out
    data = json.loads(out.with_suffix(".json").read_text())
    assert not data["passed"] and data["max_abs_error_mm"] > 0.25
    assert "data:image/png;base64," in out.with_suffix(".html").read_text()
