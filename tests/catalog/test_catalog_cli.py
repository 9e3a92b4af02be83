"""``crossfield catalog``, ``crossfield run --catalog`` and ``crossfield audit --catalog``
through the crossfield CLI. Skipped until the catalog is wired into the CLI (issue 23's
integration notes: crossfield.catalog.commands add_parsers / add_run_flag / ingest_run /
add_audit_flag / audit_command)."""

from __future__ import annotations

import contextlib
import io

import pytest

import crossfield.catalog
from crossfield.cli import build_parser, main


def _wired() -> bool:
    parser = build_parser()
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            parser.parse_args(["catalog", "sessions"])
            parser.parse_args(["run", "--catalog", "x"])
            parser.parse_args(["audit", "x.mcap", "--catalog", "x"])
    except SystemExit:
        return False
    return True


pytestmark = pytest.mark.skipif(not _wired(), reason="crossfield catalog is not wired into the CLI yet")


def test_run_keeps_its_recording_when_the_catalog_is_down_then_add_and_audit_anchor_it(tmp_path, capsys):
    status = main(["run", "--scenario", "table3", "--frames", "2", "-o", str(tmp_path), "--name", "s1",
                   "--no-rerun", "--catalog", "postgresql://nobody@127.0.0.1:1/none"])
    assert status == 0  # the measurement's status, not the catalog's
    assert "catalog: NOT added" in capsys.readouterr().out
    folder = tmp_path / "s1"
    assert (folder / "session.mcap").exists() and (folder / "report.json").exists()
    url = f"sqlite:///{tmp_path / 'c.sqlite'}"
    assert main(["catalog", "add", str(folder), "--catalog", url]) == 0  # the catch-up
    with crossfield.catalog.open(url) as cat:
        assert list(cat.sessions()["id"]) == ["s1"] and len(cat.characteristics()) == 10
    assert main(["audit", str(folder / "session.mcap"), "--catalog", url]) == 0
    assert "proves: agreement with the catalog" in capsys.readouterr().out
    assert main(["catalog", "characteristics", "--catalog", url, "--name", "L03", "--csv"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split(",")[3] == "s1"


def test_run_with_a_configured_catalog_adds_its_session(tmp_path, capsys, monkeypatch):
    """[catalog] url of the config; the run itself is replaced by the folder it would write
    (the run above is the real one)."""
    from crossfield.catalog.commands import ingest_run
    from crossfield.catalog.synthetic import write_session
    from crossfield.config import load_config

    config_file = tmp_path / "station.toml"
    config_file.write_text(f'[catalog]\nurl = "{tmp_path / "c.sqlite"}"\nstation = "cell-3"\n')
    args = build_parser().parse_args(["run", "-c", str(config_file)])
    folder = write_session(tmp_path, "s9", 1_796_298_450_000_000_000, {"L01": 300.0})
    assert ingest_run(args, load_config(config_file), folder) == "added"
    with crossfield.catalog.open(tmp_path / "c.sqlite") as cat:
        assert list(cat.sessions()["station"]) == ["cell-3"]
