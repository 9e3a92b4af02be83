"""The runner: builds the configured stages and chains them over a session.

    acquire -> centroid -> triangulate -> (reference) -> register -> measure -> report

:func:`run_session` is the one entry: ``crossfield run``, ``crossfield
replay``, ``crossfield audit`` and the Python API all start a session
there. A live session creates its acquisition from the config; a replay
passes in its recorded source (a :class:`~crossfield.stages.RecordedAcquisition`)
and the recorded raw CMM bytes, which the reference implementation then
decodes instead of reading a device. The CMM reference is imported once
per session, before the first frame; every stereo pair then runs centroid
-> triangulate -> correspondence -> register -> measure. Every output goes
to the observer hooks (recorder, Rerun logger, progress display) as soon
as it exists. The session's :class:`SessionInfo` is built in
:func:`session_info` and its :class:`SessionSummary` by
:func:`crossfield.chain.aggregate.session_summary` (in :func:`finish_session`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pluggy

from crossfield.chain.aggregate import SessionAccumulator, session_accumulator, session_summary
from crossfield.chain.correspondence import match_control_points
from crossfield.chain.interrupt import InterruptedAgain, OperatorInterrupts, operator_interrupts
from crossfield.chain.provenance import package_versions
from crossfield.chain.registry import Implementation, get_implementation
from crossfield.chain.session_pose import SessionPoseAccumulator
from crossfield.chain.weights import fit_registration
from crossfield.config import Config
from crossfield.errors import ConfigError, CrossfieldError, PluginError, RecordingError
from crossfield.plan import MeasurementPlan, load_plan
from crossfield.recording.calibration_files import session_calibration_files
from crossfield.recording.recorder import McapRecorder, SessionRecorder
from crossfield.recording.writer import DEFAULT_COMPRESSION
from crossfield.report.document import build_report, with_seal
from crossfield.report.thumbnails import ThumbnailObserver
from crossfield.session import (
    STOP_INTERRUPTED,
    STOP_SOURCE_ERROR,
    CameraThumbnail,
    FrameResult,
    SessionInfo,
    SessionStop,
    SessionSummary,
)
from crossfield.stages import (
    STAGES,
    Acquisition,
    CentroidExtractor,
    DecodesLinkEvents,
    LinkEvent,
    ListsReportFiles,
    Measurer,
    RecordedAcquisition,
    ReferenceSource,
    Registrar,
    Reporter,
    ReportsIncidents,
    SerialChunk,
    ServesSimulatedArm,
    Triangulator,
    check_implementation,
    implements,
)
from crossfield.types import (
    CameraPoints,
    GroundTruth,
    ReferenceData,
    Registration,
    StereoCalibration,
    StereoCentroids,
    StereoFrame,
)
from crossfield.uncertainty.montecarlo import session_monte_carlo

__all__ = [
    "SIMULATED_PORT",
    "ReferenceImport",
    "Stages",
    "control_points",
    "finish_session",
    "new_session_dir",
    "process_frame",
    "register_frame",
    "resolve_plan",
    "run_pipeline",
    "run_session",
    "safe_session_name",
    "session_info",
]

#: Reference ``port`` value that connects the serial plugin to the simulated arm
#: of a :class:`~crossfield.stages.ServesSimulatedArm` acquisition.
SIMULATED_PORT = "simulator"

#: What ``[session] name`` may be: letters, digits, '.', '_', '-' (not only dots).
_NAME = re.compile(r"(?!\.+$)[A-Za-z0-9._-]+")
#: What an identifier read from a recording or a device must be to name a folder:
#: the same letters, starting with a letter or digit, at most 128 of them.
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


@dataclass
class Stages:
    """The implementations chosen for a session (acquisition excepted)."""

    implementations: dict[str, Implementation[Any]]
    centroid: CentroidExtractor
    triangulate: Triangulator
    register: Registrar
    measure: Measurer
    report: Reporter

    @classmethod
    def build(cls, pm: pluggy.PluginManager, config: Config, *, skip: Iterable[str] = ()) -> Stages:
        """Look up every stage's implementation (those in ``skip`` excepted: replay
        does not need the acquisition plugin) and create the per-frame ones."""
        skip = set(skip)
        impls = {
            stage: get_implementation(pm, stage, config.stages[stage].plugin)
            for stage in STAGES
            if stage not in skip
        }
        made = {
            stage: impls[stage].create(dict(config.stages[stage].options), f"{config.source}: [{stage}]")
            for stage in ("centroid", "triangulate", "register", "measure", "report")
        }
        return cls(impls, **made)

    def describe(self) -> dict[str, dict[str, str]]:
        """stage -> {name, plugin, package, version} of each implementation looked up."""
        return {
            stage: {"name": i.name, "plugin": i.plugin, "package": i.package, "version": i.version}
            for stage, i in self.implementations.items()
        }


def process_frame(
    frame: StereoFrame,
    stages: Stages,
    calibration: StereoCalibration,
    plan: MeasurementPlan,
    reference: ReferenceData,
    ground_truth: GroundTruth | None,
    hook: Any,
    match_tolerance_mm: float,
) -> FrameResult:
    """Run centroid -> triangulate -> correspondence -> register -> measure on one pair.

    A :class:`CrossfieldError` in any stage ends this frame (``error`` says
    which stage and why); the session goes on with the next pair.
    """
    seq, ts = frame.sequence, frame.timestamp_ns
    centroids = points = registration = measurement = None
    stage = "centroid"
    try:
        centroids = StereoCentroids(
            seq,
            stages.centroid.extract(frame.upper, "upper", seq),
            stages.centroid.extract(frame.lower, "lower", seq),
        )
        hook.on_centroids(centroids=centroids)
        stage = "triangulate"
        points = stages.triangulate.triangulate(centroids, calibration)
        hook.on_camera_points(points=points)
        stage = "register"
        registration = register_frame(points, reference, plan, stages.register, match_tolerance_mm)
        hook.on_registration(registration=registration)
        stage = "measure"
        measurement = stages.measure.measure(plan, reference, points, registration, ground_truth)
        hook.on_measurement(measurement=measurement)
        return FrameResult(seq, ts, centroids, points, registration, measurement)
    except CrossfieldError as exc:
        message = f"frame {seq}: {stage}: {exc}"
        hook.on_log(level="error", message=message, timestamp_ns=ts)
        return FrameResult(seq, ts, centroids, points, registration, measurement, error=message)


def control_points(reference: ReferenceData, plan: MeasurementPlan) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Ids, (M, 3) global positions (mm) and (M,) sigmas of the probed control points."""
    by_label = reference.by_label()
    ids = [cid for cid in plan.control_ids if cid in by_label]
    xyz = np.array([by_label[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    sigma = np.array([by_label[i].sigma_mm for i in ids], dtype=np.float64)
    return ids, xyz, sigma


def register_frame(
    points: CameraPoints,
    reference: ReferenceData,
    plan: MeasurementPlan,
    registrar: Registrar,
    match_tolerance_mm: float,
) -> Registration:
    """Match camera points to the CMM control points by rigid distances, then fit."""
    ids, control_xyz, control_sigma = control_points(reference, plan)
    correspondence = match_control_points(points.xyz, control_xyz, ids, tolerance_mm=match_tolerance_mm)
    index_of = {cid: k for k, cid in enumerate(ids)}
    rows = [index_of[c] for c in correspondence.control_ids]
    camera = correspondence.camera_index
    fit = fit_registration(
        registrar,
        points.xyz[camera],
        control_xyz[rows],
        np.sum(points.sigma_xyz[camera] ** 2, axis=1) / 3,  # per-axis variance, tr(C) / 3
        control_sigma[rows],
        None if points.cov_xyz is None else points.cov_xyz[camera],
    )
    return Registration(points.sequence, fit, correspondence)


# ---- the session folder -------------------------------------------------------


def safe_session_name(text: str) -> str | None:
    """``text`` if it may name a session folder (letters, digits, '.', '_', '-',
    starting with a letter or digit, at most 128), else None. Identifiers read
    from a recording or a device pass here before they become part of a path."""
    return text if _SAFE_NAME.fullmatch(text) else None


def _session_id(config: Config, acquisition_info: Mapping[str, Any]) -> str:
    name = str(config.session.get("name") or "")
    if name:
        if not _NAME.fullmatch(name):
            raise ConfigError(
                f"{config.source}: [session] key 'name' may hold only letters, digits, '.', '_', '-' "
                f"(and not only dots), got {name!r}"
            )
        return name
    stamp = time.strftime("%Y%m%d-%H%M%S")
    tag = str(acquisition_info.get("scenario") or acquisition_info.get("source") or "session")
    # The tag comes from the device's description: data, never a path.
    return f"{stamp}-{re.sub(r'[^A-Za-z0-9._-]+', '_', tag)}"


def new_session_dir(base: Path, name: str, what: str = "") -> Path:
    """Create and return ``base/name`` (``base/name-2``, ... if it exists).

    ``name`` must be one path component (no separator, not ``.`` or ``..``):
    the folder is always a direct child of ``base``. ``what`` names ``base``
    in errors (e.g. the config key it came from)."""
    if name in ("", ".", "..") or "/" in name or "\\" in name or Path(name).name != name:
        raise ConfigError(f"session folder name {name!r} is not a single folder name")
    label = f"{what} = {str(base)!r}" if what else str(base)
    if base.exists() and not base.is_dir():
        raise ConfigError(f"{label}: not a folder (a file is there); name a folder for the sessions")
    out = base / name
    k = 1
    while out.exists():
        k += 1
        out = base / f"{name}-{k}"
    try:
        out.mkdir(parents=True)
    except OSError as exc:
        raise ConfigError(f"{label}: cannot create the session folder {out}: {exc.strerror}") from None
    return out


@contextlib.contextmanager
def _registered(
    pm: pluggy.PluginManager, observers: Iterable[object], interrupts: OperatorInterrupts | None = None
) -> Iterator[None]:
    """Register the session's observers; unregister and close them at the end,
    also when the session fails (a recorder then finishes its file; not
    interrupted by a Ctrl-C, ``interrupts``)."""
    added = []
    try:
        for obs in observers:
            pm.register(obs)
            added.append(obs)
        yield
    finally:
        with _shielded(interrupts):
            for obs in reversed(added):
                pm.unregister(obs)
                close = getattr(obs, "close", None)
                if callable(close):
                    close()


def _shielded(interrupts: OperatorInterrupts | None) -> contextlib.AbstractContextManager[None]:
    """``interrupts.shielded()``: no Ctrl-C while a recording is ended and closed."""
    return interrupts.shielded() if interrupts is not None else contextlib.nullcontext()


def _session_observers(
    config: Config, out_dir: Path, extra: Iterable[object], mcap_path: Path | None = None
) -> list[object]:
    observers: list[object] = []
    if config.session.get("record", True):
        observers.append(
            McapRecorder(
                mcap_path or out_dir / "session.mcap",
                signing_key=config.session.get("signing_key") or None,
                compression=config.session.get("compression", DEFAULT_COMPRESSION),
            )
        )
    if config.session.get("rerun", True):
        from crossfield.viz.rerun_log import RerunLogger

        observers.append(RerunLogger(out_dir / "session.rrd"))
    observers.extend(extra)
    return observers


# ---- the session --------------------------------------------------------------


def resolve_plan(config: Config, acquisition: Acquisition) -> MeasurementPlan:
    """The measurement plan: a replay's recorded one; else ``[session] plan``,
    else the source's default plan."""
    if isinstance(acquisition, RecordedAcquisition):
        # The recorded plan (an attachment); a path read from a recording is never opened.
        if acquisition.default_plan is None:
            raise ConfigError(f"{config.source}: the recorded source has no measurement plan")
        return acquisition.default_plan
    path = config.session.get("plan") or ""
    if path:
        return load_plan(path)
    if acquisition.default_plan is not None:
        return acquisition.default_plan
    raise ConfigError(
        f"{config.source}: [session] key 'plan' is empty and the {config.stages['acquire'].plugin!r} "
        f"source has no default measurement plan; name a plan file"
    )


def _with_simulated_arm(config: Config, reference: Implementation[Any], acquisition: Acquisition) -> Config:
    """The config with ``[reference] port = "simulator"`` when that is what will
    be read: the reference implementation takes a ``port``, the user named
    none, and the acquisition serves a simulated arm. A port the user named
    is kept as it is; ``"simulator"`` with a source that serves no arm is an error."""
    options = config.stages["reference"].options
    where = f"{config.source}: [reference]"
    if "port" not in reference.options():
        return config
    if "port" not in options:
        if not isinstance(acquisition, ServesSimulatedArm):
            return config  # creating the reference then says the port is needed
        stages = dict(config.stages)
        stages["reference"] = dataclasses.replace(stages["reference"], options={**options, "port": SIMULATED_PORT})
        return dataclasses.replace(config, stages=stages)
    if options["port"] == SIMULATED_PORT and not isinstance(acquisition, ServesSimulatedArm):
        raise ConfigError(
            f"{where}: port = {SIMULATED_PORT!r} needs an acquire source that serves a simulated arm "
            f"(the simulator), not {config.stages['acquire'].plugin!r}"
        )
    return config


def session_info(
    config: Config,
    stages: Stages,
    acquisition: Acquisition,
    plan: MeasurementPlan,
    out_dir: Path,
    parent: Mapping[str, Any] | None = None,
    description: Mapping[str, Any] | None = None,
) -> SessionInfo:
    """The facts fixed at the start of a session: the one place a
    :class:`SessionInfo` is made (live run and replay alike).
    description: ``acquisition.describe()`` when already asked."""
    plugins = stages.describe()
    if isinstance(acquisition, RecordedAcquisition):
        plugins["acquire"] = dict(acquisition.recorded_plugins.get("acquire", {}))
        start_time_ns = int(acquisition.start_time_ns or 0)
    else:
        start_time_ns = time.time_ns()
    return SessionInfo(
        session_id=out_dir.name,
        out_dir=out_dir,
        config=config,
        calibration=acquisition.calibration,
        plan=plan,
        plugins={stage: plugins[stage] for stage in STAGES if stage in plugins},
        packages=package_versions(),
        acquisition=dict(acquisition.describe() if description is None else description),
        ground_truth=acquisition.ground_truth,
        start_time_ns=start_time_ns,
        parent=parent,
        calibration_files=session_calibration_files(acquisition),
    )


def run_session(
    config: Config,
    pm: pluggy.PluginManager,
    *,
    observers: Iterable[object] = (),
    source: Acquisition | None = None,
    cmm_raw: Sequence[SerialChunk] | None = None,
    mcap_path: str | Path | None = None,
    parent: Mapping[str, Any] | None = None,
    reports: bool = True,
) -> SessionSummary:
    """Run one session as configured; returns its summary.

    The session folder ``<output_dir>/<name>/`` receives session.mcap,
    session.rrd and the report files. ``observers`` are extra observer
    plugins (e.g. the progress display) registered for this session only.

    source: the acquisition; None creates the config's ``[acquire]``
    implementation (and closes it at the end). A replay passes its
    :class:`~crossfield.stages.RecordedAcquisition`: then the recorded plan,
    start time and acquire plugin are the session's, and the session is
    ``incomplete`` where the recording is.
    cmm_raw: recorded reads of the CMM line (``/cmm/raw``, read order): they
    go to ``on_serial_bytes`` with their recorded times and the reference
    implementation decodes them (``decode``) instead of reading a device.
    mcap_path: the MCAP file to write (default ``<session folder>/session.mcap``);
    the session folder is then named after it, next to it.
    parent: the recording a replay re-runs and what it changed (``SessionInfo.parent``).
    reports: write the report files (the reporter's ``write``: report.json, report.html
    and its figures); False (the audit's reproduction) computes the session end all the
    same (summary, report document, recordings ended and sealed) and writes no report.
    """
    stages = Stages.build(pm, config, skip=("acquire",) if source is not None else ())
    owned = source is None
    if source is None:
        impl = stages.implementations["acquire"]
        source = impl.create(dict(config.stages["acquire"].options), f"{config.source}: [acquire]")
    else:
        source = check_implementation(source, "acquire", f"the session's source {type(source).__name__}")
    if isinstance(source, ReportsIncidents):
        source.connect_log(pm.hook.on_log)
    try:
        plan = resolve_plan(config, source)
        if cmm_raw is None:
            config = _with_simulated_arm(config, stages.implementations["reference"], source)
        description = source.describe()
        if mcap_path is not None:
            mcap_path = Path(mcap_path)
            base, name = mcap_path.parent, mcap_path.stem
        else:
            base = Path(config.session.get("output_dir", "recordings"))
            name = _session_id(config, description)
        # The reference is made before the folder: a bad option leaves nothing behind.
        reader = _reference_reader(config, stages, pm.hook)
        if cmm_raw is None:
            import_reference = _live_reference(config, stages, source, plan, reader)
        else:
            import_reference = _recorded_reference(stages.implementations["reference"].name, reader, cmm_raw, plan)
        out_dir = new_session_dir(base, name, "" if mcap_path is not None else f"{config.source}: [session] output_dir")
        info = session_info(config, stages, source, plan, out_dir, parent, description)
        recorded = source if isinstance(source, RecordedAcquisition) else None
        thumbnails = ThumbnailObserver()  # one image per camera for the report (docs/report.md, "Cameras")
        session_observers = [*_session_observers(config, out_dir, observers, mcap_path), thumbnails]
        # Ctrl-C ends the session as INCOMPLETE (crossfield.chain.interrupt); installed
        # outside the observers, so that the recorders are closed under it too.
        with operator_interrupts() as interrupts, _registered(pm, session_observers, interrupts):
            return run_pipeline(
                pm.hook,
                stages,
                info,
                import_reference,
                source.frames(),
                float(config.session.get("match_tolerance_mm", 0.5)),
                incomplete=(lambda: recorded.incomplete) if recorded is not None else (lambda: None),
                recordings=[o for o in session_observers if isinstance(o, SessionRecorder)],
                thumbnails=thumbnails.thumbnails,
                interrupts=interrupts,
                recorded_stop=getattr(recorded, "recorded_stop", None) if recorded is not None else None,
                source_errors=recorded is None,
                reports=reports,
            )
    finally:
        if owned:
            source.close()


#: ``import_reference(hook) -> (reference, time_ns)``: reads (or replays) the
#: CMM data, handing every raw byte to ``hook.on_serial_bytes`` first; time_ns
#: is when the last byte was read (None if none was), the time of the import's log lines.
#: A replay's also takes ``decode=False``: hand the recorded bytes on, decode nothing
#: (the live import was stopped there) and return None.
ReferenceImport = Callable[..., Any]


def _reference_reader(config: Config, stages: Stages, hook: Any, port: str | None = None) -> ReferenceSource:
    """The configured reference implementation (``port`` replacing the option
    when given), its incident log connected to ``hook.on_log``."""
    impl = stages.implementations["reference"]
    options = dict(config.stages["reference"].options)
    if port is not None:
        options["port"] = port
    reader = impl.create(options, f"{config.source}: [reference]")
    if isinstance(reader, ReportsIncidents):
        reader.connect_log(hook.on_log)
    return reader


def _live_reference(
    config: Config, stages: Stages, acquisition: Acquisition, plan: MeasurementPlan, reader: ReferenceSource
) -> ReferenceImport:
    """Read the CMM data from the device (``reader``), or from the simulated arm
    of the acquisition when the port is ``"simulator"`` (a reader for its pty is made then)."""
    source = stages.implementations["reference"].name
    simulated = config.stages["reference"].options.get("port") == SIMULATED_PORT

    def import_reference(hook: Any) -> tuple[ReferenceData, int | None]:
        last: list[int] = []

        def sink(data: bytes | LinkEvent) -> None:
            t = time.time_ns()
            if isinstance(data, LinkEvent):
                hook.on_serial_event(kind=data.kind, detail=data.detail, timestamp_ns=t, source=source)
                return
            last[:] = [t]
            hook.on_serial_bytes(data=data, timestamp_ns=t, source=source)

        if simulated and isinstance(acquisition, ServesSimulatedArm):
            with acquisition.serve_arm() as port:
                reference = _reference_reader(config, stages, hook, port).acquire(plan, sink)
        else:
            reference = reader.acquire(plan, sink)
        return reference, (last[0] if last else None)

    return import_reference


def _recorded_reference(
    name: str, reader: ReferenceSource, chunks: Sequence[SerialChunk], plan: MeasurementPlan
) -> ReferenceImport:
    """Hand the recorded reads to the observers with their recorded times, then
    decode them as the live import did (``reader.decode``)."""

    def import_reference(hook: Any, decode: bool = True) -> tuple[ReferenceData, int | None] | None:
        parts: list[bytes] = []
        events: list[tuple[int, LinkEvent]] = []  # (offset in the joined bytes, event)
        size = 0
        last = None
        for chunk in chunks:
            source = chunk.source or name
            if isinstance(chunk.data, LinkEvent):
                hook.on_serial_event(
                    kind=chunk.data.kind, detail=chunk.data.detail, timestamp_ns=chunk.timestamp_ns, source=source
                )
                events.append((size, chunk.data))
                continue
            hook.on_serial_bytes(data=chunk.data, timestamp_ns=chunk.timestamp_ns, source=source)
            parts.append(chunk.data)
            size += len(chunk.data)
            last = chunk.timestamp_ns
        if not decode:
            return None
        if not events:
            return reader.decode(b"".join(parts), plan), last
        if not implements(reader, DecodesLinkEvents):
            raise PluginError(
                f"the recording holds {len(events)} link event(s) of the CMM line (disconnects), and "
                f"reference plugin {name!r} cannot take them (decode(raw, plan, link_events=...)): "
                f"its lines would be split differently than live; replay with the recorded plugin"
            )
        return reader.decode(b"".join(parts), plan, link_events=events), last

    return import_reference


def run_pipeline(
    hook: Any,
    stages: Stages,
    info: SessionInfo,
    import_reference: ReferenceImport,
    frames: Iterable[StereoFrame],
    match_tolerance_mm: float,
    incomplete: Callable[[], str | None] = lambda: None,
    recordings: Sequence[SessionRecorder] = (),
    thumbnails: Callable[[], Sequence[CameraThumbnail]] = tuple,
    *,
    interrupts: OperatorInterrupts | None = None,
    recorded_stop: SessionStop | None = None,
    source_errors: bool = True,
    reports: bool = True,
) -> SessionSummary:
    """The session's chain, shared by a live run and a replay.

    on_session_start -> reference import (raw bytes to the observers first)
    -> on_reference -> per frame: on_frame, :func:`process_frame`,
    on_frame_done -> :func:`finish_session`. Every time stamp comes from the
    data (frame capture times, serial read times), so a replay that feeds
    the recorded inputs with their recorded times emits the same hook calls
    with the same arguments. ``incomplete()`` is asked after the last frame
    (a replay of a cut-short recording says so). ``recordings``: the
    session's recorders, ended by :func:`finish_session` before the reports
    are written. A recording that fails while frames are processed (disk
    full) ends the frames there: the session is then finished as incomplete.
    ``thumbnails()``: the camera thumbnails for the summary, asked after the last frame.

    Stopping early (docs/faults.md, "Interrupted runs"): a Ctrl-C (KeyboardInterrupt;
    with ``interrupts`` one that arrives while a pair is processed lets the pair
    finish) or, when ``source_errors``, a :class:`CrossfieldError` or ``OSError`` of
    the reference import or of the acquisition between pairs, ends the input there:
    a :class:`SessionStop` goes to ``on_session_stop`` (recorded on ``/session/stop``)
    and the session is finished as INCOMPLETE with the pairs measured so far, every
    result partial. ``recorded_stop``: a replay's recorded stop; the replay stops
    where it says (at the reference import: the recorded bytes are handed on, not
    decoded) and states the same stop. ``reports``: as :func:`run_session`'s.
    """
    hook.on_session_start(session=info)
    planned = _planned_pairs(info)
    reference_name = stages.implementations["reference"].name
    stop: SessionStop | None = None
    reference = ReferenceData(points=())
    reference_time_ns: int | None = None
    try:
        if recorded_stop is not None and recorded_stop.stage == "reference":
            import_reference(hook, decode=False)
            stop = recorded_stop
        else:
            reference, reference_time_ns = import_reference(hook)
    except KeyboardInterrupt as exc:
        if isinstance(exc, InterruptedAgain):
            raise
        stop = _stop(STOP_INTERRUPTED, "reference", reference_name, 0, planned)
    except RecordingError:
        raise
    except (CrossfieldError, OSError) as exc:
        if not source_errors:
            raise
        stop = _stop(STOP_SOURCE_ERROR, "reference", reference_name, 0, planned, exc)
    t = reference_time_ns if reference_time_ns is not None else time.time_ns()
    if stop is None:
        for problem in reference.problems:
            hook.on_log(level="warning", message=f"reference: {problem}", timestamp_ns=t)
        hook.on_reference(reference=reference)
    else:
        t = stop.timestamp_ns
    # Aggregated frame by frame: memory does not grow with the session's length
    # (the first rows are kept for the report; the recording has every frame).
    accumulator = session_accumulator(info, reference, stages.measure)
    session_pose = SessionPoseAccumulator()
    failed: str | None = None
    deferred = interrupts.deferred if interrupts is not None else contextlib.nullcontext
    pairs = iter(frames)
    while stop is None:
        try:
            frame = next(pairs)
        except StopIteration:
            break
        except KeyboardInterrupt as exc:  # while waiting for the source
            if isinstance(exc, InterruptedAgain):
                raise
            stop = _stop(STOP_INTERRUPTED, "acquire", _acquire_name(info), accumulator.frames_processed, planned)
            break
        except RecordingError:
            raise
        except (CrossfieldError, OSError) as exc:
            if not source_errors:
                raise
            stop = _stop(
                STOP_SOURCE_ERROR, "acquire", _acquire_name(info), accumulator.frames_processed, planned, exc
            )
            break
        with deferred():  # a first Ctrl-C now lets this pair finish: it is recorded and counted whole
            try:
                hook.on_frame(frame=frame)
                result = process_frame(
                    frame, stages, info.calibration, info.plan, reference, info.ground_truth, hook, match_tolerance_mm
                )
                hook.on_frame_done(result=result)
            except RecordingError as exc:  # an observer's recording failed (disk full): no more frames
                if not recordings:
                    raise
                failed = f"the recording failed after {accumulator.frames_processed} frame(s): {exc}"
                break
            accumulator.add(result)
            session_pose.add(result.points, result.registration)
            t = frame.timestamp_ns
        if interrupts is not None and interrupts.requested:
            stop = _stop(STOP_INTERRUPTED, "acquire", _acquire_name(info), accumulator.frames_processed, planned)
    if stop is not None:
        close = getattr(pairs, "close", None)
        if callable(close):
            close()  # the source's generator: stopped here
    if stop is None and recorded_stop is not None:
        stop = recorded_stop  # a replay: the live run stopped after these pairs
    if stop is not None:  # recorded first: once the line is shown, a replay stops here too
        hook.on_session_stop(stop=stop)
        hook.on_log(level="error", message=f"session stopped: {stop.reason}", timestamp_ns=stop.timestamp_ns)
    moved = _log_session_pose(hook, session_pose, reference, info.plan, stages.register, t)
    return finish_session(
        hook, stages, info, reference, accumulator,
        _joined(incomplete(), failed, stop.reason if stop is not None else None), recordings=recordings,
        thumbnails=thumbnails(), station_moved=moved, stop=stop, interrupts=interrupts, reports=reports,
    )


def _planned_pairs(info: SessionInfo) -> int | None:
    """How many stereo pairs the source was asked for (``[acquire] frames``), None if not said."""
    frames = info.config.stages["acquire"].options.get("frames")
    return frames if isinstance(frames, int) and not isinstance(frames, bool) and frames > 0 else None


def _acquire_name(info: SessionInfo) -> str:
    """The acquisition implementation's name (as recorded: a replay's is the recorded one)."""
    return str((info.plugins.get("acquire") or {}).get("name") or info.config.stages["acquire"].plugin)


def _stop(
    kind: str, stage: str, source: str, frames: int, planned: int | None, error: BaseException | None = None
) -> SessionStop:
    """The :class:`SessionStop` of a live run stopped now, its reason in words, e.g.
    ``interrupted by the operator (SIGINT) after 3 of 150 stereo pairs`` or
    ``reference source romer-serial failed: <message> (during the CMM import, before
    the first stereo pair)``."""
    if stage == "reference":
        where = "during the CMM import, before the first stereo pair"
    else:
        where = f"after {frames} of {planned} stereo pairs" if planned else f"after {frames} stereo pair(s)"
    message = ""
    if kind == STOP_INTERRUPTED:
        reason = f"interrupted by the operator (SIGINT) {where}"
    else:
        message = " ".join(str(error).split()) or type(error).__name__
        what = "reference" if stage == "reference" else "acquisition"
        reason = f"{what} source {source} failed: {message} ({where})"
    return SessionStop(kind, stage, source, reason, frames, time.time_ns(), message)


def _joined(*reasons: str | None) -> str | None:
    """The reasons given, joined by '; ' (None when there is none)."""
    given = [r for r in reasons if r]
    return "; ".join(given) if given else None


def _log_session_pose(
    hook: Any, session_pose: SessionPoseAccumulator, reference, plan, registrar, timestamp_ns: int
) -> str | None:
    """The joint static-station pose of all frames and its motion test, as one log line
    (time stamped with the last frame's capture time, so a replay logs it alike);
    returns that line when the test found the station moved (the verdict's), else None."""
    ids, xyz, sigma = control_points(reference, plan)
    try:
        pose = session_pose.result(dict(zip(ids, xyz)), dict(zip(ids, sigma.tolist())), registrar)
    except CrossfieldError as exc:
        hook.on_log(level="warning", message=f"session pose: {exc}", timestamp_ns=timestamp_ns)
        return None
    if pose is None or pose.frames <= 1:
        return None
    hook.on_log(level="warning" if pose.moved else "info", message=pose.message(), timestamp_ns=timestamp_ns)
    return pose.message() if pose.moved else None


def finish_session(
    hook: Any,
    stages: Stages,
    info: SessionInfo,
    reference: ReferenceData,
    accumulator: SessionAccumulator,
    incomplete: str | None = None,
    recordings: Sequence[SessionRecorder] = (),
    thumbnails: Sequence[CameraThumbnail] = (),
    station_moved: str | None = None,
    stop: SessionStop | None = None,
    interrupts: OperatorInterrupts | None = None,
    reports: bool = True,
) -> SessionSummary:
    """The session's end (``stop``: why it stopped early, if it did; ``interrupts``:
    a Ctrl-C waits while the recordings are ended; ``station_moved``: the motion test's line when the station
    moved, which fails the session): summarise the aggregated frames
    (:func:`~crossfield.chain.aggregate.session_summary`), run the Monte Carlo check
    (``[session] monte_carlo`` draws), build the report document once, end the
    recordings with it, add the seal to it, hand it to the reporter, tell the
    observers; returns the summary (its ``report`` the document as written).

    The order is the guarantee of docs/faults.md: first every recording is
    closed and checked (it reads back complete, its seal computed); only
    then are the reports written, report.json with the seal
    (``integrity``). If ending a recording fails (disk full), the reports
    say INCOMPLETE with the reason (``passed`` false) and a
    :class:`RecordingError` follows, so the command exits non-zero; what was
    written stays in the file (a truncated recording replays as INCOMPLETE).
    A report that cannot be written is a :class:`RecordingError` naming it.
    ``reports`` False: everything but the reporter's ``write`` (no report file, no
    figure drawn); the summary's ``report`` is the document all the same.
    """
    summary = session_summary(
        info, reference, accumulator, incomplete=incomplete, thumbnails=thumbnails, station_moved=station_moved,
        stop=stop,
    )
    draws = int(info.config.session.get("monte_carlo", 0))
    if draws:
        summary = dataclasses.replace(summary, monte_carlo=tuple(session_monte_carlo(summary, draws)))
    # The recording lists the report files to come, when the reporter says which they
    # are (ListsReportFiles): it is closed before they exist.
    listed = reports and implements(stages.report, ListsReportFiles)
    planned = tuple(stages.report.report_files(info.out_dir)) if listed else ()
    summary = dataclasses.replace(summary, report=build_report(summary))
    seals, failures = [], []
    with _shielded(interrupts):  # a recording is ended whole, or not at all
        for recording in recordings:
            try:
                sealed = recording.end_session(dataclasses.replace(summary, report_files=planned))
            except CrossfieldError as exc:
                failures.append(str(exc))
            else:
                if sealed is not None:
                    seals.append(sealed)
    if failures:
        reason = "; ".join(failures)
        if not reason.startswith("the recording failed"):
            reason = f"the recording failed: {reason}"
        summary = dataclasses.replace(summary, incomplete=_joined(incomplete, reason), report=None)
        summary = dataclasses.replace(summary, report=build_report(summary))  # the document says INCOMPLETE
    if seals:
        summary = dataclasses.replace(summary, report=with_seal(summary.report, seals[0]))
    try:
        files = stages.report.write(summary, info.out_dir) if reports else []
    except OSError as exc:
        where = exc.filename or info.out_dir
        also = f" (and {'; '.join(failures)})" if failures else ""
        raise RecordingError(f"{where}: cannot write the reports: {exc.strerror or exc}{also}") from None
    summary = dataclasses.replace(summary, report_files=tuple(files))
    hook.on_session_end(summary=summary)
    if failures:
        raise RecordingError(f"{'; '.join(failures)}; the reports say INCOMPLETE")
    return summary
