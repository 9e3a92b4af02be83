"""Throughput of romer-serial over a real pseudo-terminal, and of the decoder alone.

Run: ``.venv/bin/python bench/bench_serial.py [--points N] [--baud B ...] [--runs R]``

For each line rate (``0`` = unpaced: as fast as the pty accepts), a
:class:`SimulatedArm` sends ``--points`` CFP sentences back to back on a
real pty and :class:`RomerSerialReference` imports them into a plan with one
reference line of that many probes. Reported: points per second from the
reader's first byte to the import's end, whether every point arrived with
no problem (a pty has flow control, so the reader falling behind stalls the
arm instead of losing data), and the decoder's own rate on the recorded
bytes (``decode(raw)``, no I/O). Median of ``--runs`` runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from crossfield.plan import parse_plan  # noqa: E402
from crossfield.simulator.arm import SimulatedArm, probes_from_points  # noqa: E402
from crossfield.plugins.reference_romer_serial import RomerSerialReference  # noqa: E402


def make_plan(n: int):
    text = "\n".join(f'[[control]]\nid = "C{k}"' for k in (1, 2, 3))
    text += f'\n[[reference_line]]\nid = "L"\nprobes = {n - 3}\nfit = "line"\n'
    return parse_plan(text, "bench.toml")


def one_run(plan, probes, baud: int | None) -> tuple[float, float, bool, int]:
    arm = SimulatedArm(probes, baudrate=baud)
    chunks: list[bytes] = []
    first = []

    def sink(data: bytes) -> None:
        if not first:
            first.append(time.perf_counter())
        chunks.append(data)

    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, timeout_s=10.0)
        result = reader.acquire(plan, sink)
        end = time.perf_counter()
    raw = b"".join(chunks)
    ok = len(result.points) == len(probes) and not result.problems
    t0 = time.perf_counter()
    reader.decode(raw, plan)
    decode_s = time.perf_counter() - t0
    return len(probes) / (end - first[0]), len(probes) / decode_s, ok, len(raw)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=5000)
    parser.add_argument("--baud", type=int, nargs="*", default=[0, 115200, 9600])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(1)
    for baud in args.baud:
        # paced runs: about 0.25 s of line time each
        n = args.points if baud == 0 else max(10, min(args.points, baud // 400))
        plan = make_plan(n)
        probes = probes_from_points(plan.probing_order(), rng.uniform(-500, 500, (n, 3)), rng)
        runs = [one_run(plan, probes, baud or None) for _ in range(args.runs)]
        rate = statistics.median(r[0] for r in runs)
        decode_rate = statistics.median(r[1] for r in runs)
        ok = all(r[2] for r in runs)
        bytes_per_point = runs[0][3] / n
        line = "unpaced pty" if baud == 0 else f"{baud} baud 8N1"
        limit = "" if baud == 0 else f" (line limit {baud / 10 / bytes_per_point:,.0f})"
        print(
            f"{line:>16}: {n} points, {rate:10,.0f} points/s{limit}, "
            f"all points, no problems: {ok}; decoder alone {decode_rate:,.0f} points/s; "
            f"{bytes_per_point:.1f} bytes/point"
        )


if __name__ == "__main__":
    main()
