"""The runner: builds the configured stages and chains them over a session.

    acquire -> centroid -> triangulate -> (reference) -> register -> measure -> report

The CMM reference is imported once per session, before the first frame;
every stereo pair then runs centroid -> triangulate -> correspondence ->
register -> measure. Every output goes to the observer hooks (recorder,
Rerun logger, progress display) as soon as it exists.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import sys
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np
import pluggy

from crossfield.aggregate import SessionAccumulator
from crossfield.config import Config
from crossfield.correspondence import match_control_points
from crossfield.errors import ConfigError, CrossfieldError
from crossfield.plan import MeasurementPlan, load_plan
from crossfield.registry import STAGES, Implementation, get_implementation
from crossfield.session import FrameResult, SessionInfo, SessionSummary
from crossfield.session_registration import SessionPoseAccumulator
from crossfield.stages import Acquisition
from crossfield.types import (
    CameraPoints,
    GroundTruth,
    ReferenceData,
    Registration,
    StereoCalibration,
    StereoCentroids,
    StereoFrame,
)

#: Distributions whose versions are recorded with every session.
RECORDED_PACKAGES = (
    "crossfield",
    "numpy",
    "scipy",
    "opencv-python-headless",
    "pluggy",
    "mcap",
    "mcap-protobuf-support",
    "foxglove-schemas-protobuf",
    "protobuf",
    "rerun-sdk",
    "pyserial",
)

#: Reference option value that connects the serial plugin to the simulated arm.
SIMULATED_PORT = "simulator"


def package_versions() -> dict[str, str]:
    versions = {"python": sys.version.split()[0]}
    for name in RECORDED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


@dataclass
class Stages:
    """The implementations chosen for a session (acquisition excepted)."""

    implementations: dict[str, Implementation]
    centroid: Any
    triangulate: Any
    register: Any
    measure: Any
    report: Any

    @classmethod
    def build(cls, pm: pluggy.PluginManager, config: Config, *, skip: Iterable[str] = ()) -> "Stages":
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
    registrar: Any,
    match_tolerance_mm: float,
) -> Registration:
    """Match camera points to the CMM control points by rigid distances, then fit."""
    ids, control_xyz, control_sigma = control_points(reference, plan)
    correspondence = match_control_points(points.xyz, control_xyz, ids, tolerance_mm=match_tolerance_mm)
    index_of = {cid: k for k, cid in enumerate(ids)}
    rows = [index_of[c] for c in correspondence.control_ids]
    P = points.xyz[correspondence.camera_index]
    Q = control_xyz[rows]
    # Weights 1 / (sigma_camera^2 + sigma_cmm^2): Formula (5) as weighted least
    # squares (docs/registration.md); equal sigmas give the paper's unweighted fit.
    var = np.sum(points.sigma_xyz[correspondence.camera_index] ** 2, axis=1) / 3 + control_sigma[rows] ** 2
    weights = 1.0 / np.maximum(var, 1e-12)
    if getattr(registrar, "accepts_covariance", False) and points.cov_xyz is not None:
        # full camera-point covariances and CMM sigmas (register "ml", docs/registration.md)
        fit = registrar.fit(
            P, Q, weights, camera_cov=points.cov_xyz[correspondence.camera_index], control_sigma=control_sigma[rows]
        )
    else:
        fit = registrar.fit(P, Q, weights)
    return Registration(points.sequence, fit, correspondence)


def _session_id(config: Config, acquisition_info: dict[str, Any]) -> str:
    name = str(config.session.get("name") or "")
    if name:
        if not re.fullmatch(r"[A-Za-z0-9._-]+", name):
            raise ConfigError(f"{config.source}: [session] key 'name' may hold only letters, digits, '.', '_', '-'")
        return name
    stamp = time.strftime("%Y%m%d-%H%M%S")
    tag = acquisition_info.get("scenario") or acquisition_info.get("source") or "session"
    return f"{stamp}-{tag}"


def _unique_dir(base: Path, session_id: str) -> Path:
    out = base / session_id
    k = 1
    while out.exists():
        k += 1
        out = base / f"{session_id}-{k}"
    out.mkdir(parents=True)
    return out


@contextlib.contextmanager
def _registered(pm: pluggy.PluginManager, observers: Iterable[object]) -> Iterator[None]:
    """Register the session's observers; unregister and close them at the end,
    also when the session fails (a recorder then finishes its file)."""
    added = []
    try:
        for obs in observers:
            pm.register(obs)
            added.append(obs)
        yield
    finally:
        for obs in reversed(added):
            pm.unregister(obs)
            close = getattr(obs, "close", None)
            if callable(close):
                close()


def _session_observers(
    config: Config, out_dir: Path, extra: Iterable[object], mcap_path: Path | None = None
) -> list[object]:
    observers: list[object] = []
    if config.session.get("record", True):
        from crossfield.recording.recorder import McapRecorder

        observers.append(McapRecorder(mcap_path or out_dir / "session.mcap"))
    if config.session.get("rerun", True):
        from crossfield.viz.rerun_log import RerunLogger

        observers.append(RerunLogger(out_dir / "session.rrd"))
    observers.extend(extra)
    return observers


def resolve_plan(config: Config, acquisition: Acquisition) -> MeasurementPlan:
    path = config.session.get("plan") or ""
    if path:
        return load_plan(path)
    if getattr(acquisition, "default_plan", None) is not None:
        return acquisition.default_plan
    raise ConfigError(
        f"{config.source}: [session] key 'plan' is empty and the {config.stages['acquire'].plugin!r} "
        f"source has no default measurement plan; name a plan file"
    )


def run_session(
    config: Config,
    pm: pluggy.PluginManager,
    *,
    observers: Iterable[object] = (),
) -> SessionSummary:
    """Run one session as configured; returns its summary.

    The session folder ``<output_dir>/<name>/`` receives session.mcap,
    session.rrd and the report files. ``observers`` are extra observer
    plugins (e.g. the progress display) registered for this session only.
    """
    stages = Stages.build(pm, config)
    acquire_impl = stages.implementations["acquire"]
    acquisition = acquire_impl.create(dict(config.stages["acquire"].options), f"{config.source}: [acquire]")
    _connect_log(acquisition, pm.hook)
    try:
        plan = resolve_plan(config, acquisition)
        description = acquisition.describe()
        session_id = _session_id(config, description)
        out_dir = _unique_dir(Path(config.session.get("output_dir", "recordings")), session_id)
        info = SessionInfo(
            session_id=out_dir.name,
            out_dir=out_dir,
            config=config,
            calibration=acquisition.calibration,
            plan=plan,
            plugins=stages.describe(),
            packages=package_versions(),
            acquisition=description,
            ground_truth=acquisition.ground_truth,
            start_time_ns=time.time_ns(),
        )
        with _registered(pm, _session_observers(config, out_dir, observers)):
            return _run(pm, config, stages, acquisition, info)
    finally:
        acquisition.close()


#: ``import_reference(hook) -> (reference, time_ns)``: reads (or replays) the
#: CMM data, handing every raw byte to ``hook.on_serial_bytes`` first; time_ns
#: is when the last byte was read (None if none was), the time of the import's log lines.
ReferenceImport = Callable[[Any], tuple[ReferenceData, int | None]]


def _connect_log(device: Any, hook: Any) -> Any:
    """Device plugins with a ``log`` attribute (dropped frames, link down/up)
    report through the ``on_log`` hook, so the session records them."""
    if hasattr(device, "log"):
        device.log = hook.on_log
    return device


def _live_reference(
    config: Config, stages: Stages, acquisition: Any, plan: MeasurementPlan
) -> ReferenceImport:
    impl = stages.implementations["reference"]
    options = dict(config.stages["reference"].options)
    where = f"{config.source}: [reference]"
    source = f"{impl.name}"

    def import_reference(hook: Any) -> tuple[ReferenceData, int | None]:
        last: list[int] = []

        def sink(data: bytes) -> None:
            t = time.time_ns()
            last[:] = [t]
            hook.on_serial_bytes(data=data, timestamp_ns=t, source=source)

        if options.get("port") == SIMULATED_PORT:
            if not hasattr(acquisition, "serve_arm"):
                raise ConfigError(f"{where}: port = {SIMULATED_PORT!r} needs the simulator as the acquire source")
            with acquisition.serve_arm() as port:
                reader = _connect_log(impl.create({**options, "port": port}, where), hook)
                reference = reader.acquire(plan, sink)
        else:
            reference = _connect_log(impl.create(options, where), hook).acquire(plan, sink)
        return reference, (last[0] if last else None)

    return import_reference


def _run(pm: pluggy.PluginManager, config: Config, stages: Stages, acquisition: Any, info: SessionInfo) -> SessionSummary:
    return run_pipeline(
        pm.hook,
        stages,
        info,
        _live_reference(config, stages, acquisition, info.plan),
        acquisition.frames(),
        float(config.session.get("match_tolerance_mm", 0.5)),
    )


def run_pipeline(
    hook: Any,
    stages: Stages,
    info: SessionInfo,
    import_reference: ReferenceImport,
    frames: Iterable[StereoFrame],
    match_tolerance_mm: float,
    incomplete: Callable[[], str | None] = lambda: None,
) -> SessionSummary:
    """The session's chain, shared by a live run and a replay.

    on_session_start -> reference import (raw bytes to the observers first)
    -> on_reference -> per frame: on_frame, :func:`process_frame`,
    on_frame_done -> :func:`finish_session`. Every time stamp comes from the
    data (frame capture times, serial read times), so a replay that feeds
    the recorded inputs with their recorded times emits the same hook calls
    with the same arguments. ``incomplete()`` is asked after the last frame
    (a replay of a cut-short recording says so).
    """
    hook.on_session_start(session=info)
    reference, reference_time_ns = import_reference(hook)
    t = reference_time_ns if reference_time_ns is not None else time.time_ns()
    for problem in reference.problems:
        hook.on_log(level="warning", message=f"reference: {problem}", timestamp_ns=t)
    hook.on_reference(reference=reference)
    # Aggregated frame by frame: memory does not grow with the session's length
    # (the first rows are kept for the report; the recording has every frame).
    accumulator = SessionAccumulator(info.plan)
    session_pose = SessionPoseAccumulator()
    for frame in frames:
        hook.on_frame(frame=frame)
        result = process_frame(
            frame, stages, info.calibration, info.plan, reference, info.ground_truth, hook, match_tolerance_mm
        )
        hook.on_frame_done(result=result)
        accumulator.add(result)
        session_pose.add(result.points, result.registration)
        t = frame.timestamp_ns
    _log_session_pose(hook, session_pose, reference, info.plan, stages.register, t)
    return finish_session(hook, stages, info, reference, accumulator, incomplete())


def _log_session_pose(
    hook: Any, session_pose: SessionPoseAccumulator, reference, plan, registrar, timestamp_ns: int
) -> None:
    """The joint static-station pose of all frames and its motion test, as one log line
    (time stamped with the last frame's capture time, so a replay logs it alike)."""
    ids, xyz, sigma = control_points(reference, plan)
    try:
        pose = session_pose.result(dict(zip(ids, xyz)), dict(zip(ids, sigma.tolist())), registrar)
    except CrossfieldError as exc:
        hook.on_log(level="warning", message=f"session pose: {exc}", timestamp_ns=timestamp_ns)
        return
    if pose is not None and pose.frames > 1:
        hook.on_log(level="warning" if pose.moved else "info", message=pose.message(), timestamp_ns=timestamp_ns)


def finish_session(
    hook: Any,
    stages: Stages,
    info: SessionInfo,
    reference: ReferenceData,
    accumulator: SessionAccumulator,
    incomplete: str | None = None,
) -> SessionSummary:
    """Summarise the aggregated frames, write the report, tell the observers; returns the summary."""
    aggregate = accumulator.result()
    summary = SessionSummary(
        info=info,
        reference=reference,
        frames=accumulator.rows,
        characteristics=aggregate.characteristics,
        incomplete=incomplete,
        aggregate=aggregate,
    )
    files = stages.report.write(summary, info.out_dir)
    summary = dataclasses.replace(summary, report_files=tuple(files))
    hook.on_session_end(summary=summary)
    return summary
