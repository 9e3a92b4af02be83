"""The embedded cluster's workers each run in a session of their own (pipeline/batch/worker_session.py)."""

from __future__ import annotations

import os
from pathlib import Path

from crossfield.batch import engine


def _session_and_group() -> tuple[int, str | None]:
    """This process's session id and its autogroup (None where the kernel does not say: no file, or an
    empty one, as in some containers)."""
    autogroup = Path("/proc/self/autogroup")
    words = autogroup.read_text().split() if autogroup.exists() else []
    return os.getsid(0), words[0] if words else None


def _malloc_environ() -> dict[str, str | None]:
    """The glibc malloc variables of this process's environment."""
    return {name: os.environ.get(name) for name in ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")}


def _tick_interval_s(dask_worker) -> float:
    """The worker's event-loop health check interval (s), as its server read it from the Dask config."""
    return float(dask_worker._tick_interval)


def test_embedded_workers_lead_their_own_sessions_and_autogroups():
    """Each worker is the leader of its own session (so Linux's autogroup scheduler gives it
    its own CPU share), not in the client's; and it checks its event loop once a second."""
    client_session, client_group = _session_and_group()
    with engine.client(None, 2, dashboard_address=":0") as c:
        workers = c.run(_session_and_group)
        pids = c.run(os.getpid)
        ticks = c.run(_tick_interval_s)
        malloc = c.run(_malloc_environ)
    # one malloc arena for the task thread, and the mmap and trim thresholds fixed high enough that
    # a decoded image reuses the heap (crossfield.batch.engine.client), not Dask's 64 KiB trim threshold
    expected = {"MALLOC_ARENA_MAX": "1", "MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(64 << 20)}
    assert list(malloc.values()) == [expected, expected]
    # the event-loop health check wakes a worker (and takes the task's GIL) once a second, not every 20 ms
    assert set(ticks.values()) == {1.0}
    assert len(workers) == 2
    sessions = {address: session for address, (session, _) in workers.items()}
    assert sessions == pids  # each worker leads the session it is in: sid == its pid
    assert client_session not in sessions.values()
    groups = [group for _, group in workers.values()]
    if client_group is not None:  # a kernel with autogroup scheduling
        assert len(set(groups)) == 2 and client_group not in groups
