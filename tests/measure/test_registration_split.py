"""The registration residuals' excess split between camera and CMM by each one's own evidence
(crossfield.uncertainty.consistency, cmm_evidence, line_of_sight, type_a.expected_excess), on
constructed sessions of the synthetic station with a known injected excess:

(a) the arm's sigma understated 2x: the CMM term grows, the camera's does not;
(b) a camera bias along the controls' lines of sight (what the epipolar residuals cannot see):
    the camera term takes it, the CMM's stays;
(c) neither: nothing grows.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_measure import Station, measurer, register

from crossfield.chain.aggregate import SessionAccumulator
from crossfield.geometry import fit_reference_element
from crossfield.session import FrameResult
from crossfield.types import CameraPoints, ProbedPoint, ReferenceData
from crossfield.uncertainty.cmm_evidence import line_fit_evidence
from crossfield.uncertainty.consistency import check_means
from crossfield.uncertainty.line_of_sight import line_of_sight_sensitivities
from crossfield.uncertainty.type_a import expected_excess, variance_ratio

_MEASURER = measurer()
CAMERA = np.array([0.001, 0.001, 0.004])  # camera-frame x y z (mm)
STATED = 0.002  # the arm's stated sigma (mm): camera and CMM of about equal weight at the controls


def _session(station, rng, *, arm: float = STATED, los_bias: float = 0.0, beta: float = 0.0):
    """One frame: the arm's true sigma ``arm`` (stated: STATED); each control moved along its line of
    sight by N(0, los_bias^2) (a bias the epipolar residuals cannot see); the epipolar evidence of a
    centroid bias with variance ratio ``beta`` across the epipolar lines, chi2_i = (e_i + sqrt(beta) g_i)^2
    (as tests/measure/test_type_a.py)."""
    plan = station.plan
    probes = []
    for label in plan.probing_order():
        xyz = station.line_probes[int(label.split(".")[1]) - 1] if label.startswith("L3.") else station.points_g[label]
        probes.append(ProbedPoint(label, xyz + rng.normal(0, arm, 3), STATED))
    reference = ReferenceData(tuple(probes), source="test")
    truth = np.vstack([station.controls_c, [station.targets_c[t] for t in ("P1", "P2")], station.strays_c])
    n = len(truth)
    xyz = truth + rng.normal(0, 1, truth.shape) * CAMERA
    k = len(station.controls_c)
    xyz[:k] += rng.normal(0, los_bias, (k, 1)) * truth[:k] / np.linalg.norm(truth[:k], axis=1, keepdims=True)
    points = CameraPoints(0, xyz, np.tile(CAMERA, (n, 1)), np.arange(n), np.arange(n), np.zeros(n),
                          chi2=(rng.normal(0, 1, n) + math.sqrt(beta) * rng.normal(0, 1, n)) ** 2)
    registration = register(points, reference, plan)
    accumulator = SessionAccumulator(plan, reference=reference, measurer=_MEASURER)
    accumulator.add(FrameResult(0, 0, registration=registration,
                                measurement=_MEASURER.measure(plan, reference, points, registration, station.truth)))
    return accumulator.result()


def _terms(case: dict, sessions: int = 24, seed: int = 3):
    """Median over sessions of each characteristic's camera_systematic and control_cmm (mm), of f,
    of u over the model's u (the stated sigmas: CMM terms / f, no camera_systematic), and the
    coverage of |error| <= U."""
    station = Station()
    rng = np.random.default_rng(seed)
    systematic, cmm, f, covered, growth, share = {}, {}, [], [], [], []
    for _ in range(sessions):
        aggregate = _session(station, rng, **case)
        check = aggregate.consistency
        f.append(check.cmm_inflation)
        share.append(check.cmm_share)
        for c in aggregate.characteristics:
            terms = {t.source: t.u_mm for t in c.budget}
            systematic.setdefault(c.name, []).append(terms.get("camera_systematic", 0.0))
            cmm.setdefault(c.name, []).append(terms.get("control_cmm", 0.0))
            model = {k: (v / check.cmm_inflation if k in ("control_cmm", "reference_cmm") else v)
                     for k, v in terms.items() if k != "camera_systematic"}
            growth.append(c.uncertainty_mm / math.sqrt(sum(v * v for v in model.values())))
            if c.error_mm is not None:
                covered.append(abs(c.error_mm) <= c.expanded_uncertainty_mm)
    median = lambda d: {k: float(np.median(v)) for k, v in d.items()}
    _terms.growth, _terms.share = float(np.median(growth)), float(np.median(share))
    return median(systematic), median(cmm), float(np.median(f)), float(np.mean(covered))


@pytest.fixture(scope="module")
def clean():
    terms = _terms({})
    return (*terms, _terms.growth)


def test_neither_excess_nothing_grows(clean):
    _, _, f, covered, growth = clean
    assert f < 1.1  # the arm as stated: its factor stays near 1
    assert growth < 1.05  # u within a few percent of the model's (the positive part of the evidence's noise)
    assert covered >= 0.93


def test_understated_cmm_grows_the_cmm_term_not_the_camera_term(clean):
    systematic0, cmm0, *_ = clean
    systematic, cmm, f, covered = _terms({"arm": 2 * STATED})
    assert 1.6 <= f <= 2.4  # the line fits' residuals and the registration's: the arm is ~2x off
    # the camera keeps its weight's share only: its epipolar evidence agrees (12 points), which still leaves
    # a posterior mean excess of ~0.17 against the lines' ~3 (crossfield.uncertainty.type_a.expected_excess)
    assert _terms.share >= 0.85
    for name in cmm:
        if cmm0[name] > 1e-9:  # the characteristics through the registration
            assert cmm[name] >= 1.6 * cmm0[name]
            grown_cmm = math.sqrt(cmm[name] ** 2 - cmm0[name] ** 2)
            grown_camera = math.sqrt(max(systematic[name] ** 2 - systematic0[name] ** 2, 0.0))
            assert grown_camera <= 0.5 * grown_cmm  # measured 0.41 at most (all of it on the camera: ~1)
    assert covered >= 0.90


def test_camera_bias_at_the_controls_goes_to_the_camera_term_not_the_cmm(clean):
    # as on mismatch-camera: the epipolar residuals show a camera excess (beta 1.5), the registration
    # residuals a larger one along the lines of sight (~5x the stated CMM variance at the controls)
    systematic0, cmm0, *_ = clean
    systematic, cmm, f, covered = _terms({"los_bias": 2 * CAMERA[2], "beta": 1.5})
    assert _terms.share <= 0.2  # the camera takes >= 80 % of the registration excess
    assert f <= 1.3  # (all of it on the CMM: f ~ 2.5)
    grew = 0
    for name in cmm:
        if cmm0[name] > 1e-9:
            assert cmm[name] <= 1.3 * cmm0[name]
            grew += systematic[name] >= systematic0[name] + 0.5 * cmm0[name]
    assert grew >= 3  # the characteristics through the registration (P1-L3, P1-R1, P2-depth, C3-L3)
    assert covered >= 0.90


def test_split_rule_on_constructed_numbers():
    # registration residuals 4x the expectation (18 dof), camera and CMM equal at the controls
    base = {"n": 1, "ss": 4.0, "e_cam": 0.5, "e_cmm": 0.5, "dof": 18}
    # the lines say the arm is 2x off (14 dof at ratio 4), the epipolar residuals agree (14 points at 1)
    arm = check_means(**base, epipolar_chi2=14.0, epipolar_count=14, cmm_statistic=56.0, cmm_dof=14)
    w_cam, w_cmm = expected_excess(14.0, 14) * 0.5, expected_excess(56.0, 14) * 0.5
    assert arm.cmm_share == pytest.approx(w_cmm / (w_cam + w_cmm)) and arm.cmm_share > 0.9
    assert arm.cmm_inflation > 1.8 and arm.camera_excess == 0.0
    assert arm.camera_registration_excess < 0.1 * (arm.cmm_inflation**2 - 1)
    # the epipolar residuals show an excess (chi2 3 per point), the lines agree: the camera takes it
    cam = check_means(**base, epipolar_chi2=42.0, epipolar_count=14, cmm_statistic=14.0, cmm_dof=14)
    assert cam.cmm_share < 0.2 and cam.camera_excess == pytest.approx(variance_ratio(42.0, 14) - 1)
    assert cam.camera_registration_excess > 1.0 and cam.cmm_inflation < 1.3
    assert "registration residuals" in cam.note and "camera at the controls" in cam.note
    # continuous in the evidence: no step as the camera's own excess crosses 0
    shares = [check_means(**base, epipolar_chi2=x, epipolar_count=14, cmm_statistic=14.0, cmm_dof=14).cmm_share
              for x in np.linspace(10.0, 20.0, 41)]
    assert max(abs(np.diff(shares))) < 0.03
    # the posterior mean excess against a Monte Carlo of the scaled-inverse-chi-square posterior
    rng = np.random.default_rng(0)
    nu, s2 = 4 + 7, variance_ratio(9.0, 7)
    draws = nu * s2 / rng.chisquare(nu, 400_000)
    assert expected_excess(9.0, 7) == pytest.approx(np.mean(np.maximum(draws - 1, 0)), rel=0.02)


def test_line_fit_evidence_is_chi_square_with_the_fits_dof():
    # a line of 5 probes (2N - 4 = 6 dof; both perpendicular coordinates of each probe's distance)
    station = Station(fit="line")
    rng = np.random.default_rng(5)
    stats = []
    for _ in range(400):
        probes = tuple(ProbedPoint(f"L3.{k + 1}", p + rng.normal(0, 0.02, 3), 0.01)
                       for k, p in enumerate(station.line_probes))
        evidence = line_fit_evidence(station.plan, ReferenceData(probes))
        assert evidence.dof == 6 and evidence.lines == ("L3",)
        stats.append(evidence.statistic)
    # the arm 2x its stated 0.01 mm: E = 4 nu, var = 2 nu 4^2
    assert np.mean(stats) == pytest.approx(4 * 6, rel=0.07)  # 2.5 standard errors of 400 draws
    assert np.std(stats) == pytest.approx(4 * math.sqrt(12), rel=0.12)
    # a cylinder of 12 probes: N - 5 = 7 dof, the statistic its residuals' sum of squares over sigma^2
    cylinder = Station()
    probes = tuple(ProbedPoint(f"L3.{k + 1}", p + rng.normal(0, 0.01, 3), 0.01)
                   for k, p in enumerate(cylinder.line_probes))
    evidence = line_fit_evidence(cylinder.plan, ReferenceData(probes))
    fit = fit_reference_element(cylinder.plan.reference_lines[0], probes)
    assert evidence.dof == 7 and evidence.statistic == pytest.approx(np.sum(fit.residuals_mm**2) / 0.01**2)
    # no stated sigma, or no lines: no evidence
    assert line_fit_evidence(cylinder.plan, ReferenceData(())).dof == 0


def test_line_of_sight_sensitivities_match_a_re_registration():
    station = Station()
    rng = np.random.default_rng(2)
    reference = station.reference(rng)
    points = station.camera_points(rng=rng)
    registration = register(points, reference, station.plan)
    sums = line_of_sight_sensitivities(station.plan, reference, points, registration, _MEASURER)
    base = {c.name: c.measured_mm for c in _MEASURER.measure(station.plan, reference, points, registration,
                                                              None).characteristics}
    # the truth: each control moved by 5 um along its line of sight, the SVD registration fitted again
    expected = dict.fromkeys(base, 0.0)
    xyz = np.asarray(points.xyz)
    for k in registration.correspondence.camera_index:
        moved = xyz.copy()
        moved[k] += 0.005 * xyz[k] / np.linalg.norm(xyz[k])
        p = CameraPoints(0, moved, points.sigma_xyz, points.upper_index, points.lower_index, points.residual_px)
        m = _MEASURER.measure(station.plan, reference, p, register(p, reference, station.plan), None)
        for c in m.characteristics:
            expected[c.name] += ((c.measured_mm - base[c.name]) / 0.005) ** 2
    for name, value in expected.items():
        assert sums[name] == pytest.approx(value, rel=0.02, abs=1e-6)
