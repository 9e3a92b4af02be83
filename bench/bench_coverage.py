"""Coverage of the stated expanded uncertainty over simulated sessions (on demand, not a test).

    .venv/bin/python bench/bench_coverage.py --scenario table3 --sessions 200 --jsonl cov/table3.jsonl
    .venv/bin/python bench/bench_coverage.py --scenario station --arm-sigma 0.02 --stated-sigma 0.01
    .venv/bin/python bench/bench_coverage.py --scenario camera-limited --plugins weighted
    .venv/bin/python bench/bench_coverage.py --summarise cov/*.jsonl

Each session is a fresh simulator session (its own noise seed, ``--frames``
stereo pairs; the geometry is the scenario's, so each target's eccentricity is the
same bias in every session). For every characteristic with ground truth the bench
counts |error| <= U, |error| <= 2u and |error| <= u, and how often the residual chi-square
check warned (U = k u, k the Student-t factor of the budget's effective degrees of freedom,
``crossfield.uncertainty.dof``; ``within 2u`` is what k = 2 would cover; ``median k``). A calibrated U covers 95 %. Lengths of one session share their CMM
errors and are not independent: the table's +/- is the standard error of the
coverage from the spread of the per-session fractions (sessions are independent).

Defaults are the scenario's own: the arm's sigma (``DEFAULT_ARM_SIGMA_MM``), the
stated sigma = the arm's, and the plan with its targets' radius and tilt bound
stated for the eccentricity term (``[uncertainty] target_radius``, ``max_tilt_deg``:
2.5 mm / 20 deg on station and table3, 1.5 mm / 25 deg on camera-limited;
``--target-radius 0`` states none). ``--plugins default`` runs the built-in
stages (centroid ``modelfit``, the ``epipolar`` eccentricity correction with its
residual covariance, register ``ml``) and states ``eccentricity_corrected = true``
in the plan; ``--plugins weighted`` the defaults before issue 11 (``weighted``,
``svd``: the eccentricity uncorrected, its term at full size) with
``eccentricity_corrected = false``. Results as one JSON line per
session (``--jsonl``, appended: a run stopped early still counts) and a table.

Columns beyond coverage: ``U P90/P10``, the spread of U between the sessions of one
design point (per characteristic the 90th over the 10th percentile of its U, the
median over the characteristics); ``camera Type A / model``, the median over the
sessions of ``sqrt(s_cam^2)``, the shrunk ratio of the camera's standard deviation
its epipolar residuals show to the model's (``crossfield.uncertainty.type_a``).
``bench/run_coverage_all.py`` runs every case of docs/uncertainty.md in one process.

Speed: the scene of a scenario (geometry and its noise-free images, ~95 % of a
session's time when rendered afresh) is built once per process and shared by the
sessions (``--no-scene-cache`` renders it every session); the noise of each session
comes from its seed alone, so the sessions are the same either way.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.config import DEFAULT_PLUGINS, parse_config  # noqa: E402
from crossfield.chain.registry import make_plugin_manager  # noqa: E402
from crossfield.chain.runner import run_session  # noqa: E402
from crossfield.simulator import scenarios  # noqa: E402

#: Stage tables of the ``--plugins`` choices (the session config's stage sections).
PLUGINS = {
    "default": {},
    "weighted": {"centroid": {"plugin": "weighted"}, "register": {"plugin": "svd"}},
}
#: Centroid implementations that deliver edge conics, which the default ``epipolar``
#: triangulation uses to correct the eccentricity (``docs/triangulation.md``, step 5).
WITH_CONICS = ("modelfit",)


def eccentricity_corrected(plugins: str) -> bool:
    """Whether the ``--plugins`` choice corrects the eccentricity (its centroid gives conics)."""
    return PLUGINS[plugins].get("centroid", {}).get("plugin", DEFAULT_PLUGINS["centroid"]) in WITH_CONICS


#: The scenarios' targets: radius (mm) and largest tilt to the line of sight (deg).
TARGETS = {
    "station": (scenarios.TARGET_RADIUS_MM, 20.0),
    "table3": (scenarios.TARGET_RADIUS_MM, 20.0),
    "camera-limited": (scenarios.CL_TARGET_RADIUS_MM, scenarios.CL_MAX_TILT_DEG),
    # the mismatch scenarios' targets: their base's, each turned by a further ~2 deg RMS per session
    "mismatch-cmm": (scenarios.TARGET_RADIUS_MM, 25.0),
    "mismatch-camera": (scenarios.CL_TARGET_RADIUS_MM, scenarios.CL_MAX_TILT_DEG + 5.0),
    "mismatch-mixed": (scenarios.CL_TARGET_RADIUS_MM, scenarios.CL_MAX_TILT_DEG + 5.0),
}


def share_scenes() -> None:
    """Build each scenario's scene once per process: the simulator acquisition's
    ``build_scene`` memoised on its arguments (the scene is deterministic; render_pair
    and arm_probes take the session's noise from the rng they are given)."""
    from crossfield.plugins import acquire_simulator

    built: dict[tuple, object] = {}
    original = acquire_simulator.build_scene

    def build_scene(name: str = "station", **kwargs):
        key = (name, tuple(sorted(kwargs.items())))
        if key not in built:
            built[key] = original(name, **kwargs)
        return built[key]

    acquire_simulator.build_scene = build_scene


def plan_file(out: Path, scenario: str, target_radius: float, max_tilt: float, corrected: bool) -> str:
    """The scenario's own plan with the eccentricity of its circle targets stated
    (``[uncertainty] target_radius``, ``max_tilt_deg``, ``eccentricity_corrected``);
    "" = the scenario's plan as it is."""
    if not target_radius and not corrected:
        return ""
    path = out / f"{scenario}-plan.toml"
    text = scenarios.build_scene(scenario).plan.text
    path.write_text(
        text + f"\n[uncertainty]\ntarget_radius = {target_radius}\nmax_tilt_deg = {max_tilt}\n"
        f"eccentricity_corrected = {'true' if corrected else 'false'}\n",
        encoding="utf-8",
    )
    return str(path)


def one_session(out: Path, scenario: str, seed: int, frames: int, arm_sigma: float, stated: float, pm,
                plan: str = "", plugins: str = "default", station_seed: int | None = None) -> dict:
    """One simulator session through ``run_session``: per characteristic its error, u, U and
    the budget's eccentricity contribution (mm)."""
    config = parse_config(
        {
            "session": {
                "output_dir": str(out), "name": f"s{seed}", "record": False, "rerun": False, "plan": plan,
            },
            "acquire": {"plugin": "simulator", "scenario": scenario, "frames": frames, "seed": seed,
                        "arm_sigma_mm": arm_sigma,
                        **({} if station_seed is None else {"station_seed": station_seed})},
            "reference": {"plugin": "romer-serial", "port": "simulator", "sigma_mm": stated},
            "report": {"plugin": "json"},
            **PLUGINS[plugins],
        },
        "<bench_coverage>",
    )
    summary = run_session(config, pm)
    check = summary.aggregate.consistency
    rows = [
        {"name": c.name, "error_mm": c.error_mm, "u_mm": c.uncertainty_mm, "U_mm": c.expanded_uncertainty_mm,
         "u_ecc_mm": next((t.u_mm for t in c.budget if t.source == "eccentricity"), 0.0),
         "u_cam_mm": next((t.u_mm for t in c.budget if t.source == "camera"), 0.0),
         "u_cam_sys_mm": next((t.u_mm for t in c.budget if t.source == "camera_systematic"), 0.0),
         "k": c.coverage_factor, "budget": {t.source: t.u_mm for t in c.budget if t.u_mm > 0},
         "budget_u": {t.source: t.u for t in c.budget if t.u_mm > 0},
         "nu_eff": getattr(c, "effective_dof", None)}
        for c in summary.characteristics
        if c.error_mm is not None and c.expanded_uncertainty_mm is not None
    ]
    return {"seed": seed, "warned": bool(check is not None and not check.consistent),
            "inflation": None if check is None else check.cmm_inflation,
            "epipolar_chi2_per_point": None if check is None else getattr(check, "epipolar_chi2_per_point", None),
            "camera_ratio": None if check is None else getattr(check, "camera_ratio", None),
            "registration_dof": None if check is None else check.dof,
            "epipolar_points": None if check is None else getattr(check, "epipolar_points", None),
            **({} if check is None else {
                "expected_camera_ss_mm2": check.expected_camera_ss_mm2, "expected_cmm_ss_mm2": check.expected_cmm_ss_mm2,
                "observed_ss_mm2": check.observed_ss_mm2,
                "camera_excess": check.camera_excess,
                "camera_registration_excess": getattr(check, "camera_registration_excess", None),
                "cmm_ratio": getattr(check, "cmm_ratio", None), "cmm_evidence_dof": getattr(check, "cmm_evidence_dof", None),
                "cmm_share": getattr(check, "cmm_share", None)}),
            "rows": rows}


def _key(line: dict) -> tuple:
    scenario = line["scenario"] + (f" (station {line['station_seed']})" if "station_seed" in line else "")
    return (scenario, line.get("plugins", "default"), line["arm_sigma"], line["stated_sigma"],
            line.get("target_radius", 0.0), line.get("max_tilt", 20.0) if line.get("target_radius") else 0.0)


def u_spread(per_session: list[list[dict]], key: str = "U_mm") -> float:
    """The spread of U between the sessions of one design point: per characteristic, the ratio
    of the 90th to the 10th percentile of its U (``key``: ``U_mm``, or ``u_mm`` for 2u) over the
    sessions; the median over the characteristics."""
    by_name: dict[str, list[float]] = {}
    for rows in per_session:
        for r in rows:
            by_name.setdefault(r["name"], []).append(r[key])
    ratios = [np.percentile(u, 90) / np.percentile(u, 10) for u in by_name.values() if len(u) > 1]
    return float(np.median(ratios)) if ratios else float("nan")


def table(lines: list[dict], by_name: bool = False) -> str:
    """The coverage table of per-session JSON lines (grouped by scenario, plugins, sigmas and
    the stated targets); ``by_name``: one row per characteristic as well."""
    groups: dict[tuple, list[dict]] = {}
    for line in lines:
        groups.setdefault(_key(line), []).append(line)
    out = [
        "| scenario | plugins | arm sigma (mm) | stated sigma (mm) | r (mm) / tilt (deg) | sessions | lengths "
        "| within u | within 2u | within U | median k | worst abs(e)/u | median U (mm) | U P90/P10 "
        "| 2u P90/P10 | camera Type A / model | chi-square warnings |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for (scenario, plugins, arm, stated, radius, tilt), sessions in groups.items():
        subsets = [("", None)]
        if by_name:
            subsets += [(f" {name}", name) for name in dict.fromkeys(r["name"] for s in sessions for r in s["rows"])]
        for label, name in subsets:
            per_session = [[r for r in s["rows"] if name is None or r["name"] == name] for s in sessions]
            rows = [r for rs in per_session for r in rs]
            if not rows:
                continue
            n = len(rows)
            covered = [np.mean([abs(r["error_mm"]) <= r["U_mm"] for r in rs]) for rs in per_session if rs]
            se = np.std(covered, ddof=1) / np.sqrt(len(covered)) if len(covered) > 1 else float("nan")
            within_U = sum(abs(r["error_mm"]) <= r["U_mm"] for r in rows)
            within_u = sum(abs(r["error_mm"]) <= r["u_mm"] for r in rows)
            within_2u = sum(abs(r["error_mm"]) <= 2 * r["u_mm"] for r in rows)
            median_k = float(np.median([r["U_mm"] / r["u_mm"] for r in rows if r["u_mm"] > 0]))
            worst = max(abs(r["error_mm"]) / r["u_mm"] for r in rows)
            median_U = float(np.median([r["U_mm"] for r in rows]))
            warned = sum(s["warned"] for s in sessions)
            spread = u_spread(per_session)
            spread_2u = u_spread(per_session, "u_mm")
            ratios = [math.sqrt(s["camera_ratio"]) for s in sessions if s.get("camera_ratio") is not None]
            type_a = f"{np.median(ratios):.2f}" if ratios else "-"
            targets = f"{radius} / {tilt:g}" if radius else "-"
            out.append(
                f"| {scenario}{label} | {plugins} | {arm} | {stated} | {targets} | {len(sessions)} | {n} | "
                f"{within_u / n:.1%} | {within_2u / n:.1%} | {within_U / n:.1%}{f' +/- {se:.1%}' if np.isfinite(se) else ''} "
                f"| {median_k:.3f} | {worst:.2f} | "
                f"{median_U:.4f} | {spread:.2f} | {spread_2u:.2f} | {type_a} | "
                f"{warned}/{len(sessions)} |"
            )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="table3", choices=scenarios.SCENARIOS)
    parser.add_argument("--plugins", default="default", choices=tuple(PLUGINS),
                        help="default: the built-in stages (modelfit, the eccentricity correction, ml); "
                             "weighted: the defaults before issue 11 (weighted, svd: no correction)")
    parser.add_argument("--sessions", type=int, default=200)
    parser.add_argument("--frames", type=int, default=1)
    parser.add_argument("--arm-sigma", type=float, default=None,
                        help="true arm noise per coordinate (mm); default the scenario's own")
    parser.add_argument("--stated-sigma", type=float, default=None,
                        help="sigma the reference states (mm); default the scenario's arm sigma")
    parser.add_argument("--first-seed", type=int, default=1000)
    parser.add_argument("--target-radius", type=float, default=None,
                        help="state the targets' radius (mm) for the eccentricity term; default the scenario's, "
                             "0 = none")
    parser.add_argument("--max-tilt", type=float, default=None,
                        help="the targets' largest tilt (deg) stated with it; default the scenario's")
    parser.add_argument("--station-seed", type=int, default=None,
                        help="mismatch scenarios: one station (its systematic truth from this seed) for every "
                             "session, the noise new in each (the spread of U of one design point)")
    parser.add_argument("--jsonl", metavar="FILE", help="append one JSON line per session")
    parser.add_argument("--summarise", nargs="+", metavar="JSONL", help="only print the table of these files")
    parser.add_argument("--by-name", action="store_true", help="with --summarise: a row per characteristic too")
    parser.add_argument("--no-scene-cache", action="store_true", help="render the scene afresh for every session")
    args = parser.parse_args(argv)
    if args.summarise:
        lines = [json.loads(x) for f in args.summarise for x in Path(f).read_text(encoding="utf-8").splitlines()
                 if x.strip()]
        print(table(lines, args.by_name))
        return 0
    arm = args.arm_sigma if args.arm_sigma is not None else scenarios.DEFAULT_ARM_SIGMA_MM[args.scenario]
    stated = args.stated_sigma if args.stated_sigma is not None else scenarios.DEFAULT_ARM_SIGMA_MM[args.scenario]
    radius, tilt = TARGETS[args.scenario]
    radius = radius if args.target_radius is None else args.target_radius
    tilt = tilt if args.max_tilt is None else args.max_tilt
    corrected = eccentricity_corrected(args.plugins)
    if not args.no_scene_cache:
        share_scenes()
    if args.jsonl:
        Path(args.jsonl).parent.mkdir(parents=True, exist_ok=True)
    pm = make_plugin_manager()
    lines = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        plan = plan_file(Path(tmp), args.scenario, radius, tilt, corrected)
        for k in range(args.sessions):
            t0 = time.perf_counter()
            result = one_session(Path(tmp), args.scenario, args.first_seed + k, args.frames, arm, stated, pm,
                                 plan, args.plugins, args.station_seed)
            line = {"scenario": args.scenario, "plugins": args.plugins, "arm_sigma": arm, "stated_sigma": stated,
                    "target_radius": radius, "max_tilt": tilt, "frames": args.frames,
                    **({} if args.station_seed is None else {"station_seed": args.station_seed}),
                    "seconds": round(time.perf_counter() - t0, 2), **result}
            lines.append(line)
            if args.jsonl:
                with open(args.jsonl, "a", encoding="utf-8") as f:
                    f.write(json.dumps(line) + "\n")
    print(table(lines))
    print(f"({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
