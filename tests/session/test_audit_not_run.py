"""`crossfield audit --no-replay` through the real CLI: a check not run is "not run",
not a failure; the verdict and exit status go by what was checked (issue 27 item 3)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from crossfield.cli import main
from session_tools import record_session


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded, intact two-pair simulator session."""
    out = tmp_path_factory.mktemp("notrun")
    record_session(out, "s", frames=2)
    return out / "s" / "session.mcap"


def test_no_replay_on_an_intact_session_passes_what_was_checked(recording, capsys) -> None:
    assert main(["audit", str(recording), "--no-replay"]) == 0
    out = capsys.readouterr().out
    line = next(l for l in out.splitlines() if l.startswith("reproduction"))
    assert "not run" in line and "FAIL" not in line, line
    assert "Audit: PASS (reproduction not run)" in out, out
    assert main(["audit", str(recording), "--no-replay", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["passed"] is True and doc["reproduction"]["run"] is False
    assert doc["not_run"] == ["reproduction"]


def test_no_replay_still_fails_what_was_checked(recording, tmp_path, capsys) -> None:
    damaged = tmp_path / "damaged.mcap"
    data = bytearray(recording.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in a chunk: the integrity check fails
    damaged.write_bytes(bytes(data))
    assert main(["audit", str(damaged), "--no-replay"]) == 1
    out = capsys.readouterr().out
    assert "Audit: FAIL" in out and "reproduction   not run" in out, out
