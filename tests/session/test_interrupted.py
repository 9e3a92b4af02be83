"""A run that is interrupted (Ctrl-C) or whose source fails mid-run ends INCOMPLETE with a
report (issue 26, item 1; docs/faults.md, "Interrupted runs").

Through the real CLI in a subprocess: (a) a real SIGINT once two stereo pairs are done;
(b) a romer-serial reference on a real pty whose simulated arm hangs up in the middle of
the CMM import; (c) a second Ctrl-C while the session finishes. Each: what the report
says (INCOMPLETE, the reason, the pairs measured, every result partial and not_proven,
the seal), and that ``crossfield replay`` states the same and ``crossfield audit`` passes.
"""

from __future__ import annotations

import fcntl
import json
import os
import pty
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import jsonschema
import pytest
from session_tools import report_numbers, sigint_default

from crossfield.chain.interrupt import InterruptedAgain, OperatorInterrupts
from crossfield.chain.registry import make_plugin_manager
from crossfield.chain.runner import run_session
from crossfield.cli import main
from crossfield.config import parse_config
from crossfield.errors import PluginError
from crossfield.recording.reader import open_recording
from crossfield.recording.seal import sidecar_path

PAIRS = 40  # asked for; the run is stopped long before


def crossfield_command() -> list[str]:
    script = Path(sys.executable).with_name("crossfield")
    return [str(script)] if script.exists() else [sys.executable, "-m", "crossfield.cli"]


class Child:
    """``crossfield ARGS`` with its stderr on a pseudo-terminal (the progress line is
    redrawn there for every pair, so the test sees each pair as it is done)."""

    def __init__(self, args: list[str]) -> None:
        self.master, slave = pty.openpty()
        # a terminal states its size; tqdm draws nothing on one of 0 columns
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
        self.process = subprocess.Popen(
            crossfield_command() + args, stdout=subprocess.PIPE, stderr=slave, preexec_fn=sigint_default
        )
        os.close(slave)
        self.err = ""

    def expect(self, needle: str, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while needle not in self.err:
            assert time.monotonic() < deadline, f"no {needle!r} in {self.err!r}"
            assert self.process.poll() is None or self._read(0.0), f"exited without {needle!r}: {self.err!r}"
            self._read(0.2)

    def _read(self, timeout_s: float) -> bool:
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        if not ready:
            return False
        try:
            chunk = os.read(self.master, 65536)
        except OSError:  # EIO: the child closed the terminal
            return False
        self.err += chunk.decode(errors="replace").replace("\r\n", "\n")
        return bool(chunk)

    def finish(self, timeout_s: float = 120.0) -> tuple[int, str, str]:
        out, _ = self.process.communicate(timeout=timeout_s)
        while self._read(0.05):
            pass
        os.close(self.master)
        return self.process.returncode, out.decode(), self.err


def count_pairs(path: Path) -> int:
    with open_recording(path) as rec:
        return sum(1 for _ in rec.messages("/camera/lower/image", decode=False))


def check_sealed(folder: Path, report: dict) -> None:
    """report.json carries the seal of the finished recording: the sidecar's head and digest."""
    seal = json.loads(sidecar_path(folder / "session.mcap").read_text())
    assert report["integrity"]["chain_head"] == seal["chain_head"]
    assert report["integrity"]["file_sha256"] == seal["file_sha256"]
    with open_recording(folder / "session.mcap") as rec:
        assert rec.complete
        result = rec.metadata_doc("crossfield.result")
    assert result["incomplete"] == report["incomplete_reason"] and result["passed"] is False


def check_replay_and_audit(folder: Path, tmp_path: Path, capsys) -> None:
    """Replay states the same INCOMPLETE reason and the same partial figures; audit passes."""
    report = json.loads((folder / "report.json").read_text())
    code = main(["replay", str(folder / "session.mcap"), "-o", str(tmp_path / "replay.mcap"), "-q", "--no-rerun"])
    out = capsys.readouterr().out
    assert code == 1 and f"INCOMPLETE: {report['incomplete_reason']}" in out and "Result: PASS" not in out
    replayed = json.loads((tmp_path / "replay" / "report.json").read_text())
    assert report_numbers(replayed) == report_numbers(report)  # reason, stop, every partial figure
    code = main(["audit", str(folder / "session.mcap"), "--expect-head", report["integrity"]["chain_head"]])
    text = capsys.readouterr().out
    assert code == 0, text
    assert re.search(r"^integrity +PASS", text, re.M) and re.search(r"^reproduction +PASS", text, re.M)
    assert re.search(r"^seal +PASS", text, re.M) and "Audit: PASS" in text
    assert f"session INCOMPLETE (as its report says): {report['incomplete_reason']}" in text


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory) -> tuple[Path, int, str, str]:
    """`crossfield run` of the station scenario sent a real SIGINT once its second pair is done."""
    out = tmp_path_factory.mktemp("interrupted")
    child = Child(["run", "--scenario", "station", "--frames", str(PAIRS), "--seed", "3", "-o", str(out),
                   "--name", "s", "--no-rerun"])  # fmt: skip
    try:
        child.expect(f" 2/{PAIRS} [")  # the pairs bar (crossfield.progress): 2 pairs done
        child.process.send_signal(signal.SIGINT)
        code, stdout, stderr = child.finish()
    finally:
        if child.process.poll() is None:
            child.process.kill()
    return out / "s", code, stdout, stderr


def test_sigint_writes_an_incomplete_report_of_the_pairs_measured(interrupted):
    folder, code, stdout, stderr = interrupted
    assert code == 130, stderr
    report = json.loads((folder / "report.json").read_text())
    pairs = count_pairs(folder / "session.mcap")
    assert 2 <= pairs < PAIRS  # the pair in progress when the signal came is finished, then no more
    reason = f"interrupted by the operator (SIGINT) after {pairs} of {PAIRS} stereo pairs"
    assert report["incomplete"] is True and report["incomplete_reason"] == reason and report["passed"] is False
    assert report["stop"] == {"kind": "interrupted", "stage": "acquire", "source": "simulator", "frames": pairs,
                              "message": ""}  # fmt: skip
    assert report["frames_processed"] == pairs and report["frames_failed"] == 0
    assert report["characteristics"]
    for c in report["characteristics"]:
        assert c["partial"] is True and c["decision"] == "not_proven" and c["passed"] is False
        assert c["n_frames"] == pairs
        # the partial figures are real measurements: within 2 U (4 u) of the simulator's truth
        assert abs(c["measured_mm"] - c["actual_mm"]) <= 2 * c["expanded_uncertainty_mm"], c
    check_sealed(folder, report)
    html = (folder / "report.html").read_text()
    assert "INCOMPLETE" in html and reason in html and "not proven (partial)" in html and "PASS</div>" not in html
    assert f"Result: INCOMPLETE ({reason})" in stdout and "session written to" in stdout
    assert f"crossfield: session INCOMPLETE: {reason}; report in {folder}" in stderr
    with open_recording(folder / "session.mcap") as rec:
        (stop,) = [m.decoded for m in rec.messages("/session/stop")]
        for topic in ("/session/stop", "/report"):  # each valid under the schema the file carries
            validator = jsonschema.Draft202012Validator(json.loads(rec.schema(topic)))
            for m in rec.messages(topic):
                validator.validate(m.decoded)
    assert stop["reason"] == reason and stop["frames"] == pairs


def test_replay_and_audit_agree_with_the_interrupted_report(interrupted, tmp_path, capsys):
    check_replay_and_audit(interrupted[0], tmp_path, capsys)


def station_arm(**faults):
    """The station scenario's simulated arm (seed 3), as `crossfield run --seed 3` probes it."""
    from crossfield.plugins.acquire_simulator import SimulatorSource
    from crossfield.simulator.arm import SimulatedArm

    return SimulatedArm(SimulatorSource(scenario="station", frames=1, seed=3).arm_probes(), **faults)


def test_an_arm_that_hangs_up_mid_import_ends_incomplete_replayed_and_audited(tmp_path, capsys):
    """romer-serial on a real pty; the arm's end is closed after its 5th point (one every
    0.1 s; a line still in the pty when it closes is lost) and stays away."""
    arm = station_arm(line_delay_s=0.1, unplug_after={4: 60.0})
    with arm.serve_pty() as port:
        child = Child(["run", "--scenario", "station", "--frames", "3", "--seed", "3", "-o", str(tmp_path),
                       "--name", "arm", "--no-rerun", "-q", "--report", "json",
                       "--option", f"reference.port={json.dumps(port)}",
                       "--option", "reference.timeout_s=0.5"])  # fmt: skip
        code, stdout, stderr = child.finish()
    folder = tmp_path / "arm"
    assert code == 2, stderr
    report = json.loads((folder / "report.json").read_text())
    reason = report["incomplete_reason"]
    assert reason.startswith(f"reference source romer-serial failed: romer-serial: {port}: lost the connection")
    with open_recording(folder / "session.mcap") as rec:  # the bytes read before the hang-up are kept
        raw = [(m.channel_metadata.get("content"), m.data) for m in rec.messages("/cmm/raw", file_order=True)]
    assert [json.loads(d)["event"] for content, d in raw if content == "link-events"] == ["down"]
    points = sum(d.count(b"$CFP,") for content, d in raw if content != "link-events")
    assert 1 <= points <= 5 and f"did not come back within 0.5 s: {points} of 21 points arrived" in reason
    assert reason.endswith("(during the CMM import, before the first stereo pair)")
    assert report["stop"]["kind"] == "source_error" and report["stop"]["stage"] == "reference"
    assert report["passed"] is False and report["frames_processed"] == 0 and report["reference"]["n_points"] == 0
    assert report["characteristics"] and all(
        c["partial"] and c["decision"] == "not_proven" and c["n_frames"] == 0 for c in report["characteristics"]
    )
    assert count_pairs(folder / "session.mcap") == 0
    check_sealed(folder, report)
    assert f"crossfield: session INCOMPLETE: {reason}; report in {folder}" in stderr
    check_replay_and_audit(folder, tmp_path, capsys)


def test_a_second_ctrl_c_while_finishing_still_leaves_a_readable_recording(tmp_path, capsys):
    """The first Ctrl-C lands in the CMM import (the arm sends a point every 0.2 s), the
    second once the session says it stopped: no report is promised, the recording is closed."""
    arm = station_arm(line_delay_s=0.2)
    with arm.serve_pty() as port:
        child = Child(["run", "--scenario", "station", "--frames", "3", "--seed", "3", "-o", str(tmp_path),
                       "--name", "twice", "--no-rerun", "--option", f"reference.port={json.dumps(port)}"])
        try:
            while not arm._sent:  # the import is under way
                time.sleep(0.02)
            child.process.send_signal(signal.SIGINT)
            child.expect("session stopped: interrupted by the operator (SIGINT) during the CMM import")
            child.process.send_signal(signal.SIGINT)
            code, _, stderr = child.finish()
        finally:
            if child.process.poll() is None:
                child.process.kill()
    assert code == 130 and "crossfield: interrupted: interrupted again while the session was finishing" in stderr
    path = tmp_path / "twice" / "session.mcap"
    with open_recording(path) as rec:
        assert rec.complete  # closed on the way out
    assert main(["replay", str(path), "--no-record", "--no-rerun", "-q"]) == 1
    out = capsys.readouterr().out  # /session/stop was recorded before the line the test waited for
    assert "INCOMPLETE: interrupted by the operator (SIGINT) during the CMM import" in out
    with open_recording(path) as rec:
        ended = "crossfield.result" in rec.metadata()
    code = main(["audit", str(path)])
    text = capsys.readouterr().out
    if ended:  # the second Ctrl-C came after the recording was ended: it is whole, its report may be missing
        assert code == 0 and "Audit: PASS" in text
    else:  # before: the recording has no result record, and the audit says so
        assert code == 1 and "INCOMPLETE: the session did not end normally" in text and "Audit: FAIL" in text


def test_a_camera_that_fails_at_the_first_pair_still_gets_an_incomplete_report(tmp_path, monkeypatch):
    """No pair measured at all: the report is still written, INCOMPLETE, with no results."""
    import crossfield.plugins.acquire_simulator as simulator

    def frames(self):
        raise PluginError("camera upper: grab failed (cable pulled)")
        yield  # pragma: no cover - a generator

    monkeypatch.setattr(simulator.SimulatorSource, "frames", frames)
    data = {
        "session": {"output_dir": str(tmp_path), "name": "cam", "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": "station", "frames": 5, "seed": 3},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
    }
    summary = run_session(parse_config(data, "<test>"), make_plugin_manager())
    reason = (
        "acquisition source simulator failed: camera upper: grab failed (cable pulled) (after 0 of 5 stereo pairs)"
    )
    assert summary.incomplete == reason and summary.stop.kind == "source_error" and not summary.passed
    report = json.loads((tmp_path / "cam" / "report.json").read_text())
    assert report["incomplete_reason"] == reason and report["frames_processed"] == 0
    assert report["reference"]["n_points"] == 21  # the CMM import before the first pair was complete
    assert all(c["n_frames"] == 0 and c["decision"] == "not_proven" for c in report["characteristics"])
    check_sealed(tmp_path / "cam", report)


def test_the_sigint_handler_defers_the_first_inside_a_pair_and_ignores_the_third():
    handler = OperatorInterrupts()
    with handler.deferred():
        handler(signal.SIGINT, None)  # inside a pair: noted, the pair goes on
    assert handler.requested
    with pytest.raises(InterruptedAgain):
        handler(signal.SIGINT, None)
    handler(signal.SIGINT, None)  # the third while the recording is closed: ignored
    fresh = OperatorInterrupts()
    with pytest.raises(KeyboardInterrupt) as caught:  # waiting for the source: at once
        fresh(signal.SIGINT, None)
    assert not isinstance(caught.value, InterruptedAgain) and not fresh.requested
    with pytest.raises(InterruptedAgain):  # closing a recording: the second waits until the file is whole
        with fresh.shielded():
            fresh(signal.SIGINT, None)
            closed = True
    assert closed
