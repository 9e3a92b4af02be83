"""GUM Supplement 1 check of the linear budget: propagation of distributions by Monte Carlo.

JCGM 101:2008 (GUM-S1) propagates the input distributions through the
measurement model itself instead of its linearisation. Here the model is the
real pipeline: the session's registration implementation (its ``fit``) and
measurement implementation (its ``measure``), run on the session's first
measured frame (``SessionAggregate.sample_frame``) with inputs drawn from the
budget's distributions, per draw (GUM-S1 7.2-7.4):

* camera points: ``p_c + N(0, diag(sigma_xyz^2))`` (triangulation), plus
  ``N(0, sigma_ecc^2 I)`` (eccentricity, the budget's Gaussian equivalent);
* calibration: all camera points scaled by ``1 + N(0, u_s^2)``;
* CMM points (controls, reference points, line probes): ``+ N(0, (f sigma)^2 I)``,
  f the CMM inflation of the consistency check;
* repeatability and temperature: added to the output as ``N(0, u^2)`` (they
  enter the model additively, at the session level).

The correspondence is held as in the frame. For each characteristic the output
sample gives the standard uncertainty u_MC and the probabilistically symmetric
95 % coverage interval (GUM-S1 7.7); its half-width is compared with the
linear U (k = 2): ``agreement = U_MC / U_linear - 1``. N draws give u_MC to a
relative standard uncertainty of about ``1 / sqrt(2 N)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from crossfield.types import CameraPoints, ReferenceData, Registration

__all__ = ["MonteCarloResult", "monte_carlo", "session_monte_carlo"]


@dataclass(frozen=True)
class MonteCarloResult:
    """Per characteristic: u_mc_mm, interval_mm (low, high) about the linear value,
    U_mc_mm (half-width of the 95 % interval), U_linear_mm, agreement (relative)."""

    name: str
    n_draws: int
    u_mc_mm: float
    interval_mm: tuple[float, float]
    U_mc_mm: float
    U_linear_mm: float | None
    agreement: float | None


def _draw_reference(reference: ReferenceData, rng: np.random.Generator, inflation: float) -> ReferenceData:
    points = tuple(
        dataclasses.replace(p, xyz=np.asarray(p.xyz) + rng.normal(0.0, inflation * p.sigma_mm, 3))
        for p in reference.points
    )
    return dataclasses.replace(reference, points=points)


def monte_carlo(summary: Any, registrar: Any, measurer: Any, n_draws: int, seed: int = 0) -> list[MonteCarloResult]:
    """Monte Carlo check of ``summary``'s budgets through ``registrar.fit`` and
    ``measurer.measure`` (the session's implementations); [] without a sample frame."""
    if n_draws < 2:
        raise ValueError(f"the Monte Carlo check needs at least 2 draws, got {n_draws}")
    aggregate = summary.aggregate
    frame = aggregate.sample_frame
    if frame is None:
        return []
    plan = summary.info.plan
    points: CameraPoints = frame.points
    corr = frame.registration.correspondence
    reference = summary.reference
    inflation = 1.0 if aggregate.consistency is None else aggregate.consistency.cmm_inflation
    scale_u = aggregate.calibration_scale_u
    spec_u = plan.uncertainty
    from crossfield.plugins.measure_plan import eccentricity_sigma_mm, off_axis_rad

    ecc_factor = spec_u.eccentricity_residual if spec_u.eccentricity_corrected else 1.0
    ecc = np.array([
        ecc_factor * eccentricity_sigma_mm(float(np.linalg.norm(p)), spec_u.target_radius_mm, spec_u.max_tilt_deg,
                                          off_axis_rad(p))
        for p in np.asarray(points.xyz)
    ])
    rng = np.random.default_rng(seed)
    names = [c.name for c in summary.characteristics]
    samples: dict[str, list[float]] = {name: [] for name in names}
    xyz0 = np.asarray(points.xyz)
    sigma = np.asarray(points.sigma_xyz)
    for _ in range(n_draws):
        xyz = xyz0 + rng.normal(size=xyz0.shape) * sigma + rng.normal(size=xyz0.shape) * ecc[:, None]
        xyz = xyz * (1.0 + rng.normal(0.0, scale_u))
        drawn_points = dataclasses.replace(points, xyz=xyz)
        drawn_reference = _draw_reference(reference, rng, inflation)
        by_label = drawn_reference.by_label()
        Q = np.array([by_label[c].xyz for c in corr.control_ids])
        fit = registrar.fit(xyz[np.asarray(corr.camera_index)], Q)
        registration = Registration(frame.sequence, fit, corr)
        m = measurer.measure(plan, drawn_reference, drawn_points, registration, None)
        values = {c.name: c.measured_mm for c in m.characteristics}
        for name in names:
            if name in values:
                samples[name].append(values[name])
    results = []
    for c in summary.characteristics:
        y = np.asarray(samples[c.name])
        if len(y) < 2:
            continue
        extra = {t.source: t.u_mm for t in c.budget if t.source in ("repeatability", "temperature")}
        y = y + rng.normal(0.0, extra.get("repeatability", 0.0), len(y)) + rng.normal(
            0.0, extra.get("temperature", 0.0), len(y))
        low, high = np.quantile(y, [0.025, 0.975])
        centre = float(np.mean(y))
        half = float((high - low) / 2.0)
        U_lin = c.expanded_uncertainty_mm
        results.append(MonteCarloResult(
            c.name, len(y), float(np.std(y, ddof=1)), (float(low - centre), float(high - centre)), half,
            U_lin, None if not U_lin else half / U_lin - 1.0,
        ))
    return results


def session_monte_carlo(summary: Any, n_draws: int, seed: int = 0) -> list[MonteCarloResult]:
    """:func:`monte_carlo` with the session's own register and measure implementations
    and options (built from the installed plugins)."""
    from crossfield.registry import get_implementation, make_plugin_manager

    pm = make_plugin_manager(entry_points=True)
    config = summary.info.config

    def stage(name: str) -> Any:
        return get_implementation(pm, name, config.stages[name].plugin).create(dict(config.stages[name].options))

    return monte_carlo(summary, stage("register"), stage("measure"), n_draws, seed)
