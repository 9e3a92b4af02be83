"""Degrees of freedom of a budget and the Student-t coverage factor (GUM, JCGM 100:2008, annex G).

A budget term whose variance is *estimated* from the session's own data (Type A, or a
Type B value the Type A evidence replaced) is known only to its degrees of freedom nu;
a stated (Type B) value counts as exact (nu = infinity). The combined standard
uncertainty then has the Welch-Satterthwaite effective degrees of freedom

    nu_eff = u_c^4 / sum_i (u_i^4 / nu_i)                       (GUM eq. (G.2b))

and the expanded uncertainty for the coverage probability p is U = t_p(nu_eff) u_c
(GUM G.4.1, eq. (G.1d)). The plan states k for a normal output (2 by default); its
coverage probability p = 2 Phi(k) - 1 (95.45 % for k = 2) is kept and the factor
becomes ``t_p(nu_eff)``, k itself when every term is stated (nu_eff infinite).

Which terms have finite nu (:func:`source_dof`, ``docs/uncertainty.md``):

Only what the data estimated beyond a stated value carries finite degrees of freedom:
a term that is a stated floor plus an excess, w of its variance, has ``nu / w^2``
(:func:`excess_dof`), infinite when the stated value holds, so k is continuous in the
data and equals the plan's k where the evidence agrees with the model:

* ``camera_systematic`` (all excess): ``PRIOR_DOF + m`` (m matched points per frame;
  the posterior of :mod:`crossfield.uncertainty.type_a`);
* ``control_cmm``, ``reference_cmm``: the stated sigma times the inflation f, excess
  ``w = 1 - 1 / f^2``, estimated with the posterior's ``PRIOR_DOF + 3n - 6`` (n controls);
* ``reference_line``: the fit's sigma, the larger of the stated and its residuals',
  excess ``w = 1 - stated^2 / sigma^2``, with the fit's degrees of freedom (a cylinder
  of N probes N - 5, a line 2N - 4; ``plugins/measure_plan.py``);
* ``repeatability`` (the scatter beyond the modelled camera part: all excess): n - 1;
* the others (camera model, eccentricity, calibration, temperature): stated, infinite.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from scipy.stats import norm, t

__all__ = ["coverage_factor", "effective_dof", "excess_dof", "parts_dof"]


def excess_dof(nu: float, excess_fraction: float) -> float:
    """The degrees of freedom of a term whose variance is a stated floor plus an excess,
    ``excess_fraction`` w of the whole (0..1), that data with ``nu`` degrees of freedom
    estimated: ``nu / w^2`` (GUM eq. (G.3), nu_i = (Delta u_i / u_i)^-2 / 2, with
    Delta(u^2) = w u^2 sqrt(2 / nu)); infinite for w = 0 (the stated value)."""
    w = min(max(float(excess_fraction), 0.0), 1.0)
    if w <= 0 or not nu > 0:
        return math.inf
    return float(nu) / (w * w)


def parts_dof(parts: Iterable[tuple[float, float]]) -> float:
    """The degrees of freedom of a variance estimate made of independently estimated parts
    ``(variance, nu)``: Welch-Satterthwaite, ``(sum v)^2 / sum (v^2 / nu)`` (GUM eq. (G.2b) with the
    variances as the estimates); ``math.inf`` when the sum is 0 (nothing estimated)."""
    parts = [(max(float(v), 0.0), float(nu)) for v, nu in parts]
    total = sum(v for v, _ in parts)
    denominator = sum(v * v / nu for v, nu in parts if v > 0 and nu > 0)
    return total * total / denominator if total > 0 and denominator > 0 else math.inf


def effective_dof(terms: Iterable[tuple[float, float]]) -> float:
    """Welch-Satterthwaite nu_eff of ``(u_i (mm), nu_i)`` pairs (GUM eq. (G.2b));
    ``math.inf`` when no term with a contribution has finite nu."""
    terms = [(abs(float(u)), float(nu)) for u, nu in terms]
    u4 = sum(u * u for u, _ in terms) ** 2
    denominator = sum(u**4 / nu for u, nu in terms if u > 0 and math.isfinite(nu) and nu > 0)
    if denominator <= 0 or u4 <= 0:
        return math.inf
    return u4 / denominator


def coverage_factor(k_normal: float, nu_eff: float) -> float:
    """The Student-t factor ``t_p(nu_eff)`` with p = 2 Phi(k_normal) - 1, the coverage
    probability of ``k_normal`` for a normal output (GUM G.3.4, G.4.1); ``k_normal``
    itself for infinite nu_eff."""
    if not math.isfinite(nu_eff) or nu_eff <= 0:
        return float(k_normal)
    p = 2.0 * float(norm.cdf(k_normal)) - 1.0
    return float(t.ppf(0.5 + p / 2.0, nu_eff))
