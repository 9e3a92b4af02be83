"""``crossfield catalog``: the session catalog (``docs/catalog.md``); the subcommands are
:mod:`crossfield.catalog.commands`."""

from __future__ import annotations

from crossfield.catalog import commands
from crossfield.cli.common import Command

__all__ = ["COMMANDS"]

COMMANDS: tuple[Command, ...] = (
    Command("catalog", commands.add_arguments, commands.run, help=commands.HELP, description=commands.DESCRIPTION),
)
