"""Recording throughput: McapRecorder vs a plain file write of the same bytes.

    .venv/bin/python bench/bench_recording.py [--pairs 120] [--repeats 5] [--fsync] [--dir /tmp]

For each repeat (interleaved, so that both see the same disk state):

* baseline: the raw pixel bytes of every pair (2 x 1626 x 1236 uint16)
  written with ``file.write`` into one file; and for each chunk compression, the same
  images compressed with it beforehand (outside the timing) and written the same way:
  "a plain write of the same bytes" that the compressed recorder writes;
* recorder: the same pairs through ``pm.hook.on_frame`` into a
  :class:`crossfield.recording.recorder.McapRecorder` (writer thread on, then off),
  closed at the end (summary and indexes written, the file sealed), uncompressed
  and with each chunk compression (``--compressions``, ``[session] compression``);
* with ``--rerun``: the same pairs through :class:`crossfield.viz.rerun_log.RerunLogger`.

Reports pairs/s (wall clock, file closed; with ``--fsync`` also synced to
disk), the CPU time per pair of the process (every thread: the recorder's writer and
hashing threads too), and for the recorder the time the pipeline thread spends inside
the hook per pair, and the file's size (MB, and as a fraction of the plain write's).
Ratios: CPU and wall time (1 / pairs/s) against the plain write of the same bytes
(uncompressed for ``none``, compressed for lz4 / zstd); then the compression's own
CPU per image, timed once. Medians over the repeats. Without ``--fsync`` the writes land in the page cache, so the
figures measure CPU cost; with it they include the disk.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.recording.recorder import McapRecorder
from crossfield.chain.registry import make_plugin_manager
from crossfield.types import StereoFrame

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figures import record  # noqa: E402

HEIGHT, WIDTH = 1236, 1626


def make_frames(count: int = 4, seed: int = 0) -> list[StereoFrame]:
    """Plausible 12-bit pairs: dark background with read noise and a few bright spots."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    frames = []
    for k in range(count):
        images = []
        for _ in range(2):
            img = rng.normal(200.0, 8.0, (HEIGHT, WIDTH))
            for _ in range(12):
                cx, cy = rng.uniform(100, WIDTH - 100), rng.uniform(100, HEIGHT - 100)
                sl = (slice(int(cy) - 30, int(cy) + 30), slice(int(cx) - 30, int(cx) + 30))
                img[sl] += 3000 * np.exp(-((xx[sl] - cx) ** 2 + (yy[sl] - cy) ** 2) / (2 * 6.0**2))
            images.append(np.clip(img, 0, 4095).astype(np.uint16))
        frames.append(StereoFrame(k, 0, images[0], images[1], 12))
    return frames


def compressed_images(frames: list[StereoFrame], compression: str) -> list[tuple[bytes, bytes]]:
    """Each pair's two images as the chunk compression ``compression`` makes them
    (the mcap writer's own calls: lz4.frame.compress, zstandard.compress)."""
    if compression == "none":
        return [(bytes(f.upper.data), bytes(f.lower.data)) for f in frames]
    if compression == "lz4":
        import lz4.frame

        compress = lz4.frame.compress
    else:
        import zstandard

        compress = zstandard.compress
    return [(compress(f.upper.tobytes()), compress(f.lower.tobytes())) for f in frames]


def compression_ms_per_image(frames: list[StereoFrame], compression: str) -> float:
    """CPU ms to compress one image with ``compression`` (the mean over the templates)."""
    c0 = time.process_time()
    compressed_images(frames, compression)
    return 1e3 * (time.process_time() - c0) / (2 * len(frames))


def run_baseline(path: Path, images: list[tuple[bytes, bytes]], pairs: int, fsync: bool) -> dict[str, float]:
    """``pairs`` pairs of ``images`` (the bytes of each pair's two images) with file.write."""
    t0, c0 = time.perf_counter(), time.process_time()
    with open(path, "wb") as f:
        for i in range(pairs):
            upper, lower = images[i % len(images)]
            f.write(upper)
            f.write(lower)
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "pairs_per_s": pairs / wall,
        "cpu_ms_per_pair": 1e3 * cpu / pairs,
        "hook_ms_per_pair": float("nan"),
        "mb": path.stat().st_size / 1e6,
    }


def run_observer(observer, path: Path, frames: list[StereoFrame], pairs: int, fsync: bool) -> dict[str, float]:
    """The pairs through ``observer.on_frame`` into ``path``, closed at the end."""
    t0, c0 = time.perf_counter(), time.process_time()
    pm = make_plugin_manager(builtins=False, extra=[observer])
    in_hook = 0.0
    start_ns = time.time_ns()
    for i in range(pairs):
        template = frames[i % len(frames)]
        frame = StereoFrame(i, start_ns + i * 16_666_667, template.upper, template.lower, 12)
        h0 = time.perf_counter()
        pm.hook.on_frame(frame=frame)
        in_hook += time.perf_counter() - h0
    observer.close()
    if fsync:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "pairs_per_s": pairs / wall,
        "cpu_ms_per_pair": 1e3 * cpu / pairs,
        "hook_ms_per_pair": 1e3 * in_hook / pairs,
        "mb": path.stat().st_size / 1e6,
    }


def run_recorder(
    path: Path, frames: list[StereoFrame], pairs: int, fsync: bool, writer_thread: bool, compression: str = "none"
) -> dict[str, float]:
    recorder = McapRecorder(path, overwrite=True, writer_thread=writer_thread, compression=compression)
    result = run_observer(recorder, path, frames, pairs, fsync)
    Path(f"{path}.seal.json").unlink(missing_ok=True)  # the sidecar of the seal
    return result


def run_rerun_logger(path: Path, frames: list[StereoFrame], pairs: int, fsync: bool) -> dict[str, float]:
    """The same pairs through RerunLogger (images only) into an .rrd, for comparison."""
    from crossfield.viz.rerun_log import RerunLogger

    return run_observer(RerunLogger(path), path, frames, pairs, fsync)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=120)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fsync", action="store_true", help="sync to disk before stopping the clock")
    parser.add_argument("--dir", default=None, help="where to write (default: a temporary directory)")
    parser.add_argument(
        "--rerun", action="store_true", help="also time RerunLogger (images into session.rrd)"
    )
    parser.add_argument("--compressions", nargs="*", default=["zstd", "lz4"],
                        help="chunk compressions to time besides none (writer thread on)")
    args = parser.parse_args(argv)

    frames = make_frames()
    mb = args.pairs * 2 * HEIGHT * WIDTH * 2 / 1e6
    print(
        f"{args.pairs} pairs of 2 x {WIDTH}x{HEIGHT} uint16 ({mb:.0f} MB) per run, {args.repeats} repeats, "
        f"fsync={'on' if args.fsync else 'off'}, {os.cpu_count()} CPUs"
    )
    plain_images = compressed_images(frames, "none")
    cases = {
        "plain file write": lambda p: run_baseline(p, plain_images, args.pairs, args.fsync),
        "McapRecorder (writer thread)": lambda p: run_recorder(p, frames, args.pairs, args.fsync, True),
        "McapRecorder (synchronous)": lambda p: run_recorder(p, frames, args.pairs, args.fsync, False),
    }
    #: case -> the plain-write case of the same bytes it is compared with
    same_bytes = {name: "plain file write" for name in cases}
    for compression in args.compressions:
        images = compressed_images(frames, compression)
        cases[f"plain write, {compression} bytes"] = lambda p, im=images: run_baseline(p, im, args.pairs, args.fsync)
        cases[f"McapRecorder {compression} (thread)"] = (
            lambda p, c=compression: run_recorder(p, frames, args.pairs, args.fsync, True, c)
        )
        same_bytes[f"plain write, {compression} bytes"] = f"plain write, {compression} bytes"
        same_bytes[f"McapRecorder {compression} (thread)"] = f"plain write, {compression} bytes"
    if args.rerun:
        cases["RerunLogger (images)"] = lambda p: run_rerun_logger(p, frames, args.pairs, args.fsync)
    results: dict[str, list[dict[str, float]]] = {name: [] for name in cases}
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = Path(tmp) / "bench.out"
        for _ in range(args.repeats):
            for name, run in cases.items():
                results[name].append(run(path))
                path.unlink()
    print(
        f"{'case':30s} {'pairs/s':>9s} {'(min..max)':>15s} {'CPU ms/pair':>12s} {'in hook ms/pair':>16s} "
        f"{'CPU / plain':>12s} {'CPU / same':>11s} {'wall / same':>12s} {'MB':>7s} {'size / plain':>13s}"
    )

    def median(name: str, key: str) -> float:
        return statistics.median(r[key] for r in results[name])

    plain_cpu = median("plain file write", "cpu_ms_per_pair")
    plain_mb = results["plain file write"][0]["mb"]
    for name, runs in results.items():
        rates = [r["pairs_per_s"] for r in runs]
        cpu = median(name, "cpu_ms_per_pair")
        hook = median(name, "hook_ms_per_pair")
        same = same_bytes[name]
        cpu_same = cpu / median(same, "cpu_ms_per_pair")
        wall_same = median(same, "pairs_per_s") / statistics.median(rates)
        mb = runs[0]["mb"]
        span = f"({min(rates):.0f}..{max(rates):.0f})"
        hook_text = "-" if np.isnan(hook) else f"{hook:.2f}"
        print(
            f"{name:30s} {statistics.median(rates):9.1f} {span:>15s} {cpu:12.2f} {hook_text:>16s} "
            f"{cpu / plain_cpu:12.2f} {cpu_same:11.2f} {wall_same:12.2f} {mb:7.0f} {mb / plain_mb:13.3f}"
        )
        if name.startswith("McapRecorder"):
            key = name.removeprefix("McapRecorder ").replace("(", "").replace(")", "").replace(" ", "_")
            record(f"recording.{key}_cpu_vs_plain", cpu / plain_cpu, "lower")
            record(f"recording.{key}_wall_vs_same_bytes", wall_same, "lower")
            if same != "plain file write":
                record(f"recording.{key}_cpu_vs_same_bytes", cpu_same, "lower")
    for compression in args.compressions:
        print(f"{compression} compression alone: {compression_ms_per_image(frames, compression):.1f} ms CPU per image")


if __name__ == "__main__":
    main()
