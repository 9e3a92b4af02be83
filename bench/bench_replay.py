"""Replay throughput against a plain read of the same MCAP.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_replay.py [--frames 60] [--repeat 3] [--scenario station]

Records one simulator session (lossless MCAP, no .rrd), then times, on the
warm page cache, medians of ``--repeat`` runs:

* plain read: the file's bytes read in 4 MiB blocks (the I/O floor);
* MCAP read: every message iterated with the reader (no decoding);
* frames decoded: :class:`crossfield.replay.RecordingSource` yielding the stereo
  pairs (protobuf RawImage -> arrays), nothing computed;
* replay: ``replay_session`` with the recorded plugins, no recording;
* replay + record: the same, writing the replayed session's MCAP
  (what ``crossfield replay`` does, without the .rrd).

Every figure is in stereo pairs per second and as a ratio to the plain read
and to the MCAP read timed in the same run.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.config import parse_config  # noqa: E402
from crossfield.recording.reader import open_recording  # noqa: E402
from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.replay import RecordingSource, load_recorded_session, replay_session  # noqa: E402
from crossfield.chain.runner import run_session  # noqa: E402


def timed(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--scenario", default="station")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="crossfield-bench-replay-"))
    try:
        config = parse_config(
            {
                "session": {"output_dir": str(work), "name": "recorded", "rerun": False},
                "acquire": {
                    "plugin": "simulator",
                    "scenario": args.scenario,
                    "frames": args.frames,
                    "seed": 1,
                },
                "reference": {"plugin": "romer-serial", "port": "simulator"},
            },
            "<bench>",
        )
        t = time.perf_counter()
        run_session(config, make_plugin_manager())
        record_s = time.perf_counter() - t
        path = work / "recorded" / "session.mcap"
        size = path.stat().st_size
        n = args.frames
        print(f"recorded {n} pairs ({args.scenario}) in {record_s:.1f} s: {size / 1e6:.0f} MB")

        def plain_read():
            with open(path, "rb") as f:
                while f.read(1 << 22):
                    pass

        def mcap_read():
            with open_recording(path) as rec:
                for _ in rec.messages(decode=False, file_order=True):
                    pass

        def frames_decoded():
            for _ in RecordingSource(load_recorded_session(path)).frames():
                pass

        counter = iter(range(10**6))

        def replay(record: bool):
            out = work / f"replay-{next(counter)}"
            replay_session(path, make_plugin_manager(), output_dir=out, record=record, rerun=False)
            shutil.rmtree(out)

        plain_read()  # warm the page cache
        results = {
            "plain read": timed(plain_read, args.repeat),
            "MCAP read": timed(mcap_read, args.repeat),
            "frames decoded": timed(frames_decoded, args.repeat),
            "replay": timed(lambda: replay(False), args.repeat),
            "replay + record": timed(lambda: replay(True), args.repeat),
        }
        plain, mcap = n / results["plain read"], n / results["MCAP read"]
        print(f"\n{'case':<18} {'pairs/s':>10} {'MB/s':>8} {'/ plain':>9} {'/ MCAP':>8}")
        for name, seconds in results.items():
            rate = n / seconds
            print(
                f"{name:<18} {rate:>10.1f} {size / seconds / 1e6:>8.0f} {rate / plain:>9.3f} {rate / mcap:>8.3f}"
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
