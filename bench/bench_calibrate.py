"""Time `crossfield calibrate`'s solver for 20 and 40 pairs against OpenCV's stereoCalibrate alone.

Run: ``.venv/bin/python bench/bench_calibrate.py [--pairs 20 40] [--repeat 3]``

Views: the simulated station session (``render_calibration_views``, ChArUco
11 x 8, both cameras), detected once; detection time is printed per image
but not part of the comparison. Subject: ``solve_stereo`` (per-camera
calibrateCameraExtended with outlier rejection, stereoCalibrateExtended, the
full covariance and the 3-D uncertainty). Baseline, on the same detections
(the points both cameras saw in each pair): one ``cv2.stereoCalibrate`` call
that estimates everything from scratch (flags 0), the least an OpenCV user
would run. Both run in turn in each round (same machine load); prints the
median seconds and the ratio subject / baseline.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from crossfield.calibration.solve import CalibrationSettings, detect_views, solve_stereo
from crossfield.simulator.board_views import render_calibration_views


def baseline(detections, size) -> float:
    obj, up, lo = [], [], []
    for view in detections:
        a, b = view["upper"], view["lower"]
        if a is None or b is None:
            continue
        ids = np.intersect1d(a.ids, b.ids)
        if len(ids) < 8:
            continue
        a, b = a.subset(ids), b.subset(ids)
        obj.append(a.object_points.astype(np.float32))
        up.append(a.image_points.astype(np.float32))
        lo.append(b.image_points.astype(np.float32))
    rms, *_ = cv2.stereoCalibrate(obj, up, lo, None, None, None, None, size, flags=0)
    return rms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, nargs="+", default=[20, 40])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    n_max = max(args.pairs)
    t0 = time.perf_counter()
    views = render_calibration_views(n_views=n_max, seed=1)
    t1 = time.perf_counter()
    detections = detect_views(views.images, views.board, views.bit_depth)
    t2 = time.perf_counter()
    print(
        f"rendered {n_max} pairs in {t1 - t0:.1f} s; detection {1000 * (t2 - t1) / (2 * n_max):.0f} ms per image"
    )
    sizes = {c: views.calibration.camera(c).image_size for c in ("upper", "lower")}
    for n in args.pairs:
        ours, base = [], []
        for _ in range(args.repeat):
            s = time.perf_counter()
            result = solve_stereo(detections[:n], sizes, views.board, CalibrationSettings(holdout_every=0))
            ours.append(time.perf_counter() - s)
            s = time.perf_counter()
            rms = baseline(detections[:n], sizes["upper"])
            base.append(time.perf_counter() - s)
        a, b = float(np.median(ours)), float(np.median(base))
        print(
            f"{n:3d} pairs: crossfield solve_stereo {a:.3f} s (stereo RMS {result.rms_stereo_px:.4f} px), "
            f"cv2.stereoCalibrate alone {b:.3f} s (RMS {rms:.4f} px), ratio {a / b:.2f}"
        )


if __name__ == "__main__":
    main()
