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

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from crossfield.plan import CharacteristicSpec, MeasurementPlan
from crossfield.rigid import chord_to_angle, project_to_rotation, rotation_angle
from crossfield.types import CharacteristicResult, Registration, frozen_array

if TYPE_CHECKING:  # session.py imports this module
    from crossfield.session import FrameResult

#: Per-frame result rows a session keeps for its report: the first ones (about
#: 14 s of a 14 pairs/s station). Later frames count in every aggregate; their
#: rows are only in the recording.
FRAME_ROWS_KEPT = 200

#: Failed frames whose error message a session keeps (the first ones); the
#: others are counted.
FRAME_ERRORS_KEPT = 100


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

    measured_mm: mean over the n frames that measured it; std_mm: their
    sample standard deviation (repeatability, 0 for n = 1);
    uncertainty_mm: standard uncertainty of the mean, the larger of
    std/sqrt(n) and the mean per-frame propagated uncertainty. The latter is
    *not* divided by sqrt(n): most of it comes from the CMM data (control
    points, reference fits), imported once and shared by every frame, so it
    does not average down. This is conservative for the camera part.
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
    max_norm_mm: max |r|.
    """

    id: str
    n_frames: int
    residual_mm: np.ndarray
    rms_norm_mm: float
    max_norm_mm: float

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

    def __post_init__(self) -> None:
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
    in order of first miss.
    """

    frames_processed: int
    frames_failed: int
    frame_errors: tuple[FrameError, ...]
    characteristics: tuple[CharacteristicSummary, ...]
    registration: RegistrationAggregate | None
    missing_targets: tuple[tuple[str, int], ...] = ()

    @property
    def frame_errors_omitted(self) -> int:
        """Failed frames whose error is not in :attr:`frame_errors`."""
        return self.frames_failed - len(self.frame_errors)


# --------------------------------------------------------------------------
# The accumulator
# --------------------------------------------------------------------------


class _CharacteristicRun:
    """Running values of one characteristic (finite per-frame values only)."""

    __slots__ = ("actual_mm", "elements", "uncertainty", "values")

    def __init__(self) -> None:
        self.values = RunningStats()
        self.uncertainty = RunningStats()
        self.elements: tuple[str, ...] = ()
        self.actual_mm: float | None = None

    def add(self, c: CharacteristicResult) -> None:
        if self.values.n == 0:  # the first frame that measured it names its elements and truth
            self.elements, self.actual_mm = tuple(c.elements), c.actual_mm
        self.values.add(c.measured_mm)
        if c.uncertainty_mm is not None:
            self.uncertainty.add(c.uncertainty_mm)

    def summary(self, spec: CharacteristicSpec) -> CharacteristicSummary:
        n = self.values.n
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
            )
        mean = self.values.mean
        std = math.sqrt(self.values.variance()) if n > 1 else 0.0
        candidates = [std / math.sqrt(n)] if n > 1 else []
        if self.uncertainty.n:
            candidates.append(self.uncertainty.mean)
        deviation = mean - spec.nominal_mm
        actual = self.actual_mm
        return CharacteristicSummary(
            name=spec.name,
            kind=spec.kind,
            elements=self.elements,
            n=n,
            measured_mm=mean,
            std_mm=std,
            uncertainty_mm=max(candidates) if candidates else None,
            nominal_mm=spec.nominal_mm,
            tolerance_mm=spec.tolerance_mm,
            deviation_mm=deviation,
            passed=abs(deviation) <= spec.tolerance_mm,
            actual_mm=actual,
            error_mm=None if actual is None else mean - actual,
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

    def summary(self, control_id: str) -> ControlResidual:
        return ControlResidual(
            control_id, self.residual.n, self.residual.mean, math.sqrt(self.norm_sq.mean), self.max_norm
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

    def summary(self, kept: Iterable[Registration]) -> RegistrationAggregate | None:
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
            controls=tuple(run.summary(cid) for cid, run in self.controls.items()),
        )


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
        measurement = result.measurement
        if measurement is None:
            return
        for target in dict.fromkeys(measurement.missing_targets):
            self._missing[target] = self._missing.get(target, 0) + 1
        for c in measurement.characteristics:
            run = self._characteristics.get(c.name)
            if run is not None and math.isfinite(c.measured_mm):
                run.add(c)

    def result(self) -> SessionAggregate:
        """The aggregates of every frame added so far."""
        kept = [f.registration for f in self._rows if f.registration is not None]
        return SessionAggregate(
            frames_processed=self.frames_processed,
            frames_failed=self.frames_failed,
            frame_errors=tuple(self._errors),
            characteristics=tuple(
                self._characteristics[s.name].summary(s) for s in self.plan.characteristics
            ),
            registration=self._registration.summary(kept),
            missing_targets=tuple(self._missing.items()),
        )


def aggregate_frames(frames: Iterable[FrameResult], plan: MeasurementPlan) -> SessionAggregate:
    """The :class:`SessionAggregate` of ``frames`` (every frame given, none left out:
    all rows and errors are kept)."""
    frames = tuple(frames)
    accumulator = SessionAccumulator(plan, rows_kept=len(frames), errors_kept=len(frames))
    for frame in frames:
        accumulator.add(frame)
    return accumulator.result()
