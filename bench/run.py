"""Run the benchmarks the issues set targets for, one after the other.

    make bench            # or: .venv/bin/python bench/run.py [--quick]

Each script times its subject against a baseline measured in the same run
and prints the ratio; the machines are shared and noisy, so read the ratios.
Never part of the tests.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: script, arguments for a full run, arguments for --quick
BENCHMARKS = (
    ("bench_centroid.py", ["--source", "table3"], ["--source", "table3", "--runs", "100"]),
    ("bench_pipeline.py", ["--frames", "300", "--repeat", "3"], ["--frames", "100", "--repeat", "1"]),
    ("bench_serial.py", [], ["--points", "1000", "--runs", "1"]),
    ("bench_acquire.py", [], ["--pairs", "10", "--rounds", "2"]),
    ("bench_replay.py", ["--frames", "60", "--repeat", "3"], ["--frames", "20", "--repeat", "1"]),
    ("bench_calibrate.py", [], ["--pairs", "20", "--repeat", "1"]),
)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = parser.parse_args()
    status = 0
    for script, full, quick in BENCHMARKS:
        argv = [sys.executable, str(HERE / script), *(quick if args.quick else full)]
        print(f"\n=== {' '.join([script, *argv[2:]])}", flush=True)
        status |= subprocess.call(argv)
    return status


if __name__ == "__main__":
    sys.exit(main())
