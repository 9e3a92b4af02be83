"""Faults end in a named, bounded, truthful outcome (issue 9, classes 9 and 11).

* A disk that fills while the recording is finished (or while frames are
  recorded) leaves no report saying PASS: the recording is closed and
  checked before any report is written; when that fails the reports say
  INCOMPLETE and why, the command exits non-zero, and what was written
  stays readable (the truncated file replays as INCOMPLETE).
* Every bad input of the issue's examples ends in one line naming the file
  or key, exit code 2, no traceback (through the real CLI, in a subprocess).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any, Literal, Mapping, Optional

import pytest

from crossfield.errors import RecordingError
from crossfield.recording import writer as writer_module
from crossfield.recording.reader import MCAP_MAGIC, open_recording
from crossfield.recording.seal import sidecar_path

from session_tools import record_session


def crossfield(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """The installed console script, as a user runs it."""
    script = Path(sys.executable).with_name("crossfield")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "crossfield.cli"]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


class _FillsUp:
    """A real file object on a device with ``budget`` bytes left: a write that
    does not fit writes what fits, then fails with ENOSPC (as write(2) does)."""

    def __init__(self, f: Any, budget: int) -> None:
        self._f = f
        self.left = budget

    def write(self, data: Any) -> int:
        data = bytes(data)
        if len(data) > self.left:
            self._f.write(data[: self.left])
            self.left = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.left -= len(data)
        return self._f.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


def _reports(folder: Path) -> dict[str, Any]:
    return json.loads((folder / "report.json").read_text(encoding="utf-8"))


def test_sealed_report_is_written_after_the_recording_is_closed(tmp_path: Path) -> None:
    summary = record_session(tmp_path, "ok", frames=2)
    folder = summary.info.out_dir
    mcap = folder / "session.mcap"
    report = _reports(folder)
    sidecar = json.loads(sidecar_path(mcap).read_text())
    # The seal in report.json is the one of the finished file on disk.
    assert report["integrity"]["chain_head"] == sidecar["chain_head"]
    from crossfield.recording.integrity import file_sha256

    assert report["integrity"]["file_sha256"] == file_sha256(mcap)
    # Written after the recording: the report is not older than the file's last byte.
    assert (folder / "report.json").stat().st_mtime_ns >= mcap.stat().st_mtime_ns
    assert report["passed"] is True and report["incomplete"] is False


def test_disk_full_while_finishing_the_recording_gives_incomplete_reports(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    html_report = {"plugin": "html"}  # report.html is checked below
    full = record_session(tmp_path, "full-size", frames=2, report=html_report)
    size = (full.info.out_dir / "session.mcap").stat().st_size
    # Room for every frame but not for the end of the file (/report, summary, footer).
    # Two recordings of the same session differ in size by up to ~2 KB (compressed
    # chunks of time stamps; measured 5 pairs of runs: -50..1870 bytes), and the
    # summary and footer alone are ~65 KB: 16 KB short always cuts inside the end.
    budget = size - 16_000
    real_open = open

    def open_on_full_disk(path: Any, mode: str = "r", *args: Any, **kw: Any) -> Any:
        return _FillsUp(real_open(path, mode, *args, **kw), budget)

    monkeypatch.setattr(writer_module, "open", open_on_full_disk, raising=False)
    with pytest.raises(RecordingError, match="No space left on device") as caught:
        record_session(tmp_path, "cut", frames=2, report=html_report)
    monkeypatch.undo()
    assert "INCOMPLETE" in str(caught.value)
    folder = tmp_path / "cut"
    mcap = folder / "session.mcap"
    assert mcap.stat().st_size == budget  # what fitted is on disk, nothing lost
    report = _reports(folder)
    assert report["passed"] is False and report["incomplete"] is True
    assert "No space left on device" in report["incomplete_reason"]
    assert report["frames_processed"] == 2
    assert "integrity" not in report and not sidecar_path(mcap).exists()
    html = (folder / "report.html").read_text(encoding="utf-8")
    assert "INCOMPLETE" in html and "No space left on device" in html and "PASS</div>" not in html
    # The truncated file reads back as incomplete and replays / audits as INCOMPLETE.
    with open_recording(mcap) as rec:
        assert not rec.complete
    replay = crossfield("replay", str(mcap), "-o", str(tmp_path / "replayed.mcap"), "-q", "--no-rerun")
    assert replay.returncode != 0 and "INCOMPLETE" in replay.stdout + replay.stderr
    assert "Traceback" not in replay.stderr
    audit = crossfield("audit", str(mcap))
    assert audit.returncode != 0 and "INCOMPLETE" in audit.stdout + audit.stderr
    assert "Traceback" not in audit.stderr


def _mount_tmpfs(where: Path, size: str) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    where.mkdir()
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)]).returncode == 0


def test_real_full_filesystem_during_a_run(tmp_path: Path) -> None:
    """A real small filesystem (tmpfs, mounted when the tests run as root) that
    fills with the second stereo pair of a ``crossfield run``."""
    mnt = tmp_path / f"small-{uuid.uuid4().hex[:6]}"
    if not _mount_tmpfs(mnt, "8m"):  # an lz4-compressed table3 pair is ~5.5 MB (uncompressed: 8 MB)
        pytest.skip("mounting a small tmpfs needs root (the ENOSPC file test above covers the same path)")
    try:
        run = crossfield(
            "run", "--scenario", "table3", "--frames", "3", "-o", str(mnt), "--name", "s", "--no-rerun", "-q"
        )
        kept = tmp_path / "kept.mcap"
        shutil.copyfile(mnt / "s" / "session.mcap", kept)
        reports = {p.name: p.read_text(encoding="utf-8", errors="replace") for p in (mnt / "s").glob("report.*")}
    finally:
        subprocess.run(["umount", str(mnt)])
    assert run.returncode == 2, run.stdout + run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "No space left on device" in lines[0] and "Traceback" not in run.stderr
    # No report says PASS: none could be written, or each says INCOMPLETE.
    for name, text in reports.items():
        assert "INCOMPLETE" in text or '"incomplete": true' in text, name
    assert kept.read_bytes()[:8] == MCAP_MAGIC
    replay = crossfield("replay", str(kept), "-o", str(tmp_path / "replayed.mcap"), "-q", "--no-rerun")
    assert replay.returncode != 0 and "INCOMPLETE" in replay.stdout + replay.stderr
    assert "Traceback" not in replay.stderr


# ---- bad input: one line naming the file or key, exit code 2, no traceback ----


def _magic_only(d: Path) -> Path:
    path = d / "magic.mcap"
    path.write_bytes(MCAP_MAGIC)  # exactly the 8 magic bytes
    return path


def _config(d: Path, text: str) -> Path:
    path = d / "station.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _a_file(d: Path) -> Path:
    path = d / "not-a-folder"
    path.write_text("x", encoding="utf-8")
    return path


RUN = ("run", "--frames", "1", "--no-rerun", "-q")

#: (case, command builder (folder -> argv), what the one error line must name)
BAD_INPUTS: list[tuple[str, Any, list[str]]] = [
    ("replay of the 8 magic bytes", lambda d: ["replay", str(_magic_only(d)), "-q"], ["magic.mcap"]),
    ("audit of the 8 magic bytes", lambda d: ["audit", str(_magic_only(d))], ["magic.mcap"]),
    (
        "view of the 8 magic bytes",
        lambda d: ["view", str(_magic_only(d)), "--screenshot", str(d / "shot.png")],
        ["magic.mcap"],
    ),
    ("compare of the 8 magic bytes", lambda d: ["compare", str(_magic_only(d)), str(_magic_only(d))], ["magic.mcap"]),
    ("replay of an empty file", lambda d: ["replay", str(_config(d, "")), "-q"], ["station.toml"]),
    ("output_dir naming a file", lambda d: [*RUN, "-o", str(_a_file(d))], ["output_dir", "not-a-folder"]),
    (
        "output_dir naming a file, in the config",
        lambda d: [*RUN, "--config", str(_config(d, f'[session]\noutput_dir = "{_a_file(d)}"\n'))],
        ["station.toml", "output_dir"],
    ),
    (
        "threshold_sigma a word",
        lambda d: [*RUN, "-o", str(d), "--config", str(_config(d, '[centroid]\nthreshold_sigma = "eight"\n'))],
        ["station.toml", "threshold_sigma", "number"],
    ),
    (
        "threshold_sigma a word, on the command line",
        lambda d: [*RUN, "-o", str(d), "--option", "centroid.threshold_sigma=eight"],
        ["threshold_sigma", "number"],
    ),
    (
        "threshold_sigma out of range",
        lambda d: [*RUN, "-o", str(d), "--option", "centroid.threshold_sigma=-3"],
        ["threshold_sigma", "> 0"],
    ),
    (
        "refine not a bool",
        lambda d: [*RUN, "-o", str(d), "--config", str(_config(d, '[triangulate]\nrefine = "yes"\n'))],
        ["station.toml", "refine", "true or false"],
    ),
    (
        "match_tolerance_mm negative",
        lambda d: [*RUN, "-o", str(d), "--config", str(_config(d, "[session]\nmatch_tolerance_mm = -1\n"))],
        ["station.toml", "match_tolerance_mm"],
    ),
    (
        "match_tolerance_mm not finite",
        lambda d: [*RUN, "-o", str(d), "--config", str(_config(d, "[session]\nmatch_tolerance_mm = nan\n"))],
        ["station.toml", "match_tolerance_mm"],
    ),
    (
        "rerun_image_every negative",
        lambda d: [*RUN, "-o", str(d), "--config", str(_config(d, "[session]\nrerun_image_every = -2\n"))],
        ["station.toml", "rerun_image_every"],
    ),
]


@pytest.mark.parametrize("case, argv, names", BAD_INPUTS, ids=[c[0] for c in BAD_INPUTS])
def test_bad_input_is_one_line_naming_it(tmp_path: Path, case: str, argv: Any, names: list[str]) -> None:
    done = crossfield(*argv(tmp_path), cwd=tmp_path)
    assert done.returncode == 2, (case, done.returncode, done.stdout, done.stderr)
    assert "Traceback" not in done.stderr + done.stdout
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    for name in names:
        assert name in lines[0], (name, lines[0])
    # Nothing was recorded: a refused input leaves no session behind.
    assert not list(tmp_path.rglob("session.mcap"))


_MADE: list[dict[str, Any]] = []


def _probe_factory(
    *,
    sigma: float = 1.0,
    count: int = 3,
    flag: bool = True,
    mode: Literal["fast", "exact"] = "fast",
    limit: Optional[float] = None,
    names: list[str] | None = None,
    extra: Mapping[str, Any] | None = None,
    untyped=0.5,
    anything: Any = None,
) -> Any:
    """A factory whose options carry every kind of annotation the registry checks."""
    _MADE.append(dict(sigma=sigma, count=count, flag=flag, mode=mode, limit=limit, untyped=untyped))
    return object()


def test_options_are_checked_against_the_declared_types() -> None:
    from crossfield.errors import ConfigError, PluginError
    from crossfield.chain.registry import Implementation

    impl = Implementation("centroid", "probe", _probe_factory, "", "test", "test", "0")
    ok = {"sigma": 2, "count": 4, "flag": False, "mode": "exact", "limit": 0.1, "names": ["a"], "extra": {"k": 1}}
    # Every value fits: the factory runs (what it makes is no centroid extractor, refused after it).
    with pytest.raises(PluginError, match="not a centroid implementation"):
        impl.create({**ok, "untyped": 1, "anything": "x"}, "f.toml: [centroid]")
    assert _MADE and _MADE[-1]["sigma"] == 2 and _MADE[-1]["mode"] == "exact"
    bad = [
        ("sigma", "eight", "a number"),
        ("sigma", True, "a number"),
        ("count", 2.5, "an integer"),
        ("flag", 1, "true or false"),
        ("mode", "slow", "one of 'fast', 'exact'"),
        ("limit", "none", "a number or none"),
        ("names", "a", "a list or none"),
        ("extra", [1], "a table or none"),
        ("untyped", "x", "a number"),  # the default's type when there is no annotation
    ]
    for key, value, expected in bad:
        with pytest.raises(ConfigError) as caught:
            impl.create({key: value}, "f.toml: [centroid]")
        text = str(caught.value)
        assert text.startswith("f.toml: [centroid]: option ") and repr(key) in text and expected in text, text

