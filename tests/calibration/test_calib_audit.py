"""A calibration recording is auditable like a session: chain, seal, re-solve (pipeline/audit/calibration.py).

One 10-view calibration of the simulated station (the views shared with
tests/calibration/test_calibrate.py through ``cached_calibration_views``) is solved and
recorded once; each test audits it or a tampered copy.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from session_tools import edit_json, rewrite_mcap

from crossfield.audit import audit, format_report
from crossfield.audit.calibration import PARAMETER_TOLERANCE_STD, parameter_vector
from crossfield.audit.chain import verify
from crossfield.calibration.record import (
    TOPIC_IMAGE,
    TOPIC_RESULT,
    read_calibration_recording,
    record_calibration,
)
from crossfield.calibration.solve import calibrate_images
from crossfield.chain.registry import make_plugin_manager
from crossfield.cli import main
from crossfield.recording.reader import open_recording
from crossfield.recording.seal import read_sidecar, sidecar_path
from crossfield.simulator.board_views import cached_calibration_views

NAMES = [f"sim view {k}" for k in range(10)]


@pytest.fixture(scope="module")
def solved():
    views = cached_calibration_views("station", 20, 1)
    images = views.images[:10]
    return images, views.bit_depth, calibrate_images(images, views.board, views.bit_depth, names=NAMES)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, solved):
    images, bit_depth, result = solved
    path = tmp_path_factory.mktemp("calaudit") / "cal.mcap"
    # uncompressed, so that a test can flip one bit of an image in the file's bytes
    sealed = record_calibration(path, images, NAMES, bit_depth, result, "test", compression="none")
    return path, sealed


def message(path, topic, sequence):
    with open_recording(path) as rec:
        return next(m for m in rec.messages(topic, decode=False) if m.sequence == sequence)


def test_recording_has_the_session_chain_and_seal(recorded, solved):
    path, sealed = recorded
    integrity = verify(path)
    assert integrity.passed and integrity.final_record and integrity.chain_sha256 == sealed.chain_head
    # images, detections (2 per view) and the result, every record chained
    assert integrity.messages == 10 * 4 + 1 and integrity.covered == integrity.entries
    side = read_sidecar(path)
    assert side["chain_head"] == sealed.chain_head and side["file_sha256"] == sealed.file_sha256
    back = read_calibration_recording(path)
    np.testing.assert_array_equal(back.images[4]["upper"], solved[0][4]["upper"])
    assert back.names == tuple(NAMES) and back.metadata["opencv_version"]


def test_untouched_calibration_recording_passes_audit_cli(recorded, solved, capsys):
    path, sealed = recorded
    assert main(["audit", str(path), "--expect-head", sealed.chain_head, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["kind"] == "calibration" and report["passed"] and report["complete"]
    assert report["seal"]["level"] == "agreement with a head kept elsewhere"
    repro = report["reproduction"]
    assert repro["passed"] and repro["differences"] == [] and repro["views_replayed"] == 10
    assert repro["messages_identical"] == repro["messages_compared"] == 1 + 20 + 1
    # the re-solve is an independent solve of the same images: it agrees with the recorded one
    assert repro["replayed"]["baseline_mm"] == pytest.approx(solved[2].baseline_mm, rel=1e-9)
    assert report["provenance"]["calibration"]["ok"]
    assert main(["audit", str(path), "--expect-head", "0" * 64, "--no-replay"]) == 1
    assert "is not the expected" in capsys.readouterr().out


def test_flipped_byte_in_a_board_image_is_named(recorded, tmp_path):
    path, _ = recorded
    topic = TOPIC_IMAGE.format(camera="upper")
    target = message(path, topic, 3)
    blob = bytearray(path.read_bytes())
    probe = target.data[-300_000:-299_900]
    at = blob.find(probe)
    assert at > 0 and blob.find(probe, at + 1) < 0
    blob[at + 7] ^= 0x01  # one bit of one pixel
    damaged = tmp_path / "flipped.mcap"
    damaged.write_bytes(bytes(blob))
    sidecar_path(damaged).write_bytes(sidecar_path(path).read_bytes())
    report = audit(damaged, make_plugin_manager(), reproduce=False)
    assert not report.passed and report.kind == "calibration"
    changed = [p for p in report.integrity.problems if p.kind == "changed"]
    assert [(p.topic, p.sequence) for p in changed] == [(topic, 3)]
    text = format_report(report)
    assert f"changed: {topic} sequence 3 at" in text and "Audit: FAIL" in text
    assert not report.seal["passed"] and "differs from its seal" in text  # nor its sidecar


def test_edited_result_is_named_by_chain_and_re_solve(recorded, solved, tmp_path):
    """T_x in the recorded result 1 um larger: the chain names the message, the re-solve the parameter."""
    path, _ = recorded
    result = solved[2]
    k = result.param_names.index("rig.Tx")
    value = float(result.params[k])

    def edit(ms):
        return [
            edit_json(m, lambda d: d["parameters"][k].update(value=value + 0.001))
            if m.topic == TOPIC_RESULT
            else m
            for m in ms
        ]

    edited = tmp_path / "edited.mcap"
    rewrite_mcap(path, edited, edit)
    report = audit(edited, make_plugin_manager())
    assert not report.passed
    assert [(p.kind, p.topic) for p in report.integrity.problems] == [("changed", TOPIC_RESULT)]
    diffs = report.reproduction["differences"]
    assert [(d["topic"], d["path"]) for d in diffs] == [(TOPIC_RESULT, f"parameters[{k}].value (rig.Tx)")]
    assert diffs[0]["recorded"] == value + 0.001
    assert diffs[0]["replayed"] == pytest.approx(value, abs=diffs[0]["tolerance"])
    assert diffs[0]["tolerance"] == pytest.approx(PARAMETER_TOLERANCE_STD * result.std[k])
    assert f"parameters[{k}].value (rig.Tx): recorded" in format_report(report)


def test_a_consistent_forgery_is_caught_by_the_re_solve(recorded, solved, tmp_path):
    """A file re-written by this code with a baseline 0.1 % longer is self-consistent (chain and
    seal pass) but does not reproduce: the result and the attached YAML's T are named."""
    images, bit_depth, result = solved
    cal = result.calibration
    T = np.asarray(cal.t_lower_upper) * 1.001
    forged_cal = dataclasses.replace(cal, t_lower_upper=T)
    params = result.params.copy()
    params[-3:] = T
    forged = dataclasses.replace(result, calibration=forged_cal, params=params)
    np.testing.assert_allclose(parameter_vector(forged_cal, 5)[-3:], T)
    out = tmp_path / "forged.mcap"
    record_calibration(out, images, NAMES, bit_depth, forged, "test")
    report = audit(out, make_plugin_manager(), expect_head=recorded[1].chain_head)
    assert report.integrity.passed and not report.reproduction["passed"] and not report.passed
    diffs = report.reproduction["differences"]
    in_result = {d["path"] for d in diffs if d.get("topic") == TOPIC_RESULT}
    in_file = {d["path"] for d in diffs if d.get("attachment") == "calibration.yml"}
    assert {
        f"parameters[{i}].value (rig.T{c})" for i, c in zip(range(len(params) - 3, len(params)), "xyz")
    } <= in_result
    assert "baseline_mm" in in_result
    assert {"R/T rig.Tx", "R/T rig.Ty", "R/T rig.Tz"} <= in_file
    assert not any(p.startswith(("M1", "M2")) for p in in_file)  # the intrinsics were not touched
    assert not report.seal["passed"]  # and the head kept elsewhere is the original's


def test_an_existing_recording_is_not_overwritten(recorded, tmp_path, capsys):
    path, _ = recorded
    before = path.read_bytes()
    out = tmp_path / "x.yml"
    assert main(["calibrate", "--replay", str(path), "-o", str(out), "--record", str(path)]) == 2
    assert "exists; a recording is not overwritten" in capsys.readouterr().err
    assert path.read_bytes() == before and not out.exists()  # refused before solving


def _flip_image_bit(path, out, sequence=3):
    """Copy ``path`` to ``out`` with one bit of upper image ``sequence`` flipped (a
    stretch of its pixels is found verbatim in the file: lz4 keeps noisy pixels as
    literals); the sidecar is copied along."""
    target = message(path, TOPIC_IMAGE.format(camera="upper"), sequence)
    blob = bytearray(path.read_bytes())
    for start in range(len(target.data) - 200_000, 0, -50_000):
        probe = target.data[start : start + 64]
        at = blob.find(probe)
        if at > 0 and blob.find(probe, at + 1) < 0:
            break
    else:
        raise AssertionError("no stretch of the image found verbatim in the file")
    blob[at + 7] ^= 0x01
    out.write_bytes(bytes(blob))
    sidecar_path(out).write_bytes(sidecar_path(path).read_bytes())
    return out


def test_calibrate_and_verify_sign_their_recordings_from_the_cli(recorded, tmp_path, capsys):
    """Issue 26 item 3: ``--signing-key`` on calibrate and verify. The signed calibration
    recording passes ``audit --public-key``; with one image bit flipped it fails; a bad key
    or one without ``--record`` is refused before anything is computed."""
    path, _ = recorded
    key = tmp_path / "station"
    assert main(["keygen", str(key)]) == 0
    capsys.readouterr()
    out = tmp_path / "again.yml"
    assert main(["calibrate", "--replay", str(path), "-o", str(out), "--signing-key", str(key)]) == 2
    assert "--signing-key signs a recording: give --record" in capsys.readouterr().err
    assert main(["calibrate", "--replay", str(path), "-o", str(out), "--record", str(tmp_path / "x.mcap"),
                 "--signing-key", str(tmp_path / "missing")]) == 2  # fmt: skip
    assert "missing: cannot read the signing key" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "x.mcap").exists()  # refused before the solve
    signed = tmp_path / "signed.mcap"
    argv = ["calibrate", "--replay", str(path), "-o", str(out), "--record", str(signed), "--no-report"]
    assert main([*argv, "--signing-key", str(key)]) == 0
    assert "signed; audit: crossfield audit" in capsys.readouterr().out
    assert read_sidecar(signed)["signature"]["public_key"]
    public = str(key.with_name(key.name + ".pub"))
    assert main(["audit", str(signed), "--public-key", public, "--no-replay", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["kind"] == "calibration" and report["seal"]["passed"]
    assert report["seal"]["level"] == "signed by the station's key"
    flipped = _flip_image_bit(signed, tmp_path / "flipped.mcap")
    assert main(["audit", str(flipped), "--public-key", public, "--no-replay"]) == 1
    text = capsys.readouterr().out
    assert "Audit: FAIL" in text and TOPIC_IMAGE.format(camera="upper") in text
    # an unsigned recording does not pass a check that asks for a signature
    assert main(["audit", str(path), "--public-key", public, "--no-replay"]) == 1
    capsys.readouterr()
    # verify: the same flag, the same refusal without --record
    calib = out
    assert main(["verify", "--calibration", str(calib), "--signing-key", str(key)]) == 2
    assert "give --record" in capsys.readouterr().err
