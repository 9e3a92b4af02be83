"""``crossfield run | replay | compare | audit | keygen | view | export | plugins``:
one session's commands (``docs/user-guide.md``)."""

from __future__ import annotations

import argparse
import contextlib
import inspect
import json
import logging
import sys
from pathlib import Path

from crossfield.batch.engine import add_engine_flags, engine_from_args
from crossfield.chain.registry import STAGES, get_implementation, implementations
from crossfield.cli.common import (
    Command,
    add_stage_flags,
    plugin_manager,
    print_seal,
    print_session_files,
    stage_choices,
)
from crossfield.config import SIMULATOR_OPTIONS, Config, session_config
from crossfield.errors import ConfigError
from crossfield.recording.layout import IMAGE_TOPICS
from crossfield.recording.seal import generate_key

__all__ = ["COMMANDS", "resolve_run_config"]

logger = logging.getLogger(__name__)


#: The kinds of input (:data:`crossfield.cli.inputs.KINDS`) each command takes.
SESSION_RECORDING = ("session-recording",)
ANY_RECORDING = ("session-recording", "calibration-recording", "verification-recording")
VIEWABLE = ("session-folder", "session-recording", "rerun")
SESSION_REPORT = ("session-folder", "report")
TOML_TEXT = ("other",)  # not a recording, report, seal or folder: the TOML reader names any fault


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    from crossfield.catalog import commands as catalog
    parser.add_argument("-c", "--config", metavar="FILE", help="session config (TOML); defaults apply otherwise")
    parser.add_argument("--scenario", help="simulator scenario: station, table3, camera-limited, mismatch-cmm, mismatch-camera or mismatch-mixed")
    parser.add_argument("--frames", type=int, help="number of stereo pairs (simulator)")
    parser.add_argument("--seed", type=int, help="noise seed (simulator)")
    parser.add_argument("--plan", metavar="FILE", help="measurement plan (TOML)")
    parser.add_argument("-o", "--output-dir", metavar="DIR", help="where the session folder is written")
    parser.add_argument("--name", help="session folder name (default: time stamp and scenario)")
    parser.add_argument("--no-record", action="store_true", help="do not write session.mcap")
    parser.add_argument("--no-rerun", action="store_true", help="do not write session.rrd")
    parser.add_argument(
        "--view", nargs="?", const="new", metavar="URL",
        help="stream the session live to a Rerun viewer: a new native viewer, or the running one at URL "
        "(rerun+http://HOST:PORT/proxy); see docs/visualisation.md",
    )
    add_stage_flags(parser)
    parser.add_argument(
        "--monte-carlo", type=int, metavar="N",
        help="also check the uncertainty budget by a GUM Supplement 1 Monte Carlo of N draws through the "
        "session's register and measure implementations (= [session] monte_carlo = N; docs/uncertainty.md)",
    )
    add_engine_flags(parser)  # where the Monte Carlo draws run: in this process unless --scheduler or --workers
    catalog.add_run_flag(parser)  # --catalog URL: the session into the catalog when written (docs/catalog.md)


def add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="SESSION.mcap", help="the recorded session")
    parser.add_argument(
        "-o", "--output", metavar="OUT.mcap",
        help="the MCAP file to write (report files go into a folder of the same name); "
        "default: a new session folder <id>-replay next to the recorded one",
    )
    parser.add_argument("--no-record", action="store_true", help="do not write an MCAP file")
    parser.add_argument("--no-rerun", action="store_true", help="do not write session.rrd")
    add_stage_flags(parser)


def add_compare_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("a", metavar="A.mcap")
    parser.add_argument("b", metavar="B.mcap")
    parser.add_argument("--json", action="store_true", help="machine-readable output")


def add_audit_arguments(parser: argparse.ArgumentParser) -> None:
    from crossfield.catalog import commands as catalog
    parser.add_argument("recording", metavar="SESSION.mcap")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--no-replay", action="store_true", help="skip the reproduction check")
    parser.add_argument(
        "--expect-head", metavar="HEX", help="the chain head kept outside the file (printed by `crossfield run`)"
    )
    parser.add_argument(
        "--public-key", metavar="KEY", help="the station's Ed25519 public key (PEM file or 64 hex digits)"
    )
    catalog.add_audit_flag(parser)  # --catalog URL: the outside anchor (docs/catalog.md)


def add_keygen_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", metavar="PATH")
    parser.add_argument("--force", action="store_true", help="overwrite an existing key")


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", metavar="SESSION", help="session.rrd, session.mcap or a session folder")
    parser.add_argument("--web", action="store_true", help="serve the web viewer on http://127.0.0.1:PORT instead")
    parser.add_argument("--port", type=int, default=9090, help="web viewer port (default 9090)")
    parser.add_argument("--screenshot", metavar="PNG", help="render headless, write a screenshot and report view errors")
    parser.add_argument("--window-size", default="1600x1000", metavar="WxH", help="screenshot size (default 1600x1000)")
    parser.add_argument("--frame", type=int, metavar="N", help="show stereo pair N (default: the last)")
    parser.add_argument("--save", metavar="OUT.rrd", help="MCAP input: keep the .rrd made from it")
    parser.add_argument(
        "--image-every", type=int, metavar="N", help="MCAP input: show the images of every N-th pair (default: "
        "the recorded session's rerun_image_every)",
    )


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", metavar="SESSION", help="session folder or its report.json")
    parser.add_argument("--csv", metavar="FILE", help="the CSV file to write ('-' = stdout)")
    parser.add_argument("--qif", metavar="FILE", help="the QIF 3.0.0 results document to write (ISO 23952; "
                        "validated against the official schema; docs/qif.md)")


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
            "monte_carlo": args.monte_carlo,
        },
        option_texts=list(args.option),
        spell=lambda key: f"--{key}",
    )


def cmd_run(args: argparse.Namespace) -> int:
    from crossfield.catalog import commands as catalog
    from crossfield.chain.runner import run_session
    from crossfield.cli.inputs import require
    from crossfield.progress import Progress
    from crossfield.session import STOP_INTERRUPTED
    from crossfield.uncertainty.montecarlo import on_dask
    from crossfield.viz.rerun_log import RerunLogger
    from crossfield.viz.view import spawn_live_viewer
    for flag, path in (("--config", args.config), ("--plan", args.plan)):
        if path:
            require(path, TOML_TEXT, "run", f"a TOML file for {flag}", recording=False)
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
        live = RerunLogger(viewer=spawn_live_viewer() if args.view == "new" else args.view)
        observers.append(live)
    engine = engine_from_args(args)
    if engine is not None and not config.session.get("monte_carlo"):
        raise ConfigError("--scheduler and --workers apply to the Monte Carlo check: give --monte-carlo N")
    with on_dask(engine) if engine is not None else contextlib.nullcontext():
        summary = run_session(config, pm, observers=observers)
    for warning in live.warnings if live is not None else ():
        logger.warning("%s", warning)
    reporter = summary.info.plugins["report"]["name"]

    impl = get_implementation(pm, "report", reporter).create(dict(config.stages["report"].options))
    print(impl.summary_text(summary))
    print_seal(summary.info.out_dir / "session.mcap")
    print_session_files(summary.info.out_dir, "session written to")
    catalog.ingest_run(args, config, summary.info.out_dir)  # --catalog / [catalog] url; never fails the run
    if summary.stop is not None:  # Ctrl-C or a source error: the INCOMPLETE report is written
        print(
            f"crossfield: session INCOMPLETE: {summary.stop.reason}; report in {summary.info.out_dir}",
            file=sys.stderr,
        )
        return 130 if summary.stop.kind == STOP_INTERRUPTED else 2
    return 0 if summary.passed else 1


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
                "options": {k: (None if v is inspect.Parameter.empty else v) for k, v in i.options().items()},
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

    from crossfield.cli.inputs import require
    from crossfield.progress import Progress
    from crossfield.replay import load_recorded_session, replay_session
    pm = plugin_manager()
    require(args.recording, SESSION_RECORDING, "replay", "a session recording (session.mcap)")
    logger.info("replaying %s", args.recording)
    recorded = load_recorded_session(args.recording)
    total = None
    if recorded.complete:  # the summary's statistics give the count without reading the images
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
    for note in parent.get("notes", []):
        print(f"  note: {note}")
    if summary.incomplete:
        print(f"INCOMPLETE: {summary.incomplete}")
    print(impl.summary_text(summary))
    if not args.no_record:
        print_seal(Path(args.output) if args.output else summary.info.out_dir / "session.mcap")
    if args.output and not args.no_record:
        print(f"replay recorded to {args.output}")
    print_session_files(summary.info.out_dir, "session files in")
    return 0 if summary.passed else 1


def cmd_compare(args: argparse.Namespace) -> int:
    from crossfield.cli.inputs import require
    from crossfield.compare import compare, format_table
    for path in (args.a, args.b):
        require(path, SESSION_RECORDING, "compare", "two session recordings (session.mcap)")
    result = compare(args.a, args.b)
    if args.json:
        print(json.dumps(result, indent=2, allow_nan=False, default=str))
    else:
        print(format_table(result))
    return 0 if result["identical"] else 1


def cmd_audit(args: argparse.Namespace) -> int:
    from crossfield.audit import audit, format_report, to_json
    from crossfield.catalog import commands as catalog
    from crossfield.cli.inputs import require
    require(args.recording, ANY_RECORDING, "audit", "a session, calibration or verification recording (.mcap)")
    if args.catalog:  # the outside anchor: the head, SHA-256 and signature the catalog keeps
        report = catalog.audit_command(args, plugin_manager())
    else:
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
    private, public, key_hex = generate_key(args.path, overwrite=args.force)
    print(f"private key {private} (keep it on the station; [session] signing_key = {str(private)!r})")
    print(f"public key  {public}  {key_hex}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from crossfield.cli.inputs import require
    from crossfield.viz.view import parse_window_size, view
    require(args.session, VIEWABLE, "view", "a session folder, session.rrd or session.mcap")
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


def cmd_export(args: argparse.Namespace) -> int:
    from crossfield.cli.inputs import require
    from crossfield.export import characteristic_rows, load_report, to_csv, write_csv
    from crossfield.report.qif import write_qif
    if not (args.csv or args.qif):
        raise ConfigError("crossfield export: give --csv FILE and/or --qif FILE")
    require(args.session, SESSION_REPORT, "export", "a session folder or its report.json", recording=False)
    if args.csv == "-":
        sys.stdout.write(to_csv(characteristic_rows(load_report(args.session))))
    elif args.csv:
        print(f"wrote {write_csv(args.session, args.csv)}")
    if args.qif:
        print(f"wrote {write_qif(args.session, args.qif)} (valid QIF 3.0.0)")
    return 0


def add_plugins_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="machine-readable output")


COMMANDS: tuple[Command, ...] = (
    Command("run", add_run_arguments, cmd_run, help="run a measurement session (default: the built-in simulator)",
            description=""),
    Command("replay", add_replay_arguments, cmd_replay, help="re-run a recorded session from its raw inputs, optionally with other plugins",
            description="Re-run the session recorded in SESSION.mcap from its raw inputs (images, serial bytes, "
        "calibration, plan) with the recorded plugins and options, or with the ones given here. "
        "The replay is recorded as a new session whose metadata names its parent and what changed."),
    Command("compare", add_compare_arguments, cmd_compare, help="compare two recorded sessions side by side (characteristics, registration, centroids)",
            description="Side by side: every characteristic, the registration (R, t, RMS, per-point residuals) "
        "and the centroid statistics of two recorded sessions, with every difference. "
        "Exit status 0 if they agree in every compared value, 1 if not."),
    Command("audit", add_audit_arguments, cmd_audit, help="check a recorded session: integrity chain, provenance, reproduction by replay",
            description="Check a recorded session: (1) integrity: the hash chain over every record; "
        "(2) provenance: config, plugins and versions, packages, machine, plan and calibration hashes; "
        "(3) reproduction: a replay with the recorded plugins gives the recorded results. "
        "Exit status 0 if all pass, 1 if not."),
    Command("keygen", add_keygen_arguments, cmd_keygen, help="make an Ed25519 station key that signs recordings ([session] signing_key)",
            description="Write a new Ed25519 private key to PATH (PEM, mode 0600) and its public key to "
        "PATH.pub. Set [session] signing_key = PATH to sign every recording's seal; give PATH.pub to "
        "`crossfield audit --public-key`."),
    Command("view", add_view_arguments, cmd_view, help="show a session in the Rerun viewer (native, --web, or --screenshot PNG)",
            description="Open a session in the Rerun viewer with the crossfield blueprint. SESSION is a session.rrd, "
        "a session.mcap (its recorded results are shown through the full Rerun logger) or a session folder. "
        "With --screenshot the viewer renders headless and the exit status is 1 if a view reports an error."),
    Command("export", add_export_arguments, cmd_export, help="export a session's characteristics (CSV: nominal, measured, deviation, tolerances, U, k, decision)",
            description="Write one row per characteristic of a session (its folder or report.json) for SPC or "
        "QMS software: name, nominal, measured, deviation, tolerances, u, U, k, decision (mm, unrounded)."),
    Command("plugins", add_plugins_arguments, cmd_plugins, help="list every stage's registered implementations"),
)
