"""Speed of the planning kernels: batched registration and triangulation, and a default sweep.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_plan.py [--batch 100000] [--loop 5000] [--sweep-sessions 300]

Measures, in one run on this machine:

* registrations per second: ``rigid.kabsch`` on a (B, 8, 3) batch vs one at a
  time (the same kernel called per registration, and the ``svd`` register
  plugin's ``fit`` as the pipeline calls it per frame: validation, fit, reflection
  check); the ratio batched / one at a time;
* triangulated points per second of the batched kernel
  (``crossfield.precision.triangulate_batch``) vs the ``epipolar`` plugin per frame, and of
  the Monte Carlo's linearised triangulation (``linearised_triangulation``);
* Monte Carlo trials per second (one trial: a frame's centroid noise, its triangulated
  targets and controls, the weighted Kabsch registration, the characteristics): ``--trials``
  (10^6) through the linearised triangulation, against the full triangulation kernel per trial
  (the previous route) on ``--full-trials`` in the same run, and the registration's share;
* the time of a default sweep (every sweep of ``crossfield plan --sweep`` on
  the paper's station): analytic route only, and both routes with
  ``--sweep-sessions`` Monte Carlo sessions per point, with the number of
  simulated registrations and their rate.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.planning.station import load_station  # noqa: E402
from crossfield.planning.sweeps import run_sweeps  # noqa: E402
from crossfield.plugins.register_svd import SvdRegistrar  # noqa: E402
from crossfield.plugins.triangulate_epipolar import EpipolarTriangulator  # noqa: E402
from crossfield.planning.routes import camera_model, simulate_sessions  # noqa: E402
from crossfield.precision import linearised_triangulation, project_stereo, triangulate_batch  # noqa: E402
from crossfield.rigid import kabsch  # noqa: E402
from crossfield.types import CentroidSet, StereoCentroids  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "station-paper.toml"


def _rate(n: int, seconds: float) -> str:
    return f"{n / seconds:12,.0f} /s  ({1e6 * seconds / n:8.2f} us each)"


def bench_registration(batch: int, loop: int) -> None:
    rng = np.random.default_rng(0)
    P = rng.uniform(-80, 80, (batch, 8, 3))
    Q = P @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T + 5.0 + 0.01 * rng.standard_normal(P.shape)
    w = np.ones(8)
    t = time.perf_counter()
    kabsch(P, Q, w)
    t_batch = time.perf_counter() - t
    t = time.perf_counter()
    for k in range(loop):
        kabsch(P[k], Q[k], w)
    t_one = time.perf_counter() - t
    reg = SvdRegistrar()
    t = time.perf_counter()
    for k in range(loop):
        reg.fit(P[k], Q[k], w)
    t_plugin = time.perf_counter() - t
    print(f"registrations, batched kabsch ({batch}):   {_rate(batch, t_batch)}")
    print(f"registrations, kabsch one at a time:      {_rate(loop, t_one)}")
    print(f"registrations, svd plugin fit per frame:  {_rate(loop, t_plugin)}")
    print(f"  ratio batched / one at a time: {(batch / t_batch) / (loop / t_one):.1f}x (kernel), "
          f"{(batch / t_batch) / (loop / t_plugin):.1f}x (plugin)")


def bench_triangulation(station, frames: int) -> None:
    X = station.camera_xyz
    uv, _ = project_stereo(station.calibration, X)
    rng = np.random.default_rng(1)
    noisy = uv + 0.003 * rng.standard_normal((frames,) + uv.shape)
    t = time.perf_counter()
    triangulate_batch(station.calibration, noisy, 0.003)
    t_batch = time.perf_counter() - t
    tri = EpipolarTriangulator()
    n = len(X)
    sig = np.full((n, 2), 0.003)
    loop = min(frames, 300)
    sets = [
        StereoCentroids(k, CentroidSet("upper", k, noisy[k, :, :2], sig, np.ones(n), np.ones(n), np.ones(n)),
                        CentroidSet("lower", k, noisy[k, :, 2:], sig, np.ones(n), np.ones(n), np.ones(n)))
        for k in range(loop)
    ]
    t = time.perf_counter()
    for s in sets:
        tri.triangulate(s, station.calibration)
    t_plugin = time.perf_counter() - t
    linear = linearised_triangulation(station.calibration, uv, 0.003)
    t = time.perf_counter()
    linear(noisy - uv)
    t_lin = time.perf_counter() - t
    print(f"points, batched triangulation ({frames * n}): {_rate(frames * n, t_batch)}")
    print(f"points, linearised triangulation ({frames * n}): {_rate(frames * n, t_lin)}  "
          f"({t_batch / t_lin:.0f}x the batched kernel)")
    print(f"points, epipolar plugin per frame ({loop * n}):  {_rate(loop * n, t_plugin)}  "
          f"(matching included)")
    print(f"  ratio: {(frames * n / t_batch) / (loop * n / t_plugin):.1f}x")


def bench_monte_carlo(station, trials: int, full_trials: int) -> None:
    model = camera_model(station)
    F = station.frames
    t = time.perf_counter()
    simulate_sessions(station, max(trials // F, 2), np.random.default_rng(2), model)
    t_lin = time.perf_counter() - t
    t = time.perf_counter()
    simulate_sessions(station, max(full_trials // F, 2), np.random.default_rng(2), model, triangulation="full")
    t_full = time.perf_counter() - t
    n_lin, n_full = max(trials // F, 2) * F, max(full_trials // F, 2) * F
    # The registration alone, on the same number of trials (the controls of every trial).
    T = len(station.target_ids)
    X = project_stereo(station.calibration, station.camera_xyz)[0]
    P = station.camera_xyz[T:] + 0.001 * np.random.default_rng(3).standard_normal((n_lin,) + station.control_xyz.shape)
    Q = station.to_global(station.control_xyz)
    t = time.perf_counter()
    for start in range(0, n_lin, 40000):
        kabsch(P[start : start + 40000], np.broadcast_to(Q, P[start : start + 40000].shape), np.ones(len(Q)))
    t_reg = time.perf_counter() - t
    del X
    print(f"Monte Carlo, linearised triangulation: {n_lin:,} trials in {t_lin:.2f} s ({n_lin / t_lin:,.0f} /s; "
          f"{len(station.camera_xyz)} points per trial)")
    print(f"Monte Carlo, full triangulation per trial: {n_full:,} trials in {t_full:.2f} s ({n_full / t_full:,.0f} /s)")
    print(f"  ratio: {(n_lin / t_lin) / (n_full / t_full):.1f}x; the Kabsch registrations alone take {t_reg:.2f} s "
          f"of the {t_lin:.2f} s ({100 * t_reg / t_lin:.0f} %)")


def bench_sweep(station, sessions: int) -> None:
    t = time.perf_counter()
    run_sweeps(station, route="analytic")
    t_cold = time.perf_counter() - t
    t = time.perf_counter()
    doc = run_sweeps(station, route="analytic")
    t_an = time.perf_counter() - t
    points = sum(len(s["points"]) for s in doc["sweeps"].values())
    print(f"default sweep, analytic: {points} design points in {t_an:.2f} s "
          f"({t_cold:.2f} s cold: centroid bounds computed and cached)")
    t = time.perf_counter()
    run_sweeps(station, sessions=sessions)
    t_mc = time.perf_counter() - t
    registrations = points * sessions * station.frames
    print(f"default sweep, both routes, {sessions} sessions x {station.frames} frames per point: {t_mc:.1f} s, "
          f"{registrations:,} simulated registrations ({registrations / t_mc:,.0f} /s, triangulation included)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=100000)
    parser.add_argument("--loop", type=int, default=5000)
    parser.add_argument("--frames", type=int, default=5000, help="frames for the triangulation benchmark")
    parser.add_argument("--sweep-sessions", type=int, default=300)
    parser.add_argument("--trials", type=int, default=1_000_000, help="Monte Carlo trials, linearised route")
    parser.add_argument("--full-trials", type=int, default=50_000, help="Monte Carlo trials, full triangulation")
    args = parser.parse_args()
    station = load_station(EXAMPLE)
    bench_registration(args.batch, args.loop)
    bench_triangulation(station, args.frames)
    bench_monte_carlo(station, args.trials, args.full_trials)
    bench_sweep(station, args.sweep_sessions)
    return 0


if __name__ == "__main__":
    sys.exit(main())
