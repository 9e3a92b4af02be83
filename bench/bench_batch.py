"""Batch throughput on Dask against the sequential loop, and the engine's cost per task.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_batch.py [--sessions 6] [--frames 2] [--kind audit] [--tick 20ms]

Records ``--sessions`` simulator sessions (table3, ``--frames`` stereo pairs, no .rrd) in a
child process (so that neither the loop's process nor a worker starts with their reference
fits cached, :func:`crossfield.geometry.fit_reference_element`), then times, in one run:

* sequential: :func:`crossfield.batch.tasks.run_task` called in this process for each
  session, one after the other (the baseline), with the workers' malloc settings
  (:data:`crossfield.batch.engine.WORKER_MALLOC`, applied with ``mallopt``): a fresh
  process's dynamic thresholds faulted ~17000 pages in per 2-pair audit, a process that
  had recorded sessions none, so the loop's rate depended on what the process did before;
* 1 worker, 2 workers: an embedded ``LocalCluster`` of that many worker processes
  (one thread each; started and warmed up outside the timing: imports, plugin manager and
  one audit, :func:`crossfield.batch.tasks.warm_up`; the sequential loop is warmed the same way), the same tasks through
  :func:`crossfield.batch.engine.run_each` (submit, as_completed);

each in sessions per second and as a ratio to the sequential loop. Then the engine's
overhead per task: ``--noops`` tasks that do nothing (:func:`crossfield.batch.tasks.noop`)
through ``run_each`` on 1 worker (ms per task), and (1-worker time - sequential time) /
sessions on the sessions themselves, and the seconds spent inside the tasks (where they ran)
against the sequential loop's, wall clock and CPU (``time.process_time`` of the process that ran
the task, and of the task's own thread) and the voluntary context switches of that process
during the task: a task whose CPU equals the sequential one but whose wall time is longer
waited for a core (the machine's load), it did not do more work; a process CPU above the
thread's is the worker's own threads (event loop, monitors), and context switches are
where the task thread gave the GIL to them. ``--profile`` also runs one session
under ``cProfile`` in the client and in a worker and prints the functions whose cumulative
time differs most (the in-worker slowdown, issue 25 item 5). The machine is shared: read
the ratios.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figures import record as record_figure  # noqa: E402


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


def record_elsewhere(root: Path, n: int, frames: int) -> list[str]:
    """:func:`record` in a child process (spawned: nothing of it stays in this one)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(record, root, n, frames).result()


#: mallopt(3) parameters of the glibc environment variables of WORKER_MALLOC
_MALLOPT = {"MALLOC_TRIM_THRESHOLD_": -1, "MALLOC_MMAP_THRESHOLD_": -3, "MALLOC_ARENA_MAX": -8}


def heap_like_workers() -> None:
    """Give this process the embedded workers' malloc settings (engine.WORKER_MALLOC), which
    they get from their environment at start, with glibc's ``mallopt``."""
    import ctypes

    libc = ctypes.CDLL("libc.so.6")
    for name, value in engine.WORKER_MALLOC.items():
        if value is not None and not libc.mallopt(_MALLOPT[name], int(value)):
            raise RuntimeError(f"mallopt({name}={value}) failed")


def _switches() -> int:
    """Voluntary context switches of this process so far (a thread giving up the CPU: waiting
    for the GIL, a lock, I/O)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw


def timed_task(*args: object) -> tuple[float, float, float, int]:
    """run_task, returning (wall s, CPU s of the process, CPU s of the task's thread, voluntary
    context switches of the process) where it ran (pickled by value to the workers)."""
    t, c, th, sw = time.perf_counter(), time.process_time(), time.thread_time(), _switches()
    run_task(*args)
    return time.perf_counter() - t, time.process_time() - c, time.thread_time() - th, _switches() - sw


def profiled_task(*args: object) -> dict[str, float]:
    """run_task under cProfile timed by the CPU time of the task's thread (not the wall clock,
    which on a loaded machine mostly measures the wait for a core): {function: cumulative
    CPU s} where it ran (client or worker)."""
    profile = cProfile.Profile(time.thread_time)
    profile.runcall(run_task, *args)
    stats = pstats.Stats(profile, stream=io.StringIO())
    return {
        f"{Path(file).name}:{line}({name})": row[3]
        for (file, line, name), row in stats.stats.items()  # type: ignore[attr-defined]
    }


def on_dask(workers: int, kind: str, paths: list[str], out: Path) -> tuple[float, list[tuple[float, float, float, int]]]:
    """(wall seconds, :func:`timed_task`'s figures of each task) for the tasks of ``paths``
    on an embedded cluster of ``workers`` (warm)."""
    inside: list[tuple[float, float, float, int]] = []
    with engine.client(None, workers, dashboard_address=":0") as c:
        c.run(warm_up, paths[0])
        t = time.perf_counter()
        engine.run_each(
            c, timed_task, [(kind, i, p, str(out), {}, []) for i, p in enumerate(paths)],
            lambda k, result, error: inside.append(result), progress=False,
        )
        return time.perf_counter() - t, inside


def profile_worker(kind: str, path: str, out: Path) -> None:
    """One session under cProfile in the client and on a 1-worker cluster: the functions
    whose cumulative time differs most."""
    here = profiled_task(kind, 0, path, str(out / "prof-client"), {}, [])
    with engine.client(None, 1, dashboard_address=":0") as c:
        c.run(warm_up, path)
        there = c.submit(profiled_task, kind, 0, path, str(out / "prof-worker"), {}, [], pure=False).result()
    rows = sorted(set(here) | set(there), key=lambda k: -abs(there.get(k, 0.0) - here.get(k, 0.0)))
    print(f"  profile of one {kind} (cumulative CPU s of the task's thread): client / worker, largest differences first")
    for key in rows[:15]:
        print(f"    {here.get(key, 0.0):7.3f} {there.get(key, 0.0):7.3f}  {key}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sessions", type=int, default=6)
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--kind", default="audit", choices=("audit", "replay"))
    parser.add_argument("--noops", type=int, default=200)
    parser.add_argument("--profile", action="store_true", help="profile one session in the client and in a worker")
    parser.add_argument("--tick", default=engine.TICK_INTERVAL,
                        help=f"the embedded cluster's event-loop tick (default {engine.TICK_INTERVAL}; Dask's own: 20ms)")
    args = parser.parse_args()
    engine.TICK_INTERVAL = args.tick

    load_start = os.getloadavg()[0]
    work = Path(tempfile.mkdtemp(prefix="crossfield-bench-batch-"))
    try:
        paths = record_elsewhere(work / "archive", args.sessions, args.frames)
        heap_like_workers()
        n = len(paths)
        print(f"{n} sessions of {args.frames} stereo pair(s), batch {args.kind}, {os.cpu_count()} core(s), "
              f"tick {args.tick}, load {load_start:.1f}")
        warm_up(paths[0])
        t = time.perf_counter()
        tasks = [timed_task(args.kind, i, p, str(work / "seq"), {}, []) for i, p in enumerate(paths)]
        sequential = time.perf_counter() - t

        def per_session(rows: list[tuple[float, float, float, int]]) -> str:
            wall, cpu, thread, switches = (sum(r[k] for r in rows) / len(rows) for k in range(4))
            return (f"{wall * 1e3:.0f} ms per session, CPU {cpu * 1e3:.0f} ms (task thread {thread * 1e3:.0f}), "
                    f"{switches:.0f} voluntary context switches")

        print(f"  sequential loop   {n / sequential:7.3f} sessions/s   1.00 x   ({per_session(tasks)})")
        one = None
        for workers in (1, 2):
            s, inside = on_dask(workers, args.kind, paths, work / f"dask{workers}")
            one = s if workers == 1 else one
            record_figure(f"batch.workers{workers}_vs_sequential", sequential / s, "higher")
            print(
                f"  {workers} worker(s)       {n / s:7.3f} sessions/s   {sequential / s:4.2f} x the sequential loop"
                f"   (inside the tasks: {per_session(inside)})"
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
        print(f"  load average {os.getloadavg()[0]:.1f} at the end (at the start {load_start:.1f})")
        if args.profile:
            profile_worker(args.kind, paths[0], work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
