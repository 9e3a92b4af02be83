"""The benchmark guard (bench/run.py, bench/figures.py): same-run ratios against the
committed baseline, every figure more than 20 % worse flagged."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))

import figures  # noqa: E402


def test_compare_flags_what_is_worse_in_either_direction():
    base = {
        "a.lower": {"value": 2.0, "better": "lower"},
        "b.higher": {"value": 0.5, "better": "higher"},
        "c.lower": {"value": 2.0, "better": "lower"},
        "d.gone": {"value": 1.0, "better": "lower"},
    }
    now = {
        "a.lower": {"value": 2.5, "better": "lower"},  # 25 % slower
        "b.higher": {"value": 0.45, "better": "higher"},  # 11 % slower
        "c.lower": {"value": 1.0, "better": "lower"},  # twice as fast
    }
    changes, missing = figures.compare(base, now)
    worse = {c.figure: round(c.worse, 3) for c in changes}
    assert worse == {"a.lower": 0.25, "b.higher": 0.111, "c.lower": -0.5}
    assert missing == ["d.gone"]


def test_record_writes_only_when_the_guard_asks(tmp_path, monkeypatch):
    sink = tmp_path / "figures.jsonl"
    monkeypatch.delenv(figures.ENV, raising=False)
    figures.record("x.y", 1.5, "lower")
    assert not sink.exists()
    monkeypatch.setenv(figures.ENV, str(sink))
    figures.record("x.y", 1.5, "lower")
    figures.record("x.z", float("nan"), "higher")  # not a figure: left out
    assert figures.read_lines(sink) == {"x.y": {"value": 1.5, "better": "lower"}}
    with pytest.raises(ValueError, match="better"):
        figures.record("x.y", 1.0, "faster")


def run_guard(tmp_path: Path, *extra: str, slow: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "tests" / "slow_kernel")}
    env.pop(figures.ENV, None)
    if slow:
        env["CROSSFIELD_SLOW_KERNEL"] = "1"
    argv = [sys.executable, str(ROOT / "bench" / "run.py"), "--only", "bench_triangulate", "--quick",
            "--baseline", str(tmp_path / "baseline.json"), "--json", str(tmp_path / "run.json"), *extra]
    return subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120)


def test_the_guard_flags_a_slowed_kernel(tmp_path):
    """A baseline from one run, then the same bench with the triangulation made 3x slower
    (tests/slow_kernel/sitecustomize.py): its figure is flagged and the guard exits 1."""
    first = run_guard(tmp_path, "--update-baseline")
    assert first.returncode == 0, first.stdout + first.stderr
    baseline = json.loads((tmp_path / "baseline.json").read_text())["figures"]
    assert set(baseline) == {"triangulate.epipolar_vs_opencv"}
    slowed = run_guard(tmp_path, slow=True)
    assert slowed.returncode == 1, slowed.stdout + slowed.stderr
    assert "WORSE triangulate.epipolar_vs_opencv" in slowed.stdout
    measured = json.loads((tmp_path / "run.json").read_text())["figures"]["triangulate.epipolar_vs_opencv"]
    assert measured["value"] > 2 * baseline["triangulate.epipolar_vs_opencv"]["value"]
