"""Session-level data: what a session is, one frame's results, the summary."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .config import Config
from .plan import MeasurementPlan
from .types import (
    CameraPoints,
    GroundTruth,
    Measurement,
    ReferenceData,
    Registration,
    StereoCalibration,
    StereoCentroids,
)


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
class SessionSummary:
    info: SessionInfo
    reference: ReferenceData
    frames: tuple[FrameResult, ...]
    characteristics: tuple[CharacteristicSummary, ...] = ()
    report_files: tuple[Path, ...] = field(default_factory=tuple)
    incomplete: str | None = None

    @property
    def registrations(self) -> list[Registration]:
        return [f.registration for f in self.frames if f.registration is not None]

    @property
    def passed(self) -> bool:
        """True when every characteristic passed, no frame failed and the session
        ran to its end (``incomplete`` is None)."""
        return (
            bool(self.characteristics)
            and all(c.passed for c in self.characteristics)
            and not any(f.error for f in self.frames)
            and self.incomplete is None
        )

    def rms_error_mm(self) -> float | None:
        """RMS of error_mm over the characteristics with ground truth."""
        errors = [c.error_mm for c in self.characteristics if c.error_mm is not None]
        return math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None


def summarise(frames: list[FrameResult] | tuple[FrameResult, ...], plan: MeasurementPlan) -> tuple[CharacteristicSummary, ...]:
    """Aggregate per-frame characteristics in plan order.

    Only finite per-frame values count (a frame whose target was not found
    may report NaN); a characteristic no frame measured gets n = 0, NaN
    values and passed = False. See docs/report.md for the formulas.
    """
    out = []
    for spec in plan.characteristics:
        results = [
            c
            for f in frames
            if f.measurement is not None
            for c in f.measurement.characteristics
            if c.name == spec.name and math.isfinite(c.measured_mm)
        ]
        n = len(results)
        if n == 0:
            out.append(
                CharacteristicSummary(
                    spec.name, spec.kind, (spec.a,) + ((spec.b,) if spec.b else ()), 0,
                    math.nan, math.nan, None, spec.nominal_mm, spec.tolerance_mm, math.nan, False,
                )
            )
            continue
        values = np.array([c.measured_mm for c in results])
        mean = float(values.mean())
        std = float(values.std(ddof=1)) if n > 1 else 0.0
        per_frame = [c.uncertainty_mm for c in results if c.uncertainty_mm is not None]
        u_candidates = [std / math.sqrt(n)] if n > 1 else []
        if per_frame:
            u_candidates.append(float(np.mean(per_frame)))
        uncertainty = max(u_candidates) if u_candidates else None
        deviation = mean - spec.nominal_mm
        actual = results[0].actual_mm
        out.append(
            CharacteristicSummary(
                name=spec.name,
                kind=spec.kind,
                elements=results[0].elements,
                n=n,
                measured_mm=mean,
                std_mm=std,
                uncertainty_mm=uncertainty,
                nominal_mm=spec.nominal_mm,
                tolerance_mm=spec.tolerance_mm,
                deviation_mm=deviation,
                passed=abs(deviation) <= spec.tolerance_mm,
                actual_mm=actual,
                error_mm=None if actual is None else mean - actual,
            )
        )
    return tuple(out)
