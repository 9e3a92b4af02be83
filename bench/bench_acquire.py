"""Acquisition rate of the basler source through pylon's camera emulation, against the simulator source.

Run: ``.venv/bin/python bench/bench_acquire.py [--pairs N] [--rounds N] [--frames-in-folder N]``

The simulator source renders ``station`` pairs (1626 x 1236, 12 bit, fresh
noise per pair). The same pairs, written once as MSB-aligned 16-bit files
(uncompressed TIFF and PNG), are streamed by two emulated cameras
(``PYLON_CAMEMU=2``, ``ImageFileMode = On``) through the real pylon SDK:
software trigger on both, OneByOne grab, reader threads, frame-counter and
skew checks, Mono12 -> uint16. The emulator reads and decodes the image
file for every frame, so the file format matters.

Each round takes ``--pairs`` pairs from every source in turn (same machine
load for all); a basler round includes StartGrabbing/StopGrabbing. Prints
pairs/s (median over rounds) and the ratio to the simulator source.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

os.environ["PYLON_CAMEMU"] = "2"  # read by pylon's emulation transport layer when it enumerates devices

from crossfield.camera.calibration_io import write_stereo_calibration  # noqa: E402
from crossfield.plugins.acquire_basler import BaslerStereoSource  # noqa: E402
from crossfield.plugins.acquire_simulator import SimulatorSource  # noqa: E402


def write_frames(folder: Path, frames, extension: str) -> None:
    params = [cv2.IMWRITE_TIFF_COMPRESSION, 1] if extension == "tiff" else []  # 1 = none
    for camera in ("upper", "lower"):
        (folder / camera).mkdir(parents=True)
        for f in frames:
            cv2.imwrite(str(folder / camera / f"{f.sequence:04d}.{extension}"), f.image(camera) << 4, params)


def basler_source(folder: Path, calibration: Path) -> BaslerStereoSource:
    def features(camera: str) -> dict:
        return {"TestImageSelector": "Off", "ImageFileMode": "On", "ImageFilename": str(folder / camera),
                "Width": 1626, "Height": 1236}

    return BaslerStereoSource(
        upper="0815-0000", lower="0815-0001", calibration=str(calibration), frames=0, max_skew_ms=250.0,
        upper_features=features("upper"), lower_features=features("lower"),
    )


def take(frames_iter, n: int) -> int:
    got = 0
    for _ in frames_iter:
        got += 1
        if got == n:
            break
    if hasattr(frames_iter, "close"):
        frames_iter.close()
    return got


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=20, help="pairs per source per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--frames-in-folder", type=int, default=5, help="distinct pairs the emulated cameras cycle through"
    )
    args = parser.parse_args(argv)

    simulator_template = SimulatorSource(scenario="station", frames=args.frames_in_folder, seed=1)
    frames = list(simulator_template.frames())
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        calibration = write_stereo_calibration(tmp / "calibration.yml", simulator_template.calibration)
        sources = {}
        for extension in ("tiff", "png"):
            write_frames(tmp / extension, frames, extension)
            t0 = time.perf_counter()
            sources[f"basler emulation ({extension})"] = basler_source(tmp / extension, calibration)
            print(f"opened emulated pair ({extension}) in {(time.perf_counter() - t0) * 1e3:.0f} ms")
        try:
            rates: dict[str, list[float]] = {"simulator": [], **{name: [] for name in sources}}
            for _ in range(args.rounds):
                simulator = SimulatorSource(scenario="station", frames=args.pairs, seed=1)
                simulator.scene.clean_images  # noise-free images: computed once per scene, not timed
                t0 = time.perf_counter()
                n = take(simulator.frames(), args.pairs)
                rates["simulator"].append(n / (time.perf_counter() - t0))
                for name, source in sources.items():
                    t0 = time.perf_counter()
                    n = take(source.frames(), args.pairs)
                    rates[name].append(n / (time.perf_counter() - t0))
            incidents = {name: source.describe()["incident_counts"] for name, source in sources.items()}
        finally:
            for source in sources.values():
                source.close()

    base = float(np.median(rates["simulator"]))
    print(f"{args.rounds} rounds x {args.pairs} pairs, 1626x1236 Mono12, {os.cpu_count()} CPUs, "
          f"pypylon {_pypylon_version()}")
    print(f"{'source':28s} {'pairs/s (median)':>17s} {'min':>7s} {'max':>7s}  ratio to simulator")
    for name, values in rates.items():
        median = float(np.median(values))
        print(f"{name:28s} {median:17.2f} {min(values):7.2f} {max(values):7.2f}  {median / base:6.2f} x"
              + (f"   incidents {incidents[name] or 'none'}" if name in incidents else ""))
    return 0


def _pypylon_version() -> str:
    from importlib import metadata

    return metadata.version("pypylon")


if __name__ == "__main__":
    raise SystemExit(main())
