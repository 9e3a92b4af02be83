"""Profile the default chain per pair: cProfile of one in-memory session (on demand).

    .venv/bin/python bench/profile_pipeline.py [--frames 100] [--scenario station] [--record] [--top 30]

The session is bench_pipeline's (pre-rendered pairs in memory, the CSV
reference, the built-in default stages); prints the top entries by own time
and by cumulative time, per pair (ms), and writes the raw profile to
``--out`` (for ``snakeviz`` or ``python -m pstats``).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_pipeline import MemoryPlugin, pipeline_rate, write_reference_csv  # noqa: E402

from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.simulator.scenarios import build_scene  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--scenario", default="station")
    parser.add_argument("--record", action="store_true")
    parser.add_argument("--top", type=int, default=30)
    parser.add_argument("--out", default=None, help="write the raw profile here")
    args = parser.parse_args()

    scene = build_scene(args.scenario)
    rng = np.random.default_rng(0)
    pairs = [scene.render_pair(k, rng, time.time_ns()) for k in range(8)]
    pm = make_plugin_manager(extra=[MemoryPlugin(scene, pairs)])
    with tempfile.TemporaryDirectory(dir=Path(__file__).resolve().parents[1] / "recordings") as tmp:
        tmp = Path(tmp)
        csv = tmp / "reference.csv"
        write_reference_csv(scene, csv)
        pipeline_rate(pm, csv, tmp, 5, args.record, "warmup")
        profile = cProfile.Profile()
        profile.enable()
        rate, _ = pipeline_rate(pm, csv, tmp, args.frames, args.record, "profiled")
        profile.disable()
    print(f"{args.frames} pairs ({args.scenario}, record={args.record}): {rate:.1f} pairs/s under cProfile")
    if args.out:
        profile.dump_stats(args.out)
    stats = pstats.Stats(profile)
    for key in ("tottime", "cumulative"):
        print(f"\n--- top {args.top} by {key} (total s over {args.frames} pairs) ---")
        stats.sort_stats(key).print_stats(args.top)


if __name__ == "__main__":
    main()
