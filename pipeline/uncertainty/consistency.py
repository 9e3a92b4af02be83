"""Chi-square test of the registration residuals against the stated sigmas; Birge-ratio inflation.

Per frame the registration's residual sum of squares ``SS = sum_k |r_k|^2``
has the expectation ``E = (1 - 6 / 3n) sum_k tr S_k`` (n controls, 3n
coordinates, 6 fitted parameters), split into the stated camera part E_cam
and CMM part E_cmm (:class:`crossfield.types.RegistrationConsistency`). Over
a session's F frames the test statistic is

    T = dof * mean_f(SS_f) / mean_f(E_f),   dof = 3n - 6,

compared with the chi-square distribution with ``dof`` degrees of freedom
(the CMM errors of the controls are one draw, shared by every frame, so the
frames add no degrees of freedom to the CMM part). ``R_B^2 = T / dof`` is the
Birge ratio squared (Birge 1932; Kacker, Datta & Possolo 2004, Metrologia 41).

The rule: when the test rejects (p = P(chi2_dof >= T) < ``alpha``, default
0.05), the stated sigmas are contradicted by the data; the excess is put on
the CMM (the camera part is checked per frame by the triangulation's
reprojection residuals, the CMM sigma is a number typed into a file): the
CMM standard deviation is multiplied by

    f = sqrt(max(1, (mean SS - mean E_cam) / mean E_cmm)),

the data-supported value, for the control points and the reference points
alike (same arm). Otherwise f = 1.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from scipy.stats import chi2

from crossfield.types import RegistrationConsistency

__all__ = ["ALPHA", "ConsistencyCheck", "ConsistencyRun", "check"]

ALPHA = 0.05


@dataclass(frozen=True)
class ConsistencyCheck:
    """Result of the test. observed/expected residual sums of squares (mm^2, mean per
    frame); chi2 and dof; p_value; birge_ratio R_B; consistent (p >= alpha);
    cmm_inflation f (>= 1, 1 when consistent); warning text when not consistent."""

    n_frames: int
    observed_ss_mm2: float
    expected_camera_ss_mm2: float
    expected_cmm_ss_mm2: float
    dof: int
    chi2: float
    p_value: float
    birge_ratio: float
    alpha: float
    consistent: bool
    cmm_inflation: float
    warning: str | None


class ConsistencyRun:
    """Running means of the per-frame residual statistics (bounded memory)."""

    __slots__ = ("dof", "e_cam", "e_cmm", "n", "ss")

    def __init__(self) -> None:
        self.n = 0
        self.ss = self.e_cam = self.e_cmm = 0.0
        self.dof = 0

    def add(self, c: RegistrationConsistency) -> None:
        self.n += 1
        self.ss += (c.observed_ss_mm2 - self.ss) / self.n
        self.e_cam += (c.expected_camera_ss_mm2 - self.e_cam) / self.n
        self.e_cmm += (c.expected_cmm_ss_mm2 - self.e_cmm) / self.n
        self.dof = max(self.dof, int(c.dof))

    def result(self, alpha: float = ALPHA, reference: str = "") -> ConsistencyCheck | None:
        return check_means(self.n, self.ss, self.e_cam, self.e_cmm, self.dof, alpha, reference)


def check_means(
    n: int, ss: float, e_cam: float, e_cmm: float, dof: int, alpha: float = ALPHA, reference: str = ""
) -> ConsistencyCheck | None:
    """The test from per-frame means (see the module docstring); None without data."""
    expected = e_cam + e_cmm
    if n == 0 or dof <= 0 or expected <= 0:
        return None
    T = dof * ss / expected
    p = float(chi2.sf(T, dof))
    consistent = p >= alpha
    inflation = 1.0
    warning = None
    if not consistent:
        if e_cmm > 0:
            inflation = math.sqrt(max(1.0, (ss - e_cam) / e_cmm))
        warning = (
            f"registration residuals contradict the stated sigmas: chi2 = {T:.1f} for {dof} degrees of "
            f"freedom (p = {p:.2g}, Birge ratio {math.sqrt(T / dof):.2f}); the CMM standard deviation "
            f"{('stated by ' + reference + ' ') if reference else ''}is inflated by {inflation:.2f} in the budget"
        )
    return ConsistencyCheck(
        n, ss, e_cam, e_cmm, dof, T, p, math.sqrt(T / dof), alpha, consistent, inflation, warning
    )


def check(frames: Iterable[RegistrationConsistency], alpha: float = ALPHA) -> ConsistencyCheck | None:
    """The test over the frames' residual statistics."""
    run = ConsistencyRun()
    for c in frames:
        run.add(c)
    return run.result(alpha)


def describe_reference(name: str, sigmas_mm: Iterable[float], options: Mapping[str, Any]) -> str:
    """The reference source as the consistency warning names it: the plugin ``name``,
    the per-coordinate sigma(s) its points state (mm) and where they came from
    (``options`` holds ``sigma_mm``: the configuration; else the plugin's default, for
    ``romer-serial`` its ``arm_model``'s specification)."""
    values = sorted({float(s) for s in sigmas_mm})
    stated = " to ".join(f"{v:g}" for v in (values[:1] + values[-1:] if len(values) > 1 else values))
    if "sigma_mm" in options:
        origin = "option sigma_mm"
    elif "arm_model" in options:
        origin = f"the {options['arm_model']} arm model's specification"
    else:
        origin = "the plugin's default"
    return f"the reference source {name!r} ({stated or 'no'} mm per coordinate, {origin})"
