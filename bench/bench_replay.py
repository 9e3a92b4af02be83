"""Replay throughput against a plain read of the same MCAP.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_replay.py [--frames 60] [--repeat 3] [--scenario station]

Records one simulator session (lossless MCAP, no .rrd), then times, on the
warm page cache, medians of ``--repeat`` runs:

* plain read: the file's bytes read in 4 MiB blocks (the I/O floor);
* MCAP read: every message iterated with the reader (no decoding);
* frames decoded: :class:`crossfield.replay.RecordingSource` yielding the stereo
  pairs (protobuf RawImage -> arrays), nothing computed;
* pipeline, frames in memory: ``replay_session`` with the pairs decoded
  beforehand (the pipeline's own rate on these frames, no reading or decoding);
* replay: ``replay_session`` with the recorded plugins, no recording (the
  frames read and decoded ahead on a second thread, ``crossfield.recording.prefetch``);
* replay + record: the same, writing the replayed session's MCAP
  (what ``crossfield replay`` does, without the .rrd).

Every figure is in stereo pairs per second and as a ratio to the plain read
and to the MCAP read timed in the same run; then replay against the
in-memory pipeline (issue 25's target: >= 0.8) and against the in-memory
pipeline plus the decode done one after the other (1 / (1/pipeline + 1/decode)).
"""

from __future__ import annotations

import argparse
import contextlib
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figures import record  # noqa: E402


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
    parser.add_argument("--compression", default=None, choices=("zstd", "lz4", "none"),
                        help="[session] compression of the recorded session (default: the default, zstd)")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="crossfield-bench-replay-"))
    try:
        config = parse_config(
            {
                "session": {
                    "output_dir": str(work), "name": "recorded", "rerun": False,
                    **({"compression": args.compression} if args.compression else {}),
                },
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
        decoded = list(RecordingSource(load_recorded_session(path)).frames())

        @contextlib.contextmanager
        def frames_in_memory():
            import crossfield.replay as replay_module

            original = replay_module.RecordingSource.frames
            replay_module.RecordingSource.frames = lambda self: iter(decoded)
            try:
                yield
            finally:
                replay_module.RecordingSource.frames = original

        def in_memory():
            with frames_in_memory():
                replay(False)

        def replay(record: bool):
            out = work / f"replay-{next(counter)}"
            replay_session(path, make_plugin_manager(), output_dir=out, record=record, rerun=False)
            shutil.rmtree(out)

        plain_read()  # warm the page cache
        results = {
            "plain read": timed(plain_read, args.repeat),
            "MCAP read": timed(mcap_read, args.repeat),
            "frames decoded": timed(frames_decoded, args.repeat),
            "pipeline, in memory": timed(in_memory, args.repeat),
            "replay": timed(lambda: replay(False), args.repeat),
            "replay + record": timed(lambda: replay(True), args.repeat),
        }
        plain, mcap = n / results["plain read"], n / results["MCAP read"]
        print(f"\n{'case':<20} {'pairs/s':>10} {'MB/s':>8} {'/ plain':>9} {'/ MCAP':>8}")
        for name, seconds in results.items():
            rate = n / seconds
            print(
                f"{name:<20} {rate:>10.1f} {size / seconds / 1e6:>8.0f} {rate / plain:>9.3f} {rate / mcap:>8.3f}"
            )
        memory, decode, replayed = (n / results[k] for k in ("pipeline, in memory", "frames decoded", "replay"))
        serial = 1.0 / (1.0 / memory + 1.0 / decode)
        print(f"\nreplay / in-memory pipeline: {replayed / memory:.3f} (target >= 0.8); "
              f"/ (in-memory pipeline then decode, one after the other: {serial:.1f} pairs/s): {replayed / serial:.3f}")
        record("replay.replay_vs_in_memory", replayed / memory, "higher")
        for name, key in (("frames decoded", "decoded"), ("replay", "replay"), ("replay + record", "replay_record")):
            record(f"replay.{key}_vs_mcap_read", results["MCAP read"] / results[name], "higher")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
