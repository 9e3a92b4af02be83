"""The ``crossfield`` command line (``docs/user-guide.md``)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from crossfield.config import Config, load_config, with_overrides
from crossfield.errors import CrossfieldError
from crossfield.registry import STAGES, implementations, make_plugin_manager


def _add_stage_flags(parser: argparse.ArgumentParser) -> None:
    for stage in STAGES:
        parser.add_argument(f"--{stage}", metavar="NAME", help=f"{stage} implementation (see `crossfield plugins`)")
    parser.add_argument(
        "--option", action="append", default=[], metavar="STAGE.KEY=VALUE",
        help="set a stage option, e.g. centroid.threshold_sigma=8 (repeatable)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crossfield",
        description="Local stereo vision registered to out-of-view CMM references (metrology pipeline).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run a measurement session (default: the built-in simulator)")
    run.add_argument("-c", "--config", metavar="FILE", help="session config (TOML); defaults apply otherwise")
    run.add_argument("--scenario", help="simulator scenario: station, table3 or camera-limited")
    run.add_argument("--frames", type=int, help="number of stereo pairs (simulator)")
    run.add_argument("--seed", type=int, help="noise seed (simulator)")
    run.add_argument("--plan", metavar="FILE", help="measurement plan (TOML)")
    run.add_argument("-o", "--output-dir", metavar="DIR", help="where the session folder is written")
    run.add_argument("--name", help="session folder name (default: time stamp and scenario)")
    run.add_argument("--no-record", action="store_true", help="do not write session.mcap")
    run.add_argument("--no-rerun", action="store_true", help="do not write session.rrd")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    run.add_argument(
        "--view", nargs="?", const="new", metavar="URL",
        help="stream the session live to a Rerun viewer: a new native viewer, or the running one at URL "
        "(rerun+http://HOST:PORT/proxy); see docs/visualisation.md",
    )
    _add_stage_flags(run)

    sub.add_parser(
        "romer-sim", add_help=False,
        help="run the simulated ROMER arm on a pseudo-terminal or TCP port (see romer-sim --help)",
    )

    replay = sub.add_parser(
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
    replay.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    _add_stage_flags(replay)

    compare = sub.add_parser(
        "compare",
        help="compare two recorded sessions side by side (characteristics, registration, centroids)",
        description="Side by side: every characteristic, the registration (R, t, RMS, per-point residuals) "
        "and the centroid statistics of two recorded sessions, with every difference. "
        "Exit status 0 if they agree in every compared value, 1 if not.",
    )
    compare.add_argument("a", metavar="A.mcap")
    compare.add_argument("b", metavar="B.mcap")
    compare.add_argument("--json", action="store_true", help="machine-readable output")

    audit = sub.add_parser(
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

    view = sub.add_parser(
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

    plugins = sub.add_parser("plugins", help="list every stage's registered implementations")
    plugins.add_argument("--json", action="store_true", help="machine-readable output")
    return parser


def resolve_run_config(args: argparse.Namespace) -> Config:
    """The config file (or defaults) with the command-line flags applied."""
    config = load_config(args.config)
    options = list(args.option)
    acquire_plugin = args.acquire or config.stages["acquire"].plugin
    for flag, key in (("scenario", "scenario"), ("frames", "frames"), ("seed", "seed")):
        value = getattr(args, flag)
        if value is not None:
            if acquire_plugin != "simulator":
                raise CrossfieldError(f"--{flag} applies to the simulator source, not to {acquire_plugin!r}")
            options.append(f"acquire.{key}={json.dumps(value)}")
    if args.plan:
        options.append(f"session.plan={json.dumps(args.plan)}")
    if args.output_dir:
        options.append(f"session.output_dir={json.dumps(args.output_dir)}")
    if args.name:
        options.append(f"session.name={json.dumps(args.name)}")
    if args.no_record:
        options.append("session.record=false")
    if args.no_rerun:
        options.append("session.rerun=false")
    plugins = {stage: getattr(args, stage) for stage in STAGES}
    # The demo default: the serial plugin talks to the simulated arm.
    reference_plugin = args.reference or config.stages["reference"].plugin
    keeps_port = not args.reference or args.reference == config.stages["reference"].plugin
    has_port = keeps_port and "port" in config.stages["reference"].options
    if reference_plugin == "romer-serial" and acquire_plugin == "simulator" and not has_port:
        options.append('reference.port="simulator"')
    return with_overrides(config, plugins, options)


def cmd_run(args: argparse.Namespace) -> int:
    from crossfield.progress import Progress
    from crossfield.runner import run_session

    config = resolve_run_config(args)
    pm = make_plugin_manager(entry_points=True)
    frames = config.stages["acquire"].options.get("frames")
    observers = [] if args.quiet else [Progress(total=frames if isinstance(frames, int) else None)]
    live = None
    if args.view:
        from crossfield.viz.rerun_log import RerunLogger
        from crossfield.viz.view import spawn_live_viewer

        live = RerunLogger(viewer=spawn_live_viewer() if args.view == "new" else args.view)
        observers.append(live)
    summary = run_session(config, pm, observers=observers)
    for warning in live.warnings if live is not None else ():
        print(f"crossfield: warning: {warning}", file=sys.stderr)
    reporter = summary.info.plugins["report"]["name"]
    from crossfield.registry import get_implementation

    impl = get_implementation(pm, "report", reporter).create(dict(config.stages["report"].options))
    print(impl.summary_text(summary))
    print(f"session written to {summary.info.out_dir}/")
    for path in sorted(summary.info.out_dir.iterdir()):
        print(f"  {path.name:<14} {path.stat().st_size / 1e6:9.2f} MB")
    return 0 if summary.passed else 1


def cmd_plugins(args: argparse.Namespace) -> int:
    pm = make_plugin_manager(entry_points=True)
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

    pm = make_plugin_manager(entry_points=True)
    recorded = load_recorded_session(args.recording)
    total = None
    if recorded.complete:  # the summary's statistics give the count without reading the images
        info = recorded.recording.topics().get("/camera/upper/image")
        total = info.message_count if info else None
    observers = [] if args.quiet else [Progress(total=total)]
    summary = replay_session(
        args.recording,
        pm,
        plugins={stage: getattr(args, stage) for stage in STAGES},
        options=args.option,
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
    if args.output and not args.no_record:
        print(f"replay recorded to {args.output}")
    print(f"session files in {summary.info.out_dir}/")
    for path in sorted(summary.info.out_dir.iterdir()):
        print(f"  {path.name:<14} {path.stat().st_size / 1e6:9.2f} MB")
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

    report = audit(args.recording, make_plugin_manager(entry_points=True), reproduce=not args.no_replay)
    print(to_json(report) if args.json else format_report(report))
    return 0 if report.passed else 1


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


COMMANDS = {
    "run": cmd_run, "replay": cmd_replay, "compare": cmd_compare, "audit": cmd_audit, "plugins": cmd_plugins,
    "view": cmd_view,
}


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["romer-sim"]:
        from crossfield.simulator.romer_sim import main_romer_sim

        return main_romer_sim(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except CrossfieldError as exc:
        print(f"crossfield: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crossfield: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
