"""What every ``crossfield`` command shares: the command record, the common flags,
the plugin manager, the seal lines and logging to stderr."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pluggy

from crossfield.chain.registry import STAGES, make_plugin_manager
from crossfield.recording.seal import read_sidecar, sidecar_path

__all__ = [
    "Command", "add_stage_flags", "log_level", "logging_to_stderr", "plugin_manager", "print_seal",
    "print_session_files", "stage_choices", "stdout_gone", "verbosity_flags",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Command:
    """One ``crossfield`` subcommand.

    name: as typed; add_arguments: adds its options to its parser; run: runs it with
    the parsed arguments and returns the exit status; help: the one line of
    ``crossfield --help``; description: the paragraph of ``crossfield NAME --help``."""

    name: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str
    description: str = ""


def verbosity_flags(default: object = 0) -> argparse.ArgumentParser:
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
        help="log only errors, and no progress bars (they are drawn on a terminal only)",
    )
    return flags


def add_stage_flags(parser: argparse.ArgumentParser) -> None:
    """``--<stage> NAME`` for every stage and the repeatable ``--option STAGE.KEY=VALUE``."""
    for stage in STAGES:
        parser.add_argument(f"--{stage}", metavar="NAME", help=f"{stage} implementation (see `crossfield plugins`)")
    parser.add_argument(
        "--option", action="append", default=[], metavar="STAGE.KEY=VALUE",
        help="set a stage option, e.g. centroid.threshold_sigma=8 (repeatable)",
    )


def stage_choices(args: argparse.Namespace) -> tuple[dict[str, str | None], list[str]]:
    """The flags of :func:`add_stage_flags` as read by ``replay`` and ``batch``:
    (stage -> implementation name or None, the ``--option`` texts)."""
    return {stage: getattr(args, stage) for stage in STAGES}, list(args.option)


def plugin_manager() -> pluggy.PluginManager:
    """The built-in plugins and the installed third-party ones (entry-point group ``crossfield``)."""
    pm = make_plugin_manager(entry_points=True)
    logger.debug("plugins registered: %s", ", ".join(sorted(name for name, _ in pm.list_name_plugin())))
    return pm


def print_seal(recording: Path) -> None:
    """Print the recording's chain head and file SHA-256 (its seal), if it was sealed."""
    sealed = read_sidecar(recording) if sidecar_path(recording).exists() else None
    if sealed is not None:
        print(f"integrity chain head {sealed['chain_head']}")
        print(f"file SHA-256         {sealed['file_sha256']}" + ("  (signed)" if sealed.get("signature") else ""))


def print_session_files(folder: Path, heading: str) -> None:
    """``heading`` and one line per file of the session folder with its size (MB)."""
    print(f"{heading} {folder}/")
    for path in sorted(folder.iterdir()):
        print(f"  {path.name:<22} {path.stat().st_size / 1e6:9.2f} MB")


def log_level(verbose: int = 0, quiet: int = 0) -> int:
    """The logging level of ``-q`` (ERROR), no flag (WARNING), ``-v`` (INFO), ``-vv`` (DEBUG)."""
    if quiet:
        return logging.ERROR
    return (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]


class _Formatter(logging.Formatter):
    """``<logger>: <level>: <message>``, e.g. ``crossfield.cli.session: warning: ...``."""

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


def stdout_gone() -> int:
    """The reader of stdout went away (``crossfield plugins | head -1``): end quietly,
    with the status of a command stopped by SIGPIPE. Later writes (the interpreter
    flushes stdout at exit) go to /dev/null (docs.python.org, signal: Note on SIGPIPE)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout without a file descriptor
        pass
    return 128 + signal.SIGPIPE
