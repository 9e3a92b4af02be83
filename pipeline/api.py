"""The Python API: a session from a notebook or a script, with the CLI's defaults.

    import crossfield

    summary = crossfield.run(scenario="table3", frames=3)   # as `crossfield run --scenario table3 --frames 3`
    print(summary)                                          # the characteristics as a table (mm)
    summary.characteristics[0].measured_mm                  # the reported values, unrounded
    with crossfield.open_recording(summary.info.out_dir / "session.mcap") as rec:
        rec.topics()

:func:`run` builds its config with :func:`crossfield.config.session_config`,
the function ``crossfield run`` uses, so the defaults are the same (the
built-in simulator, its ``station`` scenario, the simulated ROMER arm on a
pseudo-terminal); keyword arguments replace command-line flags and option
dicts replace ``--option stage.key=value`` texts. See docs/python-api.md.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Mapping
from typing import Any

import pluggy

from crossfield.chain.registry import make_plugin_manager
from crossfield.config import Config, session_config
from crossfield.recording.reader import Recording, open_recording
from crossfield.session import SessionSummary

__all__ = ["run", "run_config", "open_recording", "Recording", "SessionSummary"]

logger = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]


def _path(value: PathLike | None) -> str | None:
    return None if value is None else os.fspath(value)


def run_config(
    config: PathLike | None = None,
    *,
    scenario: str | None = None,
    frames: int | None = None,
    seed: int | None = None,
    plan: PathLike | None = None,
    output_dir: PathLike | None = None,
    name: str | None = None,
    record: bool | None = None,
    rerun: bool | None = None,
    acquire: str | None = None,
    centroid: str | None = None,
    triangulate: str | None = None,
    reference: str | None = None,
    register: str | None = None,
    measure: str | None = None,
    report: str | None = None,
    options: Mapping[str, Mapping[str, Any]] | None = None,
) -> Config:
    """The config :func:`run` runs, without running it (same arguments, see there)."""
    return session_config(
        _path(config),
        plugins={
            "acquire": acquire,
            "centroid": centroid,
            "triangulate": triangulate,
            "reference": reference,
            "register": register,
            "measure": measure,
            "report": report,
        },
        simulator={"scenario": scenario, "frames": frames, "seed": seed},
        session={
            "plan": _path(plan),
            "output_dir": _path(output_dir),
            "name": name,
            "record": record,
            "rerun": rerun,
        },
        options=options,
        by="crossfield.run() arguments",
    )


def run(
    config: PathLike | None = None,
    *,
    scenario: str | None = None,
    frames: int | None = None,
    seed: int | None = None,
    plan: PathLike | None = None,
    output_dir: PathLike | None = None,
    name: str | None = None,
    record: bool | None = None,
    rerun: bool | None = None,
    acquire: str | None = None,
    centroid: str | None = None,
    triangulate: str | None = None,
    reference: str | None = None,
    register: str | None = None,
    measure: str | None = None,
    report: str | None = None,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    observers: Iterable[object] = (),
    progress: bool = False,
    plugin_manager: pluggy.PluginManager | None = None,
) -> SessionSummary:
    """Run one measurement session, as ``crossfield run`` does; returns its summary.

    Every argument left at None keeps the config file's value (``config``,
    a TOML file, docs/config.md) or the default:

    - scenario, frames, seed: the simulator's options (``station``, 10
      stereo pairs, seed 1); an error with any other acquisition source.
    - plan: a measurement plan file (docs/plan.md); the simulator brings its own.
    - output_dir, name: the session folder ``<output_dir>/<name>/``
      (``recordings/``, ``<date>-<time>-<scenario>``).
    - record, rerun: write session.mcap / session.rrd (both True).
    - acquire ... report: the implementation of that stage by its
      registered name (``crossfield plugins``), e.g. ``centroid="ellipse"``.
    - options: stage options, ``{"centroid": {"threshold_sigma": 8}}``
      (``"session"`` sets ``[session]`` keys); after the plugins are chosen,
      so they belong to the implementation that runs.
    - observers: extra observer plugins for this session (hook
      implementations, docs/stages.md); progress: show the progress bar
      on stderr when it is a terminal (crossfield.progress).
    - plugin_manager: the plugins to choose from (default: the built-in
      ones and the installed third-party ones, as the CLI).

    The returned :class:`~crossfield.session.SessionSummary` prints as a
    table; ``summary.characteristics`` holds the reported values (mm),
    ``summary.passed`` the verdict, ``summary.info.out_dir`` the session
    folder. Bad input raises :class:`crossfield.errors.CrossfieldError`
    (a :class:`~crossfield.errors.ConfigError` names the key).
    """
    from crossfield.chain.runner import run_session

    resolved = run_config(
        config,
        scenario=scenario,
        frames=frames,
        seed=seed,
        plan=plan,
        output_dir=output_dir,
        name=name,
        record=record,
        rerun=rerun,
        acquire=acquire,
        centroid=centroid,
        triangulate=triangulate,
        reference=reference,
        register=register,
        measure=measure,
        report=report,
        options=options,
    )
    pm = plugin_manager if plugin_manager is not None else make_plugin_manager(entry_points=True)
    extra = list(observers)
    if progress:
        from crossfield.progress import Progress

        n = resolved.stages["acquire"].options.get("frames")
        extra.append(Progress(total=n if isinstance(n, int) else None, enabled=True))
    logger.info("running a session: %s", resolved.source)
    summary = run_session(resolved, pm, observers=extra)
    logger.info("session written to %s", summary.info.out_dir)
    return summary
