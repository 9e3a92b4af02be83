"""Every ``crossfield`` command is documented in docs/user-guide.md, with every one of its
options (the datasette way: the table of commands is read from the code, not retyped)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from crossfield.cli import COMMANDS, build_parser

GUIDE = Path(__file__).resolve().parents[2] / "docs" / "user-guide.md"


def sections() -> dict[str, str]:
    """command name -> the text of its section (``## `crossfield NAME` `` up to the next ``## ``)."""
    text = GUIDE.read_text(encoding="utf-8")
    out: dict[str, str] = {}
    for block in re.split(r"^## ", text, flags=re.MULTILINE)[1:]:
        heading, _, body = block.partition("\n")
        for name in re.findall(r"`crossfield ([a-z-]+)`", heading):
            out[name] = body
    return out


def options(parser: argparse.ArgumentParser) -> set[str]:
    """The long options of ``parser`` and its subcommands' (``batch audit``), help and -v/-q aside."""
    found: set[str] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found |= options(sub)
        for flag in action.option_strings:
            if flag.startswith("--") and flag not in ("--help", "--verbose", "--quiet"):
                found.add(flag)
    return found


def command_parsers() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_every_command_has_a_section():
    assert sorted(COMMANDS) and set(COMMANDS) <= set(sections()), sorted(set(COMMANDS) - set(sections()))


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_option_of_a_command_is_in_its_section(name):
    text = sections()[name]
    missing = sorted(flag for flag in options(command_parsers()[name]) if flag not in text)
    assert missing == [], f"docs/user-guide.md, `crossfield {name}`: {missing} not documented"


def test_the_engine_flags_mean_one_thing_everywhere():
    """--scheduler / --workers / --memory-limit: the same help text in every command that has them."""
    helps: dict[str, set[str]] = {}
    for name, parser in command_parsers().items():
        stack = [parser]
        while stack:
            p = stack.pop()
            for action in p._actions:
                if isinstance(action, argparse._SubParsersAction):
                    stack.extend(action.choices.values())
                for flag in action.option_strings:
                    if flag in ("--scheduler", "--workers", "--memory-limit"):
                        helps.setdefault(flag, set()).add(action.help)
    assert set(helps) == {"--scheduler", "--workers", "--memory-limit"}
    assert all(len(texts) == 1 for texts in helps.values()), helps
