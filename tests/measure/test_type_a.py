"""Type A evidence in the budget (crossfield.uncertainty.type_a, consistency, budget.camera_terms),
on constructed sessions of the synthetic station with a known injected centroid bias.

A bias fixed for the session (the same in every frame) with variance ratio beta to the
model's per-frame camera variance moves every camera point by N(0, beta sigma^2) per
axis; its epipolar evidence is what such a bias leaves in each point's 1-dof residual:
chi2_if = (e_if + sqrt(beta) g_i)^2, e_if ~ N(0, 1) new each frame, g_i ~ N(0, 1) fixed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from crossfield.chain.aggregate import SessionAccumulator
from crossfield.session import FrameResult
from crossfield.types import BudgetTerm, CameraPoints, ProbedPoint, ReferenceData
from crossfield.uncertainty.budget import camera_terms
from crossfield.uncertainty.consistency import check_means
from crossfield.uncertainty.type_a import PRIOR_DOF, excess, variance_ratio

from test_measure import Station, measurer, register

_MEASURER = measurer()
SIGMA = np.array([0.002, 0.002, 0.008])  # camera-frame x y z (mm): the camera dominates


def _session(station, rng, *, beta: float, frames: int, cmm: float = 0.0005):
    plan = station.plan
    probes = []
    for label in plan.probing_order():
        xyz = station.line_probes[int(label.split(".")[1]) - 1] if label.startswith("L3.") else station.points_g[label]
        probes.append(ProbedPoint(label, xyz + rng.normal(0, cmm, 3), cmm))
    reference = ReferenceData(tuple(probes), source="test")
    truth = np.vstack([station.controls_c, [station.targets_c[t] for t in ("P1", "P2")], station.strays_c])
    n = len(truth)
    bias = rng.normal(0, 1, truth.shape) * SIGMA * math.sqrt(beta)  # fixed for the session
    g = rng.normal(0, 1, n)
    accumulator = SessionAccumulator(plan)
    for k in range(frames):
        xyz = truth + bias + rng.normal(0, 1, truth.shape) * SIGMA
        chi2 = (rng.normal(0, 1, n) + math.sqrt(beta) * g) ** 2
        points = CameraPoints(k, xyz, np.tile(SIGMA, (n, 1)), np.arange(n), np.arange(n), np.zeros(n), chi2=chi2)
        registration = register(points, reference, plan)
        m = _MEASURER.measure(plan, reference, points, registration, station.truth)
        accumulator.add(FrameResult(k, k, registration=registration, measurement=m))
    return accumulator.result()


def _coverage(beta: float, frames: int, sessions: int, seed: int):
    station = Station()
    rng = np.random.default_rng(seed)
    covered = covered_model = total = 0
    U = []
    for _ in range(sessions):
        aggregate = _session(station, rng, beta=beta, frames=frames)
        for c in aggregate.characteristics:
            if c.error_mm is None or c.kind != "point_point":
                continue
            total += 1
            covered += abs(c.error_mm) <= c.expanded_uncertainty_mm
            u_sys = next((t.u_mm for t in c.budget if t.source == "camera_systematic"), 0.0)
            covered_model += abs(c.error_mm) <= 2 * math.sqrt(c.uncertainty_mm**2 - u_sys**2)
            U.append(c.expanded_uncertainty_mm)
    _coverage.model = covered_model / total
    return covered / total, float(np.median(U)), aggregate


def test_variance_ratio_is_the_shrunk_pool_and_continuous():
    assert variance_ratio(14.0, 14) == pytest.approx(1.0)
    assert variance_ratio(4 * 14.0, 14) == pytest.approx((PRIOR_DOF + 56) / (PRIOR_DOF + 14))
    assert variance_ratio(5.0, 0) == 1.0  # no evidence: the model
    # continuous: no threshold at which U jumps (the chi-square switch did)
    xs = np.linspace(0, 60, 601)
    steps = np.diff([excess(x, 18) for x in xs])
    assert steps.max() <= (xs[1] - xs[0]) / (PRIOR_DOF + 18) + 1e-12
    # on sessions that agree with the model, s^2 is unbiased, its positive part small
    rng = np.random.default_rng(0)
    draws = np.array([variance_ratio(rng.chisquare(14), 14) for _ in range(4000)])
    assert abs(draws.mean() - 1) < 0.02
    sd = math.sqrt(2 * 14) / (PRIOR_DOF + 14)
    assert np.mean(np.maximum(draws - 1, 0)) < 0.45 * sd  # ~0.4 sd for a near-normal s^2


def test_consistency_rule_on_constructed_numbers_is_smooth():
    # 18 dof, the registration residuals 4x the expectation, all of it CMM
    check = check_means(1, 4.0, 0.0, 1.0, 18)
    ratio = variance_ratio(72.0, 18)
    assert not check.consistent and "contradict" in check.warning
    assert check.cmm_inflation == pytest.approx(math.sqrt(ratio))
    assert "registration residuals" in check.note
    # as expected: no inflation, no note
    ok = check_means(1, 1.0, 0.5, 0.5, 18)
    assert ok.consistent and ok.cmm_inflation == 1.0 and ok.warning is None and ok.note is None
    # the camera's epipolar evidence (14 points, chi2 3 per point) is taken first, and named
    cam = check_means(1, 1.0, 0.5, 0.5, 18, epipolar_chi2=42.0, epipolar_count=14)
    assert cam.camera_excess == pytest.approx(variance_ratio(42.0, 14) - 1)
    assert "epipolar" in cam.note and cam.cmm_inflation == 1.0


def test_systematic_camera_term_is_not_divided_by_the_frame_count():
    camera = BudgetTerm("camera", 0.002, "mm", 1.5, 0.003)
    for n in (1, 4, 25):
        random, systematic = camera_terms(camera, n, 0.69)
        assert random.u_mm == pytest.approx(0.003 / math.sqrt(n))
        assert systematic.source == "camera_systematic" and systematic.u_mm == pytest.approx(0.003 * math.sqrt(0.69))
    assert len(camera_terms(camera, 4, 0.0)) == 1
    # through the session: with the same bias and evidence, 1 and 8 frames give the same systematic term
    station = Station()
    one = _session(station, np.random.default_rng(4), beta=3.0, frames=1)
    eight = _session(station, np.random.default_rng(4), beta=3.0, frames=8)
    for a, b in zip(one.characteristics, eight.characteristics):
        ta = {t.source: t.u_mm for t in a.budget}
        tb = {t.source: t.u_mm for t in b.budget}
        if ta["camera"] == 0:  # a characteristic of CMM points only
            continue
        assert tb["camera"] < 0.5 * ta["camera"]  # the random part of a mean of 8
        assert tb["camera_systematic"] > 0.5 * ta["camera_systematic"] > 0  # the bias stays


def test_injected_bias_is_covered_and_without_bias_u_does_not_grow():
    # a bias 3x the model's variance (beta = 3): the model alone under-covers, the Type A rule covers
    biased, U_biased, last = _coverage(beta=3.0, frames=3, sessions=40, seed=7)
    assert biased >= 0.88  # 95 % less 2 standard errors of 80 lengths (40 sessions x 2, ~3 %)
    assert _coverage.model <= 0.80  # the model's camera term alone
    assert last.consistency.camera_excess > 0 and "epipolar" in last.consistency.note
    # no bias: U stays within a few percent of the model's
    clean, U_clean, _ = _coverage(beta=0.0, frames=3, sessions=40, seed=8)
    station = Station()
    rng = np.random.default_rng(8)
    U_model = []
    for _ in range(40):
        aggregate = _session(station, rng, beta=0.0, frames=3)
        for c in aggregate.characteristics:
            if c.kind == "point_point" and c.error_mm is not None:
                terms = {t.source: t.u_mm for t in c.budget}
                u_model = math.sqrt(max(c.uncertainty_mm**2 - terms.get("camera_systematic", 0.0) ** 2, 0.0))
                U_model.append(2 * u_model)
    assert clean >= 0.93
    assert U_clean <= 1.06 * float(np.median(U_model))
    assert U_biased >= 1.3 * U_clean
