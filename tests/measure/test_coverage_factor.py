"""The Welch-Satterthwaite coverage factor (crossfield.uncertainty.dof, GUM G.4), analytically and on
constructed sessions of the synthetic station: an arm at 0.02 mm stated as 0.01 mm (a known injected
understatement) is covered; with the sigma stated right, U does not grow."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm, t

from crossfield.uncertainty.dof import coverage_factor, effective_dof, excess_dof
from crossfield.uncertainty.type_a import PRIOR_DOF

from test_measure import Station
from test_uncertainty import _session

CAMERA = np.array([0.001, 0.001, 0.004])  # the simulator's rig: the CMM dominates


def test_effective_dof_and_the_t_factor_analytic():
    # GUM eq. (G.2b): two equal terms of 10 dof each -> 20; a stated (infinite) term adds none
    assert effective_dof([(1.0, 10), (1.0, 10)]) == pytest.approx(20.0)
    assert effective_dof([(1.0, math.inf), (1.0, 5)]) == pytest.approx(20.0)
    assert effective_dof([(3.0, math.inf), (0.0, 2)]) == math.inf
    # k = 2 keeps its normal coverage 95.45 %: t at Phi(2)
    assert coverage_factor(2.0, math.inf) == 2.0
    for nu in (3, 7, 22, 200):
        assert coverage_factor(2.0, nu) == pytest.approx(t.ppf(norm.cdf(2.0), nu), rel=1e-12)
    ks = [coverage_factor(2.0, nu) for nu in (3, 7, 22, 200, 1e6)]
    assert ks == sorted(ks, reverse=True) and ks[-1] == pytest.approx(2.0, abs=1e-4)
    assert coverage_factor(3.0, 10) == pytest.approx(t.ppf(norm.cdf(3.0), 10))
    # a stated floor plus an estimated excess w of the variance: nu / w^2 (GUM G.3), continuous to infinity
    assert excess_dof(7, 1.0) == 7 and excess_dof(7, 0.5) == pytest.approx(28) and excess_dof(7, 0.0) == math.inf
    assert excess_dof(7, 1e-9) > 1e18


def _sessions(stated: float, n: int, seed: int):
    station = Station()
    rng = np.random.default_rng(seed)
    return [_session(station, station.plan, rng, cmm_true=0.02, cmm_stated=stated, frames=1, camera=CAMERA)
            for _ in range(n)]


def test_understated_cmm_is_covered_by_the_t_factor_and_a_right_sigma_does_not_grow_u():
    covered = covered_2u = total = 0
    ks = []
    for aggregate in _sessions(0.01, 40, 5):  # 2x understated: the evidence sets the CMM and line terms
        check = aggregate.consistency
        for c in aggregate.characteristics:
            if c.error_mm is None:
                continue
            dofs = {s.source: s.dof for s in c.budget}
            # the excess 1 - 1/f^2 of the CMM variance, estimated with the posterior's dof (8 controls: 22)
            f = check.cmm_inflation
            assert dofs["control_cmm"] == pytest.approx(excess_dof(PRIOR_DOF + check.dof, 1 - 1 / f**2))
            if c.kind == "point_line":  # the cylinder of 12 probes: 7 dof for its sigma's excess over 0.01
                line = next(s for s in c.budget if s.source == "reference_line")
                assert dofs["reference_line"] == pytest.approx(excess_dof(12 - 5, 1 - (0.01 / line.u) ** 2))
            nu = effective_dof((s.u_mm, s.dof) for s in c.budget)
            assert c.effective_dof == pytest.approx(nu) and c.coverage_factor == pytest.approx(coverage_factor(2, nu))
            assert c.expanded_uncertainty_mm == pytest.approx(c.coverage_factor * c.uncertainty_mm)
            total += 1
            covered += abs(c.error_mm) <= c.expanded_uncertainty_mm
            covered_2u += abs(c.error_mm) <= 2 * c.uncertainty_mm
            ks.append(c.coverage_factor)
    print(f"understated: covered {covered}/{total}, with k = 2 {covered_2u}/{total}, median k {np.median(ks):.3f}")
    assert covered / total >= 0.92 and covered > covered_2u
    assert float(np.median(ks)) >= 2.03  # the evidence set the CMM and line terms: k above 2 (2.04)
    # the sigma stated right: only the noise of the evidence above the stated values carries dof
    ratios = [c.coverage_factor / 2.0 for a in _sessions(0.02, 20, 6) for c in a.characteristics if c.n]
    print(f"stated right: median k / 2 = {np.median(ratios):.3f}, largest {max(ratios):.3f}")
    assert float(np.median(ratios)) <= 1.01
