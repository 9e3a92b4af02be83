"""Run the benchmarks the issues set targets for, then guard their figures against the baseline.

    make bench            # or: .venv/bin/python bench/run.py [--quick] [--only NAME ...]
    .venv/bin/python bench/run.py --update-baseline     # accept this run's figures

Each script times its subject against a baseline measured in the same run
and prints the ratio; the machines are shared and noisy, so read the ratios.
Each also hands its guarded figures (same-run ratios, :mod:`figures`) to
this script, which writes them as JSON (``--json``, default
``bench/last-run.json``), compares them with the committed
``bench/baseline.json`` and prints every figure more than ``--tolerance``
(20 %) worse than there; it exits 1 if there is one. ``--update-baseline``
writes this run's figures as the new baseline: say in CHANGELOG.md why the
change is accepted. Never part of the tests.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import figures  # noqa: E402

BASELINE = HERE / "baseline.json"

#: bench_recording writes into memory where the machine has a tmpfs: the kernel's page-cache
#: work for a 965 MB file on disk (reclaim, write-back) scattered the plain write's CPU
#: 2.4-27 ms per pair between runs, and the ratios with it (docs/recording.md)
RAM_DIR = ["--dir", "/dev/shm"] if Path("/dev/shm").is_dir() else []

#: script, arguments for a full run, arguments for --quick
BENCHMARKS = (
    ("bench_centroid.py", ["--source", "station"], ["--source", "station", "--runs", "100"]),
    ("bench_pipeline.py", ["--frames", "300", "--repeat", "3", "--scenario", "station"],
     ["--frames", "100", "--repeat", "1", "--scenario", "station"]),
    ("bench_recording.py", ["--repeats", "3", *RAM_DIR], ["--pairs", "40", "--repeats", "2", *RAM_DIR]),
    ("bench_replay.py", ["--frames", "60", "--repeat", "3"], ["--frames", "20", "--repeat", "1"]),
    ("bench_triangulate.py", [], ["--runs", "500"]),
    ("bench_batch.py", [], ["--sessions", "4", "--noops", "50"]),
    ("bench_serial.py", [], ["--points", "1000", "--runs", "1"]),
    ("bench_acquire.py", [], ["--pairs", "10", "--rounds", "2"]),
    ("bench_calibrate.py", [], ["--pairs", "20", "--repeat", "1"]),
)


def run_benchmarks(names: list[str], quick: bool, sink: Path) -> int:
    """Run the chosen scripts one after the other, their figures appended to ``sink``."""
    env = {**os.environ, figures.ENV: str(sink)}
    status = 0
    for script, full, short in BENCHMARKS:
        if names and script not in names and script.removesuffix(".py") not in names:
            continue
        argv = [sys.executable, str(HERE / script), *(short if quick else full)]
        print(f"\n=== {' '.join([script, *argv[2:]])}", flush=True)
        status |= subprocess.call(argv, env=env)
    return status


def guard(baseline_path: Path, current: dict[str, dict], tolerance: float) -> int:
    """Print every figure against the baseline; 1 if one is more than ``tolerance`` worse."""
    if not baseline_path.exists():
        print(f"\nno baseline at {baseline_path}: nothing compared (--update-baseline writes one)")
        return 0
    baseline = json.loads(baseline_path.read_text(encoding="utf-8"))["figures"]
    changes, missing = figures.compare(baseline, current)
    print(f"\n=== guard: {len(changes)} figure(s) against {baseline_path.name} (same-run ratios; "
          f"worse by more than {tolerance:.0%} is flagged)")
    flagged = [c for c in changes if c.worse > tolerance]
    for c in changes:
        mark = "WORSE" if c in flagged else "ok"
        print(f"  {mark:5s} {c.figure:44s} {c.value:9.4g} (baseline {c.baseline:9.4g}, {c.better} is better) "
              f"{-c.worse:+7.1%}")
    for name in missing:
        print(f"  ----- {name:44s} not measured in this run")
    if flagged:
        print(f"\n{len(flagged)} figure(s) more than {tolerance:.0%} worse than the baseline:")
        for c in flagged:
            print(f"  {c.figure}: {c.value:.4g} against {c.baseline:.4g} ({c.worse:.0%} worse)")
        return 1
    print(f"all {len(changes)} figure(s) within {tolerance:.0%} of the baseline")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    parser.add_argument("--only", nargs="+", default=[], metavar="NAME", help="run only these scripts")
    parser.add_argument("--json", type=Path, default=HERE / "last-run.json", help="where this run's figures go")
    parser.add_argument("--baseline", type=Path, default=BASELINE)
    parser.add_argument("--tolerance", type=float, default=0.2, help="flag figures worse by more than this")
    parser.add_argument("--update-baseline", action="store_true", help="write this run's figures as the baseline")
    parser.add_argument("--compare-only", type=Path, metavar="JSON",
                        help="run nothing: guard the figures of an earlier run's --json file")
    args = parser.parse_args(argv)

    if args.compare_only:
        current = json.loads(args.compare_only.read_text(encoding="utf-8"))["figures"]
        return guard(args.baseline, current, args.tolerance)
    with tempfile.TemporaryDirectory() as tmp:
        sink = Path(tmp) / "figures.jsonl"
        sink.touch()
        status = run_benchmarks(args.only, args.quick, sink)
        current = figures.read_lines(sink)
    doc = {
        "measured": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "load_average": os.getloadavg()[0],
        "quick": args.quick,
        "figures": current,
    }
    args.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    print(f"\n{len(current)} figure(s) written to {args.json}")
    if args.update_baseline:
        if args.baseline.exists():  # a partial run (--only) keeps the other benches' figures
            old = json.loads(args.baseline.read_text(encoding="utf-8"))["figures"]
            doc["figures"] = {**old, **current}
        args.baseline.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        print(f"baseline {args.baseline} updated: state the change and its reason in CHANGELOG.md")
        return status
    return status | guard(args.baseline, current, args.tolerance)


if __name__ == "__main__":
    sys.exit(main())
