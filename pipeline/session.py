"""Session-level data: what a session is, one frame's results, the summary.

The aggregation over frames is :mod:`crossfield.aggregate` (CharacteristicSummary
is defined there and re-exported here)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping

from crossfield.aggregate import CharacteristicSummary, SessionAccumulator, SessionAggregate, aggregate_frames
from crossfield.config import Config
from crossfield.plan import MeasurementPlan
from crossfield.tables import SummaryTables
from crossfield.types import (
    CameraPoints,
    GroundTruth,
    Measurement,
    ReferenceData,
    Registration,
    StereoCalibration,
    StereoCentroids,
)

if TYPE_CHECKING:  # pragma: no cover
    from crossfield.report.thumbnails import CameraThumbnail

__all__ = [
    "FrameResult",
    "SessionInfo",
    "SessionSummary",
    "summarise",
]


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
class SessionSummary(SummaryTables):
    """A finished session: what the report stage and the ``on_session_end`` observers get.

    frames: the per-frame results kept for the report, slim (no centroids, no
    camera points): the first :data:`~crossfield.aggregate.FRAME_ROWS_KEPT` of
    a session run by the runner, so that a session of any length holds a
    bounded number. Every frame's results are in the recording (session.mcap).
    aggregate: the whole session (every frame): counts, failed frames' errors,
    characteristics, registration, targets not found. None when constructing
    by hand: then it is aggregated from ``frames``, which must hold every frame.
    characteristics: Table 3, normally ``aggregate.characteristics``.
    thumbnails: one downsampled image per camera with its labelled centroids
    (:class:`crossfield.report.thumbnails.CameraThumbnail`, kept by the runner's
    :class:`~crossfield.report.thumbnails.ThumbnailObserver`); () when none.
    """

    info: SessionInfo
    reference: ReferenceData
    frames: tuple[FrameResult, ...]
    characteristics: tuple[CharacteristicSummary, ...] = ()
    report_files: tuple[Path, ...] = field(default_factory=tuple)
    incomplete: str | None = None
    aggregate: SessionAggregate = None  # type: ignore[assignment]  # None: from ``frames``
    thumbnails: tuple[CameraThumbnail, ...] = ()

    def __post_init__(self) -> None:
        if self.aggregate is None:
            object.__setattr__(self, "aggregate", aggregate_frames(self.frames, self.info.plan))

    @classmethod
    def of_session(
        cls,
        info: SessionInfo,
        reference: ReferenceData,
        accumulator: SessionAccumulator,
        incomplete: str | None = None,
        report_files: Iterable[Path] = (),
        thumbnails: Iterable[CameraThumbnail] = (),
    ) -> SessionSummary:
        """The summary of a session whose frames went through ``accumulator``:
        the one place a session's summary is made (the runner's
        :func:`~crossfield.runner.finish_session`, the viewer's reading of a recording)."""
        aggregate = accumulator.result()
        return cls(
            info=info,
            reference=reference,
            frames=accumulator.rows,
            characteristics=aggregate.characteristics,
            report_files=tuple(report_files),
            incomplete=incomplete,
            aggregate=aggregate,
            thumbnails=tuple(thumbnails),
        )

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
        ran to its end (``incomplete`` is None). (A failed kept row also fails
        the session, should ``frames`` have been replaced after aggregation.)"""
        return (
            bool(self.characteristics)
            and all(c.passed for c in self.characteristics)
            and self.aggregate.frames_failed == 0
            and not any(f.error for f in self.frames)
            and self.incomplete is None
        )

    def rms_error_mm(self) -> float | None:
        """RMS of error_mm over the characteristics with ground truth."""
        errors = [c.error_mm for c in self.characteristics if c.error_mm is not None]
        return math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None


def summarise(frames: Iterable[FrameResult], plan: MeasurementPlan) -> tuple[CharacteristicSummary, ...]:
    """Aggregate per-frame characteristics in plan order (:class:`crossfield.aggregate.SessionAccumulator`).

    Only finite per-frame values count (a frame whose target was not found
    may report NaN); a characteristic no frame measured gets n = 0, NaN
    values and passed = False. See docs/report.md for the formulas.
    """
    accumulator = SessionAccumulator(plan, rows_kept=0, errors_kept=0)
    for frame in frames:
        accumulator.add(frame)
    return accumulator.result().characteristics
