"""The station cross-validation over many sessions: is the halves' difference within its stated uncertainty?

Per seed: the station scenario's 20 rendered board views (``render_calibration_views``,
noise from the seed; the pose layout fixed as ``crossfield calibrate --scenario
station`` has it, or with ``--vary-layout`` a new layout per seed,
``layout_seed = 1000 + seed`` as ``bench_calibrate_peers.py``), detected, solved as
``crossfield calibrate --cross-validate`` does (every 8th pair held out, the rest
split into interleaved halves, each solved with the same settings) and compared
(``crossval.compare``). Printed per seed: the largest ratio over the image of each
camera's projection difference and of the 3-D points at 400 mm (Mahalanobis norms
on the normal scale, ``crossval.normal_equivalent``), the share of grid points
within 2 sigma, the mean squared ratio over the grid (1 when the stated
uncertainty is right: each grid ratio is then |N(0, 1)|), the same with each
half's Jacobian covariance alone (without the jackknife's larger std), and each
half and the whole against the rendered truth (largest projection ratio over
the image).

    .venv/bin/python bench/bench_calibrate_crossval.py --seeds 10 --cache /tmp/cv-fixed
    .venv/bin/python bench/bench_calibrate_crossval.py --seeds 12 --vary-layout --cache /tmp/cv-layout

``--cache DIR`` keeps the detections (``s{seed}.npz``) so that a second run skips
the rendering (use one directory per layout mode).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from crossfield.calibration.crossval import compare, split_views
from crossfield.calibration.detect import BoardDetection
from crossfield.calibration.solve import CalibrationSettings, detect_views, solve_stereo
from crossfield.simulator.board_views import default_board, render_calibration_views, station_calibration
from crossfield.types import CAMERAS

N_VIEWS = 20


def detections(seed: int, vary_layout: bool, cache: Path | None) -> list[dict[str, BoardDetection | None]]:
    """The session's detections per view (rendered, or read from the cache)."""
    board = default_board()
    path = None if cache is None else cache / f"s{seed}.npz"
    if path is None or not path.exists():
        layout = {"layout_seed": 1000 + seed} if vary_layout else {}
        views = render_calibration_views("station", n_views=N_VIEWS, seed=seed, **layout)
        dets = detect_views(views.images, board, views.bit_depth, min_points=6)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            arrays = {}
            for k, view in enumerate(dets):
                for cam, d in view.items():
                    arrays[f"{k}_{cam}_ids"] = d.ids if d is not None else np.zeros(0, np.int64)
                    arrays[f"{k}_{cam}_uv"] = d.image_points if d is not None else np.zeros((0, 2))
            np.savez(path, **arrays)
        return dets
    with np.load(path, allow_pickle=False) as z:
        out = []
        for k in range(N_VIEWS):
            view = {}
            for cam in CAMERAS:
                ids = z[f"{k}_{cam}_ids"]
                view[cam] = (
                    BoardDetection(ids, z[f"{k}_{cam}_uv"], board.object_points()[ids]) if len(ids) else None
                )
            out.append(view)
        return out


def session(seed: int, vary_layout: bool, cache: Path | None) -> dict:
    """One seed's cross-validation figures (module docstring)."""
    dets = detections(seed, vary_layout, cache)
    truth = station_calibration()
    sizes = {cam: truth.camera(cam).image_size for cam in CAMERAS}
    board = default_board()
    full = solve_stereo(dets, sizes, board, CalibrationSettings())
    halves = split_views(tuple(full.used_stereo))
    a, b = (
        solve_stereo(
            [dets[k] if k in half else {c: None for c in CAMERAS} for k in range(len(dets))],
            sizes,
            board,
            CalibrationSettings(holdout_every=0),
        )
        for half in halves
    )
    cv = compare(a.calibration, a.covariance, b.calibration, b.covariance, halves=halves)
    z = np.concatenate([cv.projection_ratio(cam) for cam in CAMERAS])
    jac = [
        sol.covariance / np.outer(*(2 * [np.sqrt(np.diag(sol.covariance)) / sol.std_jacobian]))
        for sol in (a, b)
    ]
    cv_j = compare(a.calibration, jac[0], b.calibration, jac[1], halves=halves)
    z_j = np.concatenate([cv_j.projection_ratio(cam) for cam in CAMERAS])
    row = {
        "seed": seed,
        "max_upper": float(cv.projection_ratio("upper").max()),
        "max_lower": float(cv.projection_ratio("lower").max()),
        "max_points": float(cv.point_ratio().max()),
        "grid_within_2": float(np.mean(z <= 2)),
        "grid_mean_z2": float(np.mean(z**2)),
        "grid_mean_z2_jacobian": float(np.mean(z_j**2)),
    }
    for name, sol in (("A", a), ("B", b), ("whole", full)):
        t = compare(truth, np.zeros_like(sol.covariance), sol.calibration, sol.covariance)
        row[f"{name}_vs_truth"] = float(max(t.projection_ratio(cam).max() for cam in CAMERAS))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="sessions (seed 1..N)")
    ap.add_argument("--vary-layout", action="store_true", help="a new pose layout per seed (1000 + seed)")
    ap.add_argument("--cache", type=Path, default=None, help="directory keeping the detections (.npz)")
    ap.add_argument("--json", type=Path, default=None, help="write the per-seed rows here")
    args = ap.parse_args(argv)
    rows = []
    print(
        "| seed | max upper | max lower | max 3-D | grid within 2 | grid mean z^2 | Jacobian alone | A vs truth | B vs truth | whole vs truth |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for seed in range(1, args.seeds + 1):
        r = session(seed, args.vary_layout, args.cache)
        rows.append(r)
        print(
            f"| {seed} | {r['max_upper']:.2f} | {r['max_lower']:.2f} | {r['max_points']:.2f} | "
            f"{r['grid_within_2']:.0%} | {r['grid_mean_z2']:.2f} | {r['grid_mean_z2_jacobian']:.2f} | {r['A_vs_truth']:.2f} | "
            f"{r['B_vs_truth']:.2f} | {r['whole_vs_truth']:.2f} |",
            flush=True,
        )
    within = lambda key: sum(r[key] <= 2 for r in rows)
    print(
        f"{args.seeds} seeds ({'a layout per seed' if args.vary_layout else 'the station layout'}): "
        f"max within 2 sigma: upper {within('max_upper')}, lower {within('max_lower')}, "
        f"3-D {within('max_points')} of {len(rows)}; grid points within 2 sigma "
        f"{np.mean([r['grid_within_2'] for r in rows]):.1%}, mean z^2 {np.mean([r['grid_mean_z2'] for r in rows]):.2f} "
        f"(Jacobian alone {np.mean([r['grid_mean_z2_jacobian'] for r in rows]):.2f}); "
        f"halves within 2 sigma of the truth: {sum(r['A_vs_truth'] <= 2 for r in rows) + sum(r['B_vs_truth'] <= 2 for r in rows)} "
        f"of {2 * len(rows)}"
    )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
