"""Per-frame cost of correspondence, registration and measurement.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_registration.py [--scenes 300] [--repeat 10]

Measures, on this machine, the best of ``--repeat`` runs per random scene:

* ``match_control_points`` with 8 controls and 20 camera points (8 controls,
  2 targets, 10 strays, shuffled, 0.05 mm noise) - budget < 1 ms per frame;
  the same with 40 strays and a 1 mm tolerance (a hard case);
* each registered "register" implementation on 8 pairs, and its per-solve
  time as a ratio to a plain numpy Kabsch (SVD, no validation) measured in
  the same run;
* the batched kernel :func:`crossfield.rigid.kabsch` on ``--batch``
  registrations of 8 points at once, with each rotation route ("quaternion",
  the closed form, and "svd"), in us per registration and registrations per
  second, as ratios to the same registrations solved one at a time (the
  kernel called per registration, and the plain numpy Kabsch in a loop);
* ``fit_cylinder_axis`` on 12 probes (once per session) and ``fit_line``.

The machine is shared: absolute times vary with the load; the ratios, taken
in one run, are the figures to compare. CPU time (``time.process_time``) is
reported beside wall time for the batched kernel.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield import rigid  # noqa: E402
from crossfield.chain.correspondence import match_control_points  # noqa: E402
from crossfield.geometry import fit_cylinder_axis, fit_line, perpendicular_basis  # noqa: E402
from crossfield.chain.registry import implementations, make_plugin_manager  # noqa: E402

IDS = [f"C{k + 1}" for k in range(8)]


def best_of(func, repeat: int, clock=time.perf_counter) -> float:
    times = []
    for _ in range(repeat):
        start = clock()
        func()
        times.append(clock() - start)
    return min(times)


def plain_kabsch(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The baseline: textbook unweighted Kabsch with numpy, no validation, no mirror fit."""
    p_bar, q_bar = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - p_bar).T @ (Q - q_bar))
    d = 1.0 if np.linalg.det(Vt.T @ U.T) > 0 else -1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, q_bar - R @ p_bar


def registration_batch(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n registrations (n, 8, 3) mm: control layouts, random poses, 0.02 mm noise."""
    low, high = np.array([-80.0, -20.0, 382.0]), np.array([80.0, 70.0, 418.0])
    P = rng.uniform(low, high, (n, 8, 3))
    R = Rotation.random(n, random_state=rng).as_matrix()
    Q = np.einsum("bij,bnj->bni", R, P) + rng.uniform(-800, 800, (n, 1, 3)) + rng.normal(0, 0.02, P.shape)
    return P, Q


def bench_register_implementations(rng: np.random.Generator, scenes: int, repeat: int) -> None:
    """Each "register" implementation against the plain numpy Kabsch, per solve, same scenes."""
    pm = make_plugin_manager()
    registrars = {name: impl.create({}) for name, impl in sorted(implementations(pm, "register").items())}
    times: dict[str, list[float]] = {name: [] for name in ["plain numpy Kabsch", *registrars]}
    P_all, Q_all = registration_batch(rng, scenes)
    for P, Q in zip(P_all, Q_all):
        times["plain numpy Kabsch"].append(best_of(lambda: plain_kabsch(P, Q), repeat))
        for name, registrar in registrars.items():
            times[name].append(best_of(lambda: registrar.fit(P, Q), repeat))
    base = float(np.median(times["plain numpy Kabsch"]))
    for name, seconds in times.items():
        label = name if name == "plain numpy Kabsch" else f"register {name!r}: 8 pairs"
        print(f"{label:52s} median {np.median(seconds) * 1e3:7.3f} ms   "
              f"{np.median(seconds) / base:5.2f} x plain Kabsch")


def bench_batched_kabsch(rng: np.random.Generator, batch: int, repeat: int) -> None:
    """rigid.kabsch on a whole batch vs the same registrations one at a time."""
    P, Q = registration_batch(rng, batch)
    few = min(batch, 2000)  # one at a time: a sample is enough
    loops = max(1, repeat // 3)
    rows: dict[str, tuple[float, float | None]] = {}
    for method in ("quaternion", "svd"):
        wall = best_of(lambda: rigid.kabsch(P, Q, method=method), repeat)
        cpu = best_of(lambda: rigid.kabsch(P, Q, method=method), repeat, time.process_time)
        rows[f"rigid.kabsch batched, method={method!r}"] = (wall / batch, cpu / batch)
    for method in ("auto", "quaternion"):
        wall = best_of(lambda: [rigid.kabsch(P[k], Q[k], method=method) for k in range(few)], loops)
        rows[f"rigid.kabsch one at a time, method={method!r}"] = (wall / few, None)
    wall = best_of(lambda: [plain_kabsch(P[k], Q[k]) for k in range(few)], loops)
    rows["plain numpy Kabsch one at a time"] = (wall / few, None)
    base = rows["plain numpy Kabsch one at a time"][0]
    print(f"batched Kabsch: {batch} registrations of 8 points (one at a time: {few})")
    for label, (per, cpu) in rows.items():
        cpu_text = f"  cpu {cpu * 1e6:6.3f} us" if cpu is not None else " " * 17
        print(f"  {label:48s} {per * 1e6:8.3f} us/registration {1.0 / per:12,.0f} /s{cpu_text}"
              f"   {base / per:7.1f} x plain one at a time")
    fast = rows["rigid.kabsch batched, method='quaternion'"][0]
    svd = rows["rigid.kabsch batched, method='svd'"][0]
    single = rows["rigid.kabsch one at a time, method='auto'"][0]
    print(f"  batched closed form: {svd / fast:.2f} x the batched SVD's rate, "
          f"{single / fast:.0f} x the kernel's one at a time")


def scene(rng: np.random.Generator, n_extra: int):
    controls_c = np.column_stack([rng.uniform(-80, 80, 8), rng.uniform(-20, 70, 8), rng.uniform(382, 418, 8)])
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-800, 800, 3)
    extra = np.column_stack(
        [rng.uniform(-80, 80, n_extra), rng.uniform(-20, 70, n_extra), rng.uniform(380, 420, n_extra)]
    )
    camera = np.vstack([controls_c, extra]) + rng.normal(0, 0.05, (8 + n_extra, 3))
    return camera[rng.permutation(len(camera))], controls_c @ R.T + t


def report(label: str, seconds: list[float]) -> None:
    ms = np.array(seconds) * 1e3
    p90 = np.percentile(ms, 90)
    print(f"{label:52s} median {np.median(ms):7.3f} ms   p90 {p90:7.3f}   max {ms.max():7.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=300)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--batch", type=int, default=100_000, help="registrations in the batched Kabsch")
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    for n_extra, tol in ((12, 0.5), (40, 1.0)):
        times = []
        for _ in range(args.scenes):
            camera, G = scene(rng, n_extra)
            times.append(best_of(lambda: match_control_points(camera, G, IDS, tolerance_mm=tol), args.repeat))
        report(f"correspondence: 8 controls, {8 + n_extra} camera points, tol {tol} mm", times)

    bench_register_implementations(rng, args.scenes, args.repeat)
    bench_batched_kabsch(rng, args.batch, args.repeat)

    d = np.array([0.25, -0.30, 0.92]) / np.linalg.norm([0.25, -0.30, 0.92])
    e1, e2 = perpendicular_basis(d)
    probes = np.array([h * d + 18 * (np.cos(a) * e1 + np.sin(a) * e2)
                       for h in (-25, 0, 25) for a in np.radians([20, 80, 140, 200])])
    times = [best_of(lambda: fit_cylinder_axis(probes + rng.normal(0, 0.01, probes.shape), sigma_mm=0.01), 3)
             for _ in range(20)]
    report("fit_cylinder_axis: 12 probes (once per session)", times)
    line = np.outer(np.linspace(-40, 40, 8), d)
    times = [
        best_of(lambda: fit_line(line + rng.normal(0, 0.01, line.shape)), args.repeat) for _ in range(50)
    ]
    report("fit_line: 8 probes", times)


if __name__ == "__main__":
    main()
