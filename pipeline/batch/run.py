"""One batch: inputs expanded and checked, one task per session on Dask, the report
written as each finishes (``crossfield batch audit | replay | compare``)."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from crossfield.batch.engine import Engine, client, dashboard_text, run_each
from crossfield.batch.inputs import expand_inputs
from crossfield.batch.report import JSON_NAME, BatchReport
from crossfield.batch.tasks import KINDS, run_task
from crossfield.chain.runner import new_session_dir
from crossfield.errors import ConfigError

__all__ = ["default_output", "remove_attempts", "run_batch"]


def default_output(kind: str, base: str | Path = "recordings") -> Path:
    """A new folder ``<base>/batch-<kind>-<UTC time>`` (``-2``, ... if it exists)."""
    return new_session_dir(Path(base), f"batch-{kind}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}")


def remove_attempts(folder: Path) -> None:
    """Remove what attempts of tasks left behind, once every task has finished: the temporary
    folders (``.<name>.tmp-<id>``, :func:`crossfield.batch.tasks.in_own_folder`) of attempts
    whose worker was lost before they could rename them."""
    for tmp in folder.glob(".*.tmp-*") if folder.is_dir() else ():
        shutil.rmtree(tmp, ignore_errors=True)


def _refuse_other_batch(out: Path, kind: str, plugins: Mapping[str, Any], options: Sequence[str]) -> None:
    """``out`` may hold an earlier run of the same batch (its finished sessions are reused,
    :func:`crossfield.batch.tasks.in_own_folder`), never another kind or other plugin flags."""
    previous = out / JSON_NAME
    if not previous.exists():
        return
    try:
        doc = json.loads(previous.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{previous}: not a batch report ({exc}); use another -o DIR") from None
    wanted = {k: v for k, v in plugins.items() if v}
    if (doc.get("kind"), doc.get("plugins") or {}, doc.get("options") or []) != (kind, wanted, list(options)):
        raise ConfigError(
            f"{previous}: the report of another batch (batch {doc.get('kind')} with plugins "
            f"{doc.get('plugins')} and options {doc.get('options')}); use another -o DIR"
        )


def run_batch(
    kind: str,
    paths: Sequence[str],
    *,
    out_dir: str | Path | None = None,
    plugins: Mapping[str, str | None] | None = None,
    options: Sequence[str] = (),
    engine: Engine = Engine(),
    dashboard_address: str = ":8787",
    progress: bool = True,
    echo: Callable[[str], None] = lambda text: None,
) -> BatchReport:
    """Run ``kind`` (audit, replay, compare) over the sessions named by ``paths``.

    Unreadable inputs are ERROR entries at once (not submitted); the others are one
    Dask task each (:func:`crossfield.batch.tasks.run_task`) on the cluster ``engine``
    names (:func:`crossfield.batch.engine.client`; default an embedded LocalCluster).
    The report in ``out_dir`` (default
    :func:`default_output`) is rewritten as each session finishes; on an interruption
    (KeyboardInterrupt) it is written marked incomplete and the interruption re-raised.
    ``echo``: one line of information (the cluster and dashboard, where the report is).
    """
    if kind not in KINDS:
        raise ConfigError(f"batch {kind!r}: one of {', '.join(KINDS)}")
    inputs = expand_inputs(paths)
    if not inputs:
        raise ConfigError("batch: no session given (session folders, MCAP files or globs)")
    out = Path(out_dir) if out_dir is not None else default_output(kind)
    out = out.resolve()
    _refuse_other_batch(out, kind, plugins or {}, options)
    report = BatchReport(out, kind, inputs, plugins=plugins, options=options)
    plugins = dict(plugins or {})
    for i, item in enumerate(inputs):
        if item.error:
            report.add(i, {"verdict": "ERROR", "reason": item.error}, write=False)
    report.write_json()
    todo = [i for i, item in enumerate(inputs) if not item.error]
    echo(f"{len(inputs)} session(s), {len(todo)} submitted; report in {out}/")
    finished = False
    try:
        if todo:
            with client(
                engine.scheduler, engine.workers, memory_limit=engine.memory_limit, dashboard_address=dashboard_address
            ) as c:
                echo(dashboard_text(c))

                def on_result(k: int, entry: Any, error: str | None) -> None:
                    i = todo[k]
                    report.add(i, entry if error is None else {"verdict": "ERROR", "reason": error})

                run_each(
                    c,
                    run_task,
                    [(kind, i, inputs[i].path, str(out), plugins, list(options)) for i in todo],
                    on_result,
                    prefix=f"crossfield-{kind}",
                    progress=progress,
                    desc=f"batch {kind}",
                )
            remove_attempts(out / "sessions")
        finished = True
    finally:
        report.finish(complete=finished)
    return report
