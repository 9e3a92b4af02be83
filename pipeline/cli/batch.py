"""``crossfield batch audit | replay | compare``: many recorded sessions on Dask (``docs/batch.md``)."""

from __future__ import annotations

import argparse

from crossfield.batch.engine import Engine, add_engine_flags, engine_from_args
from crossfield.cli.common import Command, add_stage_flags, stage_choices, verbosity_flags

__all__ = ["COMMANDS"]


def add_batch_arguments(parser: argparse.ArgumentParser) -> None:
    """``crossfield batch audit | replay | compare PATHS...`` over an archive, on Dask."""
    kinds = parser.add_subparsers(dest="batch_kind", required=True, metavar="KIND")
    helps = {
        "audit": "audit every session (as crossfield audit)",
        "replay": "replay every session, optionally with other plugins (as crossfield replay)",
        "compare": "replay every session with other plugins and compare it with its original",
    }
    for kind, text in helps.items():
        p = kinds.add_parser(kind, help=text, parents=[verbosity_flags(argparse.SUPPRESS)])
        p.add_argument("paths", nargs="+", metavar="PATH", help="session folder, MCAP file or glob (quoted)")
        p.add_argument(
            "-o", "--output-dir", metavar="DIR",
            help="where the report and the per-session folders are written (default: a new folder under recordings/)",
        )
        add_engine_flags(p)
        if kind != "audit":
            add_stage_flags(p)


def cmd_batch(args: argparse.Namespace) -> int:
    from crossfield.batch.run import run_batch
    plugins, options = stage_choices(args) if args.batch_kind != "audit" else ({}, [])
    report = run_batch(
        args.batch_kind,
        args.paths,
        out_dir=args.output_dir,
        plugins=plugins,
        options=options,
        engine=engine_from_args(args) or Engine(memory_limit=args.memory_limit),
        progress=not args.quiet,  # on a terminal only (crossfield.progress)
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


COMMANDS: tuple[Command, ...] = (
    Command(
        "batch", add_batch_arguments, cmd_batch,
        help="audit, replay or compare many recorded sessions on Dask (see docs/batch.md)",
        description="Audit, replay, or replay with other plugins and compare, every session named by PATHS "
        "(session folders, MCAP files, globs), one Dask task per session, on an embedded LocalCluster "
        "(default, or --scheduler local) or --scheduler tcp://HOST:PORT. Writes batch-report.json and "
        "batch-report.html to -o DIR as sessions finish. Exit status 0 if every session's verdict is PASS, 1 if not.",
    ),
)
