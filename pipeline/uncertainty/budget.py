"""Uncertainty budgets: per-source contributions, combined and expanded uncertainty.

A characteristic Y = f(X_1 ... X_N) with independent sources gives, to first
order, the combined standard uncertainty (GUM, JCGM 100:2008, eq. (10))

    u_c(y)^2 = sum_i (c_i u(x_i))^2 ,

and the expanded uncertainty U = k u_c(y) (GUM 6.2.1), k = 2 by default
(about 95 % coverage for a near-normal output). A source made of several
correlated inputs (the control points through the shared registration) is
one term whose contribution already holds the correlations (GUM eq. (13)
in matrix form, ``c^T Sigma c``); its ``sensitivity`` is then the effective
one, ``u_mm / u``. The sources of a crossfield characteristic:
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

from crossfield.types import BudgetTerm

__all__ = [
    "SOURCES",
    "SOURCE_TEXT",
    "camera_terms",
    "combined",
    "expanded",
    "merge",
    "scaled",
    "term",
]

#: Budget sources, in report order, with what each holds.
SOURCE_TEXT: dict[str, str] = {
    "camera": "centroid noise of the camera points (target and control points, through the triangulation "
    "and the registration); drawn anew in every frame: the per-frame value divided by sqrt(n) for the mean",
    "camera_systematic": "Type A: the part of the centroid error the session's own epipolar residuals show "
    "beyond the model's (a bias the model does not know: PSF, lens, sensor), max(0, s^2 - 1) x the camera "
    "variance of one frame (s^2 the shrunk variance ratio, crossfield.uncertainty.type_a); fixed for the "
    "session: not divided by sqrt(n)",
    "eccentricity": "perspective eccentricity of circle centres (projected centre of a tilted circle is "
    "not the projection of its centre), uniform over the stated tilt range",
    "calibration": "the stereo calibration's parameter uncertainty: the calibration file's std_* keys "
    "propagated through the triangulation, the registration and the measurement (one error for the "
    "session: not divided by sqrt(n)); without them a relative scale of camera-frame distances (std_T, "
    "std_M1/M2, else the stated default)",
    "control_cmm": "CMM coordinates of the common control points, through the shared registration",
    "reference_cmm": "CMM coordinates of the reference points used directly (inflated, like control_cmm, "
    "when the residual check finds the stated sigma too small)",
    "reference_line": "fitted reference lines (cylinder or line axes): their probes' scatter, the larger of the "
    "stated sigma and the fit's own residuals (data-supported already: not inflated again)",
    "repeatability": "scatter over the frames beyond the modelled per-frame (camera) noise of the mean: "
    "sqrt(max(0, s^2 / n - u_camera^2))",
    "temperature": "correction to 20 degC (ISO 1): part and reference temperatures and expansion "
    "coefficients",
}
SOURCES: tuple[str, ...] = tuple(SOURCE_TEXT)


def term(source: str, u: float, unit: str, u_mm: float) -> BudgetTerm:
    """A budget line from its input uncertainty ``u`` (``unit``) and contribution ``u_mm``
    (mm, >= 0); the sensitivity is ``u_mm / u`` (0 when ``u`` is 0)."""
    if source not in SOURCE_TEXT:
        raise ValueError(f"unknown budget source {source!r}; sources: {', '.join(SOURCES)}")
    u_mm = abs(float(u_mm))
    u = abs(float(u))
    return BudgetTerm(source, u, unit, u_mm / u if u > 0 else 0.0, u_mm)


def combined(budget: Iterable[BudgetTerm]) -> float:
    """Combined standard uncertainty (mm): the root sum of squares of the contributions
    (GUM eq. (10); the sources are independent of each other)."""
    return math.sqrt(sum(t.u_mm * t.u_mm for t in budget))


def expanded(u_c: float | None, k: float) -> float | None:
    """Expanded uncertainty ``U = k u_c`` (GUM 6.2.1), mm; None when u_c is unknown."""
    return None if u_c is None else float(k) * float(u_c)


def scaled(t: BudgetTerm, factor: float) -> BudgetTerm:
    """``t`` with its input uncertainty and contribution multiplied by ``factor`` (>= 0)."""
    return BudgetTerm(t.source, t.u * factor, t.unit, t.sensitivity, t.u_mm * factor)


def merge(variances: Mapping[str, tuple[float, str, float]]) -> tuple[BudgetTerm, ...]:
    """Budget terms from ``source -> (u, unit, variance mm^2)``, in :data:`SOURCES` order (other
    keys are left out): :func:`term` of ``u`` and ``sqrt(max(variance, 0))``."""
    out = []
    for source in SOURCES:
        entry = variances.get(source)
        if entry is not None:
            u, unit, variance = entry
            out.append(term(source, u, unit, math.sqrt(max(variance, 0.0))))
    return tuple(out)


def camera_terms(
    camera: BudgetTerm, n_frames: int, camera_excess: float, registration_mm2: float = 0.0
) -> tuple[BudgetTerm, ...]:
    """The session's camera sources from the per-frame ``camera`` term (RMS over the frames).

    ``camera``: the random part, drawn anew in every frame, of the mean of
    ``n_frames``: ``u / sqrt(n)`` (GUM 4.2.3). ``camera_systematic`` (when
    ``camera_excess`` > 0, :mod:`crossfield.uncertainty.type_a`): the part the
    session's epipolar residuals show beyond the model, ``sqrt(camera_excess)``
    times the per-frame term, plus ``registration_mm2`` (mm^2), the camera's share of
    the registration residuals' excess carried through the registration
    (:mod:`crossfield.uncertainty.consistency`): ``u^2 = camera_excess u_camera^2 +
    registration_mm2``, a bias fixed for the session: **not** divided by sqrt(n) (a
    systematic effect does not average out, GUM 3.2.3-3.2.4)."""
    n = max(int(n_frames), 1)
    out = [scaled(camera, 1.0 / math.sqrt(n))]
    variance = max(camera_excess, 0.0) * camera.u_mm**2 + max(registration_mm2, 0.0)
    if variance > 0:
        u_mm = math.sqrt(variance)
        # the input u in the camera term's unit, at its sensitivity (u_mm / sensitivity)
        u = camera.u * u_mm / camera.u_mm if camera.u_mm > 0 else 0.0
        out.append(BudgetTerm("camera_systematic", u, camera.unit, camera.sensitivity, u_mm))
    return tuple(out)
