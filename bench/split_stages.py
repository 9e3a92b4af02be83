"""Where a pair's wall time goes: the default chain's stages, timed between their hooks (on demand).

    .venv/bin/python bench/split_stages.py [--scenario station] [--frames 300] [--runs 3]

bench_pipeline's in-memory session (pre-rendered pairs, the CSV reference, the built-in
default stages), with an observer plugin that reads the clock at each stage hook of a pair:
``on_frame`` -> ``on_centroids`` (centroid, both images) -> ``on_camera_points``
(triangulate, with the eccentricity correction) -> ``on_registration`` (correspondence
and the fit) -> ``on_measurement`` (measure) -> ``on_frame_done``. Prints, per run, the
session's pairs/s and the wall ms per pair of each stage (the hooks' own observers
included), without the profiler's overhead; ``bench/profile_pipeline.py`` gives the
functions inside them. The machine is shared: compare code A/B in one window, alternating.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pluggy

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_pipeline import MemoryPlugin, pipeline_rate, write_reference_csv  # noqa: E402

from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.simulator.scenarios import build_scene  # noqa: E402

hookimpl = pluggy.HookimplMarker("crossfield")

#: the stage each hook ends, in the order of a pair
STAGE_OF_HOOK = (
    ("on_centroids", "centroid"),
    ("on_camera_points", "triangulate"),
    ("on_registration", "register"),
    ("on_measurement", "measure"),
    ("on_frame_done", "frame done"),
)


class StageClock:
    """Observer plugin: seconds spent in each stage of every pair, summed over a session."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last: float | None = None

    def _mark(self, stage: str) -> None:
        now = time.perf_counter()
        if self._last is not None:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self._last
        self._last = now

    @hookimpl
    def on_frame(self, frame) -> None:
        self._last = time.perf_counter()

    @hookimpl
    def on_centroids(self, centroids) -> None:
        self._mark("centroid")

    @hookimpl
    def on_camera_points(self, points) -> None:
        self._mark("triangulate")

    @hookimpl
    def on_registration(self, registration) -> None:
        self._mark("register")

    @hookimpl
    def on_measurement(self, measurement) -> None:
        self._mark("measure")

    @hookimpl
    def on_frame_done(self, result) -> None:
        self._mark("frame done")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="station")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    scene = build_scene(args.scenario)
    rng = np.random.default_rng(0)
    pairs = [scene.render_pair(k, rng, time.time_ns()) for k in range(8)]
    clock = StageClock()
    pm = make_plugin_manager(extra=[MemoryPlugin(scene, pairs), clock])
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        csv = out / "reference.csv"
        write_reference_csv(scene, csv)
        pipeline_rate(pm, csv, out, 5, False, "warmup")
        for run in range(args.runs):
            clock.seconds = {}
            rate, _ = pipeline_rate(pm, csv, out, args.frames, False, f"run{run}")
            ms = {stage: clock.seconds.get(stage, 0.0) / args.frames * 1e3 for _, stage in STAGE_OF_HOOK}
            stages = "  ".join(f"{stage} {value:.3f}" for stage, value in ms.items())
            print(f"run {run + 1}: {rate:6.1f} pairs/s | ms per pair: {stages} | frames {sum(ms.values()):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
