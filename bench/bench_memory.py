"""Peak memory of replay and audit against the live run, by session length.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_memory.py [--pairs 20 60] [--scenario table3]

For each length, records one simulator session with ``crossfield run`` (no
.rrd), then runs ``crossfield replay`` (writing the replayed MCAP) and
``crossfield audit`` on it, each in its own process. Prints each process's
peak resident set size (``ru_maxrss`` of the child, MiB), wall time and
pairs per second, and the ratio of the replay's and audit's peak to the live
run's measured in the same run: a reader that streams the file keeps these
ratios flat as the session grows.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def crossfield() -> list[str]:
    script = Path(sys.executable).with_name("crossfield")
    return [str(script)] if script.exists() else [sys.executable, "-m", "crossfield.cli"]


def measured(args: list[str]) -> tuple[float, float, int]:
    """(peak RSS MiB, wall s, exit code) of one child process."""
    wrapper = (
        "import resource, subprocess, sys;"
        "rc = subprocess.call(sys.argv[1:], stdout=subprocess.DEVNULL);"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss);"
        "sys.exit(rc)"
    )
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", wrapper, *args], capture_output=True, text=True)
    wall = time.perf_counter() - t
    return int(proc.stdout.strip().splitlines()[-1]) / 1024.0, wall, proc.returncode


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, nargs="+", default=[20, 60])
    parser.add_argument("--scenario", default="table3")
    args = parser.parse_args()
    assert resource  # the children's peak comes from getrusage in the wrapper
    work = Path(tempfile.mkdtemp(prefix="crossfield-bench-memory-"))
    try:
        print(f"{'pairs':>6} {'step':<8} {'peak MiB':>9} {'wall s':>7} {'pairs/s':>8} {'peak/live':>9}  rc")
        for pairs in args.pairs:
            name = f"s{pairs}"
            live = measured(
                crossfield()
                + ["run", "--scenario", args.scenario, "--frames", str(pairs), "-o", str(work), "--name", name]
                + ["--no-rerun", "-q"]
            )
            mcap = work / name / "session.mcap"
            replay = measured(
                crossfield() + ["replay", str(mcap), "-o", str(work / f"{name}-replay.mcap"), "-q", "--no-rerun"]
            )
            audit = measured(crossfield() + ["audit", str(mcap)])
            size = mcap.stat().st_size / 2**20
            for step, (peak, wall, rc) in (("live", live), ("replay", replay), ("audit", audit)):
                print(
                    f"{pairs:>6} {step:<8} {peak:>9.0f} {wall:>7.1f} {pairs / wall:>8.2f} "
                    f"{peak / live[0]:>9.2f}  {rc}"
                )
            print(f"{'':>6} (session.mcap {size:.0f} MiB)")
            for p in work.iterdir():
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else os.unlink(p)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
