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

The test still warns when it rejects (p = P(chi2_dof >= T) < ``alpha``,
default 0.05). The inflation no longer waits for it (until issue 22 it did: a
knife edge that changed U by up to 4x between sessions of one station): both
pieces of Type A evidence enter through the shrunk variance ratio of
:mod:`crossfield.uncertainty.type_a`, continuous in the data:

1. the camera: the frames' epipolar chi-square (``epipolar_chi2`` over
   ``epipolar_count`` matched points, 1 dof each). The evidence's degrees of
   freedom are the points of one frame, m (a centroid bias is the same in
   every frame: the frames add none), so ``s_cam^2 = variance_ratio(m x, m)``
   with x the mean chi-square per point; ``camera_excess = max(0, s_cam^2 - 1)``
   is the camera variance the evidence adds, in units of the model's camera
   variance (the budget's ``camera_systematic`` source, not divided by the
   number of frames);
2. the registration: its expectation with that camera evidence,
   ``E' = E_cam (1 + camera_excess) + E_cmm``, ``T' = dof mean(SS) / E'``,
   ``s_reg^2 = variance_ratio(T', dof)``; the rest of the excess is put on the
   CMM (its sigma is a number typed into a file), which is multiplied by

    f = sqrt(max(1, (s_reg^2 E' - E_cam (1 + camera_excess)) / E_cmm)),

the data-supported value, for the control points and the reference points
alike (same arm).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from scipy.stats import chi2

from crossfield.types import RegistrationConsistency
from crossfield.uncertainty.type_a import variance_ratio

__all__ = ["ALPHA", "ConsistencyCheck", "ConsistencyRun", "check"]

ALPHA = 0.05


@dataclass(frozen=True)
class ConsistencyCheck:
    """Result of the test. observed/expected residual sums of squares (mm^2, mean per
    frame); chi2 and dof; p_value; birge_ratio R_B; consistent (p >= alpha);
    cmm_inflation f (>= 1, from the shrunk ratio whether or not the test rejects);
    warning text when not consistent. Camera evidence: epipolar_points m (matched
    points per frame), epipolar_chi2_per_point x (mean, E = 1 under the model),
    camera_ratio s_cam^2, camera_excess max(0, s_cam^2 - 1); note: which evidence
    set the camera and CMM terms (None when the model did)."""

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
    epipolar_points: float = 0.0
    epipolar_chi2_per_point: float = math.nan
    camera_ratio: float = 1.0
    camera_excess: float = 0.0
    note: str | None = None


class ConsistencyRun:
    """Running means of the per-frame residual statistics (bounded memory)."""

    __slots__ = ("dof", "e_cam", "e_cmm", "epi_chi2", "epi_count", "n", "ss")

    def __init__(self) -> None:
        self.n = 0
        self.ss = self.e_cam = self.e_cmm = 0.0
        self.dof = 0
        self.epi_chi2 = 0.0
        self.epi_count = 0

    def add(self, c: RegistrationConsistency) -> None:
        self.n += 1
        self.ss += (c.observed_ss_mm2 - self.ss) / self.n
        self.e_cam += (c.expected_camera_ss_mm2 - self.e_cam) / self.n
        self.e_cmm += (c.expected_cmm_ss_mm2 - self.e_cmm) / self.n
        self.dof = max(self.dof, int(c.dof))
        self.epi_chi2 += float(getattr(c, "epipolar_chi2", 0.0))
        self.epi_count += int(getattr(c, "epipolar_count", 0))

    def result(self, alpha: float = ALPHA, reference: str = "") -> ConsistencyCheck | None:
        return check_means(
            self.n, self.ss, self.e_cam, self.e_cmm, self.dof, alpha, self.epi_chi2, self.epi_count, reference
        )


def check_means(
    n: int, ss: float, e_cam: float, e_cmm: float, dof: int, alpha: float = ALPHA,
    epipolar_chi2: float = 0.0, epipolar_count: int = 0, reference: str = "",
) -> ConsistencyCheck | None:
    """The test and the Type A rule from per-frame means (see the module docstring); None without data.

    epipolar_chi2, epipolar_count: the sums over the session's frames."""
    expected = e_cam + e_cmm
    if n == 0 or dof <= 0 or expected <= 0:
        return None
    T = dof * ss / expected
    p = float(chi2.sf(T, dof))
    consistent = p >= alpha
    # 1. the camera, from the epipolar residuals (m points per frame: the dof of a bias)
    m = epipolar_count / n
    x = epipolar_chi2 / epipolar_count if epipolar_count else math.nan
    camera_ratio = variance_ratio(m * x, m) if epipolar_count else 1.0
    camera_excess = max(0.0, camera_ratio - 1.0)
    # 2. the registration residuals with that camera evidence; the rest on the CMM
    e_cam_a = e_cam * (1.0 + camera_excess)
    expected_a = e_cam_a + e_cmm
    reg_ratio = variance_ratio(dof * ss / expected_a, dof)
    inflation = math.sqrt(max(1.0, (reg_ratio * expected_a - e_cam_a) / e_cmm)) if e_cmm > 0 else 1.0
    warning = None
    if not consistent:
        warning = (
            f"registration residuals contradict the stated sigmas: chi2 = {T:.1f} for {dof} degrees of "
            f"freedom (p = {p:.2g}, Birge ratio {math.sqrt(T / dof):.2f}); the CMM standard deviation "
            f"{('stated by ' + reference + ' ') if reference else ''}is inflated by {inflation:.2f} in the budget"
        )
    notes = []
    if camera_excess > 0:
        notes.append(
            f"camera term set by Type A evidence (epipolar residuals: chi2 {x:.2f} per point over {m:.0f} points "
            f"per frame, shrunk ratio {camera_ratio:.2f}): camera_systematic adds {camera_excess:.2f} x the "
            "model's camera variance"
        )
    if inflation > 1.0:
        notes.append(
            f"CMM standard deviation {('stated by ' + reference + ' ') if reference else ''}inflated by "
            f"{inflation:.2f} (Type A evidence: registration residuals, "
            f"shrunk ratio {reg_ratio:.2f} for {dof} degrees of freedom)"
        )
    return ConsistencyCheck(
        n, ss, e_cam, e_cmm, dof, T, p, math.sqrt(T / dof), alpha, consistent, inflation, warning,
        m, x, camera_ratio, camera_excess, "; ".join(notes) or None,
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
