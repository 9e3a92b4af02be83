"""`crossfield verify`: the VDI/VDE 2634-1 style length test against the simulated scale bar."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from session_tools import edit_json, rewrite_mcap

from crossfield.audit import audit, format_report
from crossfield.camera.calibration_io import write_stereo_calibration
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.cli import main
from crossfield.config import DEFAULT_PLUGINS, load_config
from crossfield.errors import CrossfieldError
from crossfield.simulator.scale_bar import bar_scene, scale_bar_positions
from crossfield.simulator.scenarios import station_calibration
from crossfield.verification.procedure import MIN_POSITIONS, evaluate, simulate_positions


def message_data(path, topic, sequence) -> bytes:
    from crossfield.recording.reader import open_recording

    with open_recording(path) as rec:
        return next(m.data for m in rec.messages(topic, decode=False) if m.sequence == sequence)


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


def test_verify_records_and_re_evaluates_from_the_recording(tmp_path, capsys):
    """verify --record writes the pairs with the session's chain and seal; verify --recording
    gives the same E per position (bit for bit: the same pixels through the same stages), and
    with another calibration the E of that calibration."""
    from crossfield.audit.chain import verify
    from crossfield.recording.seal import read_sidecar
    from crossfield.verification.record import read_verification_recording

    truth = station_calibration()
    calib = write_stereo_calibration(tmp_path / "truth.yml", truth)
    first, mcap = tmp_path / "first", tmp_path / "verify.mcap"
    args = ["verify", "--calibration", str(calib), "--frames", "1", "--mpe", "0.05", "--bar-mm", "100"]
    assert main([*args, "-o", str(first), "--record", str(mcap)]) == 0
    assert "recorded to" in capsys.readouterr().out
    integrity = verify(mcap)
    assert integrity.passed and read_sidecar(mcap)["chain_head"] == integrity.chain_sha256
    # the verification record (issue 27 item 7): recorded first, so its header states the seal
    import hashlib
    import html as html_lib
    import re

    page = first.with_suffix(".html").read_text(encoding="utf-8")
    header = {m[1]: html_lib.unescape(m[2]) for m in re.finditer(r'<dd id="([a-z0-9-]+)"[^>]*>([^<]*)</dd>', page)}
    assert header["seal-chain-head"] == integrity.chain_sha256
    assert header["seal-file-sha256"] == hashlib.sha256(mcap.read_bytes()).hexdigest()
    assert header["seal-signature"].startswith("not signed")
    assert header["record-calibration-sha256"] == hashlib.sha256(calib.read_bytes()).hexdigest()
    assert header["record-software"].startswith("crossfield ") and re.match(r"\d{4}-\d\d-\d\dT", header["record-date"])
    assert header["record-operator"].startswith("not stated")
    assert "scale bar" in page and "certified length 100 mm" in page
    record = json.loads(first.with_suffix(".json").read_text())["record"]
    assert record["integrity"]["chain_head"] == integrity.chain_sha256
    assert record["calibration_sha256"] == header["record-calibration-sha256"]
    recorded = read_verification_recording(mcap)
    assert [n for n, _ in recorded.named_frames] == [p.name for p in scale_bar_positions()]
    assert recorded.certified_mm == 100.0 and recorded.mpe_mm == 0.05
    assert recorded.stages["centroid"]["plugin"] == DEFAULT_PLUGINS["centroid"]
    # auditable like a session: chain, seal, and the positions evaluated again bit for bit
    report = audit(mcap, make_plugin_manager(), expect_head=integrity.chain_sha256)
    assert report.kind == "verification" and report.passed, format_report(report)
    assert report.reproduction["messages_identical"] == report.reproduction["messages_compared"] == 8
    e = json.loads(message_data(mcap, "/verification/position", 2))["error_mm"]
    edited = tmp_path / "edited.mcap"
    rewrite_mcap(
        mcap,
        edited,
        lambda ms: [
            edit_json(m, lambda d: d.update(error_mm=e + 0.01))
            if m.topic == "/verification/position" and m.sequence == 2
            else m
            for m in ms
        ],
    )
    report = audit(edited, make_plugin_manager())
    assert not report.passed
    assert [(p.kind, p.topic, p.sequence) for p in report.integrity.problems] == [
        ("changed", "/verification/position", 2)
    ]
    assert [
        (d["topic"], d["sequence"], d["path"], d["recorded"], d["replayed"])
        for d in report.reproduction["differences"]
    ] == [("/verification/position", 2, "error_mm", e + 0.01, e)]
    again = tmp_path / "again"
    assert main(["verify", "--recording", str(mcap), "--calibration", str(calib), "-o", str(again)]) == 0
    a = json.loads(first.with_suffix(".json").read_text())
    b = json.loads(again.with_suffix(".json").read_text())
    assert [p["error_mm"] for p in a["positions"]] == [p["error_mm"] for p in b["positions"]]
    assert b["mpe_mm"] == 0.05 and b["certified_length_mm"] == 100.0
    # the recorded pairs with a calibration whose baseline is 0.3 % long: E = +0.3 mm, FAIL
    bad = dataclasses.replace(truth, t_lower_upper=np.asarray(truth.t_lower_upper) * 1.003)
    bad_path = write_stereo_calibration(tmp_path / "bad.yml", bad)
    out = tmp_path / "bad"
    assert main(["verify", "--recording", str(mcap), "--calibration", str(bad_path), "-o", str(out)]) == 1
    assert "FAIL" in capsys.readouterr().out
    data = json.loads(out.with_suffix(".json").read_text())
    assert not data["passed"] and data["max_abs_error_mm"] > 0.25
    np.testing.assert_allclose([p["error_mm"] for p in data["positions"]], 0.3, atol=0.03)
    assert 'id="figure-verification"><svg' in out.with_suffix(".html").read_text()


def test_verify_recording_errors_are_one_line(tmp_path, capsys):
    calib = write_stereo_calibration(tmp_path / "truth.yml", station_calibration())
    other = tmp_path / "other.mcap"
    other.write_bytes(b"not an mcap file at all")
    assert main(["verify", "--recording", str(other), "--calibration", str(calib)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("crossfield: error:") and "other.mcap" in err and "Traceback" not in err
    assert (
        main(["verify", "--recording", str(other), "--scenario", "station", "--calibration", str(calib)]) == 2
    )
    assert "give one" in capsys.readouterr().err
    assert main(["verify", "--calibration", str(calib), "--record", str(other)]) == 2
    assert "other.mcap exists; a recording is not overwritten" in capsys.readouterr().err
