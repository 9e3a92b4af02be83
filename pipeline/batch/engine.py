"""Where batch work runs: a Dask client (``dask.distributed``) and one task per item.

:func:`client` is the one place a crossfield command gets its Dask cluster: an embedded
``LocalCluster`` (one worker process per core, one thread per worker) unless
``scheduler`` names an existing one (``tcp://HOST:PORT``). The batch commands, the Monte
Carlo uncertainty check and the layout planner's sweeps take the same ``--scheduler`` /
``--workers`` options (:func:`add_engine_flags`) and call it.

:func:`run_each` submits one task per item and hands each result to the caller as it
completes (``distributed.as_completed``), so a report can be written incrementally. A
task whose worker is lost is rescheduled by the Dask scheduler on another worker (up to
``distributed.scheduler.allowed-failures`` times, then the future fails with
``KilledWorker``: reported as an ERROR result).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from crossfield.errors import ConfigError
from crossfield.progress import bar

if TYPE_CHECKING:
    from dask.distributed import Client

__all__ = ["Engine", "add_engine_flags", "client", "engine_from_args", "dashboard_text", "run_each", "task_error"]

logger = logging.getLogger(__name__)

#: The memory limit of each embedded worker ("auto": the machine's memory shared out
#: equally); a worker over 95 % of it is restarted by its nanny (Dask worker memory management).
DEFAULT_MEMORY_LIMIT = "auto"
#: The embedded cluster's event-loop health check interval (Dask's default: 20 ms), see :func:`client`.
TICK_INTERVAL = "1s"
#: glibc malloc settings of each embedded worker's environment (see :func:`client`): one
#: arena, and fixed mmap (32 MiB) and trim (64 MiB) thresholds, so that the images a task
#: decodes reuse the worker's heap instead of faulting their pages in again.
WORKER_MALLOC = {
    "MALLOC_ARENA_MAX": "1",
    "MALLOC_MMAP_THRESHOLD_": str(32 << 20),
    "MALLOC_TRIM_THRESHOLD_": str(64 << 20),
}


def add_engine_flags(parser: argparse.ArgumentParser) -> None:
    """``--scheduler``, ``--workers`` and ``--memory-limit`` on ``parser``: the one set of
    engine flags of every command that can run on Dask (batch, the Monte Carlo check of
    ``run``, the planner's sweeps), read back by :func:`engine_from_args`.

    ``--scheduler local`` (or ``--workers N`` alone) is an embedded ``LocalCluster``;
    ``--scheduler tcp://HOST:PORT`` an existing cluster. The same words mean the same
    thing in every command; a command whose work needs Dask (batch) uses the embedded
    cluster when neither flag is given."""
    parser.add_argument(
        "--scheduler", metavar="local|tcp://HOST:PORT",
        help="where the Dask work runs: 'local' (an embedded LocalCluster on this machine) or an existing "
        "scheduler's address",
    )
    parser.add_argument(
        "--workers", type=int, metavar="N",
        help="embedded cluster: N worker processes (default: one per core); "
        "with a scheduler address: wait until N workers are connected",
    )
    parser.add_argument(
        "--memory-limit", default=DEFAULT_MEMORY_LIMIT, metavar="BYTES",
        help="embedded cluster: memory limit per worker, e.g. 2GiB (default: auto, the memory shared out)",
    )


@dataclass(frozen=True)
class Engine:
    """Where Dask work runs, as the engine flags gave it.

    scheduler: ``tcp://HOST:PORT`` of a running scheduler, or None for an embedded
    ``LocalCluster``; workers: the embedded cluster's processes (or the workers to wait
    for); memory_limit: per embedded worker."""

    scheduler: str | None = None
    workers: int | None = None
    memory_limit: str | int | None = DEFAULT_MEMORY_LIMIT


def engine_from_args(args: argparse.Namespace) -> Engine | None:
    """The :class:`Engine` of :func:`add_engine_flags`' flags, or None when neither
    ``--scheduler`` nor ``--workers`` was given (``local`` = the embedded cluster)."""
    scheduler, workers = getattr(args, "scheduler", None), getattr(args, "workers", None)
    if scheduler is None and workers is None:
        return None
    memory_limit = getattr(args, "memory_limit", DEFAULT_MEMORY_LIMIT)
    return Engine(None if scheduler in (None, "local") else scheduler, workers, memory_limit)


@contextlib.contextmanager
def client(
    scheduler: str | None = None,
    workers: int | None = None,
    *,
    memory_limit: str | int | None = DEFAULT_MEMORY_LIMIT,
    dashboard_address: str = ":8787",
    timeout_s: float = 60.0,
) -> Iterator["Client"]:
    """A connected ``dask.distributed.Client``, closed (and an embedded cluster shut down) on exit.

    scheduler: ``tcp://HOST:PORT`` of a running scheduler, or None for an embedded
    ``LocalCluster`` of ``workers`` processes (default ``os.cpu_count()``), one thread
    each, ``memory_limit`` each. With a scheduler, ``workers`` is how many workers to wait
    for (``Client.wait_for_workers``, at most ``timeout_s`` s). A scheduler that cannot be
    reached is a :class:`ConfigError` naming it.
    """
    from dask.distributed import Client, LocalCluster

    if workers is not None and workers < 1:
        raise ConfigError(f"--workers {workers}: at least 1 worker")
    if scheduler == "local":  # the engine flags' word for the embedded cluster
        scheduler = None
    if scheduler:
        try:
            c = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        try:
            if workers:
                c.wait_for_workers(workers, timeout=timeout_s)
            yield c
        finally:
            c.close()
        return
    n = workers or os.cpu_count() or 1
    try:
        from dask.utils import parse_bytes

        if isinstance(memory_limit, str) and memory_limit != "auto":
            parse_bytes(memory_limit)
    except ValueError:
        raise ConfigError(f"--memory-limit {memory_limit!r}: a size such as 2GiB or 500MB, or auto") from None
    import dask

    # The workers' statistical profiler (a stack sample every 10 ms) cost +40-80 % of a
    # session task's time here (pure-Python, GIL-bound work): off in the embedded cluster
    # (bench/bench_batch.py; docs/batch.md "Throughput"). The nannies hand this config on.
    # Dask's nanny starts each worker with MALLOC_TRIM_THRESHOLD_=65536 (to hand freed
    # memory back to the OS); setting it disables glibc's dynamic mmap threshold, so every
    # 4 MB image array is a fresh mmap whose pages fault in again: 2.6 -> 8.6 ms per
    # decoded-and-thresholded image (measured), the in-worker slowdown of issue 25.
    # Left unset (glibc's dynamic thresholds), what a process faults in depends on what it
    # did before: per 2-pair audit ~1000-2400 pages in a warm worker, ~17000 in a fresh
    # process, none in one that had recorded sessions. Both thresholds fixed (mallopt(3):
    # mmap 32 MiB, the largest glibc takes, so an image array always comes from the heap;
    # trim 64 MiB of free heap top kept, the worker's RSS +10-17 MB): 4-21 faults per task
    # (WORKER_MALLOC; docs/batch.md "Throughput").
    # MALLOC_ARENA_MAX=1: a worker runs its task on an executor thread, whose allocations
    # glibc serves from a per-thread arena. Decoding an lz4 image and converting it on a new
    # thread faulted 10570 pages in per 20 images with that arena, 2385-3407 with one arena,
    # 3019 on a process's main thread (one process each, 2026-12-04). Measured on the task:
    # a 2-pair audit 173-183 -> 142-144 ms inside a worker, and 2 workers 1.21-1.23 ->
    # 1.41-1.53x the sequential loop (bench/bench_batch.py, alternating twice; docs/batch.md).
    # A worker has one task thread, so one arena adds no lock contention worth measuring.
    # Each worker process starts a session of its own (setsid), so that Linux's autogroup
    # scheduler gives it its own CPU share instead of one share for the client and all
    # its workers: two workers in the client's group ran at 0.90-0.95x the sequential
    # loop on this loaded machine (issue 25 item 5; crossfield.batch.worker_session).
    # Every Dask server (scheduler, nanny, worker) wakes its event loop every
    # distributed.admin.tick.interval (20 ms) to measure how responsive it is. In a worker
    # each wake-up takes the GIL from the task thread (a forced switch: the task waits
    # until the event loop's thread has run, which on a busy machine is a wait for a core):
    # 250-700 voluntary context switches per 1.5-2 s audit task, against ~15 for the same
    # audit in the client; at 1 s, 57-141, and the worker's CPU beside its task thread
    # fell from ~68 to ~42 ms per task (issue 25 item 5, docs/batch.md "Throughput"). The
    # warning for a blocked event loop (tick.limit, 3 s) still fires.
    with dask.config.set({
        "distributed.admin.tick.interval": TICK_INTERVAL,
        "distributed.worker.profile.enabled": False,
        **{f"distributed.nanny.pre-spawn-environ.{name}": value for name, value in WORKER_MALLOC.items()},
        "distributed.worker.preload": ["crossfield.batch.worker_session"],
    }):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=dashboard_address,
            host="127.0.0.1",
        )
    try:
        with Client(cluster) as c:
            yield c
    finally:
        cluster.close()


def dashboard_text(c: "Client") -> str:
    """One line: the scheduler, the workers and the dashboard address (or why there is none)."""
    info = c.scheduler_info()
    link = c.dashboard_link if "dashboard" in info.get("services", {}) else None
    return (
        f"Dask scheduler {c.scheduler.address}, {len(info.get('workers', {}))} worker(s); "
        + (f"dashboard {link}" if link else "the scheduler serves no dashboard")
    )


def task_error(exc: BaseException) -> str:
    """The reason of a failed task's future (a lost worker too often, or a task exception)."""
    from distributed.scheduler import KilledWorker

    if isinstance(exc, KilledWorker):
        return f"the task's worker was lost too often, the session was not finished ({exc})"
    return f"the task failed: {type(exc).__name__}: {exc}"


def run_each(
    c: "Client",
    function: Callable[..., Any],
    items: Iterable[Sequence[Any]],
    on_result: Callable[[int, Any, str | None], None],
    *,
    prefix: str = "crossfield",
    progress: bool = True,
    desc: str = "tasks",
) -> None:
    """Submit ``function(*item)`` once per item (one task each, ``pure=False``: a task is
    never merged with another) and call ``on_result(position, result, error)`` as each
    completes, in completion order: ``error`` is None, or the reason the task failed
    (:func:`task_error`). ``progress``: a bar of the tasks done, labelled ``desc``, on a
    terminal (:func:`crossfield.progress.bar`: not on a pipe, not under ``-q``)."""
    from dask.distributed import as_completed

    run = uuid.uuid4().hex[:8]
    futures = [
        c.submit(function, *item, key=f"{prefix}-{run}-{i:05d}", pure=False) for i, item in enumerate(items)
    ]
    if not futures:
        return
    position = {f.key: i for i, f in enumerate(futures)}
    with bar(desc=desc, total=len(futures), unit="task", enabled=None if progress else False) as done:
        try:
            for future in as_completed(futures):
                i = position[future.key]
                if future.status == "error":
                    on_result(i, None, task_error(future.exception()))
                else:
                    on_result(i, future.result(), None)
                done.update()
        except BaseException:
            c.cancel(futures)
            raise
