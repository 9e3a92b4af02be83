"""SPC kernels (crossfield.catalog.spc) against textbook cases: Montgomery's individuals
chart, each Nelson test on a constructed series, Cp / Cpk and their intervals."""

from __future__ import annotations

import numpy as np
import pytest

from crossfield.catalog import spc

#: Montgomery, Introduction to SQC, 6th ed., Example 6.5: mortgage-loan processing costs
#: (20 weeks); the book: x̄ = 300.5, MR̄ = 7.79, UCL 321.22, LCL 279.78, MR chart UCL 25.45.
MONTGOMERY_6_5 = [310, 288, 297, 298, 307, 303, 294, 297, 308, 306,
                  294, 299, 297, 299, 314, 295, 293, 306, 301, 304]


def test_individuals_chart_limits_of_montgomery_example_6_5():
    lim = spc.individuals_limits(MONTGOMERY_6_5)
    assert lim.centre == pytest.approx(300.5)
    assert lim.mr_bar == pytest.approx(7.79, abs=0.005)
    assert lim.ucl == pytest.approx(321.22, abs=0.01)
    assert lim.lcl == pytest.approx(279.78, abs=0.01)
    assert lim.mr_ucl == pytest.approx(25.45, abs=0.01)
    # the book's conclusion: the process is in control, no test fires on the 20 weeks
    assert all(not v for v in spc.nelson_rules(MONTGOMERY_6_5, lim.centre, lim.sigma).values())


#: A background (centre 0, sigma 1) on which no test fires: no run of one side over 2, no
#: monotone run over 2 steps, a broken alternation every period, a point beyond 1 sigma every 6.
BACKGROUND = [0.5, 1.5, -0.5, -1.5, 0.2, -0.2] * 5

#: rule -> (the pattern with its breakers, the index in it of the point that completes the
#: test, the same pattern one point short of firing)
PATTERNS = {
    1: ([3.5], 0, [2.9]),
    2: ([-0.5] + [0.4] * 9 + [-0.5], 9, [-0.5] + [0.4] * 8 + [-0.5]),
    3: ([1.0, -1.2, -0.7, -0.2, 0.3, 0.8, 1.2, -1.0], 6, [1.0, -1.2, -0.7, -0.2, 0.3, 0.8, -1.0]),
    4: ([0.9, 0.8] + [0.6, -0.6] * 7 + [-0.6], 15, [0.9, 0.8] + [0.6, -0.6] * 6 + [0.6, 0.6]),
    5: ([0.0, 2.5, 0.5, 2.5, 0.0], 3, [0.0, 2.5, 0.5, 0.5, 2.5, 0.0]),
    6: ([0.0, 1.5, 1.5, 0.5, 1.5, 1.5, 0.0], 5, [0.0, 1.5, 1.5, 0.5, 0.5, 1.5, 1.5, 0.0]),
    7: ([1.5] + [0.3, 0.2, -0.3, -0.2, 0.1] * 3 + [-1.5], 15, [1.5] + [0.3, 0.2, -0.3, -0.2, 0.1] * 3 + [-1.5]),
    8: ([0.0] + [1.5, -1.5] * 4 + [0.0], 8, [0.0] + [1.5, -1.5] * 3 + [1.5, 0.0]),
}
PATTERNS[7] = (PATTERNS[7][0], 15, [1.5] + ([0.3, 0.2, -0.3, -0.2, 0.1] * 3)[:14] + [-1.5])


def test_the_background_fires_no_test():
    assert spc.nelson_rules(BACKGROUND, 0.0, 1.0) == {r: [] for r in spc.NELSON_RULES}


@pytest.mark.parametrize("rule", sorted(PATTERNS))
def test_each_nelson_rule_fires_where_its_pattern_completes(rule):
    pattern, at, short = PATTERNS[rule]
    series = BACKGROUND + pattern + BACKGROUND
    fired = spc.nelson_rules(series, 0.0, 1.0)
    assert fired[rule] == [len(BACKGROUND) + at], fired
    near = spc.nelson_rules(BACKGROUND + short + BACKGROUND, 0.0, 1.0)
    assert near[rule] == [], near


def test_cp_interval_of_montgomery_example_8_5():
    """USL 62, LSL 38, n = 20, s = 1.75: Cp^ = 2.29, 95 % interval 1.57 <= Cp <= 3.01."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=20)
    x = 50 + 1.75 * (x - x.mean()) / x.std(ddof=1)  # exactly mean 50, s 1.75
    c = spc.capability(x, 38, 62)
    assert c.cp == pytest.approx(2.29, abs=0.005)
    # the book computes from the rounded Cp^ 2.29 (2.29 sqrt(8.91/19) = 1.568): to 0.01
    assert c.cp_low == pytest.approx(1.57, abs=0.01) and c.cp_high == pytest.approx(3.01, abs=0.01)
    assert c.cpk == pytest.approx(c.cp)  # centred


def test_cpk_interval_of_montgomery_example_8_6():
    """n = 20, Cpk^ = 1.33: 95 % interval 0.88 <= Cpk <= 1.78 (Bissell, eq. 8.20)."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=20)
    x = (x - x.mean()) / x.std(ddof=1)  # mean 0, s 1: Cpk = (USL - 0)/3 with USL = 3.99
    c = spc.capability(x, -10.0, 3.99)
    assert c.cpk == pytest.approx(1.33)
    assert c.cpk_low == pytest.approx(0.88, abs=0.01) and c.cpk_high == pytest.approx(1.78, abs=0.01)


def test_cp_and_cpk_intervals_cover_the_true_values():
    """Coverage of the stated 95 % over 4000 normal samples of n = 40 (reference: the true
    Cp = 1.5, Cpk = 1.0 of the drawing distribution): Cp exact (chi-square), Cpk
    Bissell's approximation, both within 95 +/- 1.5 %."""
    rng = np.random.default_rng(5)
    n, reps, mu, sigma, lsl, usl = 40, 4000, 1.5, 1.0, -4.5, 4.5
    cp_true, cpk_true = (usl - lsl) / (6 * sigma), min(usl - mu, mu - lsl) / (3 * sigma)
    hit_cp = hit_cpk = 0
    for _ in range(reps):
        c = spc.capability(rng.normal(mu, sigma, n), lsl, usl)
        hit_cp += c.cp_low <= cp_true <= c.cp_high
        hit_cpk += c.cpk_low <= cpk_true <= c.cpk_high
    assert abs(hit_cp / reps - 0.95) < 0.015, hit_cp / reps
    assert abs(hit_cpk / reps - 0.95) < 0.015, hit_cpk / reps


def test_bad_input_is_refused():
    with pytest.raises(ValueError):
        spc.individuals_limits([1.0])
    with pytest.raises(ValueError):
        spc.capability([1.0, 1.0, 1.0], 0, 2)
    with pytest.raises(ValueError):
        spc.capability([1.0, 2.0, 3.0], 2, 0)
