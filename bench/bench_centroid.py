"""Time the centroid implementations on a realistic frame against an OpenCV baseline.

Run: ``.venv/bin/python bench/bench_centroid.py [--runs N] [--targets N] [--threads N] [--source S]``
or ``.venv/bin/python bench/bench_centroid.py --efficiency [--frames N]`` (see below).

The frame: 1626 x 1236 uint16, 12-bit, background 150 DN with read noise
3 DN and photon noise (2.86 e-/DN), ``--targets`` blurred ellipses 30-60 px
across (peak 2400-3400 DN), plus the distractors of the tests (specks, an
elongated reflection, a saturated blob, two blobs cut by the border).
``--source station|table3`` uses the simulator's upper image instead.

Baseline, on the same frame and the same (precomputed) threshold:
``cv2.threshold`` (16U, to 0/1) -> ``astype(uint8)`` -> ``cv2.findContours``
(RETR_EXTERNAL, CHAIN_APPROX_NONE) -> ``cv2.moments`` of every contour: the
least work that yields a (pixel-level) centroid per blob.

The implementations and the baseline run in turn within each of ``--runs``
rounds (after a warm-up; a new random order each round), so that all see
the same machine load and none always follows the same one. Prints the
median and 90th percentile ms per frame and the ratio of the medians to the
baseline's; also the centroid error against the known ellipse centres.

``--efficiency``: the issue-11 frames: 60 targets of 6-12 px radius
(diameter 12-24 px), rendered with 32 x 32 sub-samples per pixel; the truth
is each rendered blob's centre of mass, the Cramer-Rao bound that of the
renderer's own image model (``tests/crb_tools.py``). On ``--frames`` noise
draws of the same targets, in one run: ms per frame (median) and RMS / CRB
of every implementation, of "modelfit" with these frames' pixel-then-blur
order (with its default one Gauss-Newton step, and with two), and of
OpenCV contours + moments (intensity moments inside each
filled contour, and the contour polygon's own moments).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from synthetic_targets import distractors, random_targets, render

from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.imaging.blobs import estimate_background


def baseline(image: np.ndarray, threshold_dn: int) -> list[tuple[float, float]]:
    """threshold + findContours + moments: contour-polygon centroids."""
    _, mask16 = cv2.threshold(image, threshold_dn, 1, cv2.THRESH_BINARY)
    mask = mask16.astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out = []
    for contour in contours:
        m = cv2.moments(contour)
        if m["m00"] > 0:
            out.append((m["m10"] / m["m00"], m["m01"] / m["m00"]))
    return out


def contour_intensity_moments(image: np.ndarray, threshold_dn: int, level_dn: float) -> list[tuple[float, float]]:
    """OpenCV contours + intensity moments: background-subtracted cv2.moments inside each filled contour."""
    mask = (image > threshold_dn).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out = []
    for contour in contours:
        x, y, w, h = cv2.boundingRect(contour)
        filled = np.zeros((h, w), np.uint8)
        cv2.drawContours(filled, [contour], -1, 1, thickness=-1, offset=(-x, -y))
        m = cv2.moments((image[y : y + h, x : x + w].astype(np.float32) - np.float32(level_dn)) * filled)
        if m["m00"] > 0:
            out.append((x + m["m10"] / m["m00"], y + m["m01"] / m["m00"]))
    return out


def efficiency(args) -> int:
    """RMS / CRB and time per frame of every implementation and the OpenCV baselines (module docstring)."""
    from crb_tools import centre_crb
    from synthetic_targets import coverage

    shape = (1236, 1626)
    seed = args.seed  # the target set (the tests' is 11)
    rng = np.random.default_rng(seed)
    targets = random_targets(rng, 60, shape=shape, diameter_px=(12.0, 24.0))
    truth = []
    for e in targets:
        c, r0, c0 = coverage(e, shape, 32)
        h, w = c.shape
        truth.append([(c.sum(0) @ (np.arange(w) + c0)) / c.sum(), (c.sum(1) @ (np.arange(h) + r0)) / c.sum()])
    truth = np.array(truth)
    crb = np.array([np.trace(centre_crb(e, shape=shape)) for e in targets])
    images = [render(targets, np.random.default_rng([seed, k]), supersample=32) for k in range(args.frames)]
    background = estimate_background(images[0], 8.0)
    pm = make_plugin_manager()
    candidates = {name: impl.create({}) for name, impl in sorted(implementations(pm, "centroid").items())}
    modelfit = implementations(pm, "centroid")["modelfit"]
    candidates["modelfit (psf_order=pixel)"] = modelfit.create({"psf_order": "pixel"})
    candidates["modelfit (pixel, 2 steps)"] = modelfit.create({"psf_order": "pixel", "max_iterations": 2})
    functions = {
        name: (lambda image, x=x: x.extract(image, "upper", 0).uv) for name, x in candidates.items()
    }
    functions["opencv contours + intensity moments"] = lambda image: np.array(
        contour_intensity_moments(image, background.threshold_dn, background.level_dn)
    )
    functions["opencv contours + polygon moments"] = lambda image: np.array(baseline(image, background.threshold_dn))
    times = interleaved_ms({k: (lambda f=f: f(images[0])) for k, f in functions.items()}, args.runs)
    print(
        f"{args.frames} frames 1626x1236, 60 targets of 6-12 px radius (32x32 sub-samples), "
        f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; RMS/CRB over targets and frames"
    )
    cpu = interleaved_ms.cpu
    print(
        f"{'implementation':40s} {'ms/frame':>9s} {'ratio':>6s} {'cpu ms':>7s} {'ratio':>6s} "
        f"{'found':>6s} {'RMS px':>8s} {'RMS/CRB':>8s}"
    )
    base = float(np.median(times["weighted"]))
    base_cpu = float(np.median(cpu["weighted"]))
    for name, fn in functions.items():
        err2, bound, found = [], [], 0
        for image in images:
            uv = fn(image).reshape(-1, 2)
            d = np.linalg.norm(uv[:, None] - truth[None], axis=2)
            for k in range(len(truth)):
                i = int(np.argmin(d[:, k])) if len(uv) else -1
                if i >= 0 and d[i, k] < 1.0:
                    err2.append(float(np.sum((uv[i] - truth[k]) ** 2)))
                    bound.append(crb[k])
                    found += 1
        ms = float(np.median(times[name]))
        ms_cpu = float(np.median(cpu[name]))
        rms = np.sqrt(np.mean(err2)) if err2 else float("nan")
        ratio = np.sqrt(np.sum(err2) / np.sum(bound)) if err2 else float("nan")
        print(
            f"{name:40s} {ms:9.2f} {ms / base:6.2f} {ms_cpu:7.2f} {ms_cpu / base_cpu:6.2f} "
            f"{found // len(images):6d} {rms:8.4f} {ratio:8.2f}"
        )
    print(
        f"(medians of {args.runs} interleaved runs on frame 0; ratio: time relative to 'weighted'; "
        f"cpu ms: process CPU time; CRB RMS over the targets {np.sqrt(crb.mean()):.4f} px; "
        f"load average {os.getloadavg()[0]:.1f})"
    )
    return 0


def interleaved_ms(functions: dict[str, object], runs: int) -> dict[str, np.ndarray]:
    """Per-run times (ms) of each function, run in turn within every round so
    that all see the same machine load (other processes, CPU frequency), in a
    new random order each round (seeded) so that none always follows the same
    one (the caches a slow implementation leaves cold cost the next ~0.3 ms)."""
    for fn in functions.values():  # warm-up
        for _ in range(5):
            fn()
    times = {name: np.empty(runs) for name in functions}
    cpu = {name: np.empty(runs) for name in functions}
    names = list(functions)
    rng = np.random.default_rng(0)
    for i in range(runs):
        for name in rng.permutation(names):
            fn = functions[name]
            c0 = time.process_time()
            t0 = time.perf_counter()
            fn()
            times[name][i] = (time.perf_counter() - t0) * 1e3
            cpu[name][i] = (time.process_time() - c0) * 1e3
    interleaved_ms.cpu = cpu  # CPU ms of the same runs (this process, all its threads)
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=300, help="timed runs per implementation")
    parser.add_argument("--targets", type=int, default=20, help="targets in the frame")
    parser.add_argument("--threads", type=int, default=-1, help="cv2.setNumThreads (-1: OpenCV's default)")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument(
        "--source",
        choices=("synthetic", "station", "table3"),
        default="synthetic",
        help="synthetic frame (default) or a simulator scenario's upper image",
    )
    parser.add_argument("--efficiency", action="store_true", help="RMS/CRB and time on the issue-11 frames")
    parser.add_argument("--frames", type=int, default=8, help="noise draws for --efficiency")

    args = parser.parse_args(argv)
    if args.threads >= 0:
        cv2.setNumThreads(args.threads)
    if args.efficiency:
        return efficiency(args)

    rng = np.random.default_rng(args.seed)
    if args.source == "synthetic":
        targets = random_targets(rng, args.targets, shape=(1236, 1626))
        # keep the targets clear of the distractors along the top rows
        targets = [t for t in targets if t.v0 - t.a > 110] or targets
        extra = [e for group in distractors().values() for e in group]
        image = render(targets + extra, rng)
        truth = np.array([[t.u0, t.v0] for t in targets])
        content = f"{len(targets)} targets + {len(extra)} distractors"
    else:  # the station simulator's upper image
        from crossfield.simulator.scenarios import build_scene

        scene = build_scene(args.source)
        image = scene.render_pair(0, rng).upper
        truth = np.array(list(scene.true_blob_centres("upper").values()))
        content = f"simulator scenario {args.source!r}, {len(truth)} targets"
    threshold = estimate_background(image, 8.0).threshold_dn

    print(
        f"frame {image.shape[1]}x{image.shape[0]} {image.dtype}, {content}, "
        f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} OpenCV threads, {args.runs} runs"
    )
    pm = make_plugin_manager()
    extractors = {name: impl.create({}) for name, impl in sorted(implementations(pm, "centroid").items())}
    functions = {"baseline": lambda: baseline(image, threshold)}
    for name, extractor in extractors.items():
        functions[name] = lambda extractor=extractor: extractor.extract(image, "upper", 0)
    times = interleaved_ms(functions, args.runs)
    base_ms = float(np.median(times["baseline"]))
    print(f"{'implementation':44s} {'median':>7s}    {'p90':>7s}     ratio")
    print(
        f"{'baseline (threshold+findContours+moments)':44s} {base_ms:7.3f} ms "
        f"{np.percentile(times['baseline'], 90):7.3f} ms   1.00 x"
    )
    for name, extractor in extractors.items():
        ms = float(np.median(times[name]))
        p90 = float(np.percentile(times[name], 90))
        result = extractor.extract(image, "upper", 0)
        d = np.linalg.norm(result.uv[:, None, :] - truth[None, :, :], axis=2)
        matched = d.min(axis=1) < 1.0
        err = result.uv[matched] - truth[d.argmin(axis=1)[matched]]
        rms = float(np.sqrt((err**2).sum(axis=1).mean())) if matched.any() else float("nan")
        print(
            f"{name:44s} {ms:7.3f} ms {p90:7.3f} ms {ms / base_ms:6.2f} x   "
            f"found {int(matched.sum())}/{len(truth)}, rejected {len(result.rejected)}, "
            f"radial RMS error {rms:.4f} px, median sigma_uv {np.median(result.sigma_uv):.4f} px"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
