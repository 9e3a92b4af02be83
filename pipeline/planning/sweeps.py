"""Layout sweeps (the paper's Fig. 3) and the smallest layout that reaches a target.

Each sweep varies one design parameter of a station (:mod:`crossfield.planning.station`'s
``with_*`` variants), everything else fixed, and evaluates both routes at every
value. Large grids can run on Dask (``client``: a ``distributed.Client``, from
:func:`crossfield.batch.engine.client`): each design point is one task (:func:`evaluate`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

from crossfield.planning.routes import predict
from crossfield.planning.station import (
    Station,
    with_baseline,
    with_cmm_sigma,
    with_control_spread,
    with_controls,
    with_focal_length,
    with_working_distance,
)
from crossfield.progress import bar

#: name -> (variant, default values, axis label). Values in the parameter's unit.
SWEEPS: dict[str, tuple[Callable[[Station, Any], Station], tuple[float, ...], str]] = {
    "n_controls": (lambda s, n: with_controls(s, int(n)), (3, 4, 5, 6, 8, 10, 12, 16), "number of control points"),
    "focal_length_mm": (with_focal_length, (8.0, 12.0, 16.0, 20.0, 25.0, 35.0), "focal length (mm)"),
    "working_distance_mm": (with_working_distance, (300.0, 350.0, 400.0, 500.0, 600.0, 800.0),
                            "working distance (mm)"),
    "baseline_mm": (with_baseline, (25.0, 50.0, 75.0, 100.0, 150.0), "baseline (mm)"),
    "control_spread": (with_control_spread, (0.25, 0.5, 0.75, 1.0, 1.25), "control spread (x the station's)"),
    "cmm_sigma_mm": (with_cmm_sigma, (0.001, 0.002, 0.005, 0.01, 0.02, 0.05), "CMM sigma per coordinate (mm)"),
}


#: The fixed centroid bias model of every sweep and recommendation layout: the eccentricity model
#: (a rendered bias costs ~0.5 s of rendering per target and layout; docs/planning.md).
SWEEP_BIAS_MODEL = "eccentricity"


def _layout(station: Station) -> Station:
    return dataclasses.replace(station, bias_model=SWEEP_BIAS_MODEL)


def evaluate(station: Station, sessions: int, seed: int, route: str = "both") -> dict[str, Any]:
    """One design point: the prediction without the TRE field (a Dask task)."""
    doc = predict(station, sessions=sessions, seed=seed, route=route)
    doc.pop("tre_field", None)
    return doc


def _map(points: Sequence[Station], sessions: int, seed: int, route: str, client=None) -> list[dict[str, Any]]:
    with bar(desc="plan: layout sweeps", total=len(points), unit="layout") as done:
        if client is None:
            out = []
            for s in points:
                out.append(evaluate(s, sessions, seed, route))
                done.update()
            return out
        from dask.distributed import as_completed

        futures = client.map(evaluate, list(points), sessions=sessions, seed=seed, route=route, pure=False)
        for _ in as_completed(futures):
            done.update()
        return client.gather(futures)


def run_sweeps(
    station: Station,
    *,
    sessions: int = 300,
    seed: int = 0,
    names: Sequence[str] | None = None,
    values: dict[str, Sequence[float]] | None = None,
    route: str = "both",
    client=None,
) -> dict[str, Any]:
    """Every sweep in ``names`` (default all of :data:`SWEEPS`): per value the station summary and
    each characteristic's analytic and Monte Carlo session u (mm)."""
    names = list(names or SWEEPS)
    unknown = [n for n in names if n not in SWEEPS]
    if unknown:
        raise ValueError(f"unknown sweep(s) {', '.join(unknown)}; sweeps: {', '.join(SWEEPS)}")
    jobs: list[tuple[str, float, Station]] = []
    for name in names:
        variant, default, _ = SWEEPS[name]
        for v in (values or {}).get(name, default):
            jobs.append((name, float(v), _layout(variant(station, v))))
    docs = _map([j[2] for j in jobs], sessions, seed, route, client)
    out: dict[str, Any] = {n: {"label": SWEEPS[n][2], "points": []} for n in names}
    for (name, v, _), doc in zip(jobs, docs):
        out[name]["points"].append({
            "value": v,
            "in_view": doc["station"]["in_view"],
            "characteristics": [
                {"name": c["name"], "predicted_u_mm": c["predicted_u_mm"],
                 "analytic_u_mm": c.get("analytic", {}).get("u_mm"),
                 "monte_carlo_u_mm": c.get("monte_carlo", {}).get("u_mm")}
                for c in doc["characteristics"]
            ],
        })
    return {"sessions": sessions, "seed": seed, "sweeps": out}


def recommend(
    station: Station,
    target_U_mm: float,
    *,
    n_controls: Sequence[int] = (3, 4, 5, 6, 8, 10, 12, 16),
    focal_lengths_mm: Sequence[float] = (8.0, 12.0, 16.0, 20.0, 25.0, 35.0),
    sessions: int = 2000,
    seed: int = 0,
) -> dict[str, Any]:
    """The smallest layout whose largest expanded uncertainty U = k u (all characteristics) is at
    most ``target_U_mm``: the fewest control points first, then the shortest lens, among the
    layouts whose points stay in both images. Searched with the analytic route, the choice
    confirmed by the Monte Carlo route. Returns the layout, its U and the reason."""
    if not target_U_mm > 0:
        raise ValueError(f"--target-mm must be > 0, got {target_U_mm}")
    k = station.coverage_factor
    tried = []
    grid = [(n, f) for n in n_controls for f in focal_lengths_mm]
    with bar(desc="plan: recommendation", total=len(grid), unit="layout") as layouts:
        for n, f in grid:
            layouts.update()  # counts the layout being tried
            variant = _layout(with_focal_length(with_controls(station, n), f))
            if not variant.in_view():
                tried.append({"n_controls": n, "focal_length_mm": f, "in_view": False})
                continue
            doc = predict(variant, route="analytic")
            worst = max(doc["characteristics"], key=lambda c: c["predicted_u_mm"])
            U = k * worst["predicted_u_mm"]
            floor = k * worst["analytic"]["u_cmm_mm"] if "analytic" in worst else None
            tried.append({"n_controls": n, "focal_length_mm": f, "in_view": True, "U_mm": U,
                          "worst": worst["name"], "U_cmm_mm": floor})
            if U <= target_U_mm:
                mc = predict(variant, sessions=sessions, seed=seed, route="monte-carlo")
                worst_mc = max(mc["characteristics"], key=lambda c: c["predicted_u_mm"])
                U_mc = k * worst_mc["predicted_u_mm"]
                fewer = [t for t in tried if t["n_controls"] < n and t.get("in_view")]
                best_fewer = min(fewer, key=lambda t: t["U_mm"]) if fewer else None
                shorter = [t for t in tried if t["n_controls"] == n and t["focal_length_mm"] < f and t.get("in_view")]
                reason = (
                    f"{n} control points with a {f:g} mm lens: largest U (k = {k:g}) {U:.4f} mm analytic, "
                    f"{U_mc:.4f} mm Monte Carlo ({worst['name']}) <= {target_U_mm:g} mm"
                )
                if best_fewer:
                    reason += (f"; with {best_fewer['n_controls']} control points the best in-view layout gives "
                               f"{best_fewer['U_mm']:.4f} mm ({best_fewer['focal_length_mm']:g} mm lens)")
                if shorter:
                    reason += "; shorter lenses with " + str(n) + " control points give " + ", ".join(
                        f"{t['U_mm']:.4f} mm ({t['focal_length_mm']:g} mm)" for t in shorter)
                if U_mc > target_U_mm:
                    reason += "; NOTE the Monte Carlo route does not confirm it"
                return {"reached": True, "n_controls": n, "focal_length_mm": f, "U_mm": U, "U_mc_mm": U_mc,
                        "worst": worst["name"], "reason": reason, "tried": tried}
    feasible = [t for t in tried if t.get("in_view")]
    best = min(feasible, key=lambda t: t["U_mm"]) if feasible else None
    reason = f"no layout in the grid reaches U <= {target_U_mm:g} mm"
    if best:
        reason += (f"; the best is {best['n_controls']} control points with a {best['focal_length_mm']:g} mm lens, "
                   f"U = {best['U_mm']:.4f} mm ({best['worst']}), of which the CMM part alone (control and "
                   f"reference probing, the same in every frame) is U = {best['U_cmm_mm']:.4f} mm: a better arm "
                   f"(--cmm-sigma-mm) or more frames per session may reach it, see the sweeps")
    return {"reached": False, "reason": reason, "tried": tried, "best": best}
