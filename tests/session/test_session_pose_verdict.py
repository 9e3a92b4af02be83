"""Issue 26 item 8: the motion test reads the centroid plugin's own stated uncertainty,
so a plugin that understates it raises "station MOVED" (the example "squared" plugin
did: it propagated the background noise only), and a motion warning reaches the
verdict: the session is not PASS and report.json / the text report say why."""

from __future__ import annotations

import dataclasses
import importlib
import sys
from pathlib import Path

import numpy as np

from crossfield.api import run
from crossfield.chain.registry import make_plugin_manager
from crossfield.plugin_api import hookimpl
from crossfield.plugins.centroid_weighted import WeightedCentroids

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "crossfield-squared-centroid"


class PoseLines:
    """Collects the session-pose log lines."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        if message.startswith("session pose"):
            self.lines.append(message)


class Understated(WeightedCentroids):
    """The built-in weighted centroids stating a fifth of their sigma_uv (px)."""

    def extract(self, image: np.ndarray, camera: str, sequence: int):
        found = super().extract(image, camera, sequence)
        return dataclasses.replace(found, sigma_uv=np.asarray(found.sigma_uv) / 5.0, method="understated")


class UnderstatedPlugin:
    @hookimpl
    def register_centroids(self, register) -> None:
        register("understated", Understated, "weighted centroids, sigma_uv / 5 (test)")


def session(tmp_path: Path, centroid: str, plugin: object):
    pose = PoseLines()
    pm = make_plugin_manager(extra=[plugin])
    pm.register(pose)
    summary = run(scenario="table3", frames=4, seed=1, output_dir=tmp_path, name=centroid, record=False,
                  rerun=False, centroid=centroid, plugin_manager=pm)
    return summary, pose.lines


def test_a_moved_station_is_not_a_pass_and_the_report_says_why(tmp_path):
    summary, lines = session(tmp_path, "understated", UnderstatedPlugin())
    assert len(lines) == 1 and "the station MOVED during the session" in lines[0]
    assert all(c.passed for c in summary.characteristics)  # every length within its tolerance ...
    assert summary.station_moved == lines[0] and not summary.passed  # ... yet not PASS
    report = summary.report
    assert report["passed"] is False and report["station_moved"] == lines[0]
    assert f"session pose: {lines[0]}" in report["problems"]
    text = (tmp_path / "understated" / "report.json").read_text()
    assert "station MOVED" in text


def test_the_squared_example_states_an_uncertainty_its_scatter_agrees_with(tmp_path, monkeypatch):
    """Before: chi2 = 643.7 for 96 dof over 5 frames (its sigma_uv was the background
    noise term alone); with the photon noise and the background's error: static."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    module = importlib.import_module("crossfield_squared_centroid")
    try:
        summary, lines = session(tmp_path, "squared", module)
    finally:
        sys.modules.pop("crossfield_squared_centroid", None)
    assert len(lines) == 1 and "consistent with a static station" in lines[0], lines
    assert summary.station_moved is None and summary.passed
