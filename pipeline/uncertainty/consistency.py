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
knife edge that changed U by up to 4x between sessions of one station): the
pieces of Type A evidence enter through the shrunk variance ratio of
:mod:`crossfield.uncertainty.type_a`, continuous in the data. Each source's own
evidence comes first, the registration's excess beyond it is split between them
by that evidence (issue 22, third round):

1. the camera's own: the frames' epipolar chi-square (``epipolar_chi2`` over
   ``epipolar_count`` matched points, 1 dof each). The evidence's degrees of
   freedom are the points of one frame, m (a centroid bias is the same in
   every frame: the frames add none), so ``s_cam^2 = variance_ratio(m x, m)``
   with x the mean chi-square per point, ``a = max(0, s_cam^2 - 1)``;
2. the CMM's own: the reference lines' fit residuals against the stated sigma
   (:mod:`crossfield.uncertainty.cmm_evidence`, ``cmm_statistic`` with
   ``cmm_dof``), ``s_L^2 = variance_ratio(cmm_statistic, cmm_dof)``,
   ``b = max(0, s_L^2 - 1)`` (0 without lines);
3. the registration residuals against the expectation with both,
   ``E' = E_cam (1 + a) + E_cmm (1 + b)``, ``T' = dof mean(SS) / E'``,
   ``s_reg^2 = variance_ratio(T', dof)``; what neither source's own evidence
   explains, ``X = max(0, s_reg^2 - 1) E'`` (mm^2), is split **in proportion to each
   source's evidence of its own excess** at the controls,

       w_cam = e_cam E_cam,   w_cmm = e_cmm E_cmm,   X_cmm = X w_cmm / (w_cam + w_cmm),

   with ``e = E[max(0, lambda^2 - 1)]`` the posterior mean excess of the source's own
   evidence (:func:`crossfield.uncertainty.type_a.expected_excess`: never 0, continuous;
   a source without evidence has the prior's 1.13, one whose evidence agrees with its
   model less, one whose evidence shows an excess more), so that an understated arm
   (its line fits' residuals raised) takes the registration's excess and a camera whose
   epipolar residuals show a bias (and, unseen by them, biases along the line of sight)
   takes it otherwise. The budget's terms:

       f^2 = 1 + b + X_cmm / E_cmm                 (the CMM sigma's factor)
       camera_excess = a                           (every camera point: camera_systematic)
       camera_registration_excess = (X - X_cmm) / E_cmm

   f multiplies the CMM standard deviation of controls and reference points alike
   (same arm). The camera's share of the registration excess is evidence about the
   controls only (a bias along the lines of sight there, which the epipolar residuals
   cannot see), so it enters through the registration only: as an isotropic error at
   the controls with the same trace, i.e. the stated ``control_cmm`` term times
   ``sqrt(camera_registration_excess)`` (the registration covariance is linear in the
   controls' covariance, and for ``sigma^2 I`` at every control it is
   ``sigma^2 (J^T J)^-1``), added to the budget's ``camera_systematic`` source; the
   targets' own camera error keeps the epipolar evidence's ``a``. Neither part is
   divided by the number of frames (a bias). Without a stated CMM sigma (E_cmm = 0)
   the camera's share goes to ``camera_excess`` (X / E_cam).

Degrees of freedom of the estimates: ``a`` has the epipolar posterior's ``PRIOR_DOF + m``
(``camera_excess_dof``), the registration shares ``PRIOR_DOF + dof``
(``registration_excess_dof``); the CMM's excess ``b + X_cmm / E_cmm``, from two pieces of
evidence, the Welch-Satterthwaite combination of its parts,
``nu = (p + q)^2 / (p^2 / nu_p + q^2 / nu_q)`` (GUM eq. (G.2b) applied to the variance
estimate; ``cmm_excess_dof``), with ``nu_p = PRIOR_DOF + cmm_dof``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from scipy.stats import chi2

from crossfield.types import RegistrationConsistency
from crossfield.uncertainty.dof import parts_dof
from crossfield.uncertainty.type_a import PRIOR_DOF, expected_excess, variance_ratio

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
    set the camera and CMM terms (None when the model did). The split (module docstring):
    camera_registration_excess (X - X_cmm) / E_cmm, the camera's share of the registration
    excess in units of the stated CMM variance at the controls; cmm_evidence_dof and
    cmm_ratio s_L^2 (the line fits), cmm_line_excess b; cmm_share X_cmm / X (the weights'
    share, also when X = 0); camera_excess_dof, registration_excess_dof, cmm_excess_dof the
    degrees of freedom of the excesses (inf when 0)."""

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
    camera_registration_excess: float = 0.0
    cmm_evidence_dof: int = 0
    cmm_ratio: float = 1.0
    cmm_line_excess: float = 0.0
    cmm_share: float = 1.0
    camera_excess_dof: float = math.inf
    registration_excess_dof: float = math.inf
    cmm_excess_dof: float = math.inf


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

    def result(
        self, alpha: float = ALPHA, reference: str = "", cmm_statistic: float = 0.0, cmm_dof: int = 0
    ) -> ConsistencyCheck | None:
        """The check over the frames added; cmm_statistic, cmm_dof: the CMM's own evidence
        (:func:`crossfield.uncertainty.cmm_evidence.line_fit_evidence`)."""
        return check_means(
            self.n, self.ss, self.e_cam, self.e_cmm, self.dof, alpha, self.epi_chi2, self.epi_count, reference,
            cmm_statistic, cmm_dof,
        )


def check_means(
    n: int, ss: float, e_cam: float, e_cmm: float, dof: int, alpha: float = ALPHA,
    epipolar_chi2: float = 0.0, epipolar_count: int = 0, reference: str = "",
    cmm_statistic: float = 0.0, cmm_dof: int = 0,
) -> ConsistencyCheck | None:
    """The test and the Type A rule from per-frame means (see the module docstring); None without data.

    ss, e_cam, e_cmm: mean observed and expected residual sums of squares per frame (mm^2);
    epipolar_chi2, epipolar_count: the sums over the session's frames; cmm_statistic, cmm_dof:
    the reference lines' residual chi-square against the stated sigma and its dof."""
    expected = e_cam + e_cmm
    if n == 0 or dof <= 0 or expected <= 0:
        return None
    T = dof * ss / expected
    p = float(chi2.sf(T, dof))
    consistent = p >= alpha
    # 1. the camera's own evidence, the epipolar residuals (m points per frame: the dof of a bias)
    m = epipolar_count / n
    x = epipolar_chi2 / epipolar_count if epipolar_count else math.nan
    camera_ratio = variance_ratio(m * x, m) if epipolar_count else 1.0
    a = max(0.0, camera_ratio - 1.0)
    e_camera = expected_excess(m * x, m) if epipolar_count else expected_excess(0.0, 0)
    # 2. the CMM's own evidence, the reference lines' fit residuals
    cmm_ratio = variance_ratio(cmm_statistic, cmm_dof)
    b = max(0.0, cmm_ratio - 1.0)
    e_arm = expected_excess(cmm_statistic, cmm_dof)
    # 3. the registration residuals beyond the camera's own evidence and the stated CMM sigma,
    #    split by each source's own evidence of excess
    expected_a = e_cam * (1.0 + a) + e_cmm
    T_a = dof * ss / expected_a
    reg_ratio = variance_ratio(T_a, dof)
    w_cam, w_cmm = e_camera * e_cam, e_arm * e_cmm
    share = w_cmm / (w_cam + w_cmm) if w_cam + w_cmm > 0 else (1.0 if e_cmm > 0 else 0.0)
    if e_cmm > 0:
        # the CMM's share of the registration, as a chi-square statistic on its variance ratio
        # (signed: residuals below the expectation are evidence too), pooled with the line fits'
        registration_statistic = max(0.0, dof * (1.0 + share * (T_a / dof - 1.0) * expected_a / e_cmm))
        pooled = variance_ratio(cmm_statistic + registration_statistic, cmm_dof + dof)
        inflation = math.sqrt(max(1.0, pooled))
        # the camera's share: the shrunk registration excess, in units of the stated CMM variance
        c_cam, camera_excess = (1.0 - share) * max(0.0, reg_ratio - 1.0) * expected_a / e_cmm, a
    else:  # no stated CMM sigma to carry it through the registration: on every camera point
        inflation, c_cam = 1.0, 0.0
        camera_excess = a + (max(0.0, reg_ratio - 1.0) * expected_a / e_cam if e_cam > 0 else 0.0)
    nu_reg = PRIOR_DOF + dof
    camera_dof = parts_dof(((a, PRIOR_DOF + m), (camera_excess - a, nu_reg)))
    cmm_excess_dof = PRIOR_DOF + cmm_dof + dof if inflation > 1.0 else math.inf
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
    if c_cam > 0:
        notes.append(
            f"registration residuals beyond the stated sigmas (shrunk ratio {reg_ratio:.2f} for {dof} degrees of "
            f"freedom): {1 - share:.0%} of their excess put on the camera at the controls by its own evidence "
            f"(camera_systematic through the registration, {c_cam:.2f} x the stated CMM variance there)"
        )
    if inflation > 1.0:
        lines = f"the reference line fits' residuals (shrunk ratio {cmm_ratio:.2f}, {cmm_dof} dof) and " if cmm_dof else ""
        notes.append(
            f"CMM standard deviation {('stated by ' + reference + ' ') if reference else ''}inflated by "
            f"{inflation:.2f} (Type A evidence: {lines}{share:.0%} of the registration residuals' excess "
            f"(shrunk ratio {reg_ratio:.2f} for {dof} degrees of freedom) by the CMM's own evidence)"
        )
    return ConsistencyCheck(
        n, ss, e_cam, e_cmm, dof, T, p, math.sqrt(T / dof), alpha, consistent, inflation, warning,
        m, x, camera_ratio, camera_excess, "; ".join(notes) or None,
        c_cam, int(cmm_dof), cmm_ratio, b, share, camera_dof, nu_reg if c_cam > 0 else math.inf, cmm_excess_dof,
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
