"""Dask worker preload: each embedded worker process in a session of its own (``setsid``).

One job. Linux's autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled`` = 1,
the default of most desktop kernels and of this development machine) shares the CPU
fairly between *sessions*, not between processes: every process of one terminal
session (the ``crossfield batch`` client and the worker processes its ``LocalCluster``
spawns) is one group with one share. On a machine where other sessions are busy,
two workers in the client's group then get together what the sequential loop gets
alone, and run no faster than it (measured: 0.90-0.95x at load 13-15, issue 25 item 5,
docs/batch.md "Throughput"). A worker that calls ``setsid()`` when it starts is the
leader of a new session and of a new autogroup (sched(7), "The autogroup feature"),
so each worker competes for a core as its own group, as processes do on a kernel
without autogroup. It changes nothing else: the worker stays the nanny's child (the
nanny still stops and restarts it, and a worker whose parent died still exits), it
has no terminal, and Ctrl-C reaches the client, which closes the cluster.

Named in the embedded cluster's ``distributed.worker.preload``
(:func:`crossfield.batch.engine.client`); Dask calls :func:`dask_setup` in the worker
process before it connects.
"""

from __future__ import annotations

import os
from typing import Any

__all__ = ["dask_setup", "own_session"]


def own_session() -> bool:
    """Make this process the leader of a new session (``os.setsid``); False where it
    cannot (already a process-group leader, or no ``setsid`` on this platform)."""
    setsid = getattr(os, "setsid", None)
    if setsid is None:
        return False
    try:
        setsid()
    except OSError:
        return False
    return True


def dask_setup(worker: Any) -> None:
    """Dask's preload hook (called with the Worker): the worker's own session."""
    own_session()
