"""Two report.json files compared number by number and string by string, with no tolerance.

    .venv/bin/python bench/compare_reports.py BEFORE/report.json AFTER/report.json

The check behind "results unchanged" of a speed change: run the same session (same
scenario, frames and seed) on the code before and after, then compare. Keys that hold what
differs between two runs of the same session by design are left out: time stamps and
durations, paths and file names, the host, versions, hashes and the seal. Prints each
difference (where, before, after) and the count of floats compared; exit status 1 if any.
"""

from __future__ import annotations

import json
import re
import sys
from typing import Any

#: keys whose values differ between two runs of one session by design
SKIPPED = re.compile(
    r"(time|date|_ns$|duration|elapsed|path|dir|file|host|machine|session_id|name$|started|finished|version"
    r"|python|platform|sha256|head|seal|created|utc|seconds|_s$|pid|cpu|^source$)",
    re.IGNORECASE,
)


def differences(before: Any, after: Any, where: str = "") -> tuple[list[tuple[str, Any, Any]], int]:
    """(every difference as (where, before, after), the count of floats compared)."""
    found: list[tuple[str, Any, Any]] = []
    floats = 0

    def walk(a: Any, b: Any, at: str) -> None:
        nonlocal floats
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b)):
                if SKIPPED.search(str(key)):
                    continue
                if key not in a or key not in b:
                    found.append((f"{at}/{key}", key in a, key in b))
                else:
                    walk(a[key], b[key], f"{at}/{key}")
        elif isinstance(a, list) and isinstance(b, list):
            if len(a) != len(b):
                found.append((at, f"{len(a)} items", f"{len(b)} items"))
                return
            for k, (x, y) in enumerate(zip(a, b)):
                walk(x, y, f"{at}[{k}]")
        else:
            floats += isinstance(a, float)
            if a != b and not (a != a and b != b):  # NaN equals NaN here
                found.append((at, a, b))

    walk(before, after, where)
    return found, floats


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    with open(sys.argv[1], encoding="utf-8") as f, open(sys.argv[2], encoding="utf-8") as g:
        found, floats = differences(json.load(f), json.load(g))
    for row in found[:60]:
        print(*row)
    print(f"{len(found)} differences, {floats} floats compared")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
