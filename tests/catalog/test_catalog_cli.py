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


def test_run_adds_its_session_and_audit_anchors_it(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'c.sqlite'}"
    status = main(["run", "--scenario", "table3", "--frames", "2", "-o", str(tmp_path), "--name", "s1",
                   "--no-rerun", "--catalog", url])
    assert status == 0
    out = capsys.readouterr().out
    assert "catalog: session s1 added" in out
    with crossfield.catalog.open(url) as cat:
        assert list(cat.sessions()["id"]) == ["s1"] and len(cat.characteristics()) == 10
    assert main(["audit", str(tmp_path / "s1" / "session.mcap"), "--catalog", url]) == 0
    assert "proves: agreement with the catalog" in capsys.readouterr().out
    assert main(["catalog", "characteristics", "--catalog", url, "--name", "L03", "--csv"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split(",")[3] == "s1"


def test_run_with_an_unreachable_catalog_keeps_the_recording(tmp_path, capsys):
    status = main(["run", "--scenario", "table3", "--frames", "2", "-o", str(tmp_path), "--name", "s2",
                   "--no-rerun", "--catalog", "postgresql://nobody@127.0.0.1:1/none"])
    assert status == 0  # the measurement's status, not the catalog's
    assert "catalog: NOT added" in capsys.readouterr().out
    assert (tmp_path / "s2" / "session.mcap").exists() and (tmp_path / "s2" / "report.json").exists()
