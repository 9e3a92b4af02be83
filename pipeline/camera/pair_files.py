"""File names of stereo image pairs in a folder (``upper_0000.png`` / ``lower_0000.png``).

Shared by the ``folder`` acquisition and ``crossfield calibrate --images``.
"""

from __future__ import annotations

import os
import re

from crossfield.types import CAMERAS

__all__ = ["pattern_regex"]


def pattern_regex(pattern: str) -> re.Pattern[str]:
    """Compile a file-name pattern with ``{camera}``, ``{seq}`` and ``*`` into a regex.

    Both placeholders must occur exactly once; every other character matches itself.
    """
    for placeholder in ("{camera}", "{seq}"):
        if pattern.count(placeholder) != 1:
            raise ValueError(f"option 'pattern' must contain {placeholder} exactly once, got {pattern!r}")
    if "/" in pattern or os.sep in pattern:
        raise ValueError(f"option 'pattern' names files inside the folder, not paths: {pattern!r}")
    parts = re.split(r"(\{camera\}|\{seq\}|\*)", pattern)
    regex = []
    for part in parts:
        if part == "{camera}":
            regex.append("(?P<camera>" + "|".join(CAMERAS) + ")")
        elif part == "{seq}":
            regex.append(r"(?P<seq>\d+)")
        elif part == "*":
            regex.append(".*")
        else:
            regex.append(re.escape(part))
    return re.compile("".join(regex) + r"\Z")
