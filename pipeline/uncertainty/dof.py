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

* ``camera_systematic``: the camera excess the epipolar residuals show, a posterior
  with ``PRIOR_DOF + m`` degrees of freedom (m matched points per frame;
  :mod:`crossfield.uncertainty.type_a`);
* ``control_cmm``, ``reference_cmm``: the CMM standard deviation times the inflation f
  that the registration residuals support, a posterior with ``PRIOR_DOF + 3n - 6``
  (n controls), floored at the stated value; always (f = 1 included), so that k is
  continuous in the data;
* ``reference_line``: the fitted line's sigma when the fit's own residuals set it (the
  observed above the stated), with the fit's degrees of freedom (a cylinder of N
  probes N - 5, a line 2N - 4); the stated sigma otherwise (infinite);
* ``repeatability``: the scatter of n frames, n - 1;
* the others (camera model, eccentricity, calibration, temperature): stated, infinite.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from scipy.stats import norm, t

__all__ = ["coverage_factor", "effective_dof"]


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
