"""Session aggregates computed while the session runs, in memory that does not grow with its length.

A measuring station runs for hours at 14 stereo pairs/s, so a session cannot
keep every frame's results until its report. :class:`SessionAccumulator` takes
each frame's result as soon as it is done and keeps only:

* running statistics (count, mean, sum of squared deviations) per
  characteristic, of the registration (rotation matrix, translation, scale,
  fit RMS) and of each control point's residual;
* the first ``rows_kept`` frame results, slim (no centroids, no camera
  points), for the report's per-frame table;
* the first ``errors_kept`` failed frames' errors, and counts (frames
  processed, failed, targets not found).

Every frame's full results go to the observers as they are made (the MCAP
recording holds them all: topics /frames, /registration, /measurement).

Numerics: means and variances use Welford's update (Welford 1962; Knuth,
TAOCP vol. 2, 4.2.2, eqs. (15)-(16)): for the k-th value x,
``delta = x - mean; mean += delta / k; m2 += delta * (x - mean)``, which does
not suffer the cancellation of ``sum(x^2) - n mean^2``, on data shifted by
their first value (see :class:`RunningStats`). Every update is a
fixed sequence of IEEE float64 operations in frame order, so feeding the same
frame results again (a replay) reproduces every float bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crossfield.uncertainty.instruments import gate_characteristics
from crossfield.plan import CharacteristicSpec, MeasurementPlan
from crossfield.rigid import chord_to_angle, project_to_rotation, rotation_angle
from crossfield.session import (
    CameraThumbnail,
    CharacteristicSummary,
    ControlResidual,
    FrameError,
    FrameResult,
    RegistrationAggregate,
    SessionAggregate,
    SessionInfo,
    SessionStop,
    SessionSummary,
)
from crossfield.types import (
    BudgetTerm,
    CharacteristicResult,
    ReferenceData,
    Registration,
    RegistrationConsistency,
)
from crossfield.uncertainty import budget as _budget
from crossfield.uncertainty.calibration import DEFAULT_SCALE_U, calibration_uncertainty
from crossfield.uncertainty.cmm_evidence import CmmEvidence, line_fit_evidence
from crossfield.uncertainty.consistency import ConsistencyRun
from crossfield.uncertainty.decision import decide
from crossfield.uncertainty.dof import coverage_factor, effective_dof, excess_dof, parts_dof
from crossfield.uncertainty.line_of_sight import line_of_sight_sensitivities, per_control_variance
from crossfield.uncertainty.temperature import LENGTH_KINDS, correction

#: Per-frame result rows a session keeps for its report: the first ones (about
#: 14 s of a 14 pairs/s station). Later frames count in every aggregate; their
#: rows are only in the recording.
FRAME_ROWS_KEPT = 200

#: Failed frames whose error message a session keeps (the first ones); the
#: others are counted.
FRAME_ERRORS_KEPT = 100

#: Measured frames whose camera points a session keeps for the Monte Carlo check
#: (:mod:`crossfield.uncertainty.montecarlo`): the first ones, a few kB each.
MONTE_CARLO_FRAMES_KEPT = 20


# --------------------------------------------------------------------------
# Running statistics
# --------------------------------------------------------------------------


class RunningStats:
    """Welford's running count, mean and sum of squared deviations ``m2``, on shifted data.

    The first value is kept as a shift ``k`` and Welford's update runs on
    ``x - k`` (Chan, Golub & LeVeque 1983, 'Algorithms for computing the
    sample variance', sec. 3): the data then have a mean near 0, so the
    rounding error of the variance no longer grows with mean / std (a
    translation of -300 mm with a 0.02 mm spread would otherwise lose four
    digits). ``x - k`` is exact for values within a factor 2 of each other
    (Sterbenz), the usual case for repeated measurements.

    ``shape`` () keeps Python floats; a vector shape (k,) keeps a list of Python floats per
    component (a station session updates one per control per frame: NumPy's per-call cost
    was ~2.6 us an update for 3 values, issue 25); any other shape keeps float64 arrays,
    updated element by element. All three make the same IEEE operations, so their results
    are the same bit for bit; ``mean``, ``m2`` and ``variance()`` of a vector are (k,) arrays.
    """

    __slots__ = ("_m2", "_mean", "_mode", "_shift", "n")

    def __init__(self, shape: tuple[int, ...] = ()) -> None:
        self._mode = "scalar" if shape == () else "list" if len(shape) == 1 else "array"
        self.n = 0
        zero: float | list[float] | np.ndarray = (
            0.0 if self._mode == "scalar" else [0.0] * shape[0] if self._mode == "list" else np.zeros(shape)
        )
        self._shift = self._mean = self._m2 = zero

    def add(self, x: float | np.ndarray) -> None:
        if self._mode == "list":
            self._add_components(np.asarray(x, dtype=np.float64).tolist())
            return
        x = float(x) if self._mode == "scalar" else np.asarray(x, dtype=np.float64)
        if self.n == 0:
            self._shift = x
        self.n += 1
        y = x - self._shift
        delta = y - self._mean
        self._mean = self._mean + delta / self.n
        self._m2 = self._m2 + delta * (y - self._mean)

    def _add_components(self, values: list[float]) -> None:
        """:meth:`add` of a vector, component by component on Python floats."""
        if self.n == 0:
            self._shift = values
        self.n += 1
        n = self.n
        means, m2s = [], []
        for v, shift, mean, m2 in zip(values, self._shift, self._mean, self._m2):
            y = v - shift
            delta = y - mean
            mean = mean + delta / n
            means.append(mean)
            m2s.append(m2 + delta * (y - mean))
        self._mean, self._m2 = means, m2s

    @property
    def mean(self) -> float | np.ndarray:
        """The mean of the values added (0 before the first)."""
        if self._mode == "list":
            return np.array([shift + mean for shift, mean in zip(self._shift, self._mean)])
        return self._shift + self._mean

    @property
    def m2(self) -> float | np.ndarray:
        """The sum of squared deviations from the mean."""
        return np.array(self._m2) if self._mode == "list" else self._m2

    def variance(self) -> float | np.ndarray:
        """Sample variance (ddof = 1); 0 for fewer than two values."""
        if self.n > 1:
            return self.m2 / (self.n - 1)
        return 0.0 if self._mode == "scalar" else np.zeros_like(self.m2)


# --------------------------------------------------------------------------
# The aggregates (frozen)
# --------------------------------------------------------------------------


# --------------------------------------------------------------------------
# The accumulator
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class _SessionContext:
    """What the session-level uncertainty evaluation of every characteristic shares."""

    plan: MeasurementPlan
    cmm_inflation: float
    calibration_ratio: float  # session calibration u / the per-frame one
    camera_excess: float = 0.0  # Type A: the camera variance the epipolar residuals add (crossfield.uncertainty.type_a)
    #: characteristic -> the calibration's parameters propagated (mm; crossfield.uncertainty.calibration
    #: .calibration_contributions), replacing the relative-scale term; None: the scale term
    calibration_mm: dict[str, float] | None = None
    #: degrees of freedom of the Type A-set terms (crossfield.uncertainty.dof): camera_systematic and
    #: the CMM terms (their evidence's, crossfield.uncertainty.consistency: camera_excess_dof, cmm_excess_dof)
    camera_dof: float = math.inf
    cmm_dof: float = math.inf
    #: the camera's share of the registration residuals' excess, in units of the stated CMM variance
    #: at the controls (crossfield.uncertainty.consistency), and the dof of that estimate
    camera_registration_excess: float = 0.0
    registration_dof: float = math.inf
    #: characteristic -> that share propagated along the controls' lines of sight (mm^2;
    #: crossfield.uncertainty.line_of_sight); None: through control_cmm's shape (isotropic)
    camera_registration_mm2: dict[str, float] | None = None


class _TermRun:
    """The running means of one budget source over the frames: its input u and its variance
    ``u_mm^2`` (mm^2), in its unit. Two scalar :class:`RunningStats` updated in one call, with
    the same IEEE operations (Welford on data shifted by the first value; issue 25: ~14
    updates per characteristic and frame)."""

    __slots__ = ("_u_mean", "_u_shift", "_var_mean", "_var_shift", "n", "unit")

    def __init__(self, unit: str) -> None:
        self.unit = unit
        self.n = 0
        self._u_shift = self._u_mean = self._var_shift = self._var_mean = 0.0

    def add(self, u: float, var: float) -> None:
        u, var = float(u), float(var)
        if self.n == 0:
            self._u_shift, self._var_shift = u, var
        self.n += 1
        n = self.n
        # RunningStats.add: y = x - shift; mean += (y - mean) / n (its m2 is not needed here)
        y = u - self._u_shift
        self._u_mean = self._u_mean + (y - self._u_mean) / n
        y = var - self._var_shift
        self._var_mean = self._var_mean + (y - self._var_mean) / n

    @property
    def u_mean(self) -> float:
        """The mean input uncertainty (in ``unit``)."""
        return self._u_shift + self._u_mean

    @property
    def var_mean(self) -> float:
        """The mean variance (mm^2)."""
        return self._var_shift + self._var_mean


class _CharacteristicRun:
    """Running values of one characteristic (finite per-frame values only)."""

    __slots__ = ("actual_mm", "budget", "dof", "elements", "uncertainty", "values")

    def __init__(self) -> None:
        self.values = RunningStats()
        self.uncertainty = RunningStats()
        self.budget: dict[str, _TermRun] = {}
        self.dof: dict[str, float] = {}  # the smallest per-frame dof a term stated (a fitted line's)
        self.elements: tuple[str, ...] = ()
        self.actual_mm: float | None = None

    def add(self, c: CharacteristicResult) -> None:
        if self.values.n == 0:  # the first frame that measured it names its elements and truth
            self.elements, self.actual_mm = tuple(c.elements), c.actual_mm
        self.values.add(c.measured_mm)
        if c.uncertainty_mm is not None:
            self.uncertainty.add(c.uncertainty_mm)
        for t in c.budget:
            run = self.budget.get(t.source)
            if run is None:
                run = self.budget[t.source] = _TermRun(t.unit)
            run.add(t.u, t.u_mm * t.u_mm)
            dof = getattr(t, "dof", math.inf)
            if math.isfinite(dof):
                self.dof[t.source] = min(dof, self.dof.get(t.source, math.inf))

    def _budget(self, spec: CharacteristicSpec, mean: float, std: float, ctx: _SessionContext):
        """The session budget (see :class:`CharacteristicSummary`), the temperature correction and
        the dof of camera_systematic (its two parts', crossfield.uncertainty.dof.parts_dof)."""
        n = self.values.n
        terms: list[BudgetTerm] = []
        systematic_dof = math.inf
        for source in _budget.SOURCES:
            if source not in self.budget:
                continue
            run = self.budget[source]
            t = _budget.term(source, run.u_mean, run.unit, math.sqrt(max(run.var_mean, 0.0)))
            if source in ("control_cmm", "reference_cmm"):
                t = _budget.scaled(t, ctx.cmm_inflation)
            elif source == "calibration":
                if ctx.calibration_mm is not None and spec.name in ctx.calibration_mm:
                    # the file's parameters propagated: one error for the session, not divided
                    u_cal = ctx.calibration_mm[spec.name]
                    t = _budget.term(source, u_cal, "mm", u_cal)
                else:
                    t = _budget.scaled(t, ctx.calibration_ratio)
            terms.append(t)
        if terms:
            # The camera term is the centroid noise of one frame, drawn anew in every
            # frame: its part of the mean of n frames is u / sqrt(n) (GUM 4.2.3). The
            # other sources are one error shared by every frame: not divided.
            # The Type A excess of the session's epipolar residuals is a bias: its own source,
            # camera_systematic, not divided (budget.camera_terms).
            # The camera's share of the registration excess, a bias at the controls, goes through the
            # registration only (crossfield.uncertainty.line_of_sight).
            control = self.budget.get("control_cmm")
            if ctx.camera_registration_mm2 is not None and spec.name in ctx.camera_registration_mm2:
                registration_mm2 = ctx.camera_registration_mm2[spec.name]  # along the lines of sight
            else:  # no measurer to propagate it: an isotropic error of the same trace, control_cmm's shape
                registration_mm2 = ctx.camera_registration_excess * max(control.var_mean, 0.0) if control else 0.0
            epipolar_mm2 = 0.0
            for t in terms:
                if t.source == "camera":
                    epipolar_mm2 = ctx.camera_excess * t.u_mm**2
            terms = [u for t in terms for u in (
                _budget.camera_terms(t, n, ctx.camera_excess, registration_mm2) if t.source == "camera" else (t,))]
            # camera_systematic's dof: its two parts' (GUM eq. (G.2b) on the variance estimate)
            systematic_dof = parts_dof(
                ((epipolar_mm2, ctx.camera_dof), (registration_mm2, ctx.registration_dof)))
            random_part = next((t.u_mm for t in terms if t.source == "camera"), 0.0)
        elif self.uncertainty.n:  # a measurer without a budget: its u as one term, not divided
            terms.append(_budget.term("camera", 0.0, "mm", self.uncertainty.mean))
            random_part = terms[0].u_mm
        else:
            random_part = 0.0
        type_a = std / math.sqrt(n) if n > 1 else 0.0
        # The scatter over the frames shows only the per-frame (camera) part: where
        # s^2 / n exceeds it, the excess is a term of its own, so that the random
        # part of u_c^2 is max(s^2 / n, u_camera^2 / n) (GUM 4.2.3, 4.3).
        excess = math.sqrt(max(0.0, type_a**2 - random_part**2))
        terms.append(_budget.term("repeatability", type_a, "mm", excess))
        temp = ctx.plan.temperature
        dL, u_temp = correction(mean, temp) if spec.kind in LENGTH_KINDS else (0.0, 0.0)
        terms.append(_budget.term("temperature", u_temp / abs(mean) if mean else 0.0, "1", u_temp))
        terms.sort(key=lambda t: _budget.SOURCES.index(t.source))
        return tuple(terms), dL, systematic_dof

    def summary(self, spec: CharacteristicSpec, ctx: _SessionContext) -> CharacteristicSummary:
        n = self.values.n
        rule = ctx.plan.uncertainty.decision_rule
        k = ctx.plan.uncertainty.coverage_factor
        if n == 0:
            elements = (spec.a,) + ((spec.b,) if spec.b else ())
            return CharacteristicSummary(
                spec.name,
                spec.kind,
                elements,
                0,
                math.nan,
                math.nan,
                None,
                spec.nominal_mm,
                spec.tolerance_mm,
                math.nan,
                False,
                coverage_factor=k,
                decision="not_proven",
                decision_rule=rule,
                upper_tol_mm=spec.upper_tol_mm,
                lower_tol_mm=spec.lower_tol_mm,
            )
        raw = self.values.mean
        std = math.sqrt(self.values.variance()) if n > 1 else 0.0
        budget, dL, systematic_dof = self._budget(spec, raw, std, ctx)
        mean = raw + dL
        u_c = _budget.combined(budget)
        # Welch-Satterthwaite over the terms the session's data estimated (GUM G.4;
        # crossfield.uncertainty.dof): k for a normal output becomes t_p(nu_eff)
        dofs = {"camera_systematic": systematic_dof, "control_cmm": ctx.cmm_dof, "reference_cmm": ctx.cmm_dof,
                "repeatability": float(n - 1) if n > 1 else math.inf, **self.dof}
        budget = tuple(dataclasses.replace(t, dof=dofs.get(t.source, math.inf)) for t in budget)
        nu_eff = effective_dof((t.u_mm, t.dof) for t in budget)
        k = coverage_factor(k, nu_eff)
        U = _budget.expanded(u_c, k)
        deviation = mean - spec.nominal_mm
        verdict = decide(deviation, spec.lower_tol_mm, spec.upper_tol_mm, U, rule)
        actual = self.actual_mm
        return CharacteristicSummary(
            name=spec.name,
            kind=spec.kind,
            elements=self.elements,
            n=n,
            measured_mm=mean,
            std_mm=std,
            uncertainty_mm=u_c,
            nominal_mm=spec.nominal_mm,
            tolerance_mm=spec.tolerance_mm,
            deviation_mm=deviation,
            passed=verdict.accepted,
            actual_mm=actual,
            error_mm=None if actual is None else mean - actual,
            expanded_uncertainty_mm=U,
            coverage_factor=k,
            budget=budget,
            decision=verdict.verdict,
            decision_rule=rule,
            upper_tol_mm=spec.upper_tol_mm,
            lower_tol_mm=spec.lower_tol_mm,
            measured_raw_mm=raw,
            temperature_correction_mm=dL,
            effective_dof=nu_eff,
        )


class _ControlRun:
    """Running residual statistics of one control point."""

    __slots__ = ("max_norm", "norm_sq", "residual")

    def __init__(self) -> None:
        self.residual = RunningStats((3,))
        self.norm_sq = RunningStats()
        self.max_norm = -math.inf

    def add(self, residual: np.ndarray) -> None:
        x, y, z = np.asarray(residual, dtype=np.float64).tolist()
        norm_sq = x * x + y * y + z * z
        self.residual.add(residual)
        self.norm_sq.add(norm_sq)
        self.max_norm = max(self.max_norm, math.sqrt(norm_sq))

    def summary(self, control_id: str, expected_rms_mm: float | None = None) -> ControlResidual:
        return ControlResidual(
            control_id, self.residual.n, self.residual.mean, math.sqrt(self.norm_sq.mean), self.max_norm,
            expected_rms_mm,
        )


class _RegistrationRun:
    """Running statistics of the per-frame registrations."""

    def __init__(self) -> None:
        self.R = RunningStats((3, 3))
        self.t = RunningStats((3,))
        self.scale = RunningStats()
        self.rms = RunningStats()
        self.rms_sq = RunningStats()
        self.rms_max = -math.inf
        self.controls: dict[str, _ControlRun] = {}
        self.expected_sq: dict[str, RunningStats] = {}
        self.pose_camera = RunningStats((6, 6))
        self.pose_cmm = RunningStats((6, 6))

    def add_consistency(self, c: RegistrationConsistency) -> None:
        """The stated sigmas' view of one frame's registration (from its measurement)."""
        for control_id, expected in c.expected_residual_mm.items():
            self.expected_sq.setdefault(control_id, RunningStats()).add(expected * expected)
        if c.pose_cov_camera is not None and c.pose_cov_cmm is not None:
            self.pose_camera.add(c.pose_cov_camera)
            self.pose_cmm.add(c.pose_cov_cmm)

    def add(self, registration: Registration) -> None:
        fit = registration.fit
        self.R.add(fit.R)
        self.t.add(fit.t)
        self.scale.add(fit.scale)
        rms = float(fit.rms_mm)
        self.rms.add(rms)
        self.rms_sq.add(rms * rms)
        self.rms_max = max(self.rms_max, rms)
        for control_id, residual in zip(registration.correspondence.control_ids, fit.residuals):
            run = self.controls.get(control_id)
            if run is None:
                run = self.controls[control_id] = _ControlRun()
            run.add(residual)

    def summary(self, kept: Iterable[Registration], cmm_inflation: float = 1.0) -> RegistrationAggregate | None:
        n = self.R.n
        if n == 0:
            return None
        M = self.R.mean  # (3, 3) arithmetic mean of the rotation matrices
        R_mean = project_to_rotation(M)
        # sum_f ||R_f - R_mean||^2 = sum_f ||R_f - M||^2 + n ||M - R_mean||^2, the
        # first term being the Welford m2 summed over the nine entries (sum_f (R_f - M) = 0).
        chord_sq = float(np.sum(self.R.m2)) + n * float(np.sum((M - R_mean) ** 2))
        spread = [rotation_angle(R_mean, r.fit.R) for r in kept]
        return RegistrationAggregate(
            n_frames=n,
            R_global_camera=R_mean,
            t_global_camera_mm=self.t.mean,
            t_std_mm=np.sqrt(self.t.variance()),
            scale=self.scale.mean,
            rms_mm=math.sqrt(self.rms_sq.mean),
            rms_mean_mm=self.rms.mean,
            rms_max_mm=self.rms_max,
            rotation_rms_rad=chord_to_angle(math.sqrt(max(chord_sq, 0.0) / n)),
            rotation_spread_rad=max(spread) if spread else None,
            controls=tuple(
                run.summary(cid, self._expected(cid, cmm_inflation)) for cid, run in self.controls.items()
            ),
            pose_covariance=None
            if self.pose_camera.n == 0
            else self.pose_camera.mean + cmm_inflation**2 * self.pose_cmm.mean,
        )

    def _expected(self, control_id: str, cmm_inflation: float) -> float | None:
        run = self.expected_sq.get(control_id)
        # The CMM part of the expectation is not kept apart per control: the
        # stated (uninflated) expectation is reported, the one the test compares with.
        return None if run is None or run.n == 0 else math.sqrt(run.mean)


class SessionAccumulator:
    """Aggregates a session's frame results one by one; memory bounded by
    ``rows_kept`` rows and ``errors_kept`` messages, whatever the session length.

    ``add(result)`` after every frame (in frame order), then :meth:`result`
    for the :class:`SessionAggregate`; :attr:`rows` are the kept slim results.
    calibration_files: the calibration files' contents the budget's calibration
    term reads (:class:`crossfield.recording.calibration_files.CalibrationFile`, as
    the session read them at its start; a replay's are the recorded copies); None:
    the files ``calibration_source`` names, read now.
    reference: the session's CMM data; its reference lines' fit residuals are the CMM's own
    Type A evidence (:mod:`crossfield.uncertainty.cmm_evidence`) by which the registration
    residuals' excess is split between camera and CMM; None: no such evidence.
    measurer: the session's measure stage, through which the camera's share of that excess is
    propagated along the controls' lines of sight (:mod:`crossfield.uncertainty.line_of_sight`,
    once per session, on the first measured frame); None: as an isotropic error at the controls.
    """

    def __init__(
        self,
        plan: MeasurementPlan,
        *,
        rows_kept: int = FRAME_ROWS_KEPT,
        errors_kept: int = FRAME_ERRORS_KEPT,
        calibration_source: str = "",
        reference_source: str = "",
        calibration_propagation=None,
        calibration_files: Sequence[Any] | None = None,
        reference: ReferenceData | None = None,
        measurer: Any = None,
    ) -> None:
        if rows_kept < 0 or errors_kept < 0:
            raise ValueError(f"rows_kept and errors_kept must be >= 0, got {rows_kept}, {errors_kept}")
        self.plan = plan
        self.rows_kept = rows_kept
        self.errors_kept = errors_kept
        #: How the consistency warning names the CMM sigma's source (``describe_reference``).
        self.reference_source = reference_source
        self.frames_processed = 0
        self.frames_failed = 0
        self._rows: list[FrameResult] = []
        self._errors: list[FrameError] = []
        self._missing: dict[str, int] = {}
        self._characteristics = {spec.name: _CharacteristicRun() for spec in plan.characteristics}
        self._registration = _RegistrationRun()
        self._consistency = ConsistencyRun()
        self._mc_frames: list[FrameResult] = []
        self._frames_measured = 0
        stated = plan.uncertainty.calibration_scale_u
        # the calibration files as the session read them (a replay: the recorded copies);
        # None: those calibration_source names, read now
        self._calibration = calibration_uncertainty(
            calibration_source, DEFAULT_SCALE_U if stated is None else stated, calibration_files
        )
        #: frame -> {characteristic: calibration u (mm)} (crossfield.uncertainty.calibration.session_propagation)
        #: or None; evaluated once, on the first measured frame
        self._calibration_propagation = calibration_propagation
        self._calibration_mm: dict[str, float] | None = None
        self._cmm_evidence = CmmEvidence() if reference is None else line_fit_evidence(plan, reference)
        self._reference = reference
        self._measurer = measurer
        #: characteristic -> sum of squared line-of-sight sensitivities at the controls; evaluated once
        self._line_of_sight: dict[str, float] | None = None

    def set_reference(self, reference: ReferenceData) -> None:
        """The session's CMM data, when they arrive after the accumulator was made (the viewer of a
        recording reads them from it): their reference lines' fits are the CMM's own evidence."""
        self._reference = reference
        self._cmm_evidence = line_fit_evidence(self.plan, reference)
        self._line_of_sight = None

    @property
    def rows(self) -> tuple[FrameResult, ...]:
        """The first ``rows_kept`` frame results, slim (:meth:`FrameResult.slim`)."""
        return tuple(self._rows)

    def add(self, result: FrameResult) -> None:
        """Count one frame's result (keeps no reference to it beyond the first rows)."""
        self.frames_processed += 1
        if len(self._rows) < self.rows_kept:
            self._rows.append(result.slim())
        if result.error:
            self.frames_failed += 1
            if len(self._errors) < self.errors_kept:
                self._errors.append(
                    FrameError(int(result.sequence), int(result.timestamp_ns), str(result.error))
                )
        if result.registration is not None:
            self._registration.add(result.registration)
            if result.points is not None and result.measurement is not None:
                self._frames_measured += 1
                if len(self._mc_frames) < MONTE_CARLO_FRAMES_KEPT:
                    self._mc_frames.append(dataclasses.replace(result, centroids=None))
        measurement = result.measurement
        if measurement is None:
            return
        if measurement.consistency is not None:
            self._consistency.add(measurement.consistency)
            self._registration.add_consistency(measurement.consistency)
        for target in dict.fromkeys(measurement.missing_targets):
            self._missing[target] = self._missing.get(target, 0) + 1
        for c in measurement.characteristics:
            run = self._characteristics.get(c.name)
            if run is not None and math.isfinite(c.measured_mm):
                run.add(c)

    def result(self) -> SessionAggregate:
        """The aggregates of every frame added so far."""
        kept = [f.registration for f in self._rows if f.registration is not None]
        check = self._consistency.result(
            self.plan.uncertainty.consistency_alpha, self.reference_source,
            self._cmm_evidence.statistic, self._cmm_evidence.dof,
        )
        inflation = 1.0 if check is None else check.cmm_inflation
        stated = self.plan.uncertainty.calibration_scale_u
        per_frame = DEFAULT_SCALE_U if stated is None else stated  # what the measurer used
        ratio = self._calibration.scale_u / per_frame if per_frame > 0 else 1.0
        calibration_source = self._calibration.source
        if self._calibration_propagation is not None and self._mc_frames:
            if self._calibration_mm is None:
                self._calibration_mm = self._calibration_propagation(self._mc_frames[0])
            calibration_source = f"propagated parameters ({getattr(self._calibration_propagation, 'source', '')})"
        camera_dof = cmm_dof = math.inf
        if check is not None:
            # the CMM terms: the stated sigma times f, the excess 1 - 1/f^2 of their variance
            # estimated with the dof of its evidence (crossfield.uncertainty.dof.excess_dof);
            # camera_systematic is all excess (crossfield.uncertainty.consistency)
            cmm_dof = excess_dof(check.cmm_excess_dof, 1.0 - 1.0 / check.cmm_inflation**2)
            camera_dof = check.camera_excess_dof
        ctx_registration: tuple = (0.0, math.inf, None)
        if check is not None:
            along: dict[str, float] | None = None
            if (check.camera_registration_excess > 0 and self._measurer is not None and self._reference is not None
                    and self._mc_frames):
                if self._line_of_sight is None:
                    first = self._mc_frames[0]
                    self._line_of_sight = line_of_sight_sensitivities(
                        self.plan, self._reference, first.points, first.registration, self._measurer)
                v = per_control_variance(check.camera_registration_excess * check.expected_cmm_ss_mm2,
                                         (check.dof + 6) // 3)
                along = {name: v * s2 for name, s2 in self._line_of_sight.items()}
            ctx_registration = (check.camera_registration_excess, check.registration_excess_dof, along)
        ctx = _SessionContext(self.plan, inflation, ratio, 0.0 if check is None else check.camera_excess,
                              self._calibration_mm, camera_dof, cmm_dof, *ctx_registration)
        return SessionAggregate(
            frames_processed=self.frames_processed,
            frames_failed=self.frames_failed,
            frame_errors=tuple(self._errors),
            characteristics=tuple(
                self._characteristics[s.name].summary(s, ctx) for s in self.plan.characteristics
            ),
            registration=self._registration.summary(kept, inflation),
            missing_targets=tuple(self._missing.items()),
            consistency=check,
            calibration_scale_u=self._calibration.scale_u,
            calibration_uncertainty_source=calibration_source,
            monte_carlo_frames=tuple(self._mc_frames),
            frames_measured=self._frames_measured,
        )


def session_accumulator(info: SessionInfo, reference: ReferenceData, measurer: Any = None) -> SessionAccumulator:
    """The :class:`SessionAccumulator` of a session, made one way for a live run or
    replay (:mod:`crossfield.chain.runner`) and for the viewer of a recording
    (:mod:`crossfield.viz.rerun_mcap`): the plan, the calibration files the budget's
    calibration term reads (``info.calibration_files``; none recorded: those the
    calibration's source names), and the reference source as the consistency warning
    names it (the reference plugin's name, the sigmas its points state, its options).
    ``measurer`` (the session's measure stage): the calibration's parameter covariance
    is propagated through it (crossfield.uncertainty.calibration.session_propagation);
    None (the viewer): the relative scale term only."""
    from crossfield.uncertainty.calibration import session_propagation
    from crossfield.uncertainty.consistency import describe_reference

    return SessionAccumulator(
        info.plan,
        calibration_source=info.calibration.source,
        calibration_files=info.calibration_files,
        reference=reference,
        measurer=measurer,
        reference_source=describe_reference(
            str((info.plugins.get("reference") or {}).get("name", "")),
            (p.sigma_mm for p in reference.points),
            info.config.stages["reference"].options,
        ),
        calibration_propagation=None if measurer is None else session_propagation(
            info.plan, reference, info.calibration, measurer, info.calibration_files
        ),
    )


def aggregate_frames(frames: Iterable[FrameResult], plan: MeasurementPlan) -> SessionAggregate:
    """The :class:`SessionAggregate` of ``frames`` (every frame given, none left out:
    all rows and errors are kept)."""
    frames = tuple(frames)
    accumulator = SessionAccumulator(plan, rows_kept=len(frames), errors_kept=len(frames))
    for frame in frames:
        accumulator.add(frame)
    return accumulator.result()


def session_summary(
    info: SessionInfo,
    reference: ReferenceData,
    accumulator: SessionAccumulator,
    *,
    incomplete: str | None = None,
    report_files: Iterable[Path] = (),
    thumbnails: Iterable[CameraThumbnail] = (),
    characteristics: Iterable[CharacteristicSummary] | None = None,
    station_moved: str | None = None,
    stop: SessionStop | None = None,
) -> SessionSummary:
    """The summary of a session whose frames went through ``accumulator``: the one
    place a session's summary is made (the runner's session end, the viewer's reading
    of a recording, the Python API). ``characteristics``: instead of the aggregate's
    (a test or a report that states its own); ``station_moved``: the session pose's
    motion-test line when the station moved (the session is then not PASS).
    ``incomplete``: why the session did not run to its end; every characteristic is
    then :func:`partial` (of the pairs measured so far, decision ``not_proven``).
    ``stop``: the interruption or source error that ended it early, if one did."""
    aggregate = accumulator.result()
    decided = gate_characteristics(aggregate.characteristics if characteristics is None else characteristics, info)
    return SessionSummary(
        info=info,
        reference=reference,
        frames=accumulator.rows,
        characteristics=decided if incomplete is None else partial(decided),
        report_files=tuple(report_files),
        incomplete=incomplete,
        aggregate=aggregate,
        thumbnails=tuple(thumbnails),
        station_moved=station_moved,
        stop=stop,
    )


def partial(characteristics: Iterable[CharacteristicSummary]) -> tuple[CharacteristicSummary, ...]:
    """``characteristics`` of a session that stopped before its end: each marked
    ``partial``, its decision ``not_proven`` (ISO 14253-1: conformance is not proven
    by a part of the planned measurement) and not passed; measured values, u and U
    are those of the pairs measured so far, unchanged."""
    return tuple(dataclasses.replace(c, decision="not_proven", passed=False, partial=True) for c in characteristics)


def summary_of_frames(
    info: SessionInfo,
    reference: ReferenceData,
    frames: Iterable[FrameResult],
    **kwargs: object,
) -> SessionSummary:
    """:func:`session_summary` of a session whose every frame is in ``frames`` (every
    frame's row kept)."""
    frames = tuple(frames)
    accumulator = SessionAccumulator(info.plan, rows_kept=len(frames))
    for frame in frames:
        accumulator.add(frame)
    return session_summary(info, reference, accumulator, **kwargs)  # type: ignore[arg-type]


def summarise(frames: Iterable[FrameResult], plan: MeasurementPlan) -> tuple[CharacteristicSummary, ...]:
    """Aggregate per-frame characteristics in plan order (:class:`SessionAccumulator`).

    Only finite per-frame values count (a frame whose target was not found
    may report NaN); a characteristic no frame measured gets n = 0, NaN
    values and passed = False. See docs/report.md for the formulas.
    """
    accumulator = SessionAccumulator(plan, rows_kept=0, errors_kept=0)
    for frame in frames:
        accumulator.add(frame)
    return accumulator.result().characteristics
