"""The inputs of a batch: session folders, MCAP files and globs, one entry per session.

A path given on the command line is, in this order: a glob (it has ``*``, ``?`` or
``[``; ``**`` recurses), a session folder (it holds ``session.mcap``), or a file.
Every input is checked by the client before anything is submitted: it exists, it is a
regular file, it can be opened and read and it starts with the MCAP magic. An input
that fails is an ERROR entry of the report with its reason and is not submitted; the
rest go on. Workers then open the same absolute path: the archive must be on storage
the client and the workers share, at the same path (docs/batch.md).
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

__all__ = ["MCAP_MAGIC", "SessionInput", "expand_inputs", "readable"]

#: The 8 bytes an MCAP file starts with (MCAP specification, "Magic").
MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class SessionInput:
    """One session of the batch.

    given: the path as the user named it (or the glob's match); path: the
    absolute path of the MCAP file workers open; error: why it cannot be
    submitted (None: readable).
    """

    given: str
    path: str
    error: str | None = None


def readable(path: Path) -> str | None:
    """None if ``path`` is a regular file this process can open and read that starts with
    the MCAP magic; otherwise the reason, naming the file."""
    if not path.exists():
        return f"{path}: no such file"
    if not path.is_file():
        return f"{path}: not a regular file (a session folder holds session.mcap)"
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        return f"{path}: cannot be read ({exc.strerror or exc})"
    if head != MCAP_MAGIC:
        return f"{path}: not an MCAP file (it does not start with the MCAP magic)"
    return None


def _one(given: str, path: Path) -> SessionInput:
    if path.is_dir():
        path = path / "session.mcap"
    path = Path(os.path.abspath(path))
    return SessionInput(given, str(path), readable(path))


def expand_inputs(paths: Iterable[str]) -> list[SessionInput]:
    """One :class:`SessionInput` per session named by ``paths`` (in the order given,
    glob matches sorted; a session named twice is kept once). A glob that matches
    nothing is an ERROR entry naming the pattern."""
    found: list[SessionInput] = []
    seen: set[str] = set()

    def add(entry: SessionInput) -> None:
        if entry.path not in seen:
            seen.add(entry.path)
            found.append(entry)

    for text in paths:
        if glob.has_magic(text):
            matches = sorted(glob.glob(text, recursive=True))
            if not matches:
                add(SessionInput(text, text, f"{text}: the pattern matches no file or folder"))
            for match in matches:
                add(_one(match, Path(match)))
        else:
            add(_one(text, Path(text)))
    return found
