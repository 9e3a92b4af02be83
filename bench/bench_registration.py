"""Per-frame cost of correspondence, registration and measurement.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_registration.py [--scenes 300] [--repeat 10]

Measures, on this machine, the best of ``--repeat`` runs per random scene:

* ``match_control_points`` with 8 controls and 20 camera points (8 controls,
  2 targets, 10 strays, shuffled, 0.05 mm noise) - budget < 1 ms per frame;
  the same with 40 strays and a 1 mm tolerance (a hard case);
* each registered "register" implementation on 8 pairs;
* ``fit_cylinder_axis`` on 12 probes (once per session) and ``fit_line``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.correspondence import match_control_points  # noqa: E402
from crossfield.geometry import fit_cylinder_axis, fit_line, perpendicular_basis  # noqa: E402
from crossfield.registry import implementations, make_plugin_manager  # noqa: E402

IDS = [f"C{k + 1}" for k in range(8)]


def best_of(func, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return min(times)


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
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    for n_extra, tol in ((12, 0.5), (40, 1.0)):
        times = []
        for _ in range(args.scenes):
            camera, G = scene(rng, n_extra)
            times.append(best_of(lambda: match_control_points(camera, G, IDS, tolerance_mm=tol), args.repeat))
        report(f"correspondence: 8 controls, {8 + n_extra} camera points, tol {tol} mm", times)

    pm = make_plugin_manager()
    for name, impl in sorted(implementations(pm, "register").items()):
        registrar = impl.create({})
        times = []
        for _ in range(args.scenes):
            P = rng.uniform(-80, 80, (8, 3))
            Q = P @ Rotation.random(random_state=rng).as_matrix().T + rng.normal(0, 0.02, (8, 3))
            times.append(best_of(lambda: registrar.fit(P, Q), args.repeat))
        report(f"register {name!r}: 8 pairs", times)

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
