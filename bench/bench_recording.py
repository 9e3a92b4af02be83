"""Recording throughput: McapRecorder vs a plain file write of the same bytes.

    .venv/bin/python bench/bench_recording.py [--pairs 120] [--repeats 5] [--fsync] [--dir /tmp]

For each repeat (interleaved, so that both see the same disk state):

* baseline: the raw pixel bytes of every pair (2 x 1626 x 1236 uint16)
  written with ``file.write`` into one file;
* recorder: the same pairs through ``pm.hook.on_frame`` into a
  :class:`crossfield.recording.recorder.McapRecorder` (writer thread on, then off),
  closed at the end (summary and indexes written);
* with ``--rerun``: the same pairs through :class:`crossfield.viz.rerun_log.RerunLogger`.

Reports pairs/s (wall clock, file closed; with ``--fsync`` also synced to
disk), the CPU time per pair of the process, and for the recorder the time
the pipeline thread spends inside the hook per pair. Medians over the
repeats. Without ``--fsync`` the writes land in the page cache, so the
figures measure CPU cost; with it they include the disk.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.recording.recorder import McapRecorder
from crossfield.chain.registry import make_plugin_manager
from crossfield.types import StereoFrame

HEIGHT, WIDTH = 1236, 1626


def make_frames(count: int = 4, seed: int = 0) -> list[StereoFrame]:
    """Plausible 12-bit pairs: dark background with read noise and a few bright spots."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    frames = []
    for k in range(count):
        images = []
        for _ in range(2):
            img = rng.normal(200.0, 8.0, (HEIGHT, WIDTH))
            for _ in range(12):
                cx, cy = rng.uniform(100, WIDTH - 100), rng.uniform(100, HEIGHT - 100)
                sl = (slice(int(cy) - 30, int(cy) + 30), slice(int(cx) - 30, int(cx) + 30))
                img[sl] += 3000 * np.exp(-((xx[sl] - cx) ** 2 + (yy[sl] - cy) ** 2) / (2 * 6.0**2))
            images.append(np.clip(img, 0, 4095).astype(np.uint16))
        frames.append(StereoFrame(k, 0, images[0], images[1], 12))
    return frames


def run_baseline(path: Path, frames: list[StereoFrame], pairs: int, fsync: bool) -> dict[str, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    with open(path, "wb") as f:
        for i in range(pairs):
            frame = frames[i % len(frames)]
            f.write(frame.upper.data)
            f.write(frame.lower.data)
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "pairs_per_s": pairs / wall,
        "cpu_ms_per_pair": 1e3 * cpu / pairs,
        "hook_ms_per_pair": float("nan"),
    }


def run_observer(observer, path: Path, frames: list[StereoFrame], pairs: int, fsync: bool) -> dict[str, float]:
    """The pairs through ``observer.on_frame`` into ``path``, closed at the end."""
    t0, c0 = time.perf_counter(), time.process_time()
    pm = make_plugin_manager(builtins=False, extra=[observer])
    in_hook = 0.0
    start_ns = time.time_ns()
    for i in range(pairs):
        template = frames[i % len(frames)]
        frame = StereoFrame(i, start_ns + i * 16_666_667, template.upper, template.lower, 12)
        h0 = time.perf_counter()
        pm.hook.on_frame(frame=frame)
        in_hook += time.perf_counter() - h0
    observer.close()
    if fsync:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "pairs_per_s": pairs / wall,
        "cpu_ms_per_pair": 1e3 * cpu / pairs,
        "hook_ms_per_pair": 1e3 * in_hook / pairs,
    }


def run_recorder(
    path: Path, frames: list[StereoFrame], pairs: int, fsync: bool, writer_thread: bool
) -> dict[str, float]:
    return run_observer(McapRecorder(path, overwrite=True, writer_thread=writer_thread), path, frames, pairs, fsync)


def run_rerun_logger(path: Path, frames: list[StereoFrame], pairs: int, fsync: bool) -> dict[str, float]:
    """The same pairs through RerunLogger (images only) into an .rrd, for comparison."""
    from crossfield.viz.rerun_log import RerunLogger

    return run_observer(RerunLogger(path), path, frames, pairs, fsync)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=120)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fsync", action="store_true", help="sync to disk before stopping the clock")
    parser.add_argument("--dir", default=None, help="where to write (default: a temporary directory)")
    parser.add_argument(
        "--rerun", action="store_true", help="also time RerunLogger (images into session.rrd)"
    )
    args = parser.parse_args(argv)

    frames = make_frames()
    mb = args.pairs * 2 * HEIGHT * WIDTH * 2 / 1e6
    print(
        f"{args.pairs} pairs of 2 x {WIDTH}x{HEIGHT} uint16 ({mb:.0f} MB) per run, {args.repeats} repeats, "
        f"fsync={'on' if args.fsync else 'off'}, {os.cpu_count()} CPUs"
    )
    cases = {
        "plain file write": lambda p: run_baseline(p, frames, args.pairs, args.fsync),
        "McapRecorder (writer thread)": lambda p: run_recorder(p, frames, args.pairs, args.fsync, True),
        "McapRecorder (synchronous)": lambda p: run_recorder(p, frames, args.pairs, args.fsync, False),
    }
    if args.rerun:
        cases["RerunLogger (images)"] = lambda p: run_rerun_logger(p, frames, args.pairs, args.fsync)
    results: dict[str, list[dict[str, float]]] = {name: [] for name in cases}
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = Path(tmp) / "bench.out"
        for _ in range(args.repeats):
            for name, run in cases.items():
                results[name].append(run(path))
                path.unlink()
    print(f"{'case':30s} {'pairs/s':>9s} {'(min..max)':>15s} {'CPU ms/pair':>12s} {'in hook ms/pair':>16s}")
    for name, runs in results.items():
        rates = [r["pairs_per_s"] for r in runs]
        cpu = statistics.median(r["cpu_ms_per_pair"] for r in runs)
        hook = statistics.median(r["hook_ms_per_pair"] for r in runs)
        span = f"({min(rates):.0f}..{max(rates):.0f})"
        hook_text = "-" if np.isnan(hook) else f"{hook:.2f}"
        print(f"{name:30s} {statistics.median(rates):9.1f} {span:>15s} {cpu:12.2f} {hook_text:>16s}")


if __name__ == "__main__":
    main()
