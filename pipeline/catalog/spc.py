"""Statistical process control kernels (numpy / scipy only): the individuals and moving-range
chart, the Nelson (Western Electric) run rules, and process capability with confidence
intervals.

References:

* Montgomery, D. C., *Introduction to Statistical Quality Control*, 6th ed., Wiley 2009:
  section 6.4 (individuals and moving-range chart, eq. 6.33: centre x̄, limits
  x̄ ± 3 MR̄/d2, d2 = 1.128 for a moving range of two; MR chart UCL = D4 MR̄, D4 = 3.267,
  LCL = 0), section 8.3 (Cp = (USL - LSL)/(6 σ), Cpk = min(USL - μ, μ - LSL)/(3 σ);
  eq. 8.19 the chi-square interval of Cp, eq. 8.20 Bissell's normal-approximation interval
  of Cpk).
* Nelson, L. S., "The Shewhart control chart: tests for special causes", Journal of
  Quality Technology 16(4), 1984, 237-239: the eight tests (:data:`NELSON_RULES`).
  Western Electric's four rules (Statistical Quality Control Handbook, 1956) are Nelson's
  1, 5 and 6 and "eight in a row on one side" (Nelson's 2 uses nine).

Units: whatever the values are in (mm for the catalog's characteristics). σ of the
chart is the within (short-term) estimate MR̄/d2; the capability uses the sample standard
deviation s of the same baseline points, as Montgomery's intervals assume.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

#: Control-chart constants for subgroups of n = 2 (the moving range of two): Montgomery Appendix VI.
D2 = 1.128
D4 = 3.267

#: Nelson's tests: number -> what fires it.
NELSON_RULES: dict[int, str] = {
    1: "one point beyond 3 sigma",
    2: "nine points in a row on one side of the centre line",
    3: "six points in a row steadily increasing or decreasing",
    4: "fourteen points in a row alternating up and down",
    5: "two of three points in a row beyond 2 sigma on the same side",
    6: "four of five points in a row beyond 1 sigma on the same side",
    7: "fifteen points in a row within 1 sigma (either side)",
    8: "eight points in a row beyond 1 sigma (either side), none within",
}


@dataclass(frozen=True)
class IndividualsLimits:
    """Limits of an individuals / moving-range chart from a baseline.

    centre: x̄ of the baseline; sigma: MR̄/d2 (within); ucl / lcl: centre ± 3 sigma;
    mr_bar: mean moving range; mr_ucl: D4 MR̄ (its LCL is 0); n: baseline points."""

    centre: float
    sigma: float
    ucl: float
    lcl: float
    mr_bar: float
    mr_ucl: float
    n: int


def moving_ranges(x: Sequence[float]) -> np.ndarray:
    """|x_i - x_{i-1}|, i = 1..n-1 (shape (n-1,))."""
    a = np.asarray(x, dtype=float)
    return np.abs(np.diff(a))


def individuals_limits(baseline: Sequence[float]) -> IndividualsLimits:
    """Montgomery eq. 6.33 on the baseline points (at least 2). ValueError otherwise."""
    a = np.asarray(baseline, dtype=float)
    if a.ndim != 1 or a.size < 2 or not np.all(np.isfinite(a)):
        raise ValueError("an individuals chart's baseline needs at least 2 finite values")
    mr_bar = float(np.mean(moving_ranges(a)))
    centre = float(np.mean(a))
    sigma = mr_bar / D2
    return IndividualsLimits(centre, sigma, centre + 3 * sigma, centre - 3 * sigma, mr_bar, D4 * mr_bar, int(a.size))


def _runs(flags: np.ndarray, length: int) -> np.ndarray:
    """Indices i where flags[i-length+1 .. i] are all True."""
    if flags.size < length:
        return np.zeros(0, dtype=int)
    window = np.convolve(flags.astype(int), np.ones(length, dtype=int), mode="valid")
    return np.nonzero(window == length)[0] + length - 1


def _k_of_m(flags: np.ndarray, k: int, m: int) -> np.ndarray:
    """Indices i where at least k of flags[i-m+1 .. i] are True and flags[i] is (the point
    that completes the pattern)."""
    if flags.size < m:
        return np.zeros(0, dtype=int)
    window = np.convolve(flags.astype(int), np.ones(m, dtype=int), mode="valid")
    ends = np.nonzero(window >= k)[0] + m - 1
    return ends[flags[ends]]


def nelson_rules(x: Sequence[float], centre: float, sigma: float) -> dict[int, list[int]]:
    """For each of Nelson's tests (:data:`NELSON_RULES`), the indices of the points at which
    it fires (the last point of each window that satisfies it), given the chart's centre and
    sigma (> 0). Sorted, each index once per rule."""
    a = np.asarray(x, dtype=float)
    if not sigma > 0:
        raise ValueError("sigma must be > 0")
    z = (a - centre) / sigma
    up, down = z > 0, z < 0
    d = np.diff(a)
    out: dict[int, np.ndarray] = {}
    out[1] = np.nonzero(np.abs(z) > 3)[0]
    out[2] = np.union1d(_runs(up, 9), _runs(down, 9))
    # six points increasing: five increasing steps ending at point i
    out[3] = np.union1d(_runs(d > 0, 5), _runs(d < 0, 5)) + 1
    # fourteen points alternating: thirteen steps whose signs alternate (12 sign changes)
    s = np.sign(d)
    alt = (s[1:] * s[:-1]) < 0
    out[4] = _runs(alt, 12) + 2
    out[5] = np.union1d(_k_of_m(z > 2, 2, 3), _k_of_m(z < -2, 2, 3))
    out[6] = np.union1d(_k_of_m(z > 1, 4, 5), _k_of_m(z < -1, 4, 5))
    out[7] = _runs(np.abs(z) < 1, 15)
    out[8] = _runs(np.abs(z) > 1, 8)
    return {rule: sorted(int(i) for i in idx) for rule, idx in out.items()}


@dataclass(frozen=True)
class Capability:
    """Process capability against the tolerance zone [lsl, usl] (Montgomery 8.3).

    mean, s: the points' mean and sample standard deviation (ddof 1); cp, cpk with their
    (1 - alpha) confidence intervals (eq. 8.19, 8.20); n: points."""

    n: int
    mean: float
    s: float
    lsl: float
    usl: float
    cp: float
    cp_low: float
    cp_high: float
    cpk: float
    cpk_low: float
    cpk_high: float
    alpha: float


def capability(x: Sequence[float], lsl: float, usl: float, alpha: float = 0.05) -> Capability:
    """Cp and Cpk of ``x`` against [lsl, usl] with their (1 - alpha) intervals.

    Cp: chi-square interval Cp^ sqrt(chi2_{alpha/2, n-1}/(n-1)) .. Cp^ sqrt(chi2_{1-alpha/2,
    n-1}/(n-1)) (Montgomery eq. 8.19, lower-tail quantiles). Cpk: Bissell's
    Cpk^ [1 -+ z_{alpha/2} sqrt(1/(9 n Cpk^2) + 1/(2(n-1)))] (eq. 8.20). n >= 3."""
    a = np.asarray(x, dtype=float)
    if a.size < 3 or not np.all(np.isfinite(a)):
        raise ValueError("a capability needs at least 3 finite values")
    if not usl > lsl:
        raise ValueError("the upper specification limit must exceed the lower")
    n = int(a.size)
    mean = float(np.mean(a))
    s = float(np.std(a, ddof=1))
    if not s > 0:
        raise ValueError("the values do not vary (s = 0): no capability")
    cp = (usl - lsl) / (6 * s)
    cpk = min(usl - mean, mean - lsl) / (3 * s)
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], n - 1)
    z = stats.norm.ppf(1 - alpha / 2)
    half = z * np.sqrt(1 / (9 * n * cpk**2) + 1 / (2 * (n - 1)))
    return Capability(
        n, mean, s, float(lsl), float(usl),
        cp, cp * float(np.sqrt(lo / (n - 1))), cp * float(np.sqrt(hi / (n - 1))),
        cpk, cpk * (1 - half), cpk * (1 + half), alpha,
    )
