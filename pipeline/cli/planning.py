"""``crossfield plan`` and ``crossfield crb`` (``docs/planning.md``, ``docs/precision.md``)."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from crossfield.batch.engine import add_engine_flags, client, engine_from_args
from crossfield.cli.common import Command
from crossfield.errors import ConfigError

__all__ = ["COMMANDS"]


def add_plan_arguments(parser: argparse.ArgumentParser) -> None:
    add_station_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the prediction as JSON")
    parser.add_argument("--route", choices=("both", "analytic", "monte-carlo"), default="both")
    parser.add_argument("--sessions", type=int, default=2000, help="Monte Carlo sessions (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help="Monte Carlo seed")
    parser.add_argument("--sweep", action="store_true", help="run the layout sweeps (n controls, focal length, "
                        "working distance, baseline, control spread, CMM sigma)")
    parser.add_argument("--sweep-sessions", type=int, default=300, help="Monte Carlo sessions per sweep point")
    parser.add_argument("--target-mm", type=float, metavar="U",
                        help="recommend the smallest layout whose largest expanded uncertainty is <= U (mm)")
    parser.add_argument("-o", "--output-dir", metavar="DIR",
                        help="write plan.html (plots) and plan.json there (default: plan-<station>/ with --sweep)")
    add_engine_flags(parser)  # where the sweeps run: in this process unless --scheduler or --workers


def add_crb_arguments(parser: argparse.ArgumentParser) -> None:
    add_station_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the bounds as JSON")


def add_station_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("station", nargs="?", metavar="STATION.toml", help="station description (TOML)")
    parser.add_argument("--scenario", help="a built-in simulator scenario instead: station or table3")
    parser.add_argument("--cmm-sigma-mm", type=float, help="override the CMM sigma (mm)")
    parser.add_argument("--frames", type=int, help="override the stereo pairs per session")


def _station(args: argparse.Namespace):
    from crossfield.cli.inputs import require
    from crossfield.planning.station import load_station, station_from_scenario
    import dataclasses

    if bool(args.station) == bool(args.scenario):
        raise ConfigError("give a station file or --scenario NAME (one of them)")
    if args.station:
        require(args.station, ("other",), args.command, "a station file (TOML)", recording=False)
    station = load_station(args.station) if args.station else station_from_scenario(args.scenario)
    if args.cmm_sigma_mm is not None:
        if not args.cmm_sigma_mm >= 0:
            raise ConfigError(f"--cmm-sigma-mm must be >= 0, got {args.cmm_sigma_mm}")
        station = dataclasses.replace(station, cmm_sigma_mm=args.cmm_sigma_mm)
    if args.frames is not None:
        if args.frames < 1:
            raise ConfigError(f"--frames must be >= 1, got {args.frames}")
        station = dataclasses.replace(station, frames=args.frames)
    return station


def cmd_plan(args: argparse.Namespace) -> int:

    from crossfield.planning.report import write_report
    from crossfield.planning.routes import predict
    from crossfield.planning.sweeps import recommend, run_sweeps
    station = _station(args)
    if args.sessions < 2 or args.sweep_sessions < 2:
        raise ConfigError("--sessions and --sweep-sessions must be >= 2")
    t0 = time.perf_counter()
    prediction = predict(station, sessions=args.sessions, seed=args.seed, route=args.route)
    sweeps = recommendation = None
    if args.sweep:
        options = dict(sessions=args.sweep_sessions, seed=args.seed, route=args.route)
        engine = engine_from_args(args)
        if engine is not None:  # the sweeps on Dask: an embedded LocalCluster or a scheduler
            with client(engine.scheduler, engine.workers, memory_limit=engine.memory_limit,
                        dashboard_address=":0") as dask_client:
                sweeps = run_sweeps(station, **options, client=dask_client)
        else:
            sweeps = run_sweeps(station, **options)
    elif engine_from_args(args) is not None:
        raise ConfigError("--scheduler and --workers apply to --sweep")
    if args.target_mm is not None:
        try:
            recommendation = recommend(station, args.target_mm, sessions=args.sessions, seed=args.seed)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    seconds = time.perf_counter() - t0
    out_dir = args.output_dir or (f"plan-{station.name.replace(' ', '-')}" if args.sweep else None)
    written = write_report(out_dir, prediction, sweeps, recommendation) if out_dir else None
    if args.json:
        doc = {**prediction, "recommendation": recommendation}
        if sweeps:
            doc["sweeps"] = sweeps
        print(json.dumps(doc, indent=2))
        return 0
    k = prediction["coverage_factor"]
    print(f"station: {station.name}  ({len(station.control_ids)} controls, f = {station.focal_length_mm:g} mm, "
          f"baseline {station.baseline_mm:.1f} mm, distance {station.working_distance_mm:.0f} mm, "
          f"CMM sigma {station.cmm_sigma_mm:g} mm, {station.frames} frames per session)")
    print(f"centroid sigma {prediction['centroid_sigma_px']:.5f} px (CRB {prediction['centroid_crb_px']:.5f} px)")
    print(f"fixed centroid bias ({prediction['bias_model']}) {prediction['centroid_bias_rms_px']:.5f} px RMS")
    print(f"{'characteristic':16s} {'u analytic':>11s} {'u MC':>9s} {'U (k=' + format(k, 'g') + ')':>9s}  mm")
    for c in prediction["characteristics"]:
        an = c.get("analytic", {}).get("u_mm")
        mc = c.get("monte_carlo", {}).get("u_mm")
        print(f"{c['name']:16s} {an if an is not None else float('nan'):11.5f} "
              f"{mc if mc is not None else float('nan'):9.5f} {c['predicted_U_mm']:9.5f}")
    if recommendation:
        print(f"recommendation: {recommendation['reason']}")
    if written:
        print(f"wrote {written[0]} and {written[1]}")
    print(f"({seconds:.1f} s)", file=sys.stderr)
    return 0


def cmd_crb(args: argparse.Namespace) -> int:
    from crossfield.planning.routes import camera_model
    from crossfield.precision.chain import chain_bound
    station = _station(args)
    model = camera_model(station)
    T = len(station.target_ids)
    C = len(station.control_ids)
    bound = chain_bound(station.calibration, model.X, model.crb_sigma_uv, np.arange(T, T + C),
                        np.full(C, station.cmm_sigma_mm), station.R_global_camera, station.t_global_camera)
    ids = station.target_ids + station.control_ids
    doc = {
        "station": station.name,
        "points": [
            {"id": pid, "role": "target" if k < T else "control",
             "centroid_crb_px": bound.centroid_sigma_px[k].tolist(),
             "camera_sigma_mm": bound.camera_sigma_mm[k].tolist(),
             "camera_cov_mm2": bound.camera_cov[k].tolist(),
             "global_cov_mm2": bound.global_cov[k].tolist(),
             "global_rms_mm": float(bound.global_rms_mm[k])}
            for k, pid in enumerate(ids)
        ],
        "registration": {"sigma_rad_mm": bound.registration_sigma.tolist(), "cov": bound.registration_cov.tolist(),
                         "g_bar_mm": bound.g_bar.tolist()},
        "note": "per frame; Cramér-Rao bounds (efficient centroid, ML triangulation and registration)",
    }
    if args.json:
        print(json.dumps(doc, indent=2))
        return 0
    print(f"Cramér-Rao bound, one frame: {station.name}")
    print(f"{'point':6s} {'role':8s} {'centroid px (u,v upper)':>24s} {'camera sigma x y z (mm)':>30s} {'global rms':>11s}")
    for p in doc["points"]:
        s = p["camera_sigma_mm"]
        print(f"{p['id']:6s} {p['role']:8s} {p['centroid_crb_px'][0]:12.5f} {p['centroid_crb_px'][1]:11.5f} "
              f"{s[0]:10.5f} {s[1]:9.5f} {s[2]:9.5f} {p['global_rms_mm']:11.5f}")
    r = bound.registration_sigma
    print(f"registration: sigma(theta) = {', '.join(f'{v:.2e}' for v in r[:3])} rad, "
          f"sigma(t) = {', '.join(f'{v:.5f}' for v in r[3:])} mm (about the control centroid)")
    return 0


COMMANDS: tuple[Command, ...] = (
    Command(
        "plan", add_plan_arguments, cmd_plan,
        help="predict a station's uncertainties before building it (layout sweeps, Fig. 3)",
        description="Predict the session uncertainty of each cross-field characteristic of a station by two "
        "routes (analytic: Cramér-Rao bound + Fitzpatrick TRE; Monte Carlo through the pipeline's kernels), "
        "optionally sweep the layout parameters and recommend the smallest layout reaching a target U.",
    ),
    Command(
        "crb", add_crb_arguments, cmd_crb,
        help="the Cramér-Rao bound of the chain for a station (centroid, camera point, registration, target point)",
    ),
)
