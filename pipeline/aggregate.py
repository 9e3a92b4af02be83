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
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from crossfield.plan import CharacteristicSpec, MeasurementPlan
from crossfield.rigid import chord_to_angle, project_to_rotation, rotation_angle
from crossfield.types import BudgetTerm, CharacteristicResult, Registration, RegistrationConsistency, frozen_array
from crossfield.uncertainty import budget as _budget
from crossfield.uncertainty.calibration import DEFAULT_SCALE_U, calibration_uncertainty
from crossfield.uncertainty.consistency import ConsistencyCheck, ConsistencyRun
from crossfield.uncertainty.decision import decide
from crossfield.uncertainty.temperature import LENGTH_KINDS, correction

if TYPE_CHECKING:  # session.py imports this module
    from crossfield.session import FrameResult

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

    ``shape`` () keeps Python floats (fast, the same IEEE operations); any
    other shape keeps float64 arrays, updated element by element.
    """

    __slots__ = ("_mean", "_scalar", "_shift", "m2", "n")

    def __init__(self, shape: tuple[int, ...] = ()) -> None:
        self._scalar = shape == ()
        self.n = 0
        zero: float | np.ndarray = 0.0 if self._scalar else np.zeros(shape)
        self._shift = self._mean = self.m2 = zero

    def add(self, x: float | np.ndarray) -> None:
        x = float(x) if self._scalar else np.asarray(x, dtype=np.float64)
        if self.n == 0:
            self._shift = x
        self.n += 1
        y = x - self._shift
        delta = y - self._mean
        self._mean = self._mean + delta / self.n
        self.m2 = self.m2 + delta * (y - self._mean)

    @property
    def mean(self) -> float | np.ndarray:
        """The mean of the values added (0 before the first)."""
        return self._shift + self._mean

    def variance(self) -> float | np.ndarray:
        """Sample variance (ddof = 1); 0 for fewer than two values."""
        if self.n > 1:
            return self.m2 / (self.n - 1)
        return 0.0 if self._scalar else np.zeros_like(self.m2)


# --------------------------------------------------------------------------
# The aggregates (frozen)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class CharacteristicSummary:
    """One characteristic over all frames of a session (mm).

    measured_mm: mean over the n frames that measured it, corrected to 20 degC
    (``temperature_correction_mm`` added; ``measured_raw_mm`` before it);
    std_mm: their sample standard deviation (repeatability, 0 for n = 1);
    uncertainty_mm: combined standard uncertainty u_c of measured_mm, the root
    sum of squares of ``budget`` (``docs/uncertainty.md``): per source, the
    per-frame propagated contribution (RMS over frames); the camera term (centroid
    noise, drawn anew in every frame, through the frame's own triangulation and
    registration) divided by sqrt(n), the uncertainty of a mean of n independent
    values; the others (CMM data imported once, the eccentricity of the same
    targets, the one calibration) shared by every frame, not divided. The CMM
    terms inflated when the registration residuals contradict the stated sigma,
    a repeatability term for scatter over the frames beyond the modelled camera
    part, the temperature term.
    expanded_uncertainty_mm: U = k u_c, k = coverage_factor. decision: ISO
    14253-1 verdict under ``decision_rule`` (conforms / does_not_conform /
    not_proven); passed: accepted under that rule. Zone: ``[nominal -
    lower_tol_mm, nominal + upper_tol_mm]``.
    """

    name: str
    kind: str
    elements: tuple[str, ...]
    n: int
    measured_mm: float
    std_mm: float
    uncertainty_mm: float | None
    nominal_mm: float
    tolerance_mm: float
    deviation_mm: float
    passed: bool
    actual_mm: float | None = None
    error_mm: float | None = None
    expanded_uncertainty_mm: float | None = None
    coverage_factor: float = 2.0
    budget: tuple[BudgetTerm, ...] = ()
    decision: str = "not_proven"
    decision_rule: str = "simple"
    upper_tol_mm: float | None = None
    lower_tol_mm: float | None = None
    measured_raw_mm: float | None = None
    temperature_correction_mm: float = 0.0


@dataclass(frozen=True)
class FrameError:
    """A failed frame: its sequence number, capture time (ns) and error message."""

    sequence: int
    timestamp_ns: int
    error: str


@dataclass(frozen=True, eq=False)
class ControlResidual:
    """One control point's registration residual ``R_f p + t_f - q`` over the frames
    that matched it (global frame, mm).

    residual_mm: (3,) mean over frames; rms_norm_mm: sqrt(mean |r|^2);
    max_norm_mm: max |r|; expected_rms_mm: the RMS |r| the stated sigmas
    predict, ``sqrt((1 - 2/n) tr S_k)`` (None when not evaluated).
    """

    id: str
    n_frames: int
    residual_mm: np.ndarray
    rms_norm_mm: float
    max_norm_mm: float
    expected_rms_mm: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "residual_mm", frozen_array(self.residual_mm, shape=(3,)))


@dataclass(frozen=True, eq=False)
class RegistrationAggregate:
    """The session's T_global_camera from every registered frame (mm, rad).

    R_global_camera: (3, 3) chordal L2 mean, the arithmetic mean of the
    per-frame rotations projected onto SO(3) (Hartley et al. 2013, 'Rotation
    Averaging', sec. 5.3); t_global_camera_mm: (3,) mean translation;
    t_std_mm: (3,) its sample standard deviation per axis (0 for one frame).
    scale: mean fit scale. rms_mm: sqrt(mean over frames of rms_f^2);
    rms_mean_mm, rms_max_mm: mean and largest per-frame fit RMS.
    rotation_rms_rad: the RMS over every frame of the chordal distance
    ``||R_f - R_mean||_F``, as an angle (:func:`chord_to_angle`).
    rotation_spread_rad: the largest angle between ``R_mean`` and the rotation
    of a frame in the kept rows (every frame when none was left out; None when
    no kept row is registered). controls: per control point, in order of first match.
    pose_covariance: (6, 6) covariance of (small rotation vector of R in the
    global frame, rad; t_global_camera, mm) from the stated sigmas (mean over
    frames, not divided by their number; the CMM part inflated as the budget's),
    None when not evaluated.
    """

    n_frames: int
    R_global_camera: np.ndarray
    t_global_camera_mm: np.ndarray
    t_std_mm: np.ndarray
    scale: float
    rms_mm: float
    rms_mean_mm: float
    rms_max_mm: float
    rotation_rms_rad: float
    rotation_spread_rad: float | None
    controls: tuple[ControlResidual, ...]
    pose_covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.pose_covariance is not None:
            object.__setattr__(self, "pose_covariance", frozen_array(self.pose_covariance, shape=(6, 6)))
        object.__setattr__(self, "R_global_camera", frozen_array(self.R_global_camera, shape=(3, 3)))
        object.__setattr__(self, "t_global_camera_mm", frozen_array(self.t_global_camera_mm, shape=(3,)))
        object.__setattr__(self, "t_std_mm", frozen_array(self.t_std_mm, shape=(3,)))


@dataclass(frozen=True, eq=False)
class SessionAggregate:
    """Everything a session's report needs about *all* its frames, in bounded memory.

    frames_processed / frames_failed: counts of every frame.
    frame_errors: the first failed frames (at most ``errors_kept``).
    characteristics: per plan characteristic, in plan order (see
    :class:`CharacteristicSummary`; only finite per-frame values count).
    registration: None when no frame was registered.
    missing_targets: (target id, number of frames in which it was not found),
    in order of first miss. consistency: the chi-square test of the
    registration residuals (None without data). calibration_scale_u: the
    relative scale uncertainty of the calibration used in the budgets, and
    where it came from. monte_carlo_frames: the first frames registered and
    measured (at most :data:`MONTE_CARLO_FRAMES_KEPT`), with their camera points,
    for the Monte Carlo check (:mod:`crossfield.uncertainty.montecarlo`);
    frames_measured: how many frames were registered and measured with camera
    points in all.
    """

    frames_processed: int
    frames_failed: int
    frame_errors: tuple[FrameError, ...]
    characteristics: tuple[CharacteristicSummary, ...]
    registration: RegistrationAggregate | None
    missing_targets: tuple[tuple[str, int], ...] = ()
    consistency: ConsistencyCheck | None = None
    calibration_scale_u: float = DEFAULT_SCALE_U
    calibration_uncertainty_source: str = "stated default"
    monte_carlo_frames: tuple[FrameResult, ...] = ()
    frames_measured: int = 0

    @property
    def sample_frame(self) -> FrameResult | None:
        """The first frame registered and measured, with its camera points (None if none)."""
        return self.monte_carlo_frames[0] if self.monte_carlo_frames else None

    @property
    def frame_errors_omitted(self) -> int:
        """Failed frames whose error is not in :attr:`frame_errors`."""
        return self.frames_failed - len(self.frame_errors)


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


class _CharacteristicRun:
    """Running values of one characteristic (finite per-frame values only)."""

    __slots__ = ("actual_mm", "budget", "elements", "uncertainty", "values")

    def __init__(self) -> None:
        self.values = RunningStats()
        self.uncertainty = RunningStats()
        self.budget: dict[str, tuple[RunningStats, RunningStats, str]] = {}
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
                run = self.budget[t.source] = (RunningStats(), RunningStats(), t.unit)
            run[0].add(t.u)
            run[1].add(t.u_mm * t.u_mm)

    def _budget(self, spec: CharacteristicSpec, mean: float, std: float, ctx: _SessionContext):
        """The session budget (see :class:`CharacteristicSummary`) and the temperature correction."""
        n = self.values.n
        terms: list[BudgetTerm] = []
        for source in _budget.SOURCES:
            if source not in self.budget:
                continue
            u_run, var_run, unit = self.budget[source]
            t = _budget.term(source, u_run.mean, unit, math.sqrt(max(var_run.mean, 0.0)))
            if source in ("control_cmm", "reference_cmm"):
                t = _budget.scaled(t, ctx.cmm_inflation)
            elif source == "calibration":
                t = _budget.scaled(t, ctx.calibration_ratio)
            terms.append(t)
        if terms:
            # The camera term is the centroid noise of one frame, drawn anew in every
            # frame: its part of the mean of n frames is u / sqrt(n) (GUM 4.2.3). The
            # other sources are one error shared by every frame: not divided.
            # The Type A excess of the session's epipolar residuals is a bias: its own source,
            # camera_systematic, not divided (budget.camera_terms).
            terms = [u for t in terms
                     for u in (_budget.camera_terms(t, n, ctx.camera_excess) if t.source == "camera" else (t,))]
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
        return tuple(terms), dL

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
        budget, dL = self._budget(spec, raw, std, ctx)
        mean = raw + dL
        u_c = _budget.combined(budget)
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
        )


class _ControlRun:
    """Running residual statistics of one control point."""

    __slots__ = ("max_norm", "norm_sq", "residual")

    def __init__(self) -> None:
        self.residual = RunningStats((3,))
        self.norm_sq = RunningStats()
        self.max_norm = -math.inf

    def add(self, residual: np.ndarray) -> None:
        x, y, z = (float(v) for v in residual)
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
    """

    def __init__(
        self,
        plan: MeasurementPlan,
        *,
        rows_kept: int = FRAME_ROWS_KEPT,
        errors_kept: int = FRAME_ERRORS_KEPT,
        calibration_source: str = "",
    ) -> None:
        if rows_kept < 0 or errors_kept < 0:
            raise ValueError(f"rows_kept and errors_kept must be >= 0, got {rows_kept}, {errors_kept}")
        self.plan = plan
        self.rows_kept = rows_kept
        self.errors_kept = errors_kept
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
        self._calibration = calibration_uncertainty(
            calibration_source, DEFAULT_SCALE_U if stated is None else stated
        )

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
        check = self._consistency.result(self.plan.uncertainty.consistency_alpha)
        inflation = 1.0 if check is None else check.cmm_inflation
        stated = self.plan.uncertainty.calibration_scale_u
        per_frame = DEFAULT_SCALE_U if stated is None else stated  # what the measurer used
        ratio = self._calibration.scale_u / per_frame if per_frame > 0 else 1.0
        ctx = _SessionContext(self.plan, inflation, ratio, 0.0 if check is None else check.camera_excess)
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
            calibration_uncertainty_source=self._calibration.source,
            monte_carlo_frames=tuple(self._mc_frames),
            frames_measured=self._frames_measured,
        )


def aggregate_frames(frames: Iterable[FrameResult], plan: MeasurementPlan) -> SessionAggregate:
    """The :class:`SessionAggregate` of ``frames`` (every frame given, none left out:
    all rows and errors are kept)."""
    frames = tuple(frames)
    accumulator = SessionAccumulator(plan, rows_kept=len(frames), errors_kept=len(frames))
    for frame in frames:
        accumulator.add(frame)
    return accumulator.result()
