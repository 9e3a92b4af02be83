"""Coverage of the stated expanded uncertainty over simulated sessions (on demand, not a test).

    .venv/bin/python bench/bench_coverage.py --scenario table3 --sessions 200
    .venv/bin/python bench/bench_coverage.py --scenario station --arm-sigma 0.02 --stated-sigma 0.01

Each session is a fresh simulator session (its own noise seed, ``--frames``
stereo pairs; the geometry is the scenario's). For every characteristic with
ground truth the bench counts |error| <= U (k = 2) and |error| <= u, and how
often the residual chi-square check warned. A calibrated U covers 95 %
(+/- 1.5 % binomial standard deviation for 200 x 10 lengths, though lengths of one
session share their CMM errors and are not independent). Any scenario the
simulator offers can be named (``crossfield.simulator.scenarios.SCENARIOS``).
Results as one JSON line per session (``--jsonl``) and a table row at the end.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from crossfield.config import parse_config  # noqa: E402
from crossfield.registry import make_plugin_manager  # noqa: E402
from crossfield.runner import run_session  # noqa: E402


def plan_file(out: Path, scenario: str, target_radius: float, max_tilt: float) -> str:
    """The scenario's own plan with the eccentricity of its circle targets stated
    (``[uncertainty] target_radius``, ``max_tilt_deg``); "" = the scenario's plan as it is."""
    if not target_radius:
        return ""
    from crossfield.simulator.scenarios import build_scene

    path = out / f"{scenario}-plan.toml"
    text = build_scene(scenario).plan.text
    path.write_text(text + f"\n[uncertainty]\ntarget_radius = {target_radius}\nmax_tilt_deg = {max_tilt}\n",
                    encoding="utf-8")
    return str(path)


def one_session(out: Path, scenario: str, seed: int, frames: int, arm_sigma: float, stated: float, pm,
                plan: str = "") -> dict:
    config = parse_config(
        {
            "session": {
                "output_dir": str(out), "name": f"s{seed}", "record": False, "rerun": False, "plan": plan,
            },
            "acquire": {"plugin": "simulator", "scenario": scenario, "frames": frames, "seed": seed,
                        "arm_sigma_mm": arm_sigma},
            "reference": {"plugin": "romer-serial", "port": "simulator", "sigma_mm": stated},
            "report": {"plugin": "json"},
        },
        "<bench_coverage>",
    )
    summary = run_session(config, pm)
    check = summary.aggregate.consistency
    rows = [
        {"name": c.name, "error_mm": c.error_mm, "u_mm": c.uncertainty_mm, "U_mm": c.expanded_uncertainty_mm}
        for c in summary.characteristics
        if c.error_mm is not None and c.expanded_uncertainty_mm is not None
    ]
    return {"seed": seed, "warned": bool(check is not None and not check.consistent),
            "inflation": None if check is None else check.cmm_inflation, "rows": rows}


def table(lines: list[dict]) -> str:
    """The coverage table of per-session JSON lines (grouped by scenario and sigmas)."""
    groups: dict[tuple, list[dict]] = {}
    for line in lines:
        key = (line["scenario"], line["arm_sigma"], line["stated_sigma"], line.get("target_radius", 0.0))
        groups.setdefault(key, []).append(line)
    out = [
        "| scenario | arm sigma (mm) | stated sigma (mm) | eccentricity r (mm) | sessions | lengths | within u "
        "| within U (k=2) | worst abs(e)/u | chi-square warnings |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for (scenario, arm, stated, radius), sessions in groups.items():
        rows = [r for s in sessions for r in s["rows"]]
        n = len(rows)
        within_U = sum(abs(r["error_mm"]) <= r["U_mm"] for r in rows)
        within_u = sum(abs(r["error_mm"]) <= r["u_mm"] for r in rows)
        worst = max(abs(r["error_mm"]) / r["u_mm"] for r in rows)
        warned = sum(s["warned"] for s in sessions)
        out.append(f"| {scenario} | {arm} | {stated} | {radius or '-'} | {len(sessions)} | {n} | {within_u / n:.1%} | "
                   f"{within_U / n:.1%} | {worst:.2f} | {warned}/{len(sessions)} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="table3")
    parser.add_argument("--sessions", type=int, default=200)
    parser.add_argument("--frames", type=int, default=1)
    parser.add_argument("--arm-sigma", type=float, default=0.01, help="true arm noise per coordinate (mm)")
    parser.add_argument("--stated-sigma", type=float, default=0.01, help="sigma the reference states (mm)")
    parser.add_argument("--first-seed", type=int, default=1000)
    parser.add_argument("--target-radius", type=float, default=0.0,
                        help="state the targets' radius (mm) for the eccentricity term (the simulator's: 2.5)")
    parser.add_argument("--max-tilt", type=float, default=20.0, help="with --target-radius: largest tilt (deg)")
    parser.add_argument("--jsonl", metavar="FILE", help="append one JSON line per session")
    parser.add_argument("--summarise", nargs="+", metavar="JSONL", help="only print the table of these files")
    args = parser.parse_args(argv)
    if args.summarise:
        lines = [json.loads(x) for f in args.summarise for x in Path(f).read_text(encoding="utf-8").splitlines()]
        print(table(lines))
        return 0
    pm = make_plugin_manager()
    n = within_U = within_u = warned = 0
    worst = 0.0
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        plan = plan_file(Path(tmp), args.scenario, args.target_radius, args.max_tilt)
        for k in range(args.sessions):
            result = one_session(Path(tmp), args.scenario, args.first_seed + k, args.frames,
                                 args.arm_sigma, args.stated_sigma, pm, plan)
            warned += result["warned"]
            for r in result["rows"]:
                n += 1
                within_U += abs(r["error_mm"]) <= r["U_mm"]
                within_u += abs(r["error_mm"]) <= r["u_mm"]
                worst = max(worst, abs(r["error_mm"]) / r["u_mm"])
            if args.jsonl:
                with open(args.jsonl, "a", encoding="utf-8") as f:
                    f.write(json.dumps({"scenario": args.scenario, "arm_sigma": args.arm_sigma,
                                        "target_radius": args.target_radius,
                                        "stated_sigma": args.stated_sigma, **result}) + "\n")
    elapsed = time.perf_counter() - start
    print("| scenario | arm sigma (mm) | stated sigma (mm) | sessions | lengths | within u | within U (k=2) "
          "| worst |e|/u | chi-square warnings |")
    print(f"| {args.scenario} | {args.arm_sigma} | {args.stated_sigma} | {args.sessions} | {n} | "
          f"{within_u / n:.1%} | {within_U / n:.1%} | {worst:.2f} | {warned}/{args.sessions} |")
    print(f"({elapsed:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
