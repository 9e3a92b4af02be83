"""Throughput of the Rerun logger, and the time of a headless screenshot.

    .venv/bin/python bench/bench_rerun.py [--frames 30] [--repeat 3]

A simulated station session (``--frames`` pairs) is recorded once; its
recorded inputs and results are loaded into memory
(:mod:`crossfield.viz.rerun_mcap`), then fed through a fresh
:class:`crossfield.viz.rerun_log.RerunLogger` writing an .rrd, for several
``image_every`` settings: wall-clock pairs/s (file finished) and CPU ms per
pair of the process (Rerun's batcher and file sink run on their own
threads). Baseline: the same hooks into a logger with no sink data at all
is not possible, so the ``image_every = 0`` case (overlays, points, series
only) is the floor. Finally the time of ``crossfield view --screenshot`` on
the .rrd: viewer start, load, settle, PNG. Medians over ``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.config import parse_config
from crossfield.recording.reader import open_recording
from crossfield.chain.registry import make_plugin_manager
from crossfield.viz.rerun_log import RerunLogger
from crossfield.viz.rerun_mcap import _events, session_info
from crossfield.chain.runner import run_session


class _AllImages:
    """Stands in for a logger while loading: every image is wanted."""

    @staticmethod
    def wants_images(sequence: int) -> bool:
        return True


def record(out: Path, frames: int) -> Path:
    config = parse_config(
        {
            "session": {"output_dir": str(out), "name": "bench", "rerun": False},
            "acquire": {"plugin": "simulator", "scenario": "station", "frames": frames, "seed": 1},
            "reference": {"plugin": "romer-serial", "port": "simulator"},
        },
        "<bench>",
    )
    return run_session(config, make_plugin_manager()).info.out_dir / "session.mcap"


def feed(events: list, info, path: Path, image_every: int) -> dict[str, float]:
    pairs = sum(1 for kind, _ in events if kind == "done")
    t0, c0 = time.perf_counter(), time.process_time()
    logger = RerunLogger(path, image_every=image_every)
    logger.on_session_start(session=info)
    for kind, payload in events:
        if kind == "reference":
            logger.on_reference(reference=payload)
        elif kind == "frame":
            logger.on_frame(frame=payload)
        elif kind == "done":
            logger.on_frame_done(result=payload)
        else:
            level, text, t = payload
            logger.on_log(level=level, message=text, timestamp_ns=t)
    logger.close()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "pairs_per_s": pairs / wall,
        "cpu_ms_per_pair": 1e3 * cpu / pairs,
        "mb": path.stat().st_size / 1e6,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-screenshot", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        mcap = record(out, args.frames)
        with open_recording(mcap) as recording:
            info = session_info(recording)
            events = list(_events(recording, _AllImages()))
        print(f"{args.frames} pairs of 2 x 1626 x 1236 uint16; medians of {args.repeat} runs")
        print(f"{'image_every':>12} {'pairs/s':>9} {'CPU ms/pair':>12} {'rrd MB':>8}")
        for every in (1, 2, 5, 0):
            runs = [feed(events, info, out / f"r{every}-{k}.rrd", every) for k in range(args.repeat)]
            med = {key: statistics.median(r[key] for r in runs) for key in runs[0]}
            print(f"{every:>12} {med['pairs_per_s']:>9.1f} {med['cpu_ms_per_pair']:>12.1f} {med['mb']:>8.1f}")
        if not args.no_screenshot:
            from crossfield.viz.view import view

            times = []
            for k in range(args.repeat):
                t0 = time.perf_counter()
                view(out / "r1-0.rrd", screenshot_to=out / f"shot{k}.png", say=lambda _: None)
                times.append(time.perf_counter() - t0)
            print(
                f"crossfield view --screenshot (1600x1000, {args.frames} pairs): "
                f"{statistics.median(times):.1f} s (min {min(times):.1f}, max {max(times):.1f})"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
