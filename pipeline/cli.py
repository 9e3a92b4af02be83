"""The ``crossfield`` command line (``docs/user-guide.md``)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from .config import Config, load_config, with_overrides
from .errors import CrossfieldError
from .registry import STAGES, implementations, make_plugin_manager


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
    run.add_argument("--scenario", help="simulator scenario: station or table3")
    run.add_argument("--frames", type=int, help="number of stereo pairs (simulator)")
    run.add_argument("--seed", type=int, help="noise seed (simulator)")
    run.add_argument("--plan", metavar="FILE", help="measurement plan (TOML)")
    run.add_argument("-o", "--output-dir", metavar="DIR", help="where the session folder is written")
    run.add_argument("--name", help="session folder name (default: time stamp and scenario)")
    run.add_argument("--no-record", action="store_true", help="do not write session.mcap")
    run.add_argument("--no-rerun", action="store_true", help="do not write session.rrd")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    _add_stage_flags(run)

    sub.add_parser(
        "romer-sim", add_help=False,
        help="run the simulated ROMER arm on a pseudo-terminal or TCP port (see romer-sim --help)",
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
    config = with_overrides(config, plugins, options)
    # The demo default: the serial plugin talks to the simulated arm.
    ref = config.stages["reference"]
    if ref.plugin == "romer-serial" and "port" not in ref.options and config.stages["acquire"].plugin == "simulator":
        config = with_overrides(config, {}, ['reference.port="simulator"'])
    return config


def cmd_run(args: argparse.Namespace) -> int:
    from .progress import Progress
    from .runner import run_session

    config = resolve_run_config(args)
    pm = make_plugin_manager(entry_points=True)
    frames = config.stages["acquire"].options.get("frames")
    observers = [] if args.quiet else [Progress(total=frames if isinstance(frames, int) else None)]
    summary = run_session(config, pm, observers=observers)
    reporter = summary.info.plugins["report"]["name"]
    from .registry import get_implementation

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


COMMANDS = {"run": cmd_run, "plugins": cmd_plugins}


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["romer-sim"]:
        from .simulator.romer_sim import main_romer_sim

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
