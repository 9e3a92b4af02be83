"""Audit: integrity chain, provenance and reproduction (pipeline/recording/integrity.py, pipeline/audit.py)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from session_tools import Msg, edit_json, record_session, rewrite_mcap

from crossfield.audit import audit, format_report
from crossfield.cli import main
from crossfield.recording.integrity import GENESIS, INTEGRITY_FORMAT, verify
from crossfield.recording.reader import open_recording
from crossfield.registry import make_plugin_manager
from crossfield.replay import replay_session

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("audit")
    record_session(out, "orig")
    return out / "orig" / "session.mcap"


def kinds(result):
    return sorted({p.kind for p in result.problems})


def message(path, topic, sequence):
    with open_recording(path) as rec:
        return next(m for m in rec.messages(topic, decode=False) if m.sequence == sequence)


def test_untouched_recording_passes(recorded):
    report = audit(recorded, make_plugin_manager())
    assert report.passed and report.complete and report.intact
    assert report.integrity.problems == [] and report.integrity.final_record
    assert report.integrity.covered == report.integrity.messages > 40
    prov = report.provenance
    assert prov["passed"] and prov["plan"]["ok"] and prov["calibration"]["ok"]
    assert prov["plan"]["sha256"] == prov["session"]["plan_sha256"]
    assert prov["calibration"]["recorded_sha256"] == prov["calibration"]["sha256"]
    assert prov["machine"]["hostname"] and prov["machine"]["cpu_count"] >= 1
    assert prov["plugins"]["centroid"]["name"] == "weighted" and prov["packages"]["numpy"]
    repro = report.reproduction
    assert repro["passed"] and repro["differences"] == [] and repro["only_recorded"] == []
    assert repro["messages_identical"] == repro["messages_compared"] > 30
    assert "Audit: PASS" in format_report(report)


def test_chain_follows_the_documented_formula(recorded):
    """Recompute h_k by hand (docs/recording.md) over the messages in file order."""
    h = hashlib.sha256(INTEGRITY_FORMAT.encode()).digest()
    assert h == GENESIS
    records = []
    with open_recording(recorded) as rec:
        for m in rec.messages(decode=False, file_order=True):
            if m.topic == "/integrity":
                records.append((h.hex(), json.loads(m.data)))
                continue
            t = m.topic.encode()
            h = hashlib.sha256(
                h
                + len(t).to_bytes(4, "little")
                + t
                + m.log_time_ns.to_bytes(8, "little")
                + m.sequence.to_bytes(4, "little")
                + hashlib.sha256(m.data).digest()
            ).digest()
    assert len(records) >= 5 and records[-1][1]["final"] and not any(r["final"] for _, r in records[:-1])
    for head, doc in records:
        assert doc["chain_sha256"] == head
    assert [doc["index"] for _, doc in records] == list(range(len(records)))
    assert verify(recorded).chain_sha256 == h.hex()


def test_flipped_byte_in_an_image_is_named(recorded, tmp_path):
    target = message(recorded, "/camera/upper/image", 1)
    blob = bytearray(recorded.read_bytes())
    probe = target.data[-300_000:-299_900]
    at = blob.find(probe)
    assert at > 0 and blob.find(probe, at + 1) < 0
    blob[at + 7] ^= 0x01  # one bit of one pixel
    damaged = tmp_path / "flipped.mcap"
    damaged.write_bytes(bytes(blob))
    report = audit(damaged, make_plugin_manager())
    assert not report.passed and not report.intact
    changed = [p for p in report.integrity.problems if p.kind == "changed"]
    assert [(p.topic, p.sequence, p.log_time_ns) for p in changed] == [
        ("/camera/upper/image", 1, target.log_time_ns)
    ]
    crc = [p for p in report.integrity.problems if p.kind == "crc"]
    assert len(crc) == 1 and "/camera/upper/image sequence 1" in crc[0].detail
    assert kinds(report.integrity) == ["changed", "crc"]
    text = format_report(report)
    assert "changed: /camera/upper/image sequence 1 at" in text and "bad CRC-32" in text


def test_removed_message_is_named(recorded, tmp_path):
    gone = message(recorded, "/registration", 1)
    edited = tmp_path / "removed.mcap"
    rewrite_mcap(
        recorded, edited, lambda ms: [m for m in ms if not (m.topic == "/registration" and m.sequence == 1)]
    )
    report = audit(edited, make_plugin_manager())
    assert not report.passed
    assert [(p.kind, p.topic, p.sequence, p.log_time_ns) for p in report.integrity.problems] == [
        ("removed", "/registration", 1, gone.log_time_ns)
    ]
    repro = report.reproduction
    assert not repro["passed"] and repro["differences"] == []
    assert [(m["topic"], m["sequence"]) for m in repro["only_replayed"]] == [("/registration", 1)]


def test_edited_result_is_named(recorded, tmp_path):
    original = json.loads(message(recorded, "/measurement", 2).data)
    value = original["characteristics"][3]["measured_mm"]

    def edit(ms):
        return [
            edit_json(m, lambda d: d["characteristics"][3].update(measured_mm=value + 0.05))
            if m.topic == "/measurement" and m.sequence == 2
            else m
            for m in ms
        ]

    edited = tmp_path / "edited.mcap"
    rewrite_mcap(recorded, edited, edit)
    report = audit(edited, make_plugin_manager())
    assert not report.passed
    assert [(p.kind, p.topic, p.sequence) for p in report.integrity.problems] == [
        ("changed", "/measurement", 2)
    ]
    assert [
        (d["topic"], d["sequence"], d["path"], d["recorded"], d["replayed"])
        for d in report.reproduction["differences"]
    ] == [("/measurement", 2, "characteristics[3].measured_mm", value + 0.05, value)]


def test_reordered_messages_and_edited_metadata_are_named(recorded, tmp_path):
    def swap(ms):
        i = next(k for k, m in enumerate(ms) if m.topic == "/centroids/upper" and m.sequence == 0)
        j = next(k for k, m in enumerate(ms) if m.topic == "/centroids/lower" and m.sequence == 0)
        ms[i], ms[j] = ms[j], ms[i]
        return ms

    def config(meta):
        return [(n, {**r, "source": "someone else's"} if n == "crossfield.config" else r) for n, r in meta]

    edited = tmp_path / "reordered.mcap"
    rewrite_mcap(recorded, edited, swap, config)
    result = verify(edited)
    found = [(p.kind, p.topic, p.sequence) for p in result.problems]
    assert ("reordered", "/centroids/upper", 0) in found or ("reordered", "/centroids/lower", 0) in found
    assert all(k in ("reordered", "metadata") for k, _, _ in found)
    assert [p.detail for p in result.problems if p.kind == "metadata"] == [
        "changed: metadata 'crossfield.config' differs from its recorded digest"
    ]


def test_a_removed_integrity_record_is_named(recorded, tmp_path):
    def drop(ms):
        records = [k for k, m in enumerate(ms) if m.topic == "/integrity"]
        del ms[records[2]]
        return ms

    edited = tmp_path / "no-record.mcap"
    rewrite_mcap(recorded, edited, drop)
    details = [p.detail for p in verify(edited).problems]
    assert any("/integrity record #3 found where #2 was expected" in d for d in details)
    assert any("does not link to the record before it" in d for d in details)


def test_a_log_line_the_replay_cannot_see_is_a_note_not_a_failure(recorded, tmp_path):
    """A live run may log device events (link lost and back) that a replay of the
    recorded bytes cannot see: the chain still names the line, the reproduction
    lists it as a note and passes."""
    from foxglove_schemas_protobuf.Log_pb2 import Log

    from crossfield.recording.codec import log_message, protobuf_schema

    def add(ms):
        at = next(k for k, m in enumerate(ms) if m.topic == "/reference")
        t = ms[at].log_time
        ms.insert(
            at, Msg("/log", t, 0, log_message("warning", "romer-serial: link lost, back after 0.4 s", t))
        )
        return ms

    edited = tmp_path / "log.mcap"
    rewrite_mcap(recorded, edited, add, new_channels={"/log": ("protobuf", protobuf_schema(Log))})
    report = audit(edited, make_plugin_manager())
    assert [(p.kind, p.topic) for p in report.integrity.problems] == [("added", "/log")]
    repro = report.reproduction
    assert repro["passed"] and repro["differences"] == []
    # The live run's own device log lines (port opened, points imported) are
    # notes of the same kind; the inserted line is among them.
    noted = [n["recorded"] for n in repro["log_differences"]]
    assert "romer-serial: link lost, back after 0.4 s" in noted
    assert all(line.startswith("romer-serial") for line in noted)
    assert "log lines are not results" in format_report(report)


def test_cli_audit_json_and_exit_status(recorded, tmp_path, capsys):
    assert main(["audit", str(recorded), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["passed"] and doc["integrity"]["passed"] and doc["reproduction"]["passed"]
    assert doc["provenance"]["machine"]["platform"]
    edited = tmp_path / "edited.mcap"
    rewrite_mcap(recorded, edited, lambda ms: [m for m in ms if m.topic != "/report"])
    assert main(["audit", str(edited)]) == 1
    out = capsys.readouterr().out
    assert "removed: /report sequence 0 at" in out and "Audit: FAIL" in out


def test_audit_of_a_replay_names_the_parent(recorded, tmp_path):
    summary = replay_session(
        recorded, make_plugin_manager(), plugins={"register": "horn"}, output_dir=tmp_path
    )
    report = audit(summary.info.out_dir / "session.mcap", make_plugin_manager())
    assert report.passed
    text = format_report(report)
    assert f"replay of {recorded.resolve()}" in text and "changed register: svd -> horn" in text


# --------------------------------------------------------------------------
# Damaged recordings
# --------------------------------------------------------------------------


def crossfield_command() -> list[str]:
    script = Path(sys.executable).with_name("crossfield")
    return [str(script)] if script.exists() else [sys.executable, "-m", "crossfield.cli"]


def count_images(path: Path) -> int:
    with open_recording(path) as rec:
        return sum(1 for _ in rec.messages("/camera/upper/image", decode=False))


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """A `crossfield run` of many pairs, SIGKILLed once some pairs are on disk."""
    out = tmp_path_factory.mktemp("killed")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        crossfield_command()
        + [
            "run",
            "--scenario",
            "station",
            "--frames",
            "200",
            "--seed",
            "3",
            "-o",
            str(out),
            "--name",
            "killed",
            "--no-rerun",
            "-q",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    path = out / "killed" / "session.mcap"
    deadline = time.monotonic() + 120
    try:
        # wait for about 8 pairs (8 MB each) on disk, mid-way through the 200
        while time.monotonic() < deadline and (not path.exists() or path.stat().st_size < 64e6):
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    return path


def test_killed_recording_replays_up_to_its_end(killed, tmp_path, capsys):
    pairs = count_images(killed)
    assert 5 <= pairs < 200
    with open_recording(killed) as rec:
        assert not rec.complete
    code = main(["replay", str(killed), "-o", str(tmp_path / "replayed.mcap"), "-q", "--no-rerun"])
    out = capsys.readouterr().out
    assert code == 1  # an incomplete session never passes
    assert "INCOMPLETE: the recording" in out and "is incomplete" in out
    assert "the last complete stereo pair is sequence" in out
    with open_recording(tmp_path / "replayed.mcap") as rec:
        replayed = sum(1 for _ in rec.messages("/camera/upper/image", decode=False))
        result = rec.metadata_doc("crossfield.result")
    assert replayed >= pairs - 1 and result["incomplete"] and not result["passed"]


def test_killed_recording_audits_as_incomplete_but_intact(killed, capsys):
    code = main(["audit", str(killed), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 1 and not doc["passed"] and not doc["complete"] and doc["intact"]
    integrity = doc["integrity"]
    assert {p["kind"] for p in integrity["problems"]} <= {"truncated", "uncovered"}
    assert any(p["kind"] == "truncated" for p in integrity["problems"])
    assert integrity["covered"] > 0 and "last message read is" in integrity["ends"]
    repro = doc["reproduction"]
    assert repro["passed"] and repro["differences"] == [] and repro["only_recorded"] == []
    assert main(["audit", str(killed)]) == 1
    text = capsys.readouterr().out
    assert "INCOMPLETE" in text and "intact up to where the file ends" in text


def test_truncated_file_is_replayed_and_audited_up_to_the_last_chunk(recorded, tmp_path):
    cut = tmp_path / "cut.mcap"
    data = recorded.read_bytes()
    second = message(recorded, "/camera/lower/image", 1)
    end = data.find(second.data[-1000:]) + 1000 + 5000  # shortly after pair 1's lower image
    cut.write_bytes(data[:end])
    summary = replay_session(cut, make_plugin_manager(), output_dir=tmp_path, record=False)
    assert [f.sequence for f in summary.frames] == [0, 1]
    assert "is incomplete" in summary.incomplete and "sequence 1" in summary.incomplete
    assert not summary.passed
    report = audit(cut, make_plugin_manager())
    assert report.intact and not report.complete and not report.passed
    assert "at byte" in report.integrity.ends
    shutil.rmtree(summary.info.out_dir, ignore_errors=True)
