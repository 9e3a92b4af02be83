"""Session-level data: what a session is, one frame's results, the aggregates over
its frames, the report's thumbnails, the summary.

These classes hold data only: the aggregation over frames that fills them, and every
:class:`SessionSummary` of a session, are made by :mod:`crossfield.chain.aggregate`."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from crossfield.config import Config
from crossfield.plan import MeasurementPlan
from crossfield.tables import SummaryTables
from crossfield.types import (
    DEFAULT_SCALE_U,
    BudgetTerm,
    CameraPoints,
    GroundTruth,
    Measurement,
    ReferenceData,
    Registration,
    StereoCalibration,
    StereoCentroids,
    frozen_array,
)
from crossfield.uncertainty.consistency import ConsistencyCheck

__all__ = [
    "CameraThumbnail",
    "CharacteristicSummary",
    "ControlResidual",
    "FrameError",
    "FrameResult",
    "MonteCarloResult",
    "RegistrationAggregate",
    "SessionAggregate",
    "SessionInfo",
    "SessionStop",
    "SessionSummary",
]


#: ``SessionStop.kind`` of a run stopped by the operator (SIGINT, Ctrl-C).
STOP_INTERRUPTED = "interrupted"
#: ``SessionStop.kind`` of a run stopped because its camera or reference source raised.
STOP_SOURCE_ERROR = "source_error"


@dataclass(frozen=True)
class SessionStop:
    """Why a session stopped taking input before its end (``docs/faults.md``).

    kind: :data:`STOP_INTERRUPTED` (the operator, SIGINT) or
    :data:`STOP_SOURCE_ERROR` (the camera or reference source raised);
    stage: where it stopped, ``"reference"`` (during the CMM import, before the
    first stereo pair) or ``"acquire"`` (between stereo pairs); source: the
    implementation of that stage (e.g. ``"romer-serial"``); message: the
    source's error message (empty for an interruption); reason: the whole
    sentence the report states as ``incomplete_reason``; frames: the stereo
    pairs processed before the stop; timestamp_ns: when it stopped (wall clock,
    ns since the Unix epoch). Recorded on ``/session/stop`` (a raw input: a
    replay reads it and stops where the live run stopped).
    """

    kind: str
    stage: str
    source: str
    reason: str
    frames: int
    timestamp_ns: int
    message: str = ""


@dataclass(frozen=True)
class SessionInfo:
    """Facts fixed at the start of a session (recorded as MCAP metadata).

    plugins: stage -> {"name", "plugin", "package", "version"}.
    packages: distribution -> version of the packages the result depends on.
    acquisition: the source's :meth:`describe` output.
    """

    session_id: str
    out_dir: Path
    config: Config
    calibration: StereoCalibration
    plan: MeasurementPlan
    plugins: Mapping[str, Mapping[str, str]]
    packages: Mapping[str, str]
    acquisition: Mapping[str, Any]
    ground_truth: GroundTruth | None = None
    start_time_ns: int = 0
    parent: Mapping[str, Any] | None = None  # replay: the session this one re-runs
    #: The calibration files as read at the session's start (a replay: the recorded
    #: copies), :class:`crossfield.recording.calibration_files.CalibrationFile`; recorded
    #: whole, and what the budget's calibration term reads. None (a recording made
    #: before the copies were kept): the files the calibration's source names, read then.
    calibration_files: tuple[Any, ...] | None = None


@dataclass(frozen=True)
class FrameResult:
    """Everything computed from one stereo pair. Stages after a failure are None
    and ``error`` says what failed. n_camera_points: how many points were
    triangulated (kept when :meth:`slim` drops the points themselves)."""

    sequence: int
    timestamp_ns: int
    centroids: StereoCentroids | None = None
    points: CameraPoints | None = None
    registration: Registration | None = None
    measurement: Measurement | None = None
    error: str | None = None
    n_camera_points: int | None = None

    def __post_init__(self) -> None:
        if self.points is not None and self.n_camera_points is None:
            object.__setattr__(self, "n_camera_points", len(self.points))

    def slim(self) -> "FrameResult":
        """This result without the centroids and camera points: what a session
        keeps per frame for its report (the observers had everything)."""
        return dataclasses.replace(self, centroids=None, points=None)


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
    expanded_uncertainty_mm: U = k u_c, k = coverage_factor: the plan's k for a
    normal output turned into the Student-t factor of the budget's Welch-Satterthwaite
    effective_dof (the plan's k when every term is stated; ``crossfield.uncertainty.dof``). decision: ISO
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
    #: True when the session stopped before its end (``SessionSummary.incomplete``):
    #: the value is of the pairs measured so far, the decision then never conforms.
    partial: bool = False
    effective_dof: float = math.inf


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


@dataclass(frozen=True, eq=False)
class CameraThumbnail:
    """One camera's picture for the report.

    camera: ``"upper"`` or ``"lower"``. sequence: the stereo pair it shows.
    image: (h, w) uint8, read-only: block means of ``factor`` x ``factor``
    image pixels, DN scaled by ``255 / (2**bit_depth - 1)``.
    factor: the integer reduction (1 = full size). full_size: (height, width)
    of the camera image (px). uv: (N, 2) every centroid of that image, image
    pixels (OpenCV convention). labels: (N,) its target id, "" when the
    pipeline did not identify it. kinds: (N,) :data:`~crossfield.report.thumbnails.KIND_CONTROL`,
    :data:`~crossfield.report.thumbnails.KIND_TARGET` or "". status: how far the pair got
    (:data:`~crossfield.report.thumbnails.STATUS_RANK`: ``"measured"``, ``"registered"``, ``"centroids"``, or
    ``"image"`` when its centroid stage failed: no centroids). Compared by identity
    (``eq=False``: it holds arrays).
    """

    camera: str
    sequence: int
    image: np.ndarray = field(repr=False)
    factor: int
    full_size: tuple[int, int]
    uv: np.ndarray
    labels: tuple[str, ...]
    kinds: tuple[str, ...]
    status: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "image", frozen_array(self.image, np.uint8, shape=(None, None)))
        object.__setattr__(self, "uv", frozen_array(self.uv, shape=(None, 2)))
        if not len(self.labels) == len(self.kinds) == len(self.uv):
            raise ValueError("uv, labels and kinds differ in length")

    def thumbnail_uv(self) -> np.ndarray:
        """(N, 2) the centroids in thumbnail pixels: ``(uv - (f - 1) / 2) / f``."""
        return (self.uv - (self.factor - 1) / 2.0) / self.factor


@dataclass(frozen=True)
class MonteCarloResult:
    """Per characteristic (mm): u_mc_mm, interval_mm (low, high) about the sample mean,
    U_mc_mm (its half-width, coverage probability ``coverage``), U_linear_mm,
    agreement (``U_mc / U_linear - 1``) and agreement_u (its numerical standard
    uncertainty from the number of draws)."""

    name: str
    n_draws: int
    u_mc_mm: float
    interval_mm: tuple[float, float]
    U_mc_mm: float
    U_linear_mm: float | None
    agreement: float | None
    coverage: float = 0.9545
    agreement_u: float | None = None


@dataclass(frozen=True)
class SessionSummary(SummaryTables):
    """A finished session: what the report stage and the ``on_session_end`` observers get.

    frames: the per-frame results kept for the report, slim (no centroids, no
    camera points): the first :data:`~crossfield.chain.aggregate.FRAME_ROWS_KEPT` of
    a session run by the runner, so that a session of any length holds a
    bounded number. Every frame's results are in the recording (session.mcap).
    aggregate: the whole session (every frame): counts, failed frames' errors,
    characteristics, registration, targets not found.
    characteristics: Table 3, normally ``aggregate.characteristics``.
    thumbnails: one downsampled image per camera with its labelled centroids
    (:class:`crossfield.report.thumbnails.CameraThumbnail`, kept by the runner's
    :class:`~crossfield.report.thumbnails.ThumbnailObserver`); () when none.
    monte_carlo: the GUM-S1 Monte Carlo check of the budget, one result per
    characteristic, run at the session end when ``[session] monte_carlo`` > 0
    (:mod:`crossfield.uncertainty.montecarlo`); None when not run.
    station_moved: the motion test's line when the station moved (not PASS then).
    report: the report document (report.json's content,
    :func:`crossfield.report.document.build_report`), built once at the session end
    and handed to the recorder, report.json and every reporter, with the
    recording's seal once it is closed; None until then.
    """

    info: SessionInfo
    reference: ReferenceData
    frames: tuple[FrameResult, ...]
    characteristics: tuple[CharacteristicSummary, ...] = ()
    report_files: tuple[Path, ...] = field(default_factory=tuple)
    incomplete: str | None = None
    aggregate: SessionAggregate = None  # type: ignore[assignment]  # always given: crossfield.chain.aggregate
    thumbnails: tuple[CameraThumbnail, ...] = ()
    monte_carlo: tuple[MonteCarloResult, ...] | None = None
    report: Mapping[str, Any] | None = field(default=None, repr=False)
    #: The session pose's motion-test line when it found the station moved
    #: (:mod:`crossfield.chain.session_pose`); None when static or not tested.
    station_moved: str | None = None
    #: Why the session stopped taking input early (SIGINT, a source error); None when
    #: it ran to the end of its source (:class:`SessionStop`).
    stop: SessionStop | None = None

    @property
    def registrations(self) -> list[Registration]:
        """The registrations of the kept rows (:attr:`frames`)."""
        return [f.registration for f in self.frames if f.registration is not None]

    @property
    def frames_processed(self) -> int:
        """Every frame the session processed (also those not kept in :attr:`frames`)."""
        return self.aggregate.frames_processed

    @property
    def frames_failed(self) -> int:
        """Every frame that failed (``aggregate.frame_errors`` has the first ones' errors)."""
        return self.aggregate.frames_failed

    @property
    def frames_omitted(self) -> int:
        """Frames processed but not kept in :attr:`frames`."""
        return max(0, self.aggregate.frames_processed - len(self.frames))

    @property
    def passed(self) -> bool:
        """True when every characteristic passed, no frame failed and the session
        ran to its end (``incomplete`` is None) with a static station
        (``station_moved`` is None). (A failed kept row also fails
        the session, should ``frames`` have been replaced after aggregation.)"""
        return (
            self.station_moved is None
            and bool(self.characteristics)
            and all(c.passed for c in self.characteristics)
            and self.aggregate.frames_failed == 0
            and not any(f.error for f in self.frames)
            and self.incomplete is None
        )

    def rms_error_mm(self) -> float | None:
        """RMS of error_mm over the characteristics with ground truth."""
        errors = [c.error_mm for c in self.characteristics if c.error_mm is not None]
        return math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None
