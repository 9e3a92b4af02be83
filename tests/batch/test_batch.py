"""crossfield batch on Dask (pipeline/batch/): a real ``dask scheduler`` and two ``dask worker``
processes on 127.0.0.1, an archive of small simulator sessions (one tampered, one truncated,
one that is not MCAP at all), a worker killed mid-run, a client interrupted, and the embedded
default; every verdict checked against the per-session commands' own results."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from session_tools import Msg, rewrite_mcap, sigint_default

from crossfield.batch.report import JSON_NAME, sort_key
from crossfield.batch.tasks import characteristic_shifts, expanded_uncertainty
from crossfield.cli import main

BIN = Path(sys.executable).parent
GOOD = ("s0", "s1", "s2")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def archive(dask_processes, tmp_path_factory):
    """Three simulator sessions (2 stereo pairs; one recorded, two copies of its folder: a copy
    is as valid as its original), a tampered copy (bytes changed inside an image message,
    rewritten with valid CRCs by the real mcap writer), a truncated copy and a file that is not
    MCAP. (Recorded while the Dask processes of ``dask_processes`` start.)"""
    root = tmp_path_factory.mktemp("archive")
    args = ["run", "--scenario", "table3", "--frames", "2", "--no-rerun", "-o", str(root), "--name", GOOD[0]]
    assert main([*args, "--seed", "10", "-q"]) in (0, 1)
    for name in GOOD[1:]:
        shutil.copytree(root / GOOD[0], root / name)
    source = root / "s0" / "session.mcap"

    def tamper(msgs: list[Msg]) -> list[Msg]:
        out = []
        for m in msgs:
            if m.topic == "/camera/upper/image" and m.sequence == 1:
                data = bytearray(m.data)
                data[len(data) // 2] ^= 0xFF
                m = Msg(m.topic, m.log_time, m.sequence, bytes(data))
            out.append(m)
        return out

    rewrite_mcap(source, root / "tampered.mcap", tamper)
    data = source.read_bytes()
    (root / "truncated.mcap").write_bytes(data[: int(len(data) * 0.6)])
    (root / "junk.mcap").write_text("not a recording\n")
    (root / "garbled.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)  # MCAP magic, then damage
    return root


@pytest.fixture(scope="module")
def cluster(dask_processes):
    """The cluster of ``dask_processes`` once both workers are connected: (address, {name: Popen})."""
    from dask.distributed import Client

    address, workers = dask_processes
    with Client(address, timeout=60) as c:
        c.wait_for_workers(2, timeout=90)
    return address, workers


@pytest.fixture(scope="module")
def dask_processes():
    """``dask scheduler`` and two ``dask worker`` processes (no nanny, one thread each) on
    127.0.0.1 at random free ports, started (not waited for); yields (address, {name: Popen})."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [
        subprocess.Popen(
            [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], **quiet
        )
    ]
    workers = {}
    try:
        for name in ("w0", "w1"):  # a worker waits for its scheduler to listen
            workers[name] = subprocess.Popen(
                [
                    str(BIN / "dask"), "worker", address, "--nthreads", "1", "--no-nanny", "--name", name,
                    "--host", "127.0.0.1", "--no-dashboard", "--memory-limit", "1GiB",
                ],
                **quiet,
            )
            procs.append(workers[name])
        yield address, workers
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def inputs(archive: Path) -> list[str]:
    damaged = ("tampered.mcap", "truncated.mcap", "junk.mcap", "garbled.mcap")
    return [str(archive / n) for n in GOOD] + [str(archive / f) for f in damaged]


def mcap(path: str) -> str:
    return str(Path(path) / "session.mcap") if Path(path).is_dir() else str(Path(path).resolve())


def report_of(out: Path) -> dict:
    return json.loads((out / JSON_NAME).read_text())


def cli_json(capsys, argv: list[str]) -> tuple[int, dict | None]:
    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr().out
    return code, (json.loads(out) if out.strip().startswith("{") else None)


def one_entry_per_input(report: dict, given: list[str]) -> dict[str, dict]:
    paths = [e["path"] for e in report["sessions"]]
    assert sorted(paths) == sorted(mcap(p) for p in given) and len(set(paths)) == len(paths)
    return {e["path"]: e for e in report["sessions"]}


# ---- comparison with swapped plugins, on the external cluster ---------------------------


def test_batch_compare_matches_per_session_replay_and_compare(archive, cluster, tmp_path, capsys):
    address, _ = cluster
    out = tmp_path / "cmp"
    given = [str(archive / "s0"), str(archive / "truncated.mcap"), str(archive / "junk.mcap")]
    code = main(["batch", "compare", *given, "--centroid", "ellipse", "-o", str(out), "--scheduler", address])
    assert code == 1  # not every session PASSes (truncated, junk)
    report = report_of(out)
    assert report["complete"] and report["kind"] == "compare" and report["plugins"] == {"centroid": "ellipse"}
    entries = one_entry_per_input(report, given)
    assert entries[mcap(given[2])]["verdict"] == "ERROR" and "not an MCAP file" in entries[mcap(given[2])]["reason"]
    assert entries[mcap(given[1])]["verdict"] == "INCOMPLETE"
    # s0 against the per-session commands: crossfield replay --centroid ellipse, then crossfield compare
    own = tmp_path / "own.mcap"
    assert main(["replay", mcap(given[0]), "--centroid", "ellipse", "-o", str(own), "--no-rerun", "-q"]) in (0, 1)
    for path in given[:1]:
        entry = entries[mcap(path)]
        assert entry["verdict"] in ("PASS", "FAIL") and Path(entry["replay"]).is_file()
        code, result = cli_json(capsys, ["compare", mcap(path), entry["replay"], "--json"])
        assert code == 1 and result["differences"]  # another centroid plugin: the values move
        rows = {r["name"]: r for r in result["characteristics"]}
        assert {r["name"] for r in entry["characteristics"]} == set(rows) and rows
        for r in entry["characteristics"]:
            original = rows[r["name"]]["a"]
            assert r["shift_mm"] == rows[r["name"]]["delta_mm"]
            # report.json states U (issue 12): the batch uses it, not 2 u
            assert r["U_mm"] == original["expanded_uncertainty_mm"] and r["U_source"] == "expanded_uncertainty_mm"
            assert r["shift_over_U"] == pytest.approx(r["shift_mm"] / r["U_mm"], rel=1e-12)
            assert r["decision_changed"] == (original["passed"] != rows[r["name"]]["b"]["passed"])
        assert entry["verdict"] == ("FAIL" if any(r["decision_changed"] for r in entry["characteristics"]) else "PASS")
    # the batch's replay of s0 is the per-session replay: the same measured values, bit for bit
    _, same = cli_json(capsys, ["compare", str(own), entries[mcap(given[0])]["replay"], "--json"])
    assert [d for d in same["differences"] if d["path"].startswith("characteristics.")] == []
    for name, stats in report["distribution"].items():  # over the archive: the sessions' own shifts
        shifts = [r["shift_mm"] for e in entries.values() for r in e.get("characteristics", []) if r["name"] == name]
        assert stats["sessions"] == len(shifts) == 1
        assert (stats["shift_mm"]["min"], stats["shift_mm"]["max"]) == (min(shifts), max(shifts))
    html = (out / "batch-report.html").read_text()
    assert "<svg" in html and "ellipse" in html and "s0" in html
    assert 'id="record-header"' in html and "True" not in html and "False" not in html  # no Python reprs


# ---- interrupted client: a partial report marked incomplete -----------------------------


def test_interrupted_batch_leaves_a_partial_report(archive, cluster, tmp_path):
    address, _ = cluster
    out = tmp_path / "int"
    given = [str(archive / n) for n in GOOD] + [str(archive / "junk.mcap")]
    proc = subprocess.Popen(
        [str(BIN / "crossfield"), "batch", "audit", *given, "-o", str(out), "--scheduler", address, "-q"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=sigint_default,
    )
    deadline = time.monotonic() + 60
    try:
        while True:  # until one submitted session has finished
            if (out / JSON_NAME).exists():
                doc = report_of(out)
                if any(e["verdict"] != "ERROR" for e in doc["sessions"]):
                    break
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read().decode()
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, proc.stderr.read().decode()
    doc = report_of(out)
    if doc["finished"] < doc["inputs"]:  # the usual case: interrupted before the end
        assert not doc["complete"] and doc["not_finished"]
        assert "INCOMPLETE report" in (out / "batch-report.html").read_text()
    assert {e["path"] for e in doc["sessions"]}.isdisjoint(doc["not_finished"])
    assert len(doc["sessions"]) + len(doc["not_finished"]) == len(given) == doc["inputs"]
    assert any(e["verdict"] == "PASS" for e in doc["sessions"])
    # the same command again finishes the rest; what finished is not recomputed
    done = {Path(e["folder"]): (Path(e["folder"]) / "entry.json").stat().st_mtime_ns for e in doc["sessions"] if "folder" in e}
    assert main(["batch", "audit", *given, "-o", str(out), "--scheduler", address, "-q"]) == 1  # junk: ERROR
    again = report_of(out)
    assert again["complete"] and again["counts"] == {"PASS": 3, "FAIL": 0, "INCOMPLETE": 0, "ERROR": 1}
    assert {f: (f / "entry.json").stat().st_mtime_ns for f in done} == done
    assert len(list((out / "sessions").iterdir())) == len(GOOD)
    assert main(["batch", "compare", *given, "-o", str(out), "--scheduler", address, "-q"]) == 2  # another batch


# ---- audit with a worker killed mid-task --------------------------------------------------


def test_batch_audit_survives_a_killed_worker_and_matches_crossfield_audit(archive, cluster, tmp_path, capsys):
    from dask.distributed import Client

    address, workers = cluster
    out = tmp_path / "audit"
    given = inputs(archive)
    result: dict = {}
    run = threading.Thread(
        target=lambda: result.update(code=main(["batch", "audit", *given, "-o", str(out), "--scheduler", address]))
    )
    killed = None
    with Client(address, timeout=30) as watcher:
        names = {a: w["name"] for a, w in watcher.scheduler_info()["workers"].items()}
        run.start()
        deadline = time.monotonic() + 60
        while killed is None and time.monotonic() < deadline:
            busy = [a for a, keys in watcher.processing().items() if any("crossfield-audit" in str(k) for k in keys)]
            if busy:
                time.sleep(0.3)  # well inside the task (an audit replays the session)
                if watcher.processing().get(busy[0]):
                    killed = names[busy[0]]
                    workers[killed].send_signal(signal.SIGKILL)
                    workers[killed].wait(timeout=10)
            time.sleep(0.02)
    run.join(timeout=120)
    assert killed is not None and not run.is_alive()
    assert result["code"] == 1
    report = report_of(out)
    assert report["complete"] and report["finished"] == len(given)
    entries = one_entry_per_input(report, given)
    # one folder per submitted session, nothing left half-written
    folders = sorted(p.name for p in (out / "sessions").iterdir())
    assert len(folders) == len(given) - 1 and not [f for f in folders if f.startswith(".")]
    for path in given:
        entry = entries[mcap(path)]
        code, doc = cli_json(capsys, ["audit", mcap(path), "--json"])
        if doc is None:  # not a recording: crossfield audit refuses it with one error line
            assert code == 2 and entry["verdict"] == "ERROR"
            continue
        assert (code == 0) == (entry["verdict"] == "PASS")
        assert entry["file_sha256"] == doc["file_sha256"] and entry["complete"] == doc["complete"]
        assert entry["intact"] == doc["intact"]
        expected = "PASS" if doc["passed"] else ("INCOMPLETE" if doc["intact"] and not doc["complete"] else "FAIL")
        assert entry["verdict"] == expected
    assert entries[mcap(given[3])]["verdict"] == "FAIL" and "integrity:" in entries[mcap(given[3])]["reason"]
    assert entries[mcap(given[4])]["verdict"] == "INCOMPLETE"
    assert [entries[mcap(p)]["verdict"] for p in given[:3]] == ["PASS"] * 3
    garbled = entries[mcap(given[6])]  # submitted (it starts as MCAP does); the worker names the damage
    assert garbled["verdict"] == "ERROR" and "garbled.mcap" in garbled["reason"] and garbled["folder"]


# ---- the embedded default -----------------------------------------------------------------


@pytest.mark.filterwarnings("ignore:Port 8787 is already in use")  # another cluster's dashboard (shared machine)
def test_embedded_cluster_replay_reproduces_the_recorded_results(archive, tmp_path, capsys):
    out = tmp_path / "emb"
    code = main(["batch", "replay", str(archive / "s2"), "-o", str(out), "--workers", "1"])  # no --scheduler
    text = capsys.readouterr().out
    assert "Dask scheduler tcp://127.0.0.1:" in text and "worker(s)" in text
    report = report_of(out)
    (entry,) = report["sessions"]
    recorded = json.loads((archive / "s2" / "report.json").read_text())
    assert entry["verdict"] == ("PASS" if recorded["passed"] else "FAIL") and code == (0 if recorded["passed"] else 1)
    assert {c["name"]: c["measured_mm"] for c in entry["characteristics"]} == {
        c["name"]: c["measured_mm"] for c in recorded["characteristics"]
    }
    # the page names each characteristic's ISO 14253-1 decision, not a Python bool (was "passed True")
    page = (out / "batch-report.html").read_text()
    for c in recorded["characteristics"]:
        words = {"conforms": "conforms", "does_not_conform": "does not conform", "not_proven": "not proven"}
        assert f"{c['name']}: {c['measured_mm']:.4f} mm, {words[c['decision']]}" in page
    assert "passed True" not in page and "passed False" not in page and 'id="record-header"' in page


# ---- pieces ---------------------------------------------------------------------------------


def test_shift_relative_to_U_uses_the_expanded_uncertainty_when_reported():
    original = {"characteristics": [
        {"name": "A", "measured_mm": 100.0, "uncertainty_mm": 0.01, "passed": True},
        {"name": "B", "measured_mm": 50.0, "uncertainty_mm": 0.01, "expanded_uncertainty_mm": 0.03, "passed": True},
        {"name": "C", "measured_mm": 10.0, "uncertainty_mm": 0.02, "passed": True},
    ]}
    replayed = {"characteristics": [
        {"name": "A", "measured_mm": 100.005, "uncertainty_mm": 0.01, "passed": True},
        {"name": "B", "measured_mm": 50.015, "uncertainty_mm": 0.01, "passed": False},
    ]}
    rows = {r["name"]: r for r in characteristic_shifts(original, replayed)}
    assert rows["A"]["U_mm"] == 0.02 and rows["A"]["U_source"] == "2 x uncertainty_mm"
    assert rows["A"]["shift_over_U"] == pytest.approx(0.25) and not rows["A"]["decision_changed"]
    assert rows["B"]["U_mm"] == 0.03 and rows["B"]["U_source"] == "expanded_uncertainty_mm"
    assert rows["B"]["shift_over_U"] == pytest.approx(0.5) and rows["B"]["decision_changed"]
    assert rows["C"]["shift_mm"] is None and rows["C"]["decision_changed"]
    assert expanded_uncertainty({"uncertainty_mm": None}) == (None, "2 x uncertainty_mm")
    entries = [
        {"verdict": "PASS", "characteristics": [rows["A"]]},
        {"verdict": "ERROR", "characteristics": []},
        {"verdict": "FAIL", "characteristics": [rows["B"]]},
    ]
    assert [e["verdict"] for e in sorted(entries, key=sort_key)] == ["FAIL", "ERROR", "PASS"]


def test_unreadable_input_and_empty_glob_are_errors_with_their_reason(tmp_path):
    from crossfield.batch.inputs import expand_inputs

    locked = tmp_path / "locked.mcap"
    locked.write_bytes(b"\x89MCAP0\r\n")
    locked.chmod(0)
    found = {Path(i.given).name: i for i in expand_inputs([str(locked), str(tmp_path / "none-*.mcap"), str(tmp_path)])}
    if os.geteuid() != 0:  # root reads a file of mode 0
        assert "cannot be read" in found["locked.mcap"].error
    assert "matches no file" in found["none-*.mcap"].error
    assert found[tmp_path.name].error == f"{tmp_path / 'session.mcap'}: no such file"
