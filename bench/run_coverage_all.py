"""Run the coverage bench's cases in one process, one JSON-lines file each (on demand, not a test).

    .venv/bin/python bench/run_coverage_all.py --out cov/after --sessions 200 [--only mismatch]

The cases: the three mismatch scenarios and the eight of ``docs/uncertainty.md``'s
coverage table (``bench_coverage.py``'s own arguments). One process imports the
code once: a run started before an edit measures the code as it was.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_coverage  # noqa: E402

CASES = {
    "mc": ["--scenario", "mismatch-camera"],
    "mx": ["--scenario", "mismatch-mixed"],
    "mm": ["--scenario", "mismatch-cmm"],
    "t3": ["--scenario", "table3"],
    "st": ["--scenario", "station"],
    "cl": ["--scenario", "camera-limited"],
    "cl-w": ["--scenario", "camera-limited", "--plugins", "weighted"],
    "t3-2x": ["--scenario", "table3", "--arm-sigma", "0.02", "--stated-sigma", "0.01"],
    "st-2x": ["--scenario", "station", "--arm-sigma", "0.02", "--stated-sigma", "0.01"],
    "cl-2x": ["--scenario", "camera-limited", "--arm-sigma", "0.002", "--stated-sigma", "0.001"],
    "cl-w-2x": ["--scenario", "camera-limited", "--plugins", "weighted", "--arm-sigma", "0.002",
                "--stated-sigma", "0.001"],
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder of the JSON-lines files")
    parser.add_argument("--sessions", type=int, default=200)
    parser.add_argument("--only", default="", help="comma-separated case keys, or 'mismatch' / 'model'")
    args = parser.parse_args()
    keys = list(CASES)
    if args.only == "mismatch":
        keys = keys[:3]
    elif args.only == "model":
        keys = keys[3:]
    elif args.only:
        keys = args.only.split(",")
    for key in keys:
        bench_coverage.main([*CASES[key], "--sessions", str(args.sessions), "--jsonl", f"{args.out}/{key}.jsonl"])
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
