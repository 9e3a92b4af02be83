"""Batch work over an archive of recorded sessions, on Dask (``crossfield batch``, docs/batch.md).

* :mod:`crossfield.batch.inputs`: session folders, MCAP files and globs expanded
  to one input per session, each checked readable by the client before it is submitted;
* :mod:`crossfield.batch.engine`: the Dask client (an embedded ``LocalCluster`` by
  default, or ``--scheduler tcp://HOST:PORT``), one task per session, results taken
  as they complete;
* :mod:`crossfield.batch.tasks`: what one task does (audit, replay, compare one
  session), each writing into its own folder atomically so that a retried task
  (its worker was lost) leaves nothing duplicated;
* :mod:`crossfield.batch.report`: the archive report (``batch-report.json``,
  ``batch-report.html``), written as results arrive;
* :mod:`crossfield.batch.plot`: the distribution of shifts (matplotlib, SVG).

Shared storage: workers open the recordings by the absolute path the client
resolved, so the client and every worker must see the archive (and the output
folder) at the same path (one machine, NFS, a shared volume).
"""

from __future__ import annotations

__all__ = ["inputs", "engine", "tasks", "report", "plot"]
