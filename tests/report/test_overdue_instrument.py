"""An instrument whose calibration fell due before the session, through the real CLI
(issue 27 item 8): a problem in the report, every decision not proven and exit 1,
unless ``[session] allow_overdue_instruments = true`` (recorded in the config)."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

from crossfield.cli import main
from crossfield.simulator.scenarios import build_scene

YESTERDAY = (dt.datetime.now(dt.timezone.utc).date() - dt.timedelta(days=1)).isoformat()
NEXT_YEAR = (dt.datetime.now(dt.timezone.utc).date() + dt.timedelta(days=365)).isoformat()


def _plan(tmp_path: Path, due: str) -> Path:
    """The table3 scenario's plan with one arm whose calibration is due on ``due``."""
    path = tmp_path / f"plan-{due}.toml"
    path.write_text(
        build_scene("table3").plan.text
        + f'\n[job]\npart = "Housing 42"\n\n[[job.instrument]]\nid = "ROMER-7525"\nkind = "CMM arm"\n'
        f'calibrated = "2020-01-01"\ndue = "{due}"\n',
        encoding="utf-8",
    )
    return path


def _run(tmp_path: Path, name: str, plan: Path, *extra: str) -> tuple[int, dict]:
    argv = ["run", "--scenario", "table3", "--frames", "2", "--seed", "4", "--plan", str(plan),
            "-o", str(tmp_path), "--name", name, "--no-rerun", "-q", *extra]
    status = main(argv)
    return status, json.loads((tmp_path / name / "report.json").read_text(encoding="utf-8"))


def test_an_overdue_instrument_makes_every_decision_not_proven(tmp_path, capsys) -> None:
    status, report = _run(tmp_path, "in-date", _plan(tmp_path, NEXT_YEAR))
    assert status == 0 and not any("ROMER-7525" in p for p in report["problems"])
    decided = {c["name"]: c["decision"] for c in report["characteristics"]}
    assert set(decided.values()) == {"conforms"}

    status, report = _run(tmp_path, "overdue", _plan(tmp_path, YESTERDAY))
    assert status == 1
    problem = [p for p in report["problems"] if "ROMER-7525" in p]
    assert len(problem) == 1 and f"fell due {YESTERDAY}" in problem[0] and "not proven" in problem[0]
    assert {c["decision"] for c in report["characteristics"]} == {"not_proven"}
    assert not any(c["passed"] for c in report["characteristics"])
    in_date = json.loads((tmp_path / "in-date" / "report.json").read_text(encoding="utf-8"))
    # the same measurement (same seed): only the decisions change, not the values or U
    for key in ("measured_mm", "expanded_uncertainty_mm"):
        assert [c.get(key) for c in report["characteristics"]] == [c.get(key) for c in in_date["characteristics"]]


def test_the_override_keeps_the_decisions_and_is_recorded(tmp_path) -> None:
    config = tmp_path / "station.toml"
    config.write_text("[session]\nallow_overdue_instruments = true\n", encoding="utf-8")
    status, report = _run(tmp_path, "allowed", _plan(tmp_path, YESTERDAY), "--config", str(config))
    assert status == 0
    assert {c["decision"] for c in report["characteristics"]} == {"conforms"}
    assert report["config"]["session"]["allow_overdue_instruments"] is True
    problem = [p for p in report["problems"] if "ROMER-7525" in p]
    assert len(problem) == 1 and "allow_overdue_instruments = true" in problem[0]
