"""Type A evidence on the stated variances: a shrunk (Bayesian) variance ratio, no knife edge.

A session's own data test the variances the budget assumes (Type B: the
centroid model's sigma_uv, the CMM's stated sigma):

* the **epipolar residuals**: each matched target's weighted reprojection
  residual ``chi2_i = sum_k r_ik^2 / sigma_ik^2`` over its four image
  coordinates has 4 - 3 = 1 degree of freedom and expectation 1 when the
  centroids' errors are as the model states (Hartley & Zisserman 4.2.6,
  12.4); a centroid bias that differs between the two cameras (a PSF, lens or
  sensor the model does not know) raises it;
* the **registration residuals** against their predicted covariance
  (:mod:`crossfield.uncertainty.consistency`, ``T ~ chi2(3n - 6)``);
* the **scatter between frames** (the budget's ``repeatability``).

**Rule** (for the first two). With ``nu`` degrees of freedom of evidence,
observed ratio ``x = statistic / nu`` (``E[x] = 1`` under the model), the
variance ratio lambda^2 = (true variance) / (model variance) has, for a
scaled-inverse-chi-square prior with ``nu0`` degrees of freedom centred on
the model (lambda0^2 = 1), the posterior Scaled-Inv-chi2(nu0 + nu, s^2) with
scale

    s^2 = (nu0 * 1 + nu * x) / (nu0 + nu)

(Gelman et al., Bayesian Data Analysis, 3rd ed., sec. 2.6, the normal model
with unknown variance; the precision-weighted pool of the model and the
data). The budget takes ``s^2`` where it exceeds 1 and the model (1) otherwise:
continuous in the data, so U moves smoothly between sessions; with little
evidence (small nu) it stays near the model, with much it follows the data.
``E[s^2] = 1`` under the model, so on a session that agrees U grows only by
the positive part of the noise of s^2, ``E[(s^2 - 1)_+] ~ 0.4 sd(s^2)``,
``sd(s^2) = sqrt(2 nu) / (nu0 + nu)``.

:data:`PRIOR_DOF` = 4: the model counts as much as four targets' evidence
(tests/measure/test_type_a.py checks, on constructed sessions, that an injected bias
is covered and that without it U does not grow by more than a few percent).

The posterior scale, not an upper quantile, and k = 2 (no Student-t on top): the
shrinkage is the rule for few degrees of freedom; on the mismatch scenarios a
Welch-Satterthwaite t-factor on top covered 98 % (docs/uncertainty.md).
"""

from __future__ import annotations

import math

from scipy.stats import invgamma

__all__ = ["PRIOR_DOF", "excess", "expected_excess", "variance_ratio"]

#: Degrees of freedom of the prior on the model's variance (scaled-inverse-chi-square at 1).
PRIOR_DOF = 4.0


def variance_ratio(statistic: float, dof: float, prior_dof: float = PRIOR_DOF) -> float:
    """The posterior scale s^2 of the variance ratio (see the module docstring).

    statistic: a chi-square-like sum with expectation ``dof`` under the model
    (dimensionless); dof: its degrees of freedom (> 0; else the model, 1)."""
    if not dof > 0 or not math.isfinite(statistic):
        return 1.0
    return (prior_dof + statistic) / (prior_dof + dof)


def excess(statistic: float, dof: float, prior_dof: float = PRIOR_DOF) -> float:
    """``max(0, s^2 - 1)``: the variance the evidence adds to the model's, in units of the model's."""
    return max(0.0, variance_ratio(statistic, dof, prior_dof) - 1.0)


def expected_excess(statistic: float, dof: float, prior_dof: float = PRIOR_DOF) -> float:
    """The posterior mean of the excess ``E[max(0, lambda^2 - 1)]`` (in units of the model's variance).

    The posterior of the variance ratio is Scaled-Inv-chi2(nu', s^2), nu' = prior_dof + dof and
    s^2 = :func:`variance_ratio`, i.e. an inverse gamma with shape a = nu'/2 and scale
    b = nu' s^2 / 2 (Gelman et al., BDA3, sec. 2.6 and appendix A), so

        E[(lambda^2 - 1)_+] = b / (a - 1) P(IG(a - 1, b) > 1) - P(IG(a, b) > 1)

    (the first term is E[lambda^2; lambda^2 > 1], by the inverse gamma's density
    x p_IG(a, b)(x) = b / (a - 1) p_IG(a - 1, b)(x)). Unlike the positive part of s^2 it is
    never 0 and continuous in the data: it weighs how much excess a source may hold by
    its own evidence (no evidence, dof 0: the prior's 1.13; 7 dof that agree with the
    model: 0.33; 14 points at s^2 = 2.4: 1.7). Needs nu' > 2."""
    nu = prior_dof + (dof if dof > 0 and math.isfinite(statistic) else 0.0)
    if not nu > 2:
        raise ValueError(f"expected_excess needs prior_dof + dof > 2, got {nu}")
    a = nu / 2.0
    b = nu * variance_ratio(statistic, dof, prior_dof) / 2.0
    return max(0.0, b / (a - 1.0) * float(invgamma.sf(1.0, a - 1.0, scale=b)) - float(invgamma.sf(1.0, a, scale=b)))
