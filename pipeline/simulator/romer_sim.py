"""``crossfield romer-sim``: run the simulated CMM arm for a real reader.

Serves probes on a pseudo-terminal (CFP or PC-DMIS lines) or as an I++ DME
server on TCP, prints the port to open on the first line of stdout (a
stable pty path, or ``socket://host:port``) and serves until every probe is
sent and the reader has disconnected (``--exit-when-done``) or until
Ctrl-C. Example::

    crossfield romer-sim --plan plans/table3.toml --line-delay 0.5
    # -> /tmp/crossfield-arm-1a2b3c/romer-arm
    crossfield run --option 'reference.port="/tmp/crossfield-arm-1a2b3c/romer-arm"' ...

Probes come from ``--scenario`` (the station simulator's arm probes), from
``--csv`` (``id,x,y,z`` in mm, plus Gaussian noise ``--sigma``), or from
``--plan`` / ``--points`` (random positions in a 1 m cube).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from crossfield.errors import CrossfieldError
from crossfield.plan import load_plan
from crossfield.simulator.arm import ArmProbe, SimulatedArm, bad_checksum, probes_from_points


def _index_value(text: str, kind=float) -> tuple[int, float]:
    index, _, value = text.partition(":")
    try:
        return int(index), kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected INDEX:VALUE, got {text!r}") from None


#: ``crossfield romer-sim --help``'s description.
DESCRIPTION = "Simulated ROMER arm: CFP / PC-DMIS lines on a pty, or an I++ DME server on TCP."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulator's options on ``parser`` (the ``romer-sim`` subcommand's)."""
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--scenario", help="station scenario whose arm probes are sent (e.g. table3)")
    source.add_argument("--csv", type=Path, help="file of id,x,y,z (mm) to probe")
    source.add_argument("--plan", type=Path, help="measurement plan: its probing order at random positions")
    source.add_argument("--points", type=int, default=10, help="N random points P1..PN (default 10)")
    parser.add_argument("--format", choices=("cfp", "pcdmis", "pcdmis-plain", "ippdme"), default="cfp")
    parser.add_argument("--units", choices=("mm", "inch"), default="mm", help="pcdmis formats only")
    parser.add_argument("--seed", type=int, default=0, help="random seed (noise, positions)")
    parser.add_argument("--sigma", type=float, default=0.01, help="arm noise per coordinate, mm")
    parser.add_argument("--line-delay", type=float, default=0.0, help="seconds between probes")
    parser.add_argument("--baud", type=int, default=None, help="pace the pty like an 8N1 line")
    parser.add_argument(
        "--tcp", default="127.0.0.1:1294", help="ippdme: HOST:PORT to listen on (port 0: any free port)"
    )
    parser.add_argument("--first-seq", type=int, default=1, help="cfp: seq of the first probe")
    parser.add_argument("--bad-checksum", type=int, action="append", default=[], metavar="INDEX",
                        help="cfp: corrupt the checksum of probe INDEX (0-based); repeatable")
    parser.add_argument("--burst", type=lambda t: _index_value(t, int), action="append", default=[],
                        metavar="INDEX:N", help="hold the button on probe INDEX for N repeats")
    parser.add_argument("--unplug", type=_index_value, action="append", default=[], metavar="INDEX:S",
                        help="pty: pull the cable for S seconds after probe INDEX")
    parser.add_argument("--drop", type=int, action="append", default=[], metavar="INDEX",
                        help="ippdme: close the connection after probe INDEX")
    parser.add_argument("--exit-when-done", action="store_true",
                        help="exit once every probe is sent and the reader has disconnected")


def _probes(args: argparse.Namespace, rng: np.random.Generator) -> list[ArmProbe]:
    if args.scenario:
        from crossfield.simulator.scenarios import build_scene  # the station simulator

        try:
            scene = build_scene(args.scenario, arm_sigma_mm=args.sigma)
        except (KeyError, ValueError) as exc:
            raise CrossfieldError(f"--scenario: {exc}") from None
        return list(scene.arm_probes(rng))
    if args.csv:
        labels, xyz = [], []
        try:
            lines = args.csv.read_text(encoding="utf-8-sig").splitlines()
        except OSError as exc:
            raise CrossfieldError(f"{args.csv}: cannot read: {exc.strerror}") from None
        for number, line in enumerate(lines, start=1):
            fields = [f.strip() for f in line.split("#", 1)[0].split(",")]
            if fields == [""] or [f.lower() for f in fields[:4]] == ["id", "x", "y", "z"]:
                continue
            try:
                labels.append(fields[0])
                xyz.append([float(v) for v in fields[1:4]])
                if len(fields) < 4:
                    raise ValueError
            except ValueError:
                message = f"{args.csv}, line {number}: expected id,x,y,z in mm: {line!r}"
                raise CrossfieldError(message) from None
        return probes_from_points(labels, np.array(xyz).reshape(-1, 3), rng, args.sigma)
    if args.plan:
        labels = load_plan(args.plan).probing_order()
    else:
        labels = [f"P{k}" for k in range(1, args.points + 1)]
    return probes_from_points(labels, rng.uniform(-500.0, 500.0, (len(labels), 3)), rng, args.sigma)


def main_romer_sim(argv: Sequence[str] | None = None) -> int:
    """Run the simulator with command-line arguments ``argv``; returns the process exit code."""
    parser = argparse.ArgumentParser(prog="crossfield romer-sim", description=DESCRIPTION)
    add_arguments(parser)
    return serve(parser.parse_args(argv))


def serve(args: argparse.Namespace) -> int:
    """Run the simulator with the options of :func:`add_arguments`; returns the exit code."""
    rng = np.random.default_rng(args.seed)
    try:
        probes = _probes(args, rng)
    except CrossfieldError as exc:
        print(f"crossfield romer-sim: {exc}", file=sys.stderr)
        return 2
    bursts = dict(args.burst)
    if args.format == "ippdme":
        from crossfield.simulator.ippdme_server import SimulatedIppDmeServer

        host, _, port = args.tcp.rpartition(":")
        device = SimulatedIppDmeServer(
            probes, host=host or "127.0.0.1", port=int(port), line_delay_s=args.line_delay,
            drop_after=args.drop, bursts=bursts,
        )
        serving = device.serve()
    else:
        device = SimulatedArm(
            probes, format=args.format, units=args.units, line_delay_s=args.line_delay, baudrate=args.baud,
            first_seq=args.first_seq, faults={i: bad_checksum for i in args.bad_checksum}, bursts=bursts,
            unplug_after=dict(args.unplug),
        )
        serving = device.serve_pty()
    try:
        with serving as port:
            print(port, flush=True)
            print(
                f"crossfield romer-sim: {len(probes)} probes ({', '.join(p.label for p in probes[:6])}"
                f"{' ...' if len(probes) > 6 else ''}), format {args.format}, waiting for a reader on {port}",
                file=sys.stderr,
                flush=True,
            )
            while not (device.wait_done(0.1) and args.exit_when_done and not device.client_connected()):
                pass
            print("crossfield romer-sim: all probes sent, reader gone", file=sys.stderr)
    except KeyboardInterrupt:
        print("crossfield romer-sim: stopped", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main_romer_sim())
