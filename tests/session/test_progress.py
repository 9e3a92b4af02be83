"""Progress on a terminal (crossfield.progress, docs/user-guide.md "Progress"): a real
``crossfield run`` under a pseudo-terminal draws a bar with an ETA; with -q, or with
stderr a pipe, it draws nothing. The rules themselves (one bar at a time, the
first-compile notice) are checked in-process on a stream that says it is a terminal."""

from __future__ import annotations

import errno
import fcntl
import io
import os
import re
import select
import struct
import subprocess
import sys
import termios
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace

import numba
import pytest

from crossfield import compile_notice, progress

# tqdm's "n/total [elapsed<remaining" with a remaining time (ETA) in it, e.g. "1/2 [00:01<00:01"
ETA = re.compile(r"pairs: .*\d+/2 \[\d\d:\d\d<\d\d:\d\d")
BAR = re.compile(r"\d+/\d+ \[")


def _command(*args: str) -> list[str]:
    script = Path(sys.executable).with_name("crossfield")
    return [str(script) if script.exists() else sys.executable, *([] if script.exists() else ["-m", "crossfield.cli"]), *args]


def _on_terminal(argv: list[str], cwd: Path, timeout: float = 300.0) -> tuple[int, str]:
    """Run ``argv`` with stdin, stdout and stderr on a new pseudo-terminal (120x40): (status, all output)."""
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, cwd=cwd, close_fds=True,
                            env={**os.environ, "TERM": "xterm"})
    os.close(slave)
    out = bytearray()
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 1.0)
            if ready:
                try:
                    data = os.read(master, 65536)
                except OSError as exc:  # EIO: the child closed its side of the terminal
                    if exc.errno != errno.EIO:
                        raise
                    break
                if not data:
                    break
                out += data
            elif proc.poll() is not None:
                break
        status = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
    return status, out.decode("utf-8", "replace")


# --report json: the bars are drawn while the pairs run; report.html's figures add only time here.
RUN = ("run", "--scenario", "table3", "--frames", "2", "--no-record", "--no-rerun", "--report", "json", "-o", "out")


def test_run_draws_a_bar_with_eta_on_a_terminal_only(tmp_path: Path) -> None:
    # The three runs are independent (own session folders): they run side by side, as two
    # cores allow, instead of one after the other.
    with ThreadPoolExecutor(max_workers=3) as pool:
        tty = pool.submit(_on_terminal, _command(*RUN, "--name", "tty"), tmp_path)
        quiet = pool.submit(_on_terminal, _command(*RUN, "--name", "quiet", "-q"), tmp_path)
        piped = pool.submit(subprocess.run, _command(*RUN, "--name", "pipe"), cwd=tmp_path, capture_output=True,
                            text=True, timeout=300)
        (status, text), (quiet_status, quiet_text), piped = tty.result(), quiet.result(), piped.result()
    assert status == 0, text
    assert ETA.search(text), text  # the pairs' bar with its ETA, drawn while the pairs run
    assert "Result: PASS" in text

    assert quiet_status == 0, quiet_text
    assert "Result: PASS" in quiet_text and not BAR.search(quiet_text) and "pairs:" not in quiet_text, quiet_text

    assert piped.returncode == 0, piped.stderr
    assert "Result: PASS" in piped.stdout
    assert not BAR.search(piped.stderr) and "pairs:" not in piped.stderr and "\r" not in piped.stderr, piped.stderr


class _Terminal(io.StringIO):
    """A stream that says it is a terminal (what tqdm and crossfield.progress ask)."""

    def isatty(self) -> bool:
        return True


def test_bar_rules_switch_terminal_and_one_at_a_time() -> None:
    tty, pipe = _Terminal(), io.StringIO()
    with progress.shown(False):
        assert not progress.drawing(stream=tty)
        with progress.bar(range(3), desc="off", stream=tty) as b:
            list(b)
    assert tty.getvalue() == ""
    with progress.shown(True):
        assert not progress.drawing(stream=pipe)
        list(progress.bar(range(3), desc="piped", stream=pipe))
        assert pipe.getvalue() == ""
        with progress.bar(total=2, desc="outer", unit="step", stream=tty) as outer:
            with progress.bar(total=5, desc="inner", stream=tty) as inner:
                assert inner.disable and not outer.disable  # one bar at a time: the outer one counts
            outer.update(2)
            outer.refresh()
        assert "outer" in tty.getvalue() and "2/2" in tty.getvalue() and "inner" not in tty.getvalue()
        with progress.bar(total=1, desc="after", stream=tty) as later:
            assert not later.disable  # the closed bars gave the terminal back


def _result(rms_mm: float, error: str | None = None) -> SimpleNamespace:
    fit = SimpleNamespace(rms_mm=rms_mm)
    return SimpleNamespace(error=error, registration=SimpleNamespace(fit=fit))


def test_session_observer_counts_pairs_and_keeps_warnings() -> None:
    tty = _Terminal()
    shown = progress.Progress(total=2, stream=tty, enabled=True)
    shown.on_session_start(session=None)
    shown.on_frame_done(result=_result(0.0179))
    shown.on_log(level="warning", message="link lost", timestamp_ns=0)
    shown.on_frame_done(result=_result(0.0181, error="frame 1: register: boom"))
    shown.on_session_end(summary=None)
    text = tty.getvalue()
    assert "pairs:" in text and "1/2" in text and "RMS 0.0179 mm" in text
    assert "warning: link lost" in text and "1 failed" in text
    pipe = io.StringIO()
    silent = progress.Progress(total=2, stream=pipe, enabled=True)
    silent.on_session_start(session=None)
    silent.on_frame_done(result=_result(0.02))
    silent.on_log(level="warning", message="link lost", timestamp_ns=0)
    silent.on_session_end(summary=None)
    assert pipe.getvalue() == "warning: link lost\n"  # no bar on a pipe, the warning kept


def test_first_compile_is_announced_once(monkeypatch: pytest.MonkeyPatch) -> None:
    tty = _Terminal()
    monkeypatch.setattr(sys, "stderr", tty)

    @numba.njit(cache=False)
    def twice(x):  # a kernel that is not in any cache: numba compiles it here
        return 2 * x

    @numba.njit(cache=False)
    def thrice(x):
        return 3 * x

    with progress.shown(True), compile_notice.announced():
        assert twice(2) == 4 and thrice(2) == 6 and twice(2.5) == 5.0  # three compilations
    assert tty.getvalue().count(compile_notice.MESSAGE) == 1
    tty.truncate(0)
    with progress.shown(False), compile_notice.announced():  # -q
        assert twice(1j) == 2j
    assert tty.getvalue().strip("\x00") == ""
