"""The stages, and what each stage implementation must provide.

:data:`STAGES` names the stages in data-flow order; :data:`STAGE_PROTOCOLS`
maps each to the structural protocol its implementations satisfy. A
registry hook offers ``factory(**options) -> implementation``;
:meth:`crossfield.chain.registry.Implementation.create` checks the object it makes
against the stage's protocol (:func:`check_implementation`), so a plugin
that lacks a method fails when it is chosen, with an error naming it.

Besides the stage contracts, a device may declare optional side channels
(:class:`ReportsIncidents`, :class:`ServesSimulatedArm`) and a replay's
source is a :class:`RecordedAcquisition`; the runner checks them with
``isinstance``, never by attribute or name. Units and frames as in
:mod:`crossfield.types`.

This module imports only the data modules (:mod:`crossfield.types`,
:mod:`crossfield.plan`), so the config, the registry and the hook specs
can all import it without a circle.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from crossfield.errors import PluginError
from crossfield.plan import MeasurementPlan
from crossfield.types import (
    STAGES,
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

if TYPE_CHECKING:  # pragma: no cover
    from crossfield.session import SessionSummary

__all__ = [
    "STAGES",
    "STAGE_PROTOCOLS",
    "AcceptsCovariance",
    "Acquisition",
    "BytesSink",
    "CentroidExtractor",
    "DecodesLinkEvents",
    "LinkEvent",
    "ListsReportFiles",
    "LogCallback",
    "Measurer",
    "RecordedAcquisition",
    "ReferenceSource",
    "Registrar",
    "Reporter",
    "ReportsIncidents",
    "SerialChunk",
    "ServesSimulatedArm",
    "Triangulator",
    "check_implementation",
    "implements",
    "protocol_members",
]



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


class SerialChunk(NamedTuple):
    """One read from the CMM line as recorded on ``/cmm/raw``: the bytes (or a
    :class:`LinkEvent` of the line, in order with them), the read time (ns
    since the Unix epoch) and the reference implementation's name."""

    data: "bytes | LinkEvent"
    timestamp_ns: int
    source: str


class LogCallback(Protocol):
    """``log(level=..., message=..., timestamp_ns=...)``, as ``pm.hook.on_log``:
    level is debug, info, warning or error; timestamp_ns since the Unix epoch."""

    def __call__(self, *, level: str, message: str, timestamp_ns: int) -> Any: ...


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
    def write(self, summary: SessionSummary, out_dir: Path) -> list[Path]:
        """Write the report files into ``out_dir``; return their paths."""

    def summary_text(self, summary: SessionSummary) -> str:
        """A short terminal summary."""


#: stage -> the protocol its implementations satisfy.
STAGE_PROTOCOLS: Mapping[str, type] = {
    "acquire": Acquisition,
    "centroid": CentroidExtractor,
    "triangulate": Triangulator,
    "reference": ReferenceSource,
    "register": Registrar,
    "measure": Measurer,
    "report": Reporter,
}


# ---- optional capabilities (checked by type: :func:`implements`) ----------


@runtime_checkable
class AcceptsCovariance(Protocol):
    """A register implementation that takes each camera point's full covariance and
    the CMM sigmas (``ml``), given to it when ``accepts_covariance`` is true
    (:func:`crossfield.chain.weights.fit_registration`)."""

    accepts_covariance: bool

    def fit(
        self,
        camera_xyz: np.ndarray,
        global_xyz: np.ndarray,
        weights: np.ndarray | None = None,
        *,
        camera_cov: np.ndarray | None = None,
        control_sigma: np.ndarray | None = None,
    ) -> RigidFit:
        """As :meth:`Registrar.fit`; camera_cov (N, 3, 3) mm^2, control_sigma (N,) mm."""


@runtime_checkable
class DecodesLinkEvents(Protocol):
    """A reference implementation whose line can drop and come back: its
    :meth:`decode` takes the recorded :class:`LinkEvent` s, so that a replay splits
    the lines as the live read did."""

    def decode(
        self, raw: bytes, plan: MeasurementPlan, link_events: Sequence[tuple[int, LinkEvent]] = ()
    ) -> ReferenceData:
        """Decode ``raw`` with ``link_events``: (offset in raw, event) pairs in order."""


@runtime_checkable
class ListsReportFiles(Protocol):
    """A reporter that says which files it will write, so that the recording (closed
    before they exist) lists them."""

    def report_files(self, out_dir: Path) -> list[Path]:
        """The files :meth:`Reporter.write` will write into ``out_dir``."""


def implements(obj: Any, protocol: type) -> bool:
    """True if ``obj`` has every member of ``protocol`` and each of its methods can be
    called with every parameter the protocol's method names (by keyword)."""
    if not isinstance(obj, protocol):
        return False
    methods, _ = protocol_members(protocol)
    for name, spec in methods.items():
        try:
            have = inspect.signature(getattr(obj, name))
        except (TypeError, ValueError):
            continue
        params = list(inspect.signature(spec).parameters.values())[1:]
        try:
            have.bind(**{p.name: object() for p in params if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)})
        except TypeError:
            return False
    return True


# ---- optional side channels (checked with isinstance) -------------------


@runtime_checkable
class ReportsIncidents(Protocol):
    """A device that reports incidents as they happen (dropped frames, link
    down and up, rejected lines). The runner connects it to the session's
    ``on_log`` hook, so the recording holds them on ``/log``."""

    def connect_log(self, log: LogCallback) -> None:
        """Report every later incident through ``log``."""


@runtime_checkable
class ServesSimulatedArm(Protocol):
    """An acquisition that can also run the simulated CMM arm of its scene.

    Used only when the reference implementation takes a ``port`` option and
    the user named none, or named ``"simulator"``: any other port is read
    as given."""

    def serve_arm(self) -> AbstractContextManager[str]:
        """Run the simulated arm on a pseudo-terminal while the context is open;
        yields its device path."""


@runtime_checkable
class RecordedAcquisition(Acquisition, Protocol):
    """The acquisition of a replay: stereo pairs read back from a recording.

    recorded_plugins: the recording's ``crossfield.plugins`` record (stage ->
    {name, plugin, package, version}); its ``acquire`` entry is what the
    replay names as its source. start_time_ns: the recorded session start.
    incomplete: after :meth:`frames` is exhausted, where a cut-short
    recording ends (None if it is complete).
    """

    recorded_plugins: Mapping[str, Mapping[str, str]]
    start_time_ns: int
    incomplete: str | None


# ---- the check ----------------------------------------------------------

_PROTOCOL_BASES = frozenset(vars(object)) | frozenset(vars(Protocol)) | {
    "__annotations__",
    "__dict__",
    "__weakref__",
    "__parameters__",
    "__protocol_attrs__",
    "__non_callable_proto_members__",
    "__abstractmethods__",
    "__orig_bases__",
    "__callable_proto_members_only__",
    "_is_protocol",
    "_is_runtime_protocol",
    "__subclasshook__",
    "__init__",
    "__module__",
    "__qualname__",
    "__doc__",
}


def protocol_members(protocol: type) -> tuple[dict[str, Any], tuple[str, ...]]:
    """(methods, attributes) a protocol declares: method name -> the protocol's
    function, and the names of its annotated data attributes (bases included)."""
    methods: dict[str, Any] = {}
    attributes: list[str] = []
    for klass in reversed(protocol.__mro__):
        if klass in (object, Protocol) or not getattr(klass, "_is_protocol", False):
            continue
        for name, value in vars(klass).items():
            if name in _PROTOCOL_BASES or name.startswith("_abc"):
                continue
            if callable(value):
                methods[name] = value
        for name in vars(klass).get("__annotations__", {}):
            if name not in attributes:
                attributes.append(name)
    return methods, tuple(attributes)


def _arity_problem(bound: Any, spec: Any) -> str | None:
    """Why ``bound`` (a method of the implementation) cannot be called as the
    protocol's ``spec`` is (same positional parameters), or None."""
    try:
        have = inspect.signature(bound)
    except (TypeError, ValueError):  # a builtin without a signature: not checkable
        return None
    params = list(inspect.signature(spec).parameters.values())[1:]  # without self
    args = [object()] * sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty for p in params)
    kwargs = {p.name: object() for p in params if p.kind is p.KEYWORD_ONLY and p.default is p.empty}
    try:
        have.bind(*args, **kwargs)
    except TypeError as exc:
        return f"{spec.__name__}({', '.join(p.name for p in params)}) cannot be called on it: {exc}"
    return None


def check_implementation(obj: Any, stage: str, who: str) -> Any:
    """``obj`` if it satisfies ``STAGE_PROTOCOLS[stage]``; else
    :class:`~crossfield.errors.PluginError` naming ``who`` (the implementation
    and the plugin that registered it) and every missing or uncallable member."""
    protocol = STAGE_PROTOCOLS[stage]
    methods, attributes = protocol_members(protocol)
    problems = [f"no attribute {a!r}" for a in attributes if not hasattr(obj, a)]
    for name, spec in methods.items():
        member = getattr(obj, name, None)
        if member is None:
            problems.append(f"no method {name}()")
        elif not callable(member):
            problems.append(f"{name} is not callable")
        else:
            problem = _arity_problem(member, spec)
            if problem:
                problems.append(problem)
    if problems:
        raise PluginError(
            f"{who} made a {type(obj).__name__}, which is not a {stage} implementation "
            f"(crossfield.stages.{protocol.__name__}): {'; '.join(problems)}"
        )
    return obj
