"""What each stage implementation must provide (structural protocols).

A registry hook offers ``factory(**options) -> implementation``; the
implementation then satisfies one of these protocols. Units and frames as
in :mod:`crossfield.types`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol, runtime_checkable

import numpy as np

from crossfield.plan import MeasurementPlan
from crossfield.types import (
    CameraPoints,
    CentroidSet,
    GroundTruth,
    Measurement,
    ReferenceData,
    Registration,
    RigidFit,
    StereoCalibration,
    StereoCentroids,
    StereoFrame,
)


@dataclass(frozen=True)
class LinkEvent:
    """A line source's link went down or came back, between two chunks of
    its bytes. kind: ``"down"`` (detail: the transport's reason) or ``"up"``
    (detail: ""). Handed to the :data:`BytesSink` in order with the bytes,
    recorded with them (``/cmm/raw``, channel ``content = link-events``),
    and given back to ``decode(raw, plan, link_events=...)`` on replay, so
    that a line cut by a disconnect is split there as it was live."""

    kind: str
    detail: str = ""


#: Called with each chunk of raw bytes as it is read, before parsing; a
#: source with a link (serial line, TCP) also calls it with a
#: :class:`LinkEvent` when the link goes down or comes back, in order with
#: the bytes.
BytesSink = Callable[["bytes | LinkEvent"], None]


@runtime_checkable
class Acquisition(Protocol):
    """A source of stereo pairs.

    calibration: the stereo calibration the frames belong to.
    ground_truth: the true geometry when the source is a simulator, else None.
    default_plan: the measurement plan that goes with the source (simulator
    scenarios ship one), else None.
    """

    calibration: StereoCalibration
    ground_truth: GroundTruth | None
    default_plan: MeasurementPlan | None

    def frames(self) -> Iterator[StereoFrame]:
        """Yield stereo pairs in acquisition order."""

    def describe(self) -> dict[str, Any]:
        """Device/scene parameters to record with the session (JSON-able)."""

    def close(self) -> None:
        """Release devices."""


@runtime_checkable
class CentroidExtractor(Protocol):
    def extract(self, image: np.ndarray, camera: str, sequence: int) -> CentroidSet:
        """Find target centroids in one (H, W) image of camera ``camera``."""


@runtime_checkable
class Triangulator(Protocol):
    def triangulate(self, centroids: StereoCentroids, calibration: StereoCalibration) -> CameraPoints:
        """Match centroids under the epipolar constraint and triangulate
        them into the upper-camera frame (mm)."""


@runtime_checkable
class ReferenceSource(Protocol):
    def acquire(self, plan: MeasurementPlan, sink: BytesSink) -> ReferenceData:
        """Read the CMM points for ``plan``; pass every raw byte to ``sink``
        before parsing it; label points by the plan's probing order."""

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:
        """Decode recorded raw bytes exactly as :meth:`acquire` would (replay).
        A source that hands :class:`LinkEvent` s to its sink also takes
        ``link_events``: ``(offset in raw, LinkEvent)`` pairs in order."""


@runtime_checkable
class Registrar(Protocol):
    def fit(self, camera_xyz: np.ndarray, global_xyz: np.ndarray, weights: np.ndarray | None = None) -> RigidFit:
        """Rigid transform with ``global ~ R @ camera + t`` from (N, 3) mm
        corresponding points. A reflection is an error (raise
        :class:`crossfield.errors.RegistrationError`)."""


@runtime_checkable
class Measurer(Protocol):
    def measure(
        self,
        plan: MeasurementPlan,
        reference: ReferenceData,
        points: CameraPoints,
        registration: Registration,
        ground_truth: GroundTruth | None,
    ) -> Measurement:
        """Evaluate the plan's characteristics for one stereo pair."""


@runtime_checkable
class Reporter(Protocol):
    def write(self, summary: "SessionSummary", out_dir: Path) -> list[Path]:  # noqa: F821
        """Write the report files into ``out_dir``; return their paths."""

    def summary_text(self, summary: "SessionSummary") -> str:  # noqa: F821
        """A short terminal summary."""
