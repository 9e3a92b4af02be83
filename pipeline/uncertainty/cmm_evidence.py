"""The CMM's own Type A evidence: the reference lines' fit residuals against the stated sigma.

The registration residuals see the camera and the CMM together (their excess
cannot tell which one holds it, :mod:`crossfield.uncertainty.consistency`). The
arm's probes of a fitted reference line see the arm alone: a cylinder of N probes
leaves N residuals (``distance - radius``) with N - 5 degrees of freedom, a line
2N perpendicular coordinates with 2N - 4 (the dof of
:func:`crossfield.geometry.fit_cylinder_axis` / :func:`~crossfield.geometry.fit_line`),
and with the probes' stated sigma per coordinate sigma (mm) each line gives

    chi2_l = sum_k r_lk^2 / sigma_l^2  ~  lambda_cmm^2 chi2(nu_l)

(lambda_cmm^2 the ratio of the arm's true variance to the stated one; the normal
component of an isotropic probe error has the per-coordinate variance). Over the
plan's lines the statistics and their degrees of freedom add up; the session's
CMM evidence is their sum, taken by the same shrunk variance ratio as the camera's
(:func:`crossfield.uncertainty.type_a.variance_ratio`). The fits are
:func:`crossfield.geometry.fit_reference_element`, the ones the measurement uses;
a line that cannot be fitted gives no evidence (the measurement reports it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossfield.geometry import fit_reference_element
from crossfield.plan import MeasurementPlan
from crossfield.types import ReferenceData

__all__ = ["CmmEvidence", "line_fit_evidence"]


@dataclass(frozen=True)
class CmmEvidence:
    """The reference lines' residual chi-square against the stated sigma (dimensionless),
    its degrees of freedom, and the lines it came from (plan ids)."""

    statistic: float = 0.0
    dof: int = 0
    lines: tuple[str, ...] = ()


def line_fit_evidence(plan: MeasurementPlan, reference: ReferenceData) -> CmmEvidence:
    """The CMM evidence of ``plan``'s reference lines fitted to ``reference``'s probes (see the
    module docstring); no lines (or none fitted, or no stated sigma): ``CmmEvidence()`` (0 dof)."""
    statistic, dof, lines = 0.0, 0, []
    for spec in plan.reference_lines:
        try:
            fit = fit_reference_element(spec, reference.points)
        except ValueError:
            continue
        stated = max((float(p.sigma_mm) for p in reference.labelled(spec.id) if p.label != spec.id), default=0.0)
        n = len(fit.residuals_mm)
        nu = n - 5 if fit.kind == "cylinder" else 2 * n - 4
        if nu <= 0 or not stated > 0:
            continue
        # a line's residual is a distance in the plane normal to it: both coordinates' squares
        statistic += float(np.sum(np.asarray(fit.residuals_mm) ** 2)) / stated**2
        dof += nu
        lines.append(spec.id)
    return CmmEvidence(statistic, dof, tuple(lines))
