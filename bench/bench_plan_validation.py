"""Validation of ``crossfield plan``'s predictions against full-simulator sessions.

Run on demand (slow: every session renders its images and runs the whole
pipeline, ~2 s per 10-pair session on this machine)::

    .venv/bin/python bench/bench_plan_validation.py [--sessions 100] [--frames 10] [--json out.json]
    .venv/bin/python bench/bench_plan_validation.py --efficiency   # centroid RMS / CRB, the rendered bias
    .venv/bin/python bench/bench_plan_validation.py --record-sessions LOG [--only K] [--first-seed S]
    .venv/bin/python bench/bench_plan_validation.py --sessions-from LOG_OR_JSON   # new predictions, old sessions
    .venv/bin/python bench/bench_plan_validation.py --split LOG [--only K]        # CMM part / camera part

For each design point (the paper's station, table3, and the station with a
more precise arm) it predicts the session uncertainty of every characteristic
by both routes (``crossfield.planning.predict``), then runs ``--sessions``
sessions with crossfield's runner and the simulator source (record=False,
new noise seed per session, the simulated ROMER arm on a pseudo-terminal), and
compares the RMS of the session errors (measured - true) with the prediction:
``ratio = predicted / RMS``. With n sessions the RMS itself is uncertain by
about 1 / sqrt(2 n) (7 % for n = 100). ``--efficiency`` measures the
``weighted`` centroid's RMS scatter over rendered frames against the
Cramér-Rao bound (the station's ``centroid_efficiency``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.config import parse_config  # noqa: E402
from crossfield.planning.routes import camera_model, predict  # noqa: E402
from crossfield.planning.station import PLANNED_STAGES, station_from_scenario  # noqa: E402
from crossfield.plugins.acquire_simulator import SimulatorSource  # noqa: E402
from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.chain.runner import run_session  # noqa: E402
from crossfield.types import StereoFrame  # noqa: E402

#: The romer-serial reference plugin's default stated sigma (mm per coordinate).
ROMER_STATED_SIGMA_MM = 0.01

DESIGN_POINTS = (
    ("paper station", "station", 0.01),
    ("table3", "table3", 0.01),
    ("station, arm 0.003 mm", "station", 0.003),
)


#: The stages the planner's defaults model (docs/planning.md): the sessions it is validated on,
#: not the session defaults since issue 11 (modelfit, ml).
STAGES = {stage: {"plugin": plugin} for stage, plugin in PLANNED_STAGES.items()}


def run_sessions(scenario: str, arm_sigma: float, frames: int, sessions: int, out: str,
                 log: Path | None = None, label: str = "", first_seed: int = 1001) -> dict[str, list[float]]:
    """Session errors (measured - true, mm) per characteristic; with ``log``, each session's errors
    are appended to it as one JSON line ``{"design_point", "seed", "errors": {name: mm}}`` as it ends."""
    pm = make_plugin_manager()
    errors: dict[str, list[float]] = {}
    for seed in range(first_seed - 1000, first_seed - 1000 + sessions):
        data = {
            "session": {"output_dir": out, "name": f"{scenario}-{arm_sigma}-{seed}", "record": False, "rerun": False},
            "acquire": {"plugin": "simulator", "scenario": scenario, "frames": frames, "seed": 1000 + seed,
                        "arm_sigma_mm": arm_sigma},
            "reference": {"plugin": "romer-serial", "port": "simulator"},
            **STAGES,
        }
        summary = run_session(parse_config(data, "<validation>"), pm)
        session = {c.name: float(c.error_mm) for c in summary.characteristics
                   if c.error_mm is not None and c.n == frames}
        for name, e in session.items():
            errors.setdefault(name, []).append(e)
        if log is not None:
            with log.open("a") as f:
                f.write(json.dumps({"design_point": label, "scenario": scenario, "arm_sigma_mm": arm_sigma,
                                    "frames": frames, "seed": 1000 + seed, "errors": session}) + "\n")
    return errors


def _stats(errors: dict[str, list[float]]) -> dict[str, dict]:
    return {name: {"sessions": len(e), "rms_error_mm": float(np.sqrt(np.mean(np.square(e)))),
                   "mean_error_mm": float(np.mean(e)), "std_error_mm": float(np.std(e, ddof=1))}
            for name, e in errors.items() if len(e) > 1}


def recorded_stats(path: Path, label: str) -> dict[str, dict]:
    """Session statistics of design point ``label`` from FILE: a JSON-lines log of
    ``--record-sessions`` (one line per session) or the ``--json`` rows of an earlier run."""
    text = path.read_text()
    if text.lstrip().startswith("["):
        return {r["characteristic"]: r for r in json.loads(text) if r["design_point"] == label}
    errors: dict[str, list[float]] = {}
    seen: set[int] = set()
    for line in text.splitlines():
        if not line.strip():
            continue
        rec = json.loads(line)
        if rec["design_point"] != label or rec["seed"] in seen:
            continue
        seen.add(rec["seed"])
        for name, e in rec["errors"].items():
            errors.setdefault(name, []).append(float(e))
    return _stats(errors)


def efficiency(frames: int = 40) -> None:
    """RMS scatter of the weighted centroid over rendered frames / its CRB (per axis, per target)."""
    from crossfield.chain.registry import implementations
    from crossfield.simulator.scenarios import build_scene

    scene = build_scene("station")
    station = station_from_scenario("station", centroid_efficiency=1.0)  # the rendered bias
    model = camera_model(station)
    ids = station.target_ids + station.control_ids
    pm = make_plugin_manager()
    centroider = implementations(pm, "centroid")["weighted"].create({}, "<bench>")
    rng = np.random.default_rng(5)
    true = {cam: scene.true_blob_centres(cam) for cam in ("upper", "lower")}
    errs: dict[str, list[np.ndarray]] = {"upper": [], "lower": []}
    for k in range(frames):
        pair = scene.render_pair(k, rng)
        for cam in ("upper", "lower"):
            found = centroider.extract(pair.image(cam), cam, k)
            uv = np.asarray(found.uv)
            row = []
            for tid in ids:
                d = np.linalg.norm(uv - true[cam][tid], axis=1)
                row.append(uv[np.argmin(d)] - true[cam][tid])
            errs[cam].append(np.array(row))
    for j, cam in enumerate(("upper", "lower")):
        e = np.array(errs[cam])  # (frames, M, 2)
        scatter = e.std(axis=0, ddof=1)  # per target, per axis
        bias = e.mean(axis=0)
        crb = model.crb_sigma_uv[:, 2 * j : 2 * j + 2]
        print(f"{cam}: RMS scatter / CRB = {np.sqrt(np.mean(scatter**2)) / np.sqrt(np.mean(crb**2)):.3f}  "
              f"(scatter {np.sqrt(np.mean(scatter**2)):.5f} px, CRB {np.sqrt(np.mean(crb**2)):.5f} px, "
              f"RMS bias {np.sqrt(np.mean(bias**2)):.5f} px)")
    bias_check(scene, station, model, centroider, ids, 2 * frames)


def bias_check(scene, station, model, centroider, ids, frames: int) -> None:
    """The planner's rendered bias (one antithetic pair) against the mean centroid of ``frames``
    noisy frames of the simulator's own images (frames/2 other antithetic pairs, each frame a valid
    noisy image; the pairs cancel the noise's first-order part, so the mean is precise)."""
    from crossfield.planning.image_bias import antithetic_pair

    rng = np.random.default_rng(11)
    for j, cam in enumerate(("upper", "lower")):
        expected = model.uv[:, 2 * j : 2 * j + 2]
        found = []
        for _ in range(max(frames // 2, 1)):
            for image in antithetic_pair(scene.clean_images[cam], scene.sensor, rng):
                uv = np.asarray(centroider.extract(image, cam, 0).uv)
                found.append(np.array([uv[np.argmin(np.linalg.norm(uv - e, axis=1))] for e in expected]))
        mean = np.mean(found, axis=0) - expected
        planner = model.bias_uv[:, 2 * j : 2 * j + 2]
        print(f"{cam}: rendered bias - mean centroid bias of {len(found)} noisy frames: "
              f"RMS {np.sqrt(np.mean((planner - mean) ** 2)):.5f} px (the bias: RMS {np.sqrt(np.mean(mean**2)):.5f} px)")


class NoiseFreeSource(SimulatorSource):
    """The simulator source with every pair the scene's clean image (rounded to DN): the
    session's errors are then the fixed bias plus what the arm's noise does. ``scene``: a built
    scene to share (its images are rendered once for all the sessions)."""

    def __init__(self, scene, **options):
        super().__init__(**options)
        self.scene = scene

    def frames(self):
        clean = {c: np.rint(self.scene.clean_images[c]).astype(np.uint16) for c in ("upper", "lower")}
        for k in range(self.n_frames):
            yield StereoFrame(k, 1_700_000_000_000_000_000 + k, clean["upper"], clean["lower"],
                              self.scene.sensor.bit_depth)


def split(k: int, log: Path, mc_sessions: int) -> None:
    """The recorded sessions of design point k split into their CMM part and their camera part.

    For each seed in ``log`` a session of noise-free images with the same arm draws (the arm's
    noise comes from the seed alone) gives ``bias_nf + cmm part``; a session with an exact arm gives
    ``bias_nf``. The camera part of a recorded session is its error minus its noise-free twin's.
    Compared with the Monte Carlo's spread (std_mm) with the camera noise off (CMM part) and with
    the arm's noise off (camera part)."""
    from crossfield.simulator.scenarios import build_scene

    label, scenario, arm = DESIGN_POINTS[k]
    full: dict[int, dict] = {}
    for line in log.read_text().splitlines():
        rec = json.loads(line) if line.strip() else None
        if rec and rec["design_point"] == label:
            full[rec["seed"]] = rec["errors"]
    pm = make_plugin_manager()
    scenes = {a: build_scene(scenario, arm_sigma_mm=a) for a in (arm, 0.0)}

    def session(seed: int, a: float, out: str) -> dict[str, float]:
        data = {"session": {"output_dir": out, "name": f"split-{seed}", "record": False, "rerun": False},
                "acquire": {"plugin": "simulator", "scenario": scenario, "frames": 1, "seed": seed, "arm_sigma_mm": a},
                "reference": {"plugin": "romer-serial", "port": "simulator"}, **STAGES}
        source = NoiseFreeSource(scenes[a], scenario=scenario, frames=1, seed=seed, arm_sigma_mm=a)
        summary = run_session(parse_config(data, "<split>"), pm, source=source)
        return {c.name: float(c.error_mm) for c in summary.characteristics}

    with tempfile.TemporaryDirectory() as out:
        bias_nf = session(1, 0.0, out)
        cmm = {seed: session(seed, arm, out) for seed in sorted(full)}
    station = dataclasses.replace(station_from_scenario(scenario, arm_sigma_mm=arm),
                                  weight_cmm_sigma_mm=ROMER_STATED_SIGMA_MM)
    mc_cmm = predict(dataclasses.replace(station, centroid_efficiency=1e-6), sessions=mc_sessions, route="monte-carlo")
    mc_cam = predict(dataclasses.replace(station, cmm_sigma_mm=0.0), sessions=mc_sessions, route="monte-carlo")
    print(f"# {label}: {len(cmm)} recorded sessions split (CMM part: noise-free images, the same arm draws)")
    print(f"{'char':9s} {'CMM RMS':>9s} {'MC std':>9s} {'ratio':>6s}   {'cam std':>9s} {'MC std':>9s} {'ratio':>6s}")
    for a, b in zip(mc_cmm["characteristics"], mc_cam["characteristics"]):
        name = a["name"]
        part_cmm = np.array([cmm[s][name] - bias_nf[name] for s in cmm])
        part_cam = np.array([full[s][name] - cmm[s][name] for s in cmm])
        rc, sc = np.sqrt(np.mean(part_cmm**2)), part_cam.std(ddof=1)
        print(f"{name:9s} {rc:9.5f} {a['monte_carlo']['std_mm']:9.5f} {rc / max(a['monte_carlo']['std_mm'], 1e-12):6.3f}"
              f"   {sc:9.5f} {b['monte_carlo']['std_mm']:9.5f} {sc / b['monte_carlo']['std_mm']:6.3f}", flush=True)


def _table(rows: list[dict]) -> None:
    print(f"{'design point':24s} {'char':9s} {'n':>4s} {'RMS err':>9s} {'mean':>9s} {'bias MC':>9s} {'u MC':>9s} "
          f"{'u an.':>9s} {'MC/RMS':>7s} {'an/RMS':>7s} {'cam %':>6s}")
    for r in rows:
        print(f"{r['design_point']:24s} {r['characteristic']:9s} {r['sessions']:4d} {r['rms_error_mm']:9.5f} "
              f"{r['mean_error_mm']:9.5f} {r.get('predicted_bias_mm', float('nan')):9.5f} "
              f"{r['monte_carlo_u_mm']:9.5f} {r['analytic_u_mm']:9.5f} "
              f"{r['ratio_mc']:7.3f} {r['ratio_analytic']:7.3f} {100 * r['camera_share']:6.1f}", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=100)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--mc-sessions", type=int, default=4000)
    parser.add_argument("--json", metavar="FILE")
    parser.add_argument("--efficiency", action="store_true")
    parser.add_argument("--only", type=int, help="run only design point k (0-based)")
    parser.add_argument("--sessions-from", metavar="FILE",
                        help="do not run sessions: compare new predictions with the session errors in FILE "
                        "(a --record-sessions log, or a --json output of an earlier run)")
    parser.add_argument("--first-seed", type=int, default=1001, help="noise seed of the first session (1001)")
    parser.add_argument("--record-sessions", metavar="FILE",
                        help="only run the sessions (no prediction), appending each session's errors to FILE "
                        "(JSON lines) as it ends")
    parser.add_argument("--split", metavar="LOG",
                        help="split the sessions of design point --only (default 2) recorded in LOG (a "
                        "--record-sessions log) into their CMM and camera parts")
    args = parser.parse_args()
    if args.split:
        split(2 if args.only is None else args.only, Path(args.split), args.mc_sessions)
        return 0
    if args.efficiency:
        efficiency()
        return 0
    if args.record_sessions:
        order = [args.only] if args.only is not None else range(len(DESIGN_POINTS))
        with tempfile.TemporaryDirectory() as out:
            for k in order:
                label, scenario, arm = DESIGN_POINTS[k]
                t0 = time.perf_counter()
                run_sessions(scenario, arm, args.frames, args.sessions, out, Path(args.record_sessions), label,
                             args.first_seed)
                print(f"# {label}: {args.sessions} sessions in {time.perf_counter() - t0:.0f} s", flush=True)
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as out:
        for k, (label, scenario, arm) in enumerate(DESIGN_POINTS):
            if args.only is not None and k != args.only:
                continue
            # The sessions' romer-serial reference states its default sigma_mm (0.01 mm) whatever the
            # simulated arm's noise: the runner's registration weights use that.
            station = dataclasses.replace(station_from_scenario(scenario, arm_sigma_mm=arm, frames=args.frames),
                                          weight_cmm_sigma_mm=ROMER_STATED_SIGMA_MM)
            prediction = predict(station, sessions=args.mc_sessions)
            t0 = time.perf_counter()
            if args.sessions_from:
                stats = recorded_stats(Path(args.sessions_from), label)
            else:
                stats = _stats(run_sessions(scenario, arm, args.frames, args.sessions, out,
                                            first_seed=args.first_seed))
            seconds = time.perf_counter() - t0
            for c in prediction["characteristics"]:
                if c["name"] not in stats:
                    continue
                st = stats[c["name"]]
                rms = st["rms_error_mm"]
                rows.append({
                    "design_point": label, "characteristic": c["name"], "sessions": st["sessions"],
                    "rms_error_mm": rms, "mean_error_mm": st["mean_error_mm"], "std_error_mm": st["std_error_mm"],
                    "predicted_bias_mm": c["monte_carlo"]["bias_mm"],
                    "analytic_u_mm": c["analytic"]["u_mm"], "monte_carlo_u_mm": c["monte_carlo"]["u_mm"],
                    "ratio_mc": c["monte_carlo"]["u_mm"] / rms, "ratio_analytic": c["analytic"]["u_mm"] / rms,
                    "camera_share": c["analytic"]["u_camera_frame_mm"] ** 2 / args.frames / c["analytic"]["u_mm"] ** 2,
                })
            if args.sessions_from:
                print(f"# {label}: compared with the sessions recorded in {args.sessions_from}", flush=True)
            else:
                print(f"# {label}: {args.sessions} sessions in {seconds:.0f} s", flush=True)
            _table([r for r in rows if r["design_point"] == label])
    print("# all design points")
    _table(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
