"""Throughput of romer-serial over a real pseudo-terminal and TCP, and the cost of noise floods.

Run: ``.venv/bin/python bench/bench_serial.py [--points N] [--baud B ...] [--runs R]
[--socket-mb M] [--flood-mb F] [--skip-flood]``

For each line rate (``0`` = unpaced: as fast as the pty accepts), a
:class:`SimulatedArm` sends ``--points`` CFP sentences back to back on a
real pty and :class:`RomerSerialReference` imports them into a plan with one
reference line of that many probes. Reported: points per second from the
reader's first byte to the import's end, whether every point arrived with
no problem (a pty has flow control, so the reader falling behind stalls the
arm instead of losing data), and the decoder's own rate on the recorded
bytes (``decode(raw)``, no I/O). Median of ``--runs`` runs.

Socket reads: a local TCP server sends ``--socket-mb`` MB as fast as it
can; the client reads them through pyserial's ``socket://`` with
:class:`SerialTransport` (block reads) and with :func:`one_byte_reads`, the
transport's former read (one byte per call on a socket, whose ``in_waiting``
says only "some"), in the same run: MB/s of each and their ratio.

Noise floods: a whole recorded session (simulator acquisition, one stereo
pair, romer-serial over the simulated arm's pty) where the arm sends
``--flood-mb`` MB of stray ``$`` bytes, or of random bytes, before its third
point, against the same session without a flood: the session's time, the
bytes it wrote (session folder) beyond the flood's own bytes (which are
recorded on ``/cmm/raw`` as read; these sessions record uncompressed, so that
the flood's bytes are in the file as they are), and its count of reference problems.
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

import socket  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402

import crossfield.plugins.acquire_simulator as acquire_simulator  # noqa: E402
from crossfield.cmm.protocol import SerialTransport  # noqa: E402
from crossfield.config import parse_config  # noqa: E402
from crossfield.plan import parse_plan  # noqa: E402
from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.chain.runner import run_session  # noqa: E402
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


# ---- socket:// read throughput ------------------------------------------------------------


def one_byte_reads(transport: SerialTransport, max_bytes: int = 4096) -> bytes:
    """The baseline: the transport's read before block reads (kept here to measure
    against): one ``read(1)``, then ``read(in_waiting)`` while ``in_waiting`` says
    bytes wait, which on ``socket://`` is 1 per call."""
    port = transport._serial
    data = port.read(1)
    while data and len(data) < max_bytes:
        waiting = port.in_waiting
        if not waiting:
            break
        data += port.read(min(waiting, max_bytes - len(data)))
    return bytes(data)


def socket_throughput(megabytes: float, read) -> float:
    """MB/s of ``read(transport)`` over a real loopback TCP connection."""
    size = int(megabytes * 1e6)
    payload = bytes(range(256)) * (size // 256)
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    ready = threading.Event()

    def serve() -> None:
        connection, _ = server.accept()
        with connection:
            ready.wait(5.0)
            connection.sendall(payload)
            connection.recv(1)  # until the client closes

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    transport = SerialTransport(f"socket://127.0.0.1:{port}", poll_s=0.05)
    time.sleep(0.2)  # pyserial's socket:// flushes its input right after connecting
    ready.set()
    got = 0
    t0 = None
    try:
        while got < len(payload):
            data = read(transport)
            if data and t0 is None:
                t0 = time.perf_counter()
            got += len(data)
        elapsed = time.perf_counter() - t0
    finally:
        transport.close()
        thread.join(2.0)
        server.close()
    return got / 1e6 / elapsed


# ---- noise floods in a recorded session --------------------------------------------------


def flood_session(out: Path, name: str, flood: bytes) -> tuple[float, int, int]:
    """(seconds, bytes written in the session folder, reference problems) of a one-pair
    simulator session whose arm sends ``flood`` before its third point."""

    class FloodArm(SimulatedArm):
        def __init__(self, probes, **kwargs):
            faults = {2: lambda sentence: flood + sentence} if flood else {}
            super().__init__(probes, faults=faults, **kwargs)

    # the simulator acquisition serves the arm it imported (through crossfield.plugin_api): patch that name
    real = acquire_simulator.SimulatedArm
    acquire_simulator.SimulatedArm = FloodArm
    try:
        config = parse_config(
            {
                "session": {"output_dir": str(out), "name": name, "rerun": False, "compression": "none"},
                "acquire": {"plugin": "simulator", "scenario": "table3", "frames": 1, "seed": 4},
                "reference": {"plugin": "romer-serial", "port": "simulator", "timeout_s": 60.0},
            },
            "<bench>",
        )
        t0 = time.perf_counter()
        summary = run_session(config, make_plugin_manager())
        elapsed = time.perf_counter() - t0
    finally:
        acquire_simulator.SimulatedArm = real
    folder = summary.info.out_dir
    written = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    return elapsed, written, len(summary.reference.problems)


def floods(megabytes: float) -> None:
    size = int(megabytes * 1e6)
    rng = np.random.default_rng(7)
    cases = {
        "no flood": b"",
        f"{megabytes:g} MB of '$'": b"$" * size,
        f"{megabytes:g} MB random bytes": bytes(rng.integers(0, 256, size, dtype=np.uint8)) + b"\n",
    }
    with tempfile.TemporaryDirectory(prefix="bench-serial-") as tmp:
        flood_session(Path(tmp), "warm-up", b"")  # imports, first renders: not the flood's cost
        base = None
        for k, (label, flood) in enumerate(cases.items()):
            elapsed, written, problems = flood_session(Path(tmp), f"s{k}", flood)
            if base is None:
                base = (elapsed, written)
                print(f"{label:>22}: session {elapsed:6.2f} s, {written / 1e6:8.2f} MB written, {problems} problem(s)")
                continue
            extra = written - base[1] - len(flood)
            print(
                f"{label:>22}: session {elapsed:6.2f} s (+{elapsed - base[0]:.2f} s), {written / 1e6:8.2f} MB "
                f"written = the flood's {len(flood) / 1e6:.2f} MB on /cmm/raw + {extra / 1e3:+.1f} kB beyond the "
                f"session without flood ({extra / len(flood):.4f} extra bytes per flood byte), {problems} problem(s)"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=5000)
    parser.add_argument("--baud", type=int, nargs="*", default=[0, 115200, 9600])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--socket-mb", type=float, default=20.0, help="MB sent for the block-read rate")
    parser.add_argument("--baseline-mb", type=float, default=2.0, help="MB sent for the one-byte-read rate")
    parser.add_argument("--flood-mb", type=float, default=10.0)
    parser.add_argument("--skip-flood", action="store_true")
    args = parser.parse_args()
    blocks = statistics.median(socket_throughput(args.socket_mb, SerialTransport.read) for _ in range(args.runs))
    bytes_ = statistics.median(socket_throughput(args.baseline_mb, one_byte_reads) for _ in range(args.runs))
    print(
        f"socket:// loopback reads: block reads {blocks:8.1f} MB/s ({args.socket_mb:g} MB), one byte per read "
        f"{bytes_:8.3f} MB/s ({args.baseline_mb:g} MB): {blocks / bytes_:,.0f} x"
    )
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
    if not args.skip_flood:
        floods(args.flood_mb)


if __name__ == "__main__":
    main()
