"""Hook specifications: the contract between crossfield and its plugins.

Two kinds of hook (``docs/plugins.md``):

* **Registry hooks**, one per stage, ``register_<stage>s(register)``. pluggy
  calls every implementation; each plugin calls ``register(name, factory,
  description)`` once per implementation it offers. The config names the one
  that runs. ``factory(**options)`` builds it; its keyword parameters are the
  stage's options, so the config is validated against the signature.
* **Observer hooks**, ``on_<event>(...)``. Every implementation is called with
  each stage output as it is produced: the recorder, the Rerun logger and
  the progress display are observers. An observer must not change what it
  is given (the data classes are frozen and their arrays read-only).

Hook parameters are typed the way tox 4 types its hooks: the spec
functions carry the real parameter types (imported for type checking only,
so this module imports nothing at run time but pluggy and
:mod:`crossfield.stages`), and ``Register`` is a protocol with the call
signature, generic in what the stage's factories build.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol, TypeVar

import pluggy

from crossfield.stages import (
    Acquisition,
    CentroidExtractor,
    Measurer,
    ReferenceSource,
    Registrar,
    Reporter,
    Triangulator,
)

if TYPE_CHECKING:  # pragma: no cover
    from crossfield.session import FrameResult, SessionInfo, SessionStop, SessionSummary
    from crossfield.types import (
        CameraPoints,
        Measurement,
        ReferenceData,
        Registration,
        StereoCentroids,
        StereoFrame,
    )

__all__ = ["PROJECT", "Factory", "Register", "hookimpl", "hookspec"]

PROJECT = "crossfield"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

T_co = TypeVar("T_co", covariant=True)

#: A stage factory: called with the stage's options as keyword arguments
#: (its keyword parameters *are* the options), returns the implementation.
Factory = Callable[..., T_co]


class Register(Protocol[T_co]):
    """The ``register`` callable passed to every registry hook.

    ``register(name, factory, description="")``: ``name`` is what users type
    (``--centroid NAME``); ``factory(**options)`` builds an implementation
    of the stage (``T_co``, e.g. :class:`~crossfield.stages.CentroidExtractor`);
    ``description`` is shown by ``crossfield plugins`` (default: the first
    line of the factory's docstring).
    """

    def __call__(self, name: str, factory: Factory[T_co], description: str = "") -> None: ...


# ---- registry hooks -------------------------------------------------------


@hookspec
def register_acquires(register: Register[Acquisition]) -> None:
    """Offer acquisition sources. ``factory(**options)`` returns an
    :class:`crossfield.stages.Acquisition`."""


@hookspec
def register_centroids(register: Register[CentroidExtractor]) -> None:
    """Offer centroid extractors (:class:`crossfield.stages.CentroidExtractor`)."""


@hookspec
def register_triangulates(register: Register[Triangulator]) -> None:
    """Offer stereo matchers/triangulators (:class:`crossfield.stages.Triangulator`)."""


@hookspec
def register_references(register: Register[ReferenceSource]) -> None:
    """Offer CMM reference importers (:class:`crossfield.stages.ReferenceSource`)."""


@hookspec
def register_registers(register: Register[Registrar]) -> None:
    """Offer rigid registration solvers (:class:`crossfield.stages.Registrar`)."""


@hookspec
def register_measures(register: Register[Measurer]) -> None:
    """Offer characteristic evaluators (:class:`crossfield.stages.Measurer`)."""


@hookspec
def register_reports(register: Register[Reporter]) -> None:
    """Offer report writers (:class:`crossfield.stages.Reporter`)."""


# ---- observer hooks -------------------------------------------------------


@hookspec
def on_session_start(session: SessionInfo) -> None:
    """A session begins: resolved config, calibration, plan, plugin versions."""


@hookspec
def on_frame(frame: StereoFrame) -> None:
    """A stereo pair was acquired (raw input: recorded losslessly)."""


@hookspec
def on_serial_bytes(data: bytes, timestamp_ns: int, source: str) -> None:
    """Bytes read from the CMM line (or file), before any parsing (raw input)."""


@hookspec
def on_serial_event(kind: str, detail: str, timestamp_ns: int, source: str) -> None:
    """The CMM line went down (``kind = "down"``, ``detail`` = the reason) or
    came back (``"up"``), between two ``on_serial_bytes`` calls (raw input:
    recorded in order with the bytes, replayed to split lines the same way)."""


@hookspec
def on_reference(reference: ReferenceData) -> None:
    """The CMM reference points were imported and labelled."""


@hookspec
def on_centroids(centroids: StereoCentroids) -> None:
    """Centroids of one stereo pair."""


@hookspec
def on_camera_points(points: CameraPoints) -> None:
    """Triangulated camera-frame points of one stereo pair."""


@hookspec
def on_registration(registration: Registration) -> None:
    """``T_global_camera`` of one stereo pair."""


@hookspec
def on_measurement(measurement: Measurement) -> None:
    """Characteristics of one stereo pair."""


@hookspec
def on_frame_done(result: FrameResult) -> None:
    """All stages of one stereo pair have run (or one failed: see result.error)."""


@hookspec
def on_log(level: str, message: str, timestamp_ns: int) -> None:
    """A log line (``level`` one of debug, info, warning, error)."""


@hookspec
def on_session_stop(stop: SessionStop) -> None:
    """The session stopped taking input before its end: the operator interrupted it
    (SIGINT) or its camera or reference source raised (raw input: recorded on
    ``/session/stop``; a replay stops there too). ``on_session_end`` follows, the
    session INCOMPLETE."""


@hookspec
def on_session_end(summary: SessionSummary) -> None:
    """The session is over; ``summary.report`` holds the aggregated results."""


