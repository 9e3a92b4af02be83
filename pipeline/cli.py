"""The ``crossfield`` command line (``docs/user-guide.md``)."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

from crossfield.config import SIMULATOR_OPTIONS, Config, session_config
from crossfield.errors import CrossfieldError
from crossfield.registry import STAGES, implementations, make_plugin_manager

if TYPE_CHECKING:
    import pluggy

logger = logging.getLogger(__name__)


def _add_stage_flags(parser: argparse.ArgumentParser) -> None:
    for stage in STAGES:
        parser.add_argument(f"--{stage}", metavar="NAME", help=f"{stage} implementation (see `crossfield plugins`)")
    parser.add_argument(
        "--option", action="append", default=[], metavar="STAGE.KEY=VALUE",
        help="set a stage option, e.g. centroid.threshold_sigma=8 (repeatable)",
    )


def stage_choices(args: argparse.Namespace) -> tuple[dict[str, str | None], list[str]]:
    """The flags of :func:`_add_stage_flags` as read by ``replay`` and ``batch``:
    (stage -> implementation name or None, the ``--option`` texts)."""
    return {stage: getattr(args, stage) for stage in STAGES}, list(args.option)


def _verbosity_flags(default: object = 0) -> argparse.ArgumentParser:
    """-v / -q of every command: the level of the ``crossfield`` loggers (:func:`logging_to_stderr`).
    A nested command's flags (``batch -v audit`` and ``batch audit -v``) are made with
    ``default=argparse.SUPPRESS``, so that they do not reset the outer command's count
    (given at both levels, the inner count is the one kept)."""
    flags = argparse.ArgumentParser(add_help=False)
    flags.add_argument(
        "-v", "--verbose", action="count", default=default,
        help="log more: -v progress of the steps (INFO), -vv details (DEBUG)",
    )
    flags.add_argument(
        "-q", "--quiet", action="count", default=default,
        help="log only errors (and no progress display for run and replay)",
    )
    return flags


def build_parser() -> argparse.ArgumentParser:
    from crossfield import __version__

    parser = argparse.ArgumentParser(
        prog="crossfield",
        description="Local stereo vision registered to out-of-view CMM references (metrology pipeline).",
    )
    parser.add_argument("--version", action="version", version=f"crossfield {__version__}")
    verbosity = _verbosity_flags()
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, **kwargs: object) -> argparse.ArgumentParser:
        """A subcommand; every one takes -v / -q."""
        return sub.add_parser(name, parents=[verbosity], **kwargs)  # type: ignore[arg-type]

    run = command("run", help="run a measurement session (default: the built-in simulator)")
    run.add_argument("-c", "--config", metavar="FILE", help="session config (TOML); defaults apply otherwise")
    run.add_argument("--scenario", help="simulator scenario: station, table3 or camera-limited")
    run.add_argument("--frames", type=int, help="number of stereo pairs (simulator)")
    run.add_argument("--seed", type=int, help="noise seed (simulator)")
    run.add_argument("--plan", metavar="FILE", help="measurement plan (TOML)")
    run.add_argument("-o", "--output-dir", metavar="DIR", help="where the session folder is written")
    run.add_argument("--name", help="session folder name (default: time stamp and scenario)")
    run.add_argument("--no-record", action="store_true", help="do not write session.mcap")
    run.add_argument("--no-rerun", action="store_true", help="do not write session.rrd")
    run.add_argument(
        "--view", nargs="?", const="new", metavar="URL",
        help="stream the session live to a Rerun viewer: a new native viewer, or the running one at URL "
        "(rerun+http://HOST:PORT/proxy); see docs/visualisation.md",
    )
    _add_stage_flags(run)
    run.add_argument(
        "--monte-carlo", type=int, metavar="N",
        help="also check the uncertainty budget by a GUM Supplement 1 Monte Carlo of N draws through the "
        "session's register and measure implementations (= --option report.monte_carlo=N; docs/uncertainty.md)",
    )
    from crossfield.batch.engine import add_engine_flags

    add_engine_flags(run)  # where the Monte Carlo draws run: in this process unless --scheduler or --workers

    sub.add_parser(
        "romer-sim", add_help=False,
        help="run the simulated ROMER arm on a pseudo-terminal or TCP port (see romer-sim --help)",
    )

    replay = command(
        "replay",
        help="re-run a recorded session from its raw inputs, optionally with other plugins",
        description="Re-run the session recorded in SESSION.mcap from its raw inputs (images, serial bytes, "
        "calibration, plan) with the recorded plugins and options, or with the ones given here. "
        "The replay is recorded as a new session whose metadata names its parent and what changed.",
    )
    replay.add_argument("recording", metavar="SESSION.mcap", help="the recorded session")
    replay.add_argument(
        "-o", "--output", metavar="OUT.mcap",
        help="the MCAP file to write (report files go into a folder of the same name); "
        "default: a new session folder <id>-replay next to the recorded one",
    )
    replay.add_argument("--no-record", action="store_true", help="do not write an MCAP file")
    replay.add_argument("--no-rerun", action="store_true", help="do not write session.rrd")
    _add_stage_flags(replay)

    compare = command(
        "compare",
        help="compare two recorded sessions side by side (characteristics, registration, centroids)",
        description="Side by side: every characteristic, the registration (R, t, RMS, per-point residuals) "
        "and the centroid statistics of two recorded sessions, with every difference. "
        "Exit status 0 if they agree in every compared value, 1 if not.",
    )
    compare.add_argument("a", metavar="A.mcap")
    compare.add_argument("b", metavar="B.mcap")
    compare.add_argument("--json", action="store_true", help="machine-readable output")

    audit = command(
        "audit",
        help="check a recorded session: integrity chain, provenance, reproduction by replay",
        description="Check a recorded session: (1) integrity: the SHA-256 chain over every message; "
        "(2) provenance: config, plugins and versions, packages, machine, plan and calibration hashes; "
        "(3) reproduction: a replay with the recorded plugins gives the recorded results. "
        "Exit status 0 if all pass, 1 if not.",
    )
    audit.add_argument("recording", metavar="SESSION.mcap")
    audit.add_argument("--json", action="store_true", help="machine-readable output")
    audit.add_argument("--no-replay", action="store_true", help="skip the reproduction check")
    audit.add_argument(
        "--expect-head", metavar="HEX", help="the chain head kept outside the file (printed by `crossfield run`)"
    )
    audit.add_argument(
        "--public-key", metavar="KEY", help="the station's Ed25519 public key (PEM file or 64 hex digits)"
    )
    keygen = command(
        "keygen",
        help="make an Ed25519 station key that signs recordings ([session] signing_key)",
        description="Write a new Ed25519 private key to PATH (PEM, mode 0600) and its public key to "
        "PATH.pub. Set [session] signing_key = PATH to sign every recording's seal; give PATH.pub to "
        "`crossfield audit --public-key`.",
    )
    keygen.add_argument("path", metavar="PATH")
    keygen.add_argument("--force", action="store_true", help="overwrite an existing key")

    view = command(
        "view",
        help="show a session in the Rerun viewer (native, --web, or --screenshot PNG)",
        description="Open a session in the Rerun viewer with the crossfield blueprint. SESSION is a session.rrd, "
        "a session.mcap (its recorded results are shown through the full Rerun logger) or a session folder. "
        "With --screenshot the viewer renders headless and the exit status is 1 if a view reports an error.",
    )
    view.add_argument("session", metavar="SESSION", help="session.rrd, session.mcap or a session folder")
    view.add_argument("--web", action="store_true", help="serve the web viewer on http://127.0.0.1:PORT instead")
    view.add_argument("--port", type=int, default=9090, help="web viewer port (default 9090)")
    view.add_argument("--screenshot", metavar="PNG", help="render headless, write a screenshot and report view errors")
    view.add_argument("--window-size", default="1600x1000", metavar="WxH", help="screenshot size (default 1600x1000)")
    view.add_argument("--frame", type=int, metavar="N", help="show stereo pair N (default: the last)")
    view.add_argument("--save", metavar="OUT.rrd", help="MCAP input: keep the .rrd made from it")
    view.add_argument(
        "--image-every", type=int, metavar="N", help="MCAP input: show the images of every N-th pair (default: "
        "the recorded session's rerun_image_every)",
    )

    add_batch_commands(command)
    # -- export (docs/user-guide.md, "Exporting results") ------------------------------------
    export = command(
        "export",
        help="export a session's characteristics (CSV: nominal, measured, deviation, tolerances, U, k, decision)",
        description="Write one row per characteristic of a session (its folder or report.json) for SPC or "
        "QMS software: name, nominal, measured, deviation, tolerances, u, U, k, decision (mm, unrounded).",
    )
    export.add_argument("session", metavar="SESSION", help="session folder or its report.json")
    export.add_argument("--csv", metavar="FILE", help="the CSV file to write ('-' = stdout)")
    export.add_argument("--qif", metavar="FILE", help="the QIF 3.0.0 results document to write (ISO 23952; "
                        "validated against the official schema; docs/qif.md)")

    plugins = command("plugins", help="list every stage's registered implementations")
    plugins.add_argument("--json", action="store_true", help="machine-readable output")

    # calibrate / verify (crossfield.calibration_cli): parsers and their commands
    from crossfield.calibration_cli import add_parsers as _add_calibration_parsers

    COMMANDS.update(_add_calibration_parsers(command))
    # Station planning and the Cramér-Rao calculator (crossfield.planning.cli).
    from crossfield.planning.cli import add_parsers as add_planning_parsers

    add_planning_parsers(command)
    return parser


def resolve_run_config(args: argparse.Namespace) -> Config:
    """The config file (or defaults) with the command-line flags applied
    (:func:`crossfield.config.session_config`, shared with :func:`crossfield.run`)."""
    return session_config(
        args.config,
        plugins={stage: getattr(args, stage) for stage in STAGES},
        simulator={key: getattr(args, key) for key in SIMULATOR_OPTIONS},
        session={
            "plan": args.plan or None,
            "output_dir": args.output_dir or None,
            "name": args.name or None,
            "record": False if args.no_record else None,
            "rerun": False if args.no_rerun else None,
        },
        option_texts=[*args.option, *_monte_carlo_option(args)],
        spell=lambda key: f"--{key}",
    )


def _monte_carlo_option(args: argparse.Namespace) -> list[str]:
    """``--monte-carlo N`` as the report option it stands for."""
    n = getattr(args, "monte_carlo", None)
    return [f"report.monte_carlo={n}"] if n else []


def _monte_carlo_engine(args: argparse.Namespace, config: Config) -> contextlib.AbstractContextManager:
    """``--scheduler`` / ``--workers`` of ``run``: the Monte Carlo draws on Dask (``local``
    or ``--workers`` alone: an embedded LocalCluster); neither: in this process, no Dask."""
    from crossfield.errors import ConfigError

    scheduler, workers = getattr(args, "scheduler", None), getattr(args, "workers", None)
    if scheduler is None and workers is None:
        return contextlib.nullcontext()
    if not config.stages["report"].options.get("monte_carlo"):
        raise ConfigError("--scheduler and --workers apply to the Monte Carlo check: give --monte-carlo N")
    from crossfield.uncertainty.montecarlo import on_dask

    return on_dask(None if scheduler == "local" else scheduler, workers, args.memory_limit)


def plugin_manager() -> "pluggy.PluginManager":
    """The built-in plugins and the installed third-party ones (entry-point group ``crossfield``)."""
    pm = make_plugin_manager(entry_points=True)
    logger.debug("plugins registered: %s", ", ".join(sorted(name for name, _ in pm.list_name_plugin())))
    return pm


def cmd_run(args: argparse.Namespace) -> int:
    from crossfield.progress import Progress
    from crossfield.runner import run_session

    config = resolve_run_config(args)
    logger.info(
        "config %s: %s", config.source, ", ".join(f"{s}={config.stages[s].plugin}" for s in STAGES)
    )
    logger.debug("resolved config: %s", json.dumps(config.to_dict(), default=str))
    pm = plugin_manager()
    frames = config.stages["acquire"].options.get("frames")
    observers = [] if args.quiet else [Progress(total=frames if isinstance(frames, int) else None)]
    live = None
    if args.view:
        from crossfield.viz.rerun_log import RerunLogger
        from crossfield.viz.view import spawn_live_viewer

        live = RerunLogger(viewer=spawn_live_viewer() if args.view == "new" else args.view)
        observers.append(live)
    with _monte_carlo_engine(args, config):
        summary = run_session(config, pm, observers=observers)
    for warning in live.warnings if live is not None else ():
        logger.warning("%s", warning)
    reporter = summary.info.plugins["report"]["name"]
    from crossfield.registry import get_implementation

    impl = get_implementation(pm, "report", reporter).create(dict(config.stages["report"].options))
    print(impl.summary_text(summary))
    print_seal(summary.info.out_dir / "session.mcap")
    print(f"session written to {summary.info.out_dir}/")
    for path in sorted(summary.info.out_dir.iterdir()):
        print(f"  {path.name:<22} {path.stat().st_size / 1e6:9.2f} MB")
    return 0 if summary.passed else 1


def print_seal(recording: Path) -> None:
    """Print the recording's chain head and file SHA-256 (its seal), if it was sealed."""
    from crossfield.recording.seal import read_sidecar, sidecar_path

    sealed = read_sidecar(recording) if sidecar_path(recording).exists() else None
    if sealed is not None:
        print(f"integrity chain head {sealed['chain_head']}")
        print(f"file SHA-256         {sealed['file_sha256']}" + ("  (signed)" if sealed.get("signature") else ""))


def cmd_plugins(args: argparse.Namespace) -> int:
    pm = plugin_manager()
    table = {
        stage: [
            {
                "name": i.name,
                "description": i.description,
                "plugin": i.plugin,
                "package": i.package,
                "version": i.version,
                "options": {k: (None if v is __import__("inspect").Parameter.empty else v) for k, v in i.options().items()},
            }
            for i in implementations(pm, stage).values()
        ]
        for stage in STAGES
    }
    if args.json:
        print(json.dumps(table, indent=2, default=str))
        return 0
    for stage in STAGES:
        print(f"{stage}:")
        for entry in table[stage]:
            print(f"  {entry['name']:<16} {entry['package']} {entry['version']}  ({entry['plugin']})")
            if entry["description"]:
                print(f"  {'':<16} {entry['description']}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from crossfield.progress import Progress
    from crossfield.registry import get_implementation
    from crossfield.replay import load_recorded_session, replay_session

    pm = plugin_manager()
    logger.info("replaying %s", args.recording)
    recorded = load_recorded_session(args.recording)
    total = None
    if recorded.complete:  # the summary's statistics give the count without reading the images
        from crossfield.recording.layout import IMAGE_TOPICS

        info = recorded.recording.topics().get(IMAGE_TOPICS[0])
        total = info.message_count if info else None
    observers = [] if args.quiet else [Progress(total=total)]
    plugins, options = stage_choices(args)
    summary = replay_session(
        args.recording,
        pm,
        plugins=plugins,
        options=options,
        output=args.output,
        record=not args.no_record,
        rerun=False if args.no_rerun else None,
        observers=observers,
        recorded=recorded,
    )
    config = summary.info.config
    impl = get_implementation(pm, "report", config.stages["report"].plugin).create(
        dict(config.stages["report"].options)
    )
    parent = summary.info.parent or {}
    print(
        f"replay of {parent.get('path')} (session {parent.get('session_id')}, SHA-256 {parent.get('sha256')})"
    )
    changed = parent.get("changed") or {}
    if not changed.get("plugins") and not changed.get("options"):
        print("  with the recorded plugins and options")
    for stage, c in (changed.get("plugins") or {}).items():
        print(f"  {stage}: {c['from']} -> {c['to']}")
    for key, c in (changed.get("options") or {}).items():
        print(f"  {key}: {c['from']!r} -> {c['to']!r}")
    if summary.incomplete:
        print(f"INCOMPLETE: {summary.incomplete}")
    print(impl.summary_text(summary))
    if not args.no_record:
        print_seal(Path(args.output) if args.output else summary.info.out_dir / "session.mcap")
    if args.output and not args.no_record:
        print(f"replay recorded to {args.output}")
    print(f"session files in {summary.info.out_dir}/")
    for path in sorted(summary.info.out_dir.iterdir()):
        print(f"  {path.name:<22} {path.stat().st_size / 1e6:9.2f} MB")
    return 0 if summary.passed else 1


def cmd_compare(args: argparse.Namespace) -> int:
    from crossfield.compare import compare, format_table

    result = compare(args.a, args.b)
    if args.json:
        print(json.dumps(result, indent=2, allow_nan=False, default=str))
    else:
        print(format_table(result))
    return 0 if result["identical"] else 1


def cmd_audit(args: argparse.Namespace) -> int:
    from crossfield.audit import audit, format_report, to_json

    report = audit(
        args.recording,
        plugin_manager(),
        reproduce=not args.no_replay,
        expect_head=args.expect_head,
        public_key=args.public_key,
    )
    print(to_json(report) if args.json else format_report(report))
    return 0 if report.passed else 1


def cmd_keygen(args: argparse.Namespace) -> int:
    from crossfield.recording.seal import generate_key

    private, public, key_hex = generate_key(args.path, overwrite=args.force)
    print(f"private key {private} (keep it on the station; [session] signing_key = {str(private)!r})")
    print(f"public key  {public}  {key_hex}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from crossfield.viz.view import parse_window_size, view

    return view(
        args.session,
        web=args.web,
        port=args.port,
        screenshot_to=args.screenshot,
        window_size=parse_window_size(args.window_size),
        frame=args.frame,
        save=args.save,
        image_every=args.image_every,
    )


# ---- crossfield batch (docs/batch.md) ------------------------------------------------


def add_batch_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    """``crossfield batch audit | replay | compare PATHS...`` over an archive, on Dask."""
    from crossfield.batch.engine import add_engine_flags

    batch = command(
        "batch",
        help="audit, replay or compare many recorded sessions on Dask (see docs/batch.md)",
        description="Audit, replay, or replay with other plugins and compare, every session named by PATHS "
        "(session folders, MCAP files, globs), one Dask task per session, on an embedded LocalCluster or "
        "--scheduler. Writes batch-report.json and batch-report.html to -o DIR as sessions finish. "
        "Exit status 0 if every session's verdict is PASS, 1 if not.",
    )
    kinds = batch.add_subparsers(dest="batch_kind", required=True, metavar="KIND")
    helps = {
        "audit": "audit every session (as crossfield audit)",
        "replay": "replay every session, optionally with other plugins (as crossfield replay)",
        "compare": "replay every session with other plugins and compare it with its original",
    }
    for kind, text in helps.items():
        p = kinds.add_parser(kind, help=text, parents=[_verbosity_flags(argparse.SUPPRESS)])
        p.add_argument("paths", nargs="+", metavar="PATH", help="session folder, MCAP file or glob (quoted)")
        p.add_argument(
            "-o", "--output-dir", metavar="DIR",
            help="where the report and the per-session folders are written (default: a new folder under recordings/)",
        )
        add_engine_flags(p)
        if kind != "audit":
            _add_stage_flags(p)


def cmd_batch(args: argparse.Namespace) -> int:
    from crossfield.batch.run import run_batch

    plugins, options = stage_choices(args) if args.batch_kind != "audit" else ({}, [])
    report = run_batch(
        args.batch_kind,
        args.paths,
        out_dir=args.output_dir,
        plugins=plugins,
        options=options,
        scheduler=args.scheduler,
        workers=args.workers,
        memory_limit=args.memory_limit,
        progress=not args.quiet and sys.stdout.isatty(),
        echo=(lambda text: None) if args.quiet else print,
    )
    doc = report.to_json()
    print(", ".join(f"{v} {n}" for v, n in doc["counts"].items()) + f" of {doc['inputs']} session(s)")
    for entry in doc["sessions"]:
        if entry["verdict"] != "PASS":
            where = "" if entry["reason"].startswith(entry["path"]) else f"{entry['path']}: "
            print(f"  {entry['verdict']:<10} {where}{entry['reason']}")
    print(f"report: {report.json_path}")
    print(f"        {report.html_path}")
    return 0 if doc["counts"]["PASS"] == doc["inputs"] else 1


def cmd_export(args: argparse.Namespace) -> int:
    from crossfield.export import characteristic_rows, load_report, to_csv, write_csv

    if not (args.csv or args.qif):
        raise CrossfieldError("crossfield export: give --csv FILE and/or --qif FILE")
    if args.csv == "-":
        sys.stdout.write(to_csv(characteristic_rows(load_report(args.session))))
    elif args.csv:
        print(f"wrote {write_csv(args.session, args.csv)}")
    if args.qif:
        from crossfield.report.qif import write_qif

        print(f"wrote {write_qif(args.session, args.qif)} (valid QIF 3.0.0)")
    return 0


COMMANDS = {
    "run": cmd_run, "replay": cmd_replay, "compare": cmd_compare, "audit": cmd_audit, "keygen": cmd_keygen, "plugins": cmd_plugins,
    "view": cmd_view, "batch": cmd_batch, "export": cmd_export,
}


def log_level(verbose: int = 0, quiet: int = 0) -> int:
    """The logging level of ``-q`` (ERROR), no flag (WARNING), ``-v`` (INFO), ``-vv`` (DEBUG)."""
    if quiet:
        return logging.ERROR
    return (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]


class _Formatter(logging.Formatter):
    """``<logger>: <level>: <message>``, e.g. ``crossfield.cli: warning: ...``."""

    def format(self, record: logging.LogRecord) -> str:
        return f"{record.name}: {record.levelname.lower()}: {record.getMessage()}" + (
            "\n" + self.formatException(record.exc_info) if record.exc_info else ""
        )


@contextlib.contextmanager
def logging_to_stderr(level: int) -> Iterator[None]:
    """While a command runs, the ``crossfield`` loggers (one per module, named
    ``crossfield.<module>``, and the device plugins' ``crossfield.<stage>.<name>``)
    write records of ``level`` and above to stderr."""
    root = logging.getLogger("crossfield")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter())
    previous = root.level
    root.setLevel(level)
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)
        root.setLevel(previous)


def _stdout_gone() -> int:
    """The reader of stdout went away (``crossfield plugins | head -1``): end quietly,
    with the status of a command stopped by SIGPIPE. Later writes (the interpreter
    flushes stdout at exit) go to /dev/null (docs.python.org, signal: Note on SIGPIPE)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout without a file descriptor
        pass
    return 128 + signal.SIGPIPE
def _planning_command(name: str):
    def run(args: argparse.Namespace) -> int:
        from crossfield.planning import cli as planning_cli

        return getattr(planning_cli, name)(args)

    return run


COMMANDS.update(plan=_planning_command("cmd_plan"), crb=_planning_command("cmd_crb"))


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["romer-sim"]:
        from crossfield.simulator.romer_sim import main_romer_sim

        return main_romer_sim(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        with logging_to_stderr(log_level(args.verbose, args.quiet)):
            status = COMMANDS[args.command](args)
            sys.stdout.flush()  # here, so that a closed pipe is caught below
            return status
    except BrokenPipeError:
        return _stdout_gone()
    except CrossfieldError as exc:
        print(f"crossfield: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crossfield: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
