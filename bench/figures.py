"""The benchmarks' figures for the guard (``bench/run.py``, docs/benchmarks.md).

A bench calls :func:`record` for each figure the guard compares: a **ratio
against a baseline timed in the same run** (never an absolute time, which
depends on the machine and its load), with the direction that is better.
When ``CROSSFIELD_BENCH_JSON`` names a file (``bench/run.py`` sets it), each
figure is appended to it as one JSON line ``{"figure", "value", "better"}``;
otherwise :func:`record` does nothing, so a bench run by hand is unchanged.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

#: the environment variable naming the JSON-lines file the figures go to
ENV = "CROSSFIELD_BENCH_JSON"
#: "higher" or "lower": which way a figure is better
DIRECTIONS = ("higher", "lower")


def record(figure: str, value: float, better: str) -> None:
    """Append ``figure`` (``"<bench>.<what>"``, a same-run ratio) to the guard's file, if any."""
    if better not in DIRECTIONS:
        raise ValueError(f"better must be one of {DIRECTIONS}, got {better!r}")
    path = os.environ.get(ENV)
    if not path or not math.isfinite(value):
        return
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps({"figure": figure, "value": float(value), "better": better}) + "\n")


def read_lines(path: Path) -> dict[str, dict]:
    """figure -> {"value", "better"} from a JSON-lines file of :func:`record` (the last one wins)."""
    out: dict[str, dict] = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.strip():
            try:
                doc = json.loads(line)
                out[doc["figure"]] = {"value": float(doc["value"]), "better": doc["better"]}
            except (ValueError, KeyError, TypeError) as exc:
                raise ValueError(f"{path}:{number}: not a figure line: {exc}") from None
    return out


@dataclass(frozen=True)
class Change:
    """One figure against the baseline. worse: the fraction by which it is worse (negative: better)."""

    figure: str
    baseline: float
    value: float
    better: str

    @property
    def worse(self) -> float:
        if self.better == "higher":
            return self.baseline / self.value - 1.0 if self.value > 0 else math.inf
        return self.value / self.baseline - 1.0 if self.baseline > 0 else math.inf


def compare(baseline: dict[str, dict], current: dict[str, dict]) -> tuple[list[Change], list[str]]:
    """The changes of the figures in both, in the baseline's order, and the baseline's
    figures the current run did not produce. ``worse`` is a ratio of ratios: 0.25 means
    25 % slower relative to the bench's own baseline (higher-better figures inverted)."""
    changes = [
        Change(name, float(base["value"]), float(current[name]["value"]), base["better"])
        for name, base in baseline.items()
        if name in current
    ]
    return changes, [name for name in baseline if name not in current]
