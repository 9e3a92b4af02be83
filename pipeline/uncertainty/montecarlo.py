"""GUM Supplement 1 check of the linear budget: propagation of distributions by Monte Carlo.

JCGM 101:2008 (GUM-S1) propagates the input distributions through the
measurement model itself instead of its linearisation. The model here is the
session result: for each characteristic, the mean over the measured frames of
what the session's registration implementation (its ``fit``) and measurement
implementation (its ``measure``) give, corrected to 20 degC. One draw
(GUM-S1 7.2-7.4) is one whole session:

* one CMM draw shared by every frame (controls, reference points, line probes):
  ``+ N(0, (f sigma)^2 I)`` for controls and reference points, f the CMM inflation
  of the consistency check; each probe of a reference line ``+ N(0, sigma_line^2 I)``,
  sigma_line the one per-probe sigma of the linear budget's ``reference_line`` term
  (the line fit's posterior sigma, max(stated, observed): already supported by the
  data, so not inflated again; :func:`reference_draw_sigmas`);
* one calibration error shared by every frame: when the session's budget propagated the
  calibration file's parameters (its ``std_*`` keys, :mod:`crossfield.uncertainty.calibration`),
  the parameters drawn ``dtheta = C z``, z ~ N(0, I), C the columns of the stated covariance's
  square root, and every camera point moved by ``G dtheta`` (G the triangulation's sensitivity
  to the parameters, :func:`crossfield.uncertainty.calibration.point_displacements`: the first
  order model the linear term propagates; the registration is fitted again to the moved
  controls); otherwise a scale, the camera points times ``1 + N(0, u_s^2)``;
* one eccentricity offset per target (and per control), shared by every frame
  (the same tilted circle): ``N(0, sigma_ecc^2 I)``, the budget's Gaussian
  equivalent of its uniform distribution;
* one camera bias per target and control ``N(0, camera_excess diag(sigma_xyz^2))``, shared by
  every frame, when the budget has a ``camera_systematic`` term (issue 22);
* one bias per control along its line of sight ``N(0, v) l_k`` (l_k the unit vector from the
  upper camera, camera frame), shared by every frame, when the session put a share of the
  registration residuals' excess on the camera (``camera_registration_excess``;
  ``v`` of :func:`crossfield.uncertainty.line_of_sight.per_control_variance`, the budget's
  second part of ``camera_systematic``);
* per frame, the camera points' own centroid noise ``N(0, diag(sigma_xyz^2))``
  (camera frame), independent from frame to frame;
* the frames' mean, then the temperature correction through
  :func:`crossfield.uncertainty.temperature.correction` with the temperatures and
  expansion coefficients drawn (``N(value, u^2)``), then the repeatability excess
  ``N(0, u^2)`` (the budget's term: scatter beyond the model, additive).

The frames are the session's first measured ones, kept with their camera points
(``SessionAggregate.monte_carlo_frames``, at most
:data:`crossfield.chain.aggregate.MONTE_CARLO_FRAMES_KEPT`); when the session measured
n > K of them, each kept frame's camera noise is drawn with ``sigma sqrt(K / n)``,
so that the mean of the K frames carries the camera variance of a mean of n
(exact for the linear part of the model). Correspondences are held as in each frame.

For each characteristic the sample gives u_MC (its standard deviation) and the
probabilistically symmetric coverage interval (GUM-S1 7.7; its ends the sample
quantiles of Hyndman & Fan 1996, definition 8) for the coverage
probability the coverage factor stands for with a normal output,
``p = erf(k / sqrt 2)`` (95.45 % for k = 2): its half-width U_MC is compared with
the linear ``U = k u``, ``agreement = U_MC / U - 1``. The numerical standard
uncertainty of that agreement (an asymptotic result for a normal output, the
sample quantile's variance ``p' (1 - p') / (N phi(k)^2)``) is
``sqrt((1 - Phi(k)) / (2 N)) / (k phi(k))``: 0.99 / sqrt(N) for k = 2.

Where the draws run: the N draws are split into chunks of :data:`CHUNK_DRAWS`,
each with its own generator from ``numpy.random.SeedSequence(seed).spawn``, so the
sample does not depend on where or in how many processes the chunks run:
in this process (default), or one Dask task per chunk (``client``, from
:func:`crossfield.batch.engine.client`), the same numbers bit for bit. What
travels to the workers is a :class:`MonteCarloProblem`: numbers, arrays, the
plan and the implementations' names and options (rebuilt on the worker from the
installed plugins).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from crossfield.batch.engine import Engine, client
from crossfield.errors import CrossfieldError
from crossfield.geometry import element_probes, fit_reference_element
from crossfield.plan import MeasurementPlan
from crossfield.progress import bar
from crossfield.session import MonteCarloResult
from crossfield.types import CameraPoints, Correspondence, ReferenceData, Registration
from crossfield.uncertainty.eccentricity import eccentricity_sigma_mm, off_axis_rad
from crossfield.uncertainty.temperature import LENGTH_KINDS, Temperature, correction

__all__ = [
    "CHUNK_DRAWS",
    "MonteCarloFrame",
    "MonteCarloProblem",
    "MonteCarloResult",
    "monte_carlo",
    "on_dask",
    "problem_from_summary",
    "run_draws",
    "session_monte_carlo",
    "summarise",
]

#: Draws per chunk (one Dask task each); fixed, so the sample does not depend on the workers.
CHUNK_DRAWS = 25


@dataclass(frozen=True, eq=False)
class MonteCarloFrame:
    """One measured frame's inputs: its camera points (camera frame, mm) and the
    correspondence its registration used. eccentricity_mm: (N,) per-axis standard
    uncertainty of each point's circle centre (mm); labels: (N,) the target or
    control id each point stands for ("" for none), whose eccentricity draw is
    shared by the frames."""

    points: CameraPoints
    correspondence: Correspondence
    eccentricity_mm: np.ndarray
    labels: tuple[str, ...]
    #: (N, 3, q) mm: each point's displacement per unit draw of the calibration's q independent
    #: parameter columns (camera frame); None: the calibration is drawn as a scale
    calibration_mm: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class MonteCarloProblem:
    """Everything a draw needs, as plain data (picklable for Dask workers).

    plan: the measurement plan; reference: the imported CMM points; frames: the
    kept measured frames; camera_scale: factor on the camera noise (``sqrt(K / n)``
    for n > K measured frames, else 1); cmm_inflation: the consistency check's f;
    calibration_scale_u: relative scale u_s; names: characteristics in report
    order, kinds their kinds; repeatability_mm: (C,) the budget's repeatability
    terms (mm); temperature: the plan's temperatures; register / measure: the
    implementations' (name, options); camera_excess: the Type A camera excess
    (``camera_systematic``: a centroid bias per target shared by the frames);
    line_of_sight_mm2: the variance v (mm^2) of the bias along each control's line of sight
    (the camera's share of the registration excess), 0 when none.
    """

    plan: MeasurementPlan
    reference: ReferenceData
    frames: tuple[MonteCarloFrame, ...]
    camera_scale: float
    cmm_inflation: float
    calibration_scale_u: float
    names: tuple[str, ...]
    kinds: tuple[str, ...]
    repeatability_mm: np.ndarray
    temperature: Temperature
    register: tuple[str, Mapping[str, Any]]
    measure: tuple[str, Mapping[str, Any]]
    camera_excess: float = 0.0
    line_of_sight_mm2: float = 0.0


# --------------------------------------------------------------------------
# The problem, from a finished session
# --------------------------------------------------------------------------


def _frame_inputs(frame: Any, plan: MeasurementPlan, calibration: tuple | None = None) -> MonteCarloFrame:
    points: CameraPoints = frame.points
    registration: Registration = frame.registration
    spec_u = plan.uncertainty
    factor = spec_u.eccentricity_residual if spec_u.eccentricity_corrected else 1.0
    xyz = np.asarray(points.xyz)
    ecc = np.array([
        factor * eccentricity_sigma_mm(
            float(np.linalg.norm(p)), spec_u.target_radius_mm, spec_u.max_tilt_deg, off_axis_rad(p)
        )
        for p in xyz
    ])
    labels = [""] * len(xyz)
    corr = registration.correspondence
    for cid, i in zip(corr.control_ids, corr.camera_index):
        labels[int(i)] = cid
    if len(xyz):  # the targets found: the camera point at the reported global position
        global_xyz = registration.fit.apply(xyz)
        for tid, g in frame.measurement.target_points.items():
            i = int(np.argmin(np.linalg.norm(global_xyz - np.asarray(g), axis=1)))
            labels[i] = tid
    displacements = None
    if calibration is not None and len(xyz):
        from crossfield.uncertainty.calibration import point_displacements

        stereo, n_dist, columns = calibration
        displacements = point_displacements(xyz, stereo, n_dist, columns)
    return MonteCarloFrame(points, corr, ecc, tuple(labels), displacements)


def _calibration_columns(summary: Any) -> tuple | None:
    """(the session's StereoCalibration, n_dist, (p, q) columns of the stated covariance's square
    root) when the session's budget propagated the calibration file's parameters, else None."""
    from crossfield.uncertainty.calibration import calibration_covariance, sqrt_columns

    aggregate, info = summary.aggregate, summary.info
    if not str(getattr(aggregate, "calibration_uncertainty_source", "")).startswith("propagated parameters"):
        return None
    stated = calibration_covariance(getattr(info.calibration, "source", ""), getattr(info, "calibration_files", None))
    if stated is None:
        return None
    return info.calibration, stated.n_dist, sqrt_columns(stated.covariance)


def _stage(config: Any, name: str) -> tuple[str, dict[str, Any]]:
    stage = config.stages[name]
    return stage.plugin, dict(stage.options)


def problem_from_summary(summary: Any) -> MonteCarloProblem | None:
    """The :class:`MonteCarloProblem` of a finished session (its aggregate's kept
    frames, reference, budgets and config); None when no frame was measured."""
    aggregate = summary.aggregate
    kept = aggregate.monte_carlo_frames
    if not kept:
        return None
    plan = summary.info.plan
    n = max(aggregate.frames_measured, len(kept))
    characteristics = [c for c in summary.characteristics if c.n > 0]
    repeatability = np.array([
        next((t.u_mm for t in c.budget if t.source == "repeatability"), 0.0) for c in characteristics
    ])
    config = summary.info.config
    calibration = _calibration_columns(summary)
    return MonteCarloProblem(
        plan=plan,
        reference=summary.reference,
        frames=tuple(_frame_inputs(f, plan, calibration) for f in kept),
        camera_scale=math.sqrt(len(kept) / n),
        cmm_inflation=1.0 if aggregate.consistency is None else float(aggregate.consistency.cmm_inflation),
        calibration_scale_u=float(aggregate.calibration_scale_u),
        names=tuple(c.name for c in characteristics),
        kinds=tuple(c.kind for c in characteristics),
        repeatability_mm=repeatability,
        temperature=plan.temperature,
        register=_stage(config, "register"),
        measure=_stage(config, "measure"),
        camera_excess=0.0 if aggregate.consistency is None else float(getattr(aggregate.consistency, "camera_excess", 0.0)),
        line_of_sight_mm2=_line_of_sight_variance(aggregate.consistency),
    )


def _line_of_sight_variance(check: Any) -> float:
    """v (mm^2) along each control's line of sight, from the consistency check's camera share."""
    from crossfield.uncertainty.line_of_sight import per_control_variance

    if check is None:
        return 0.0
    excess = float(getattr(check, "camera_registration_excess", 0.0)) * float(check.expected_cmm_ss_mm2)
    return per_control_variance(excess, (int(check.dof) + 6) // 3)


# --------------------------------------------------------------------------
# The draws (run in this process or on a Dask worker)
# --------------------------------------------------------------------------


@functools.lru_cache(maxsize=1)
def _plugin_manager() -> Any:
    """The installed plugins (one plugin manager per process: a worker builds it once)."""
    from crossfield.chain.registry import make_plugin_manager

    return make_plugin_manager(entry_points=True)


def _implementations(problem: MonteCarloProblem) -> tuple[Any, Any]:
    """Fresh register and measure implementations from the installed plugins."""
    from crossfield.chain.registry import get_implementation

    pm = _plugin_manager()
    return tuple(  # type: ignore[return-value]
        get_implementation(pm, stage, name).create(dict(options))
        for stage, (name, options) in (("register", problem.register), ("measure", problem.measure))
    )


def reference_draw_sigmas(problem: MonteCarloProblem) -> tuple[float, ...]:
    """The standard deviation (mm, per coordinate) each reference point is drawn with,
    in ``problem.reference.points`` order: a reference line's probe gets the line fit's
    ``sigma_mm`` (one sigma per probe, as the linear budget's ``reference_line`` term:
    ``measure_plan`` and :func:`crossfield.geometry.fit_reference_element`), any other
    point ``cmm_inflation * sigma_mm`` (as the ``control_cmm`` / ``reference_cmm`` terms)."""
    points = problem.reference.points
    line_sigma: dict[str, float] = {}
    for spec in problem.plan.reference_lines:
        try:
            fit = fit_reference_element(spec, points)
        except ValueError:
            continue  # not measurable: the measurement reports it, the draws change nothing
        for probe in element_probes(spec.id, points):
            line_sigma[probe.label] = float(fit.sigma_mm)
    return tuple(line_sigma.get(p.label, problem.cmm_inflation * float(p.sigma_mm)) for p in points)


def draw_reference(
    reference: ReferenceData, rng: np.random.Generator, sigmas_mm: tuple[float, ...]
) -> ReferenceData:
    """One CMM draw: each point ``+ N(0, sigma^2 I)``, sigma from ``sigmas_mm`` (mm,
    :func:`reference_draw_sigmas`)."""
    points = tuple(
        dataclasses.replace(p, xyz=np.asarray(p.xyz) + rng.normal(0.0, sigma, 3))
        for p, sigma in zip(reference.points, sigmas_mm, strict=True)
    )
    return dataclasses.replace(reference, points=points)


def _draw_temperature(t: Temperature, rng: np.random.Generator) -> Temperature:
    """The temperatures and expansion coefficients drawn from N(value, u^2), stated exactly."""
    return dataclasses.replace(
        t,
        part_c=t.part_c + rng.normal(0.0, t.u_part_k), u_part_k=0.0,
        part_alpha_per_k=t.part_alpha_per_k + rng.normal(0.0, t.u_part_alpha_per_k), u_part_alpha_per_k=0.0,
        reference_c=t.reference_c + rng.normal(0.0, t.u_reference_k), u_reference_k=0.0,
        reference_alpha_per_k=t.reference_alpha_per_k + rng.normal(0.0, t.u_reference_alpha_per_k),
        u_reference_alpha_per_k=0.0,
    )


def draw_chunk(problem: MonteCarloProblem, seed: np.random.SeedSequence, n_draws: int) -> np.ndarray:
    """``n_draws`` session results drawn with the generator of ``seed``: (n_draws, C) mm,
    column j characteristic ``problem.names[j]`` (NaN where a draw did not measure it)."""
    registrar, measurer = _implementations(problem)
    rng = np.random.default_rng(seed)
    plan = problem.plan
    column = {name: j for j, name in enumerate(problem.names)}
    out = np.full((n_draws, len(problem.names)), np.nan)
    labels = sorted({label for f in problem.frames for label in f.labels if label})
    sigmas = reference_draw_sigmas(problem)
    for d in range(n_draws):
        reference = draw_reference(problem.reference, rng, sigmas)  # shared by the frames
        by_label = reference.by_label()
        q = next((f.calibration_mm.shape[2] for f in problem.frames if f.calibration_mm is not None), 0)
        if q:  # the calibration's parameters, one draw for the session
            z = rng.normal(size=q)
            scale = 1.0
        else:
            scale = 1.0 + rng.normal(0.0, problem.calibration_scale_u)
        offsets = dict(zip(labels, rng.normal(size=(len(labels), 3))))  # eccentricity, per target
        # camera_systematic: a bias per target, shared by the frames (drawn only when the budget has it,
        # so that the draws of a session without it stay as they were)
        biases = dict(zip(labels, rng.normal(size=(len(labels), 3)))) if problem.camera_excess > 0 else {}
        along = ({label: rng.normal(0.0, math.sqrt(problem.line_of_sight_mm2)) for label in labels}
                 if problem.line_of_sight_mm2 > 0 else {})
        sums = np.zeros(len(problem.names))
        counts = np.zeros(len(problem.names))
        for frame in problem.frames:
            xyz0 = np.asarray(frame.points.xyz)
            unit = np.array([offsets[label] if label else rng.normal(size=3) for label in frame.labels])
            unit = unit.reshape(xyz0.shape)
            noise = rng.normal(size=xyz0.shape) * np.asarray(frame.points.sigma_xyz) * problem.camera_scale
            xyz = xyz0 + noise + unit * frame.eccentricity_mm[:, None]
            if biases:
                bias = np.array([biases[label] if label else rng.normal(size=3) for label in frame.labels])
                xyz = xyz + bias.reshape(xyz0.shape) * np.asarray(frame.points.sigma_xyz) * math.sqrt(problem.camera_excess)
            if q and frame.calibration_mm is not None:
                xyz = xyz + frame.calibration_mm @ z
            corr = frame.correspondence
            for cid, i in zip(corr.control_ids, corr.camera_index):
                if cid in along:  # the camera's share of the registration excess, along the line of sight
                    xyz[int(i)] = xyz[int(i)] + along[cid] * xyz0[int(i)] / np.linalg.norm(xyz0[int(i)])
            xyz = xyz * scale
            Q = np.array([by_label[c].xyz for c in corr.control_ids])
            fit = registrar.fit(xyz[np.asarray(corr.camera_index)], Q)
            registration = Registration(frame.points.sequence, fit, corr)
            drawn = dataclasses.replace(frame.points, xyz=xyz)
            m = measurer.measure(plan, reference, drawn, registration, None)
            for c in m.characteristics:
                j = column.get(c.name)
                if j is not None and math.isfinite(c.measured_mm):
                    sums[j] += c.measured_mm
                    counts[j] += 1
        temperature = _draw_temperature(problem.temperature, rng)
        for j, kind in enumerate(problem.kinds):
            if counts[j]:
                mean = sums[j] / counts[j]
                dL = correction(mean, temperature)[0] if kind in LENGTH_KINDS else 0.0
                out[d, j] = mean + dL
        out[d] += rng.normal(size=len(problem.names)) * problem.repeatability_mm
    return out


def _chunks(n_draws: int, seed: int, size: int) -> list[tuple[np.random.SeedSequence, int]]:
    if size < 1:
        raise ValueError(f"chunk_draws must be >= 1, got {size}")
    sizes = [min(size, n_draws - start) for start in range(0, n_draws, size)]
    return list(zip(np.random.SeedSequence(seed).spawn(len(sizes)), sizes))


def run_draws(
    problem: MonteCarloProblem,
    n_draws: int,
    seed: int = 0,
    client: Any = None,
    *,
    chunk_draws: int = CHUNK_DRAWS,
) -> np.ndarray:
    """The (n_draws, C) sample (mm): :func:`draw_chunk` over chunks of ``chunk_draws``
    draws, chunk i drawn with ``SeedSequence(seed).spawn(...)[i]``, in this process, or
    one Dask task per chunk on ``client`` (a ``distributed.Client``). The same sample
    bit for bit either way, whatever the number of workers."""
    chunks = _chunks(n_draws, seed, chunk_draws)
    if client is None:
        parts_here = []
        with bar(desc="Monte Carlo check", total=n_draws, unit="draw") as drawn:
            for s, n in chunks:
                parts_here.append(draw_chunk(problem, s, n))
                drawn.update(n)
        return np.vstack(parts_here)
    from crossfield.batch.engine import run_each

    shared = client.scatter(problem, broadcast=True)  # sent once, not once per task
    parts: list[np.ndarray | None] = [None] * len(chunks)
    errors: list[str] = []

    def collect(i: int, result: Any, error: str | None) -> None:
        if error is not None:
            errors.append(f"chunk {i}: {error}")
        else:
            parts[i] = np.asarray(result, dtype=np.float64)

    run_each(client, draw_chunk, [(shared, s, n) for s, n in chunks], collect,
             prefix="crossfield-monte-carlo", desc="Monte Carlo check (chunks)")
    if errors:  # e.g. a worker without the session's plugins, or lost too often
        raise CrossfieldError("the Monte Carlo check on Dask failed: " + "; ".join(errors))
    return np.vstack(parts)  # type: ignore[arg-type]


# --------------------------------------------------------------------------
# Summary statistics (GUM-S1 7.6-7.7) beside the linear U
# --------------------------------------------------------------------------


def _normal_pdf(x: float) -> float:
    return math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)


def summarise(
    samples: np.ndarray, names: tuple[str, ...], U_linear: Mapping[str, float | None], k: float
) -> list[MonteCarloResult]:
    """Per characteristic (column of ``samples``, mm): u_MC, the probabilistically
    symmetric interval for ``p = erf(k / sqrt 2)`` about the sample mean, its
    half-width beside the linear U and the agreement with its numerical standard
    uncertainty (module docstring)."""
    p = math.erf(k / math.sqrt(2.0))
    results = []
    for j, name in enumerate(names):
        y = samples[:, j]
        y = y[np.isfinite(y)]
        if len(y) < 2:
            continue
        # Sample quantiles by Hyndman & Fan's definition 8 (approximately median-unbiased
        # for any continuous distribution): numpy's default (definition 7) pulls tail
        # quantiles inwards, the half-width by -2.3 % at 200 normal draws, -1.2 % at 400.
        low, high = np.quantile(y, [(1.0 - p) / 2.0, (1.0 + p) / 2.0], method="median_unbiased")
        centre = float(np.mean(y))
        half = float((high - low) / 2.0)
        U = U_linear.get(name)
        tail = (1.0 - p) / 2.0
        rel_u = math.sqrt(tail / (2.0 * len(y))) / (k * _normal_pdf(k)) if k > 0 else None
        results.append(MonteCarloResult(
            name, len(y), float(np.std(y, ddof=1)), (float(low - centre), float(high - centre)), half,
            U, None if not U else half / U - 1.0, p,
            None if not U or rel_u is None else rel_u * half / U,
        ))
    return results


def monte_carlo(
    summary: Any,
    n_draws: int,
    seed: int = 0,
    *,
    problem: MonteCarloProblem | None = None,
    client: Any = None,
    chunk_draws: int = CHUNK_DRAWS,
) -> list[MonteCarloResult]:
    """The Monte Carlo check of ``summary``'s budgets ([] without a measured frame):
    ``n_draws`` whole-session draws (module docstring), in this process or on ``client``."""
    if n_draws < 2:
        raise ValueError(f"the Monte Carlo check needs at least 2 draws, got {n_draws}")
    problem = problem_from_summary(summary) if problem is None else problem
    if problem is None:
        return []
    samples = run_draws(problem, n_draws, seed, client, chunk_draws=chunk_draws)
    U = {c.name: c.expanded_uncertainty_mm for c in summary.characteristics}
    return summarise(samples, problem.names, U, problem.plan.uncertainty.coverage_factor)


# --------------------------------------------------------------------------
# Where: in this process, or on Dask (crossfield run --scheduler / --workers)
# --------------------------------------------------------------------------

_ENGINE: contextvars.ContextVar[Engine | None] = contextvars.ContextVar(
    "crossfield_monte_carlo_engine", default=None
)


@contextlib.contextmanager
def on_dask(engine: Engine | None = None) -> Iterator[None]:
    """Within the block, :func:`session_monte_carlo` runs its chunks on Dask where
    ``engine`` says (:class:`crossfield.batch.engine.Engine`: a scheduler's address,
    or an embedded ``LocalCluster`` started only when a Monte Carlo check runs).
    Where it runs is not a session fact: the sample is the same."""
    token = _ENGINE.set(engine or Engine())
    try:
        yield
    finally:
        _ENGINE.reset(token)


def session_monte_carlo(summary: Any, n_draws: int, seed: int = 0) -> list[MonteCarloResult]:
    """:func:`monte_carlo` with the session's own register and measure implementations
    and options, in this process or, inside :func:`on_dask`, on Dask."""
    engine = _ENGINE.get()
    if engine is None:
        return monte_carlo(summary, n_draws, seed)
    where = dict(memory_limit=engine.memory_limit, dashboard_address=":0")
    with client(engine.scheduler, engine.workers, **where) as c:
        return monte_carlo(summary, n_draws, seed, client=c)
