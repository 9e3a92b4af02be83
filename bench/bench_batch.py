"""Batch throughput on Dask against the sequential loop, and the engine's cost per task.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_batch.py [--sessions 6] [--frames 2] [--kind audit]

Records ``--sessions`` simulator sessions (table3, ``--frames`` stereo pairs, no .rrd),
then times, in one run:

* sequential: :func:`crossfield.batch.tasks.run_task` called in this process for each
  session, one after the other (the baseline);
* 1 worker, 2 workers: an embedded ``LocalCluster`` of that many worker processes
  (one thread each; started and warmed up outside the timing: imports, plugin manager and
  one audit, :func:`crossfield.batch.tasks.warm_up`; the sequential loop is warmed the same way), the same tasks through
  :func:`crossfield.batch.engine.run_each` (submit, as_completed);

each in sessions per second and as a ratio to the sequential loop. Then the engine's
overhead per task: ``--noops`` tasks that do nothing (:func:`crossfield.batch.tasks.noop`)
through ``run_each`` on 1 worker (ms per task), and (1-worker time - sequential time) /
sessions on the sessions themselves, and the seconds spent inside the tasks (where they ran)
against the sequential loop's. The machine is shared: read the ratios.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.batch import engine  # noqa: E402
from crossfield.batch.tasks import noop, run_task, warm_up  # noqa: E402
from crossfield.config import parse_config  # noqa: E402
from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.chain.runner import run_session  # noqa: E402


def record(root: Path, n: int, frames: int) -> list[str]:
    paths = []
    for i in range(n):
        config = parse_config(
            {
                "session": {"output_dir": str(root), "name": f"s{i}", "rerun": False},
                "acquire": {"plugin": "simulator", "scenario": "table3", "frames": frames, "seed": i},
                "reference": {"plugin": "romer-serial", "port": "simulator"},
            },
            "<bench>",
        )
        run_session(config, make_plugin_manager())
        paths.append(str(root / f"s{i}" / "session.mcap"))
    return paths


def timed_task(*args: object) -> float:
    """run_task, returning the seconds it took where it ran (pickled by value to the workers)."""
    t = time.perf_counter()
    run_task(*args)
    return time.perf_counter() - t


def on_dask(workers: int, kind: str, paths: list[str], out: Path) -> tuple[float, float]:
    """(wall seconds, sum of the seconds inside the tasks) for the tasks of ``paths`` on an
    embedded cluster of ``workers`` (warm)."""
    inside: list[float] = []
    with engine.client(None, workers, dashboard_address=":0") as c:
        c.run(warm_up, paths[0])
        t = time.perf_counter()
        engine.run_each(
            c, timed_task, [(kind, i, p, str(out), {}, []) for i, p in enumerate(paths)],
            lambda k, result, error: inside.append(result), progress=False,
        )
        return time.perf_counter() - t, sum(inside)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sessions", type=int, default=6)
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--kind", default="audit", choices=("audit", "replay"))
    parser.add_argument("--noops", type=int, default=200)
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="crossfield-bench-batch-"))
    try:
        paths = record(work / "archive", args.sessions, args.frames)
        n = len(paths)
        print(f"{n} sessions of {args.frames} stereo pair(s), batch {args.kind}, {os.cpu_count()} core(s)")
        warm_up(paths[0])
        t = time.perf_counter()
        for i, p in enumerate(paths):
            run_task(args.kind, i, p, str(work / "seq"), {}, [])
        sequential = time.perf_counter() - t
        print(f"  sequential loop   {n / sequential:7.3f} sessions/s   1.00 x")
        one = None
        for workers in (1, 2):
            s, inside = on_dask(workers, args.kind, paths, work / f"dask{workers}")
            one = s if workers == 1 else one
            print(
                f"  {workers} worker(s)       {n / s:7.3f} sessions/s   {sequential / s:4.2f} x the sequential loop"
                f"   (inside the tasks: {inside / n * 1e3:.0f} ms per session, sequential {sequential / n * 1e3:.0f})"
            )
        with engine.client(None, 1, dashboard_address=":0") as c:
            c.run(warm_up)
            t = time.perf_counter()
            engine.run_each(c, noop, [(i,) for i in range(args.noops)], lambda k, r, e: None, progress=False)
            per_noop = (time.perf_counter() - t) / args.noops
        print(f"  engine overhead   {per_noop * 1e3:7.2f} ms per no-op task (1 worker, {args.noops} tasks)")
        print(
            f"                    {(one - sequential) / n * 1e3:7.1f} ms per session task "
            f"(1 worker - sequential) / sessions, {(one - sequential) / sequential * 100:+.1f} %"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
