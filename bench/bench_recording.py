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
hashing threads too; user and system apart, the system part being the kernel's page
cache work, which is the same for the same bytes and is where the spread between runs
comes from), the CPU time of the **pipeline thread** per pair (``time.thread_time``
around the hook, or around the plain write: what recording costs the thread that runs
the pipeline; the writer and hashing threads run beside it), the wall time the pipeline
thread spends inside the hook per pair (it waits there when the writer's queue is full),
and the file's size (MB, and as a fraction of the plain write's).

``--pipeline-ms W`` paces every case like a pipeline: before each pair the main thread
works W ms of its own CPU in Python (holding the GIL, the worst case for overlap), and a
case "pipeline work alone" (no writing) is added; "added wall ms/pair" is then what
writing adds to a pair's wall time, the figure that says whether the recorder's threads
(SHA-256 and BLAKE3 release the GIL while they hash, zlib's CRC-32 too) run in parallel
with the pipeline on the machine's cores. ``--costs`` times, in the same run, each
item the recorder adds per 4 MB image (SHA-256, BLAKE3, CRC-32, one copy, one plain
write of the image into the same folder).
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


_STEPS_PER_MS: list[int] = []


def pipeline_work(ms: float) -> None:
    """About ``ms`` milliseconds of this thread's CPU in Python holding the GIL throughout
    (``sum(range(n))``, calibrated once against ``time.thread_time``): a pipeline's pair."""
    if ms <= 0:
        return
    if not _STEPS_PER_MS:
        n = 100_000
        while True:
            c = time.thread_time()
            sum(range(n))
            spent = time.thread_time() - c
            if spent > 0.05:
                break
            n *= 2
        _STEPS_PER_MS.append(max(1, int(n / spent / 1e3)))
    sum(range(int(ms * _STEPS_PER_MS[0])))


def _figures(pairs: int, wall: float, t0: os.times_result, t1: os.times_result, thread_s: float,
             hook_s: float, path: Path | None) -> dict[str, float]:
    user, system = t1.user - t0.user, t1.system - t0.system
    return {
        "pairs_per_s": pairs / wall,
        "wall_ms_per_pair": 1e3 * wall / pairs,
        "cpu_ms_per_pair": 1e3 * (user + system) / pairs,
        "user_ms_per_pair": 1e3 * user / pairs,
        "sys_ms_per_pair": 1e3 * system / pairs,
        "thread_ms_per_pair": 1e3 * thread_s / pairs,
        "hook_ms_per_pair": 1e3 * hook_s / pairs if hook_s == hook_s else float("nan"),
        "mb": path.stat().st_size / 1e6 if path is not None else 0.0,
    }


def run_work_alone(pairs: int, work_ms: float) -> dict[str, float]:
    """The pipeline work of ``--pipeline-ms`` alone, nothing written (the paced cases' baseline)."""
    t0, w0 = os.times(), time.perf_counter()
    for _ in range(pairs):
        pipeline_work(work_ms)
    return _figures(pairs, time.perf_counter() - w0, t0, os.times(), 0.0, float("nan"), None)


def run_baseline(
    path: Path, images: list[tuple[bytes, bytes]], pairs: int, fsync: bool, work_ms: float = 0.0
) -> dict[str, float]:
    """``pairs`` pairs of ``images`` (the bytes of each pair's two images) with file.write."""
    t0, w0 = os.times(), time.perf_counter()
    in_thread = 0.0
    with open(path, "wb") as f:
        for i in range(pairs):
            pipeline_work(work_ms)
            upper, lower = images[i % len(images)]
            c = time.thread_time()
            f.write(upper)
            f.write(lower)
            in_thread += time.thread_time() - c
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    return _figures(pairs, time.perf_counter() - w0, t0, os.times(), in_thread, float("nan"), path)


def run_observer(
    observer, path: Path, frames: list[StereoFrame], pairs: int, fsync: bool, work_ms: float = 0.0
) -> dict[str, float]:
    """The pairs through ``observer.on_frame`` into ``path``, closed at the end (the
    observer was made before the clock started; closing it is timed)."""
    t0, w0 = os.times(), time.perf_counter()
    pm = make_plugin_manager(builtins=False, extra=[observer])
    in_hook = in_thread = 0.0
    start_ns = time.time_ns()
    for i in range(pairs):
        pipeline_work(work_ms)
        template = frames[i % len(frames)]
        frame = StereoFrame(i, start_ns + i * 16_666_667, template.upper, template.lower, 12)
        h0, c = time.perf_counter(), time.thread_time()
        pm.hook.on_frame(frame=frame)
        in_thread += time.thread_time() - c
        in_hook += time.perf_counter() - h0
    c = time.thread_time()
    observer.close()
    in_thread += time.thread_time() - c
    if fsync:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    return _figures(pairs, time.perf_counter() - w0, t0, os.times(), in_thread, in_hook, path)


def run_recorder(
    path: Path, frames: list[StereoFrame], pairs: int, fsync: bool, writer_thread: bool, compression: str = "none",
    work_ms: float = 0.0,
) -> dict[str, float]:
    recorder = McapRecorder(path, overwrite=True, writer_thread=writer_thread, compression=compression)
    result = run_observer(recorder, path, frames, pairs, fsync, work_ms)
    Path(f"{path}.seal.json").unlink(missing_ok=True)  # the sidecar of the seal
    return result


def run_rerun_logger(path: Path, frames: list[StereoFrame], pairs: int, fsync: bool) -> dict[str, float]:
    """The same pairs through RerunLogger (images only) into an .rrd, for comparison."""
    from crossfield.viz.rerun_log import RerunLogger

    return run_observer(RerunLogger(path), path, frames, pairs, fsync)


def item_costs(frames: list[StereoFrame], folder: Path, reps: int = 20) -> dict[str, float]:
    """CPU ms per 4 MB image of each item the recorder adds to a plain write, timed here
    (process CPU, the mean over ``reps`` images): the seal's SHA-256, the chain's BLAKE3,
    the mcap writer's chunk CRC-32, one copy of the image, and the plain write itself
    (into ``folder``, each image a fresh file)."""
    import hashlib
    import zlib

    import blake3

    image = bytes(frames[0].upper.data)
    path = folder / "cost.out"

    def write() -> None:
        with open(path, "wb") as f:
            f.write(image)
        path.unlink()

    items = {
        "seal SHA-256 (hashlib)": lambda: hashlib.sha256(image).digest(),
        "chain BLAKE3": lambda: blake3.blake3(image).digest(),
        "chunk CRC-32 (zlib)": lambda: zlib.crc32(image),
        "one copy (bytes join)": lambda: b"".join((b"x", image)),
        "plain write": write,
    }
    out = {}
    for name, run in items.items():
        run()
        c0 = time.process_time()
        for _ in range(reps):
            run()
        out[name] = 1e3 * (time.process_time() - c0) / reps
    return out


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
    parser.add_argument("--pipeline-ms", type=float, default=0.0, metavar="W",
                        help="pace every case: W ms of the main thread's CPU (Python, GIL held) before each pair")
    parser.add_argument("--costs", action="store_true", help="time each item the recorder adds per image")
    args = parser.parse_args(argv)

    frames = make_frames()
    mb = args.pairs * 2 * HEIGHT * WIDTH * 2 / 1e6
    work = args.pipeline_ms
    print(
        f"{args.pairs} pairs of 2 x {WIDTH}x{HEIGHT} uint16 ({mb:.0f} MB) per run, {args.repeats} repeats, "
        f"fsync={'on' if args.fsync else 'off'}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}"
        + (f", paced: {work:g} ms of pipeline work per pair" if work else "")
    )
    plain_images = compressed_images(frames, "none")
    cases = {}
    if work:
        cases["pipeline work alone"] = lambda p: run_work_alone(args.pairs, work)
    cases.update({
        "plain file write": lambda p: run_baseline(p, plain_images, args.pairs, args.fsync, work),
        "McapRecorder (writer thread)": lambda p: run_recorder(p, frames, args.pairs, args.fsync, True, "none", work),
        "McapRecorder (synchronous)": lambda p: run_recorder(p, frames, args.pairs, args.fsync, False, "none", work),
    })
    #: case -> the plain-write case of the same bytes it is compared with
    same_bytes = {name: "plain file write" for name in cases}
    for compression in args.compressions:
        images = compressed_images(frames, compression)
        cases[f"plain write, {compression} bytes"] = (
            lambda p, im=images: run_baseline(p, im, args.pairs, args.fsync, work)
        )
        cases[f"McapRecorder {compression} (thread)"] = (
            lambda p, c=compression: run_recorder(p, frames, args.pairs, args.fsync, True, c, work)
        )
        same_bytes[f"plain write, {compression} bytes"] = f"plain write, {compression} bytes"
        same_bytes[f"McapRecorder {compression} (thread)"] = f"plain write, {compression} bytes"
    if args.rerun:
        cases["RerunLogger (images)"] = lambda p: run_rerun_logger(p, frames, args.pairs, args.fsync)
        same_bytes["RerunLogger (images)"] = "plain file write"
    results: dict[str, list[dict[str, float]]] = {name: [] for name in cases}
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = Path(tmp) / "bench.out"
        for _ in range(args.repeats):
            for name, run in cases.items():
                results[name].append(run(path))
                path.unlink(missing_ok=True)
        costs = item_costs(frames, Path(tmp)) if args.costs else {}
    print(
        f"{'case':30s} {'pairs/s':>8s} {'(min..max)':>12s} {'CPU ms/pair':>11s} {'user':>6s} {'sys':>6s} "
        f"{'thread ms':>9s} {'in hook':>8s} {'CPU/plain':>9s} {'CPU/same':>8s} {'thread/same':>11s} "
        f"{'wall/same':>9s} {'added wall':>10s} {'MB':>5s} {'size/plain':>10s}"
    )

    def median(name: str, key: str) -> float:
        return statistics.median(r[key] for r in results[name])

    plain_cpu = median("plain file write", "cpu_ms_per_pair")
    plain_mb = results["plain file write"][0]["mb"]
    alone = median("pipeline work alone", "wall_ms_per_pair") if work else 0.0
    for name, runs in results.items():
        if name == "pipeline work alone":
            print(f"{name:30s} {median(name, 'pairs_per_s'):8.1f} {'':12s} {median(name, 'cpu_ms_per_pair'):11.2f}")
            continue
        rates = [r["pairs_per_s"] for r in runs]
        cpu = median(name, "cpu_ms_per_pair")
        thread = median(name, "thread_ms_per_pair")
        hook = median(name, "hook_ms_per_pair")
        same = same_bytes[name]
        cpu_same = cpu / median(same, "cpu_ms_per_pair")
        thread_same = thread / median(same, "thread_ms_per_pair")
        wall_same = median(same, "pairs_per_s") / statistics.median(rates)
        added = median(name, "wall_ms_per_pair") - alone
        mb = runs[0]["mb"]
        span = f"({min(rates):.0f}..{max(rates):.0f})"
        hook_text = "-" if np.isnan(hook) else f"{hook:.2f}"
        added_text = f"{added:.2f}" if work else "-"
        print(
            f"{name:30s} {statistics.median(rates):8.1f} {span:>12s} {cpu:11.2f} {median(name, 'user_ms_per_pair'):6.2f} "
            f"{median(name, 'sys_ms_per_pair'):6.2f} {thread:9.2f} {hook_text:>8s} {cpu / plain_cpu:9.2f} "
            f"{cpu_same:8.2f} {thread_same:11.2f} {wall_same:9.2f} {added_text:>10s} {mb:5.0f} {mb / plain_mb:10.3f}"
        )
        if name.startswith("McapRecorder") and not work:
            key = name.removeprefix("McapRecorder ").replace("(", "").replace(")", "").replace(" ", "_")
            record(f"recording.{key}_cpu_vs_plain", cpu / plain_cpu, "lower")
            record(f"recording.{key}_wall_vs_same_bytes", wall_same, "lower")
            if same == "plain file write":
                record(f"recording.{key}_thread_vs_same_bytes", thread_same, "lower")
            else:
                # Not the pipeline thread's figure of a compressed case: its same bytes' plain
                # write is 0.7-1.3 ms of thread CPU per pair, and the pipeline thread waits for
                # the compressor's full queue, so the ratio measured where the waits fell
                # (zstd: 0.83, 1.53, 0.85 in three runs of the same code, 2026-12-04).
                record(f"recording.{key}_cpu_vs_same_bytes", cpu_same, "lower")
    if work:
        plain_added = median("plain file write", "wall_ms_per_pair") - alone
        for name in results:
            if name.startswith("McapRecorder"):
                added = median(name, "wall_ms_per_pair") - alone
                ratio = f"{added / plain_added:.2f}" if plain_added > 0.05 else "- (the plain write added nothing measurable)"
                print(f"added wall per pair, {name}: {added:.2f} ms; / plain write ({plain_added:.2f} ms): {ratio}")
    for compression in args.compressions:
        print(f"{compression} compression alone: {compression_ms_per_image(frames, compression):.1f} ms CPU per image")
    if costs:
        print("CPU ms per 4 MB image, each item (same run):")
        for item, ms in costs.items():
            print(f"  {item:28s} {ms:6.2f}")


if __name__ == "__main__":
    main()
