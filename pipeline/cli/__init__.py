"""The ``crossfield`` command line (``docs/user-guide.md``).

Every command is one :class:`~crossfield.cli.common.Command` in the ``COMMANDS``
tuple of one module of this package, each module filling it the same way:

* :mod:`crossfield.cli.session`: run, replay, compare, audit, keygen, view, export, plugins;
* :mod:`crossfield.cli.batch`: batch (audit, replay, compare over an archive, on Dask);
* :mod:`crossfield.cli.calibration`: calibrate, verify;
* :mod:`crossfield.cli.planning`: plan, crb;
* :mod:`crossfield.cli.simulator`: romer-sim;
* :mod:`crossfield.cli.catalog`: catalog.

:data:`COMMANDS` is their union (name -> command), in that order; :func:`main` parses
the arguments, runs the command with the ``crossfield`` loggers on stderr, and turns
a :class:`~crossfield.errors.CrossfieldError` into one line and exit status 2.

The command modules import at their top only what their parsers need; each command
imports the pipeline, Dask, Rerun and the rest inside its ``run`` function, so that
building the parser (``crossfield --help``, ``--version``, a mistyped flag) loads none of
them: ``import crossfield.cli`` took 2.7 s with everything at the top, 0.5 s now.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from crossfield import __version__, progress
from crossfield.cli import batch, calibration, catalog, planning, session, simulator
from crossfield.cli.common import Command, log_level, logging_to_stderr, stdout_gone, verbosity_flags
from crossfield.compile_notice import announced
from crossfield.errors import CrossfieldError

__all__ = ["COMMANDS", "Command", "build_parser", "main"]

#: Every ``crossfield`` command by name, from the modules' ``COMMANDS`` tables.
COMMANDS: dict[str, Command] = {
    command.name: command
    for module in (session, batch, calibration, planning, simulator, catalog)
    for command in module.COMMANDS
}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser: one subcommand per entry of :data:`COMMANDS`, each with -v / -q."""
    parser = argparse.ArgumentParser(
        prog="crossfield",
        description="Local stereo vision registered to out-of-view CMM references (metrology pipeline).",
    )
    parser.add_argument("--version", action="version", version=f"crossfield {__version__}")
    verbosity = verbosity_flags()
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS.values():
        p = sub.add_parser(
            command.name, parents=[verbosity], help=command.help, description=command.description or None
        )
        command.add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``crossfield`` command; returns its exit status (2: an error, 130: interrupted)."""
    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        # progress bars and the first-compile notice on a terminal, none under -q (crossfield.progress)
        with (
            logging_to_stderr(log_level(args.verbose, args.quiet)),
            progress.shown(not args.quiet),
            announced(),
        ):
            status = COMMANDS[args.command].run(args)
            sys.stdout.flush()  # here, so that a closed pipe is caught below
            return status
    except BrokenPipeError:
        return stdout_gone()
    except CrossfieldError as exc:
        print(f"crossfield: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # a second Ctrl-C of a session says what it left (InterruptedAgain)
        print(f"crossfield: interrupted{': ' + str(exc) if str(exc) else ''}", file=sys.stderr)
        return 130
