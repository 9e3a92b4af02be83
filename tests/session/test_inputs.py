"""A path of the wrong kind, through the real CLI: one line on stderr naming what
the path is and what the command wants, exit status 2 (issue 27 items 1 and 2)."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.writer import Writer

from crossfield.cli import main
from crossfield.cli.inputs import kind_of
from crossfield.recording import layout as L
from session_tools import record_session


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded two-pair simulator session folder."""
    out = tmp_path_factory.mktemp("inputs")
    record_session(out, "s", frames=2)
    return out / "s"


def _profiled_mcap(path: Path, profile: str) -> Path:
    """An MCAP file whose header names ``profile`` (as calibrate/verify --record write)."""
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile=profile, library="crossfield/test")
        writer.finish()
    return path


def _one_error_line(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run the CLI, check exit 2 and one stderr line without a traceback; return it."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_kinds_are_recognised_by_content(folder: Path, tmp_path: Path) -> None:
    assert kind_of(folder) == "session-folder"
    assert kind_of(folder / "session.mcap") == "session-recording"
    assert kind_of(folder / "report.json") == "report"
    assert kind_of(folder / "session.mcap.seal.json") == "seal"
    assert kind_of(_profiled_mcap(tmp_path / "c.mcap", L.CALIBRATION_PROFILE)) == "calibration-recording"
    assert kind_of(_profiled_mcap(tmp_path / "v.mcap", L.VERIFICATION_PROFILE)) == "verification-recording"
    assert kind_of(tmp_path) == "folder"


def test_export_of_a_recording_is_one_line(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = _one_error_line(capsys, ["export", str(folder / "session.mcap"), "--csv", "-"])
    assert "session.mcap: a session recording" in line
    assert "export wants a session folder or its report.json" in line


@pytest.mark.parametrize(
    "argv, got, wants",
    [
        (lambda f: ["audit", str(f)], "a session folder", "audit wants a session, calibration or verification"),
        (lambda f: ["replay", str(f)], "a session folder", "replay wants a session recording"),
        (lambda f: ["compare", str(f / "report.json"), str(f / "session.mcap")], "report.json",
         "compare wants two session recordings"),
        (lambda f: ["view", str(f / "report.json")], "report.json", "view wants a session folder"),
        (lambda f: ["export", str(f / "session.mcap.seal.json"), "--csv", "-"], "a recording's seal",
         "export wants a session folder"),
        (lambda f: ["export", str(f.parent.parent), "--csv", "-"], "a folder without session.mcap",
         "export wants a session folder"),
        (lambda f: ["run", "--plan", str(f / "session.mcap"), "-o", str(f.parent / "never")],
         "a session recording", "run wants a TOML file for --plan"),
        (lambda f: ["run", "--config", str(f / "report.json"), "-o", str(f.parent / "never")],
         "report.json", "run wants a TOML file for --config"),
        (lambda f: ["crb", str(f / "session.mcap")], "a session recording", "crb wants a station file"),
    ],
    ids=["audit-folder", "replay-folder", "compare-report", "view-report", "export-seal", "export-empty-folder",
         "run-plan-recording", "run-config-report", "crb-station-recording"],
)
def test_a_path_of_the_wrong_kind_is_one_line(folder, capsys, argv, got, wants) -> None:
    line = _one_error_line(capsys, argv(folder))
    assert got in line and wants in line, line
    assert not (folder.parent / "never").exists()


@pytest.mark.parametrize("flag", ["--plan", "--config"])
def test_a_binary_file_as_toml_is_one_line(tmp_path, capsys, flag) -> None:
    binary = tmp_path / "noise.bin"
    binary.write_bytes(bytes(range(128, 256)))
    line = _one_error_line(capsys, ["run", flag, str(binary), "-o", str(tmp_path / "out")])
    assert f"{binary}: not a" in line and "not UTF-8 TOML text" in line, line


@pytest.mark.parametrize("profile, kind", [(L.CALIBRATION_PROFILE, "a calibration recording"),
                                           (L.VERIFICATION_PROFILE, "a verification recording")])
@pytest.mark.parametrize("command", ["view", "replay", "compare"])
def test_a_calibration_or_verification_recording_is_named(folder, tmp_path, capsys, profile, kind, command) -> None:
    recording = str(_profiled_mcap(tmp_path / "other.mcap", profile))
    argv = [command, recording] + ([str(folder / "session.mcap")] if command == "compare" else [])
    line = _one_error_line(capsys, argv)
    assert f"{recording}: {kind} (MCAP profile {profile!r}" in line, line
    assert f"{command} wants" in line and "ends early" not in line, line
    assert "crossfield audit" in line and ("calibrate --replay" in line or "verify --recording" in line), line
