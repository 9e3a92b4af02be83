"""Time triangulate "epipolar" per frame against an OpenCV baseline; report its accuracy.

Run: ``.venv/bin/python bench/bench_triangulate.py [--runs N] [--points N] [--noise PX]``

Frames: ``--points`` targets at z = 350..450 mm seen by the synthetic
scA1600-like rig of ``tests/triangulate/test_triangulate.py`` (fx ~ 3636 px, 50 mm vertical
baseline, mild distortion), centroids with ``--noise`` px Gaussian noise and
the lower set shuffled.

Baseline, on the same centroids but **already paired** (it does no matching,
no ambiguity checks, no refinement, no uncertainty): ``cv2.undistortPoints``
for both cameras + ``cv2.triangulatePoints``, the least work that yields
3-D points. Both run in turn within each round (after a warm-up) so that they
see the same machine load. Prints the median and 90th percentile microseconds
per frame and the ratio of the medians; then the RMS error per axis against
the truth and the RMS of error / sigma_xyz.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from test_triangulate import make_calibration, observe, random_points, stereo  # noqa: E402

from crossfield.plugins.triangulate_epipolar import EpipolarTriangulator  # noqa: E402


def baseline(calibration, uv_u: np.ndarray, uv_l: np.ndarray) -> np.ndarray:
    up, lo = calibration.upper, calibration.lower
    P_u = np.hstack([np.eye(3), np.zeros((3, 1))])
    P_l = np.hstack([calibration.R_lower_upper, calibration.t_lower_upper[:, None]])
    xn_u = cv2.undistortPoints(uv_u.reshape(-1, 1, 2), up.camera_matrix, up.dist_coeffs).reshape(-1, 2)
    xn_l = cv2.undistortPoints(uv_l.reshape(-1, 1, 2), lo.camera_matrix, lo.dist_coeffs).reshape(-1, 2)
    Xh = cv2.triangulatePoints(P_u, P_l, xn_u.T, xn_l.T)
    return (Xh[:3] / Xh[3]).T


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=2000)
    parser.add_argument("--points", type=int, default=20)
    parser.add_argument("--noise", type=float, default=0.02, help="centroid noise, px")
    args = parser.parse_args()

    rng = np.random.default_rng(1)
    calibration = make_calibration()
    triangulator = EpipolarTriangulator()
    frames = []
    for _ in range(50):
        X = random_points(rng, calibration, args.points)
        uv_u, uv_l = observe(calibration, X, rng, args.noise)
        order = rng.permutation(args.points)
        frames.append((X, stereo(uv_u, uv_l[order], args.noise, args.noise), uv_u, uv_l, order))

    ours, base = [], []
    for k in range(args.runs + 100):
        X, centroids, uv_u, uv_l, order = frames[k % len(frames)]
        t0 = time.perf_counter()
        triangulator.triangulate(centroids, calibration)
        t1 = time.perf_counter()
        baseline(calibration, uv_u, uv_l)
        t2 = time.perf_counter()
        if k >= 100:  # warm-up
            ours.append(t1 - t0)
            base.append(t2 - t1)
    ours_us, base_us = np.array(ours) * 1e6, np.array(base) * 1e6
    print(f"triangulate 'epipolar', {args.points} points/frame, {args.runs} frames:")
    print(f"  epipolar : median {np.median(ours_us):7.1f} us, p90 {np.percentile(ours_us, 90):7.1f} us")
    print(f"  baseline : median {np.median(base_us):7.1f} us, p90 {np.percentile(base_us, 90):7.1f} us "
          f"(undistortPoints x2 + triangulatePoints, pre-paired)")
    print(f"  ratio    : {np.median(ours_us) / np.median(base_us):.1f} x baseline")

    errors, normalised, matched, total = [], [], 0, 0
    for X, centroids, *_ in frames:
        points = triangulator.triangulate(centroids, calibration)
        truth = X[points.upper_index]
        errors.append(points.xyz - truth)
        normalised.append((points.xyz - truth) / points.sigma_xyz)
        matched += len(points)
        total += len(X)
    rms = np.sqrt(np.mean(np.concatenate(errors) ** 2, axis=0))
    rms_norm = np.sqrt(np.mean(np.concatenate(normalised) ** 2, axis=0))
    print(f"accuracy at {args.noise} px centroid noise ({matched}/{total} points matched):")
    print(f"  RMS error x y z   : {rms[0]:.4f} {rms[1]:.4f} {rms[2]:.4f} mm")
    print(f"  RMS error / sigma : {rms_norm[0]:.2f} {rms_norm[1]:.2f} {rms_norm[2]:.2f}")


if __name__ == "__main__":
    main()
