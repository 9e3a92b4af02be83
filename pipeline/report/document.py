"""The session report as plain JSON data (``report.json``), shared by the report writers.

:func:`build_report` turns a :class:`crossfield.session.SessionSummary` into
JSON-able data: dicts, lists, str, int, bool, None and Python floats. Floats
are never rounded; ``json.dumps`` writes them with ``repr``, the shortest
text that reads back to the same double, so an auditor can compare numbers
bit for bit. Non-finite floats (NaN for a characteristic no frame measured)
become ``null``: JSON has no NaN.

Units: mm for lengths, radians for angles. Frames: ``R_global_camera``,
``t_global_camera`` map upper-camera points into the CMM (global) frame,
``p_g = R @ p_c + t``. The format is described in ``docs/report.md`` and
fixed by ``pipeline/recording/schemas/report.schema.json``.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from crossfield.errors import RecordingError
from crossfield.uncertainty.instruments import instrument_problems
from crossfield.jsonable import matrix, plain, real, vector
from crossfield.rigid import rotation_angle
from crossfield.session import FrameResult, SessionSummary
from crossfield.uncertainty.budget import SOURCE_TEXT
from crossfield.uncertainty.type_a import PRIOR_DOF

__all__ = [
    "REGISTRATION_AGGREGATE",
    "REGISTRATION_AGGREGATE_TEXT",
    "REPORT_FORMAT",
    "REPORT_JSON",
    "TEMPLATE_DIR",
    "add_seal_to_file",
    "build_report",
    "calibration_sha256",
    "document_of",
    "dumps",
    "frames_note",
    "load_schema",
    "monte_carlo_section",
    "problems",
    "utc_time",
    "validate",
    "with_seal",
]

#: The report file that carries the recording's seal.
REPORT_JSON = "report.json"

#: The report page's Jinja2 templates and style sheet (``docs/report.md``, "Templates").
TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"

#: Identifies the layout of report.json; bump on incompatible changes.
REPORT_FORMAT = "crossfield-report/2"

#: How the session's T_global_camera is formed from the per-frame registrations.
REGISTRATION_AGGREGATE = "session_mean"
REGISTRATION_AGGREGATE_TEXT = (
    "mean over the registered frames: rotation = chordal L2 mean (arithmetic mean of the "
    "per-frame rotation matrices projected onto SO(3) by SVD, Hartley et al. 2013 'Rotation "
    "Averaging' sec. 5.3), translation = arithmetic mean of the per-frame translations"
)


# --------------------------------------------------------------------------
# Plain-data helpers
# --------------------------------------------------------------------------


def utc_time(timestamp_ns: int) -> str | None:
    """ISO 8601 UTC time of a nanosecond Unix timestamp (None for 0 / unset)."""
    if not timestamp_ns or timestamp_ns <= 0:
        return None
    seconds, nanos = divmod(int(timestamp_ns), 1_000_000_000)
    moment = _dt.datetime.fromtimestamp(seconds, tz=_dt.timezone.utc)
    return moment.replace(microsecond=nanos // 1000).isoformat()


# --------------------------------------------------------------------------
# Report sections
# --------------------------------------------------------------------------


def _registration_section(summary: SessionSummary) -> dict[str, Any] | None:
    """Session-mean T_global_camera over every registered frame, its spread, the
    fit RMS, per-control residuals (``summary.aggregate.registration``); the
    per-frame entries of the kept rows."""
    agg = summary.aggregate.registration
    if agg is None:
        return None
    R_mean, t_mean = agg.R_global_camera, agg.t_global_camera_mm
    controls = [
        {
            "id": c.id,
            "n_frames": c.n_frames,
            "residual_mm": vector(c.residual_mm),
            "residual_norm_mm": real(np.linalg.norm(c.residual_mm)),
            "rms_norm_mm": real(c.rms_norm_mm),
            "max_norm_mm": real(c.max_norm_mm),
            "expected_rms_mm": real(c.expected_rms_mm),
        }
        for c in agg.controls
    ]
    section: dict[str, Any] = {
        "aggregate": REGISTRATION_AGGREGATE,
        "aggregate_description": REGISTRATION_AGGREGATE_TEXT,
        "n_frames": agg.n_frames,
        "R_global_camera": matrix(R_mean),
        "det_R": real(np.linalg.det(R_mean)),
        "t_global_camera_mm": vector(t_mean),
        "scale": real(agg.scale),
        "rms_mm": real(agg.rms_mm),
        "rotation_spread_rad": real(agg.rotation_spread_rad),
        "rotation_rms_rad": real(agg.rotation_rms_rad),
        "t_std_mm": vector(agg.t_std_mm),
        "per_frame": [
            {
                "sequence": int(r.sequence),
                "method": r.fit.method,
                "rms_mm": real(r.fit.rms_mm),
                "n_controls": len(r.correspondence.control_ids),
                "R_global_camera": matrix(r.fit.R),
                "t_global_camera_mm": vector(r.fit.t),
                "scale": real(r.fit.scale),
                "unmatched_control": list(r.correspondence.unmatched_control),
            }
            for r in summary.registrations
        ],
        "control_points": controls,
        "covariance": _covariance_section(agg),
        "ground_truth": None,
    }
    truth = summary.info.ground_truth
    if truth is not None:
        R_true = np.asarray(truth.R_global_camera, dtype=np.float64)
        t_true = np.asarray(truth.t_global_camera, dtype=np.float64)
        section["ground_truth"] = {
            "R_global_camera": matrix(R_true),
            "t_global_camera_mm": vector(t_true),
            "rotation_error_rad": real(rotation_angle(R_true, R_mean)),
            "translation_error_mm": vector(t_mean - t_true),
            "translation_error_norm_mm": real(np.linalg.norm(t_mean - t_true)),
        }
    return section


def _covariance_section(agg) -> dict[str, Any] | None:
    """R and t with their covariance: (6, 6) over (rotation vector rad, t mm) and the
    standard uncertainties it gives."""
    C = agg.pose_covariance
    if C is None:
        return None
    sd = np.sqrt(np.clip(np.diagonal(C), 0.0, None))
    return {
        "parameters": ["rx_rad", "ry_rad", "rz_rad", "tx_mm", "ty_mm", "tz_mm"],
        "matrix": [[real(v) for v in row] for row in np.asarray(C)],
        "rotation_u_rad": vector(sd[:3]),
        "t_u_mm": vector(sd[3:]),
        "description": "covariance of a small rotation vector of R_global_camera (global frame, rad) and of "
        "t_global_camera (mm) from the stated camera and CMM sigmas (mean over frames, not divided by their "
        "number; the CMM part inflated as the budgets' when the residuals contradict it)",
    }


def _consistency_section(summary: SessionSummary) -> dict[str, Any] | None:
    check = summary.aggregate.consistency
    if check is None:
        return None
    return {
        "test": "chi-square of the registration residuals against the stated sigmas (docs/uncertainty.md)",
        "n_frames": int(check.n_frames),
        "observed_ss_mm2": real(check.observed_ss_mm2),
        "expected_camera_ss_mm2": real(check.expected_camera_ss_mm2),
        "expected_cmm_ss_mm2": real(check.expected_cmm_ss_mm2),
        "dof": int(check.dof),
        "chi2": real(check.chi2),
        "p_value": real(check.p_value),
        "birge_ratio": real(check.birge_ratio),
        "alpha": real(check.alpha),
        "consistent": bool(check.consistent),
        "cmm_inflation": real(check.cmm_inflation),
        "epipolar_points_per_frame": real(check.epipolar_points),
        "epipolar_chi2_per_point": real(check.epipolar_chi2_per_point),
        "camera_ratio": real(check.camera_ratio),
        "camera_excess": real(check.camera_excess),
        "camera_registration_excess": real(check.camera_registration_excess),
        "cmm_evidence_dof": int(check.cmm_evidence_dof),
        "cmm_ratio": real(check.cmm_ratio),
        "cmm_line_excess": real(check.cmm_line_excess),
        "cmm_share": real(check.cmm_share),
        "camera_excess_dof": real(check.camera_excess_dof),
        "registration_excess_dof": real(check.registration_excess_dof),
        "cmm_excess_dof": real(check.cmm_excess_dof),
        "rule": f"Type A evidence through a shrunk variance ratio s^2 = (nu0 + chi2) / (nu0 + dof), nu0 = {PRIOR_DOF} "
        "(crossfield.uncertainty.type_a): each source's own evidence first (the camera's epipolar residuals: "
        "camera_excess a; the CMM's reference-line fits: cmm_line_excess b), then what the registration "
        "residuals show beyond both, X, split between camera and CMM in proportion to each one's posterior mean "
        "excess (cmm_share the CMM's part); f = sqrt(1 + b + X_cmm / E_cmm), the camera's part along the "
        "controls' lines of sight into camera_systematic (crossfield.uncertainty.consistency); continuous, "
        "no threshold",
        "warning": check.warning,
        "note": check.note,
    }


def _uncertainty_section(summary: SessionSummary) -> dict[str, Any]:
    plan = summary.info.plan
    spec, temp = plan.uncertainty, plan.temperature
    aggregate = summary.aggregate
    return {
        "coverage_factor": real(spec.coverage_factor),
        "decision_rule": spec.decision_rule,
        "calibration_scale_u": real(aggregate.calibration_scale_u),
        "calibration_scale_u_source": aggregate.calibration_uncertainty_source,
        "eccentricity": {
            "target_radius_mm": real(spec.target_radius_mm),
            "max_tilt_deg": real(spec.max_tilt_deg),
            "corrected": bool(spec.eccentricity_corrected),
            "residual_fraction": real(spec.eccentricity_residual),
        },
        "temperature": {
            "stated": bool(temp.stated),
            "part_c": real(temp.part_c),
            "u_part_k": real(temp.u_part_k),
            "part_alpha_per_k": real(temp.part_alpha_per_k),
            "u_part_alpha_per_k": real(temp.u_part_alpha_per_k),
            "reference_c": real(temp.reference_c),
            "u_reference_k": real(temp.u_reference_k),
            "reference_alpha_per_k": real(temp.reference_alpha_per_k),
            "u_reference_alpha_per_k": real(temp.u_reference_alpha_per_k),
        },
        "sources": dict(SOURCE_TEXT),
        "consistency": _consistency_section(summary),
    }


def _job_section(summary: SessionSummary) -> dict[str, Any]:
    job = summary.info.plan.job
    return {
        "part": job.part,
        "serial": job.serial,
        "operator": job.operator,
        "order": job.order,
        "instruments": [
            {"id": i.id, "kind": i.kind, "calibrated": i.calibrated, "due": i.due} for i in job.instruments
        ],
    }


def _characteristic_entry(index: int, c) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "no": index,
        "name": c.name,
        "kind": c.kind,
        "elements": list(c.elements),
        "n_frames": int(c.n),
        "measured_mm": real(c.measured_mm),
        "std_mm": real(c.std_mm),
        "uncertainty_mm": real(c.uncertainty_mm),
        "nominal_mm": real(c.nominal_mm),
        "tolerance_mm": real(c.tolerance_mm),
        "deviation_mm": real(c.deviation_mm),
        "passed": bool(c.passed),
        "upper_tol_mm": real(c.upper_tol_mm if c.upper_tol_mm is not None else c.tolerance_mm),
        "lower_tol_mm": real(c.lower_tol_mm if c.lower_tol_mm is not None else c.tolerance_mm),
        "expanded_uncertainty_mm": real(c.expanded_uncertainty_mm),
        "coverage_factor": real(c.coverage_factor),
        "effective_dof": real(c.effective_dof),
        "budget": [
            {"source": t.source, "u": real(t.u), "unit": t.unit, "sensitivity": real(t.sensitivity),
             "u_mm": real(t.u_mm)}
            for t in c.budget
        ],
        "decision": c.decision,
        "decision_rule": c.decision_rule,
        "measured_raw_mm": real(c.measured_raw_mm),
        "temperature_correction_mm": real(c.temperature_correction_mm),
    }
    if c.actual_mm is not None:  # ground truth known (simulator)
        entry["actual_mm"] = real(c.actual_mm)
        entry["error_mm"] = real(c.error_mm)
    if getattr(c, "partial", False):  # the session stopped early: of the pairs measured so far
        entry["partial"] = True
    return entry


def _frame_entry(frame: FrameResult) -> dict[str, Any]:
    registration = frame.registration
    measurement = frame.measurement
    return {
        "sequence": int(frame.sequence),
        "timestamp_ns": int(frame.timestamp_ns),
        "error": frame.error,
        "n_camera_points": frame.n_camera_points,
        "registration_rms_mm": None if registration is None else real(registration.fit.rms_mm),
        "n_controls": None if registration is None else len(registration.correspondence.control_ids),
        "missing_targets": [] if measurement is None else list(measurement.missing_targets),
        "target_points_mm": {}
        if measurement is None
        else {str(k): vector(v) for k, v in measurement.target_points.items()},
        "characteristics": []
        if measurement is None
        else [
            {
                "name": c.name,
                "measured_mm": real(c.measured_mm),
                "uncertainty_mm": real(c.uncertainty_mm),
                "passed": bool(c.passed),
            }
            for c in measurement.characteristics
        ],
    }


def _frame_problem(sequence: int, error: str) -> str:
    """``frame <sequence>: <error>`` (the runner's messages already start so)."""
    prefix = f"frame {sequence}: "
    return error if error.startswith(prefix) else prefix + error


def problems(summary: SessionSummary) -> list[str]:
    """Every problem of the session as one human-readable line each.

    Failed frames and targets not found are listed frame by frame for the
    kept rows, then the other failed frames whose error was kept, then counts
    of what is not listed (all of it is in the recording)."""
    lines: list[str] = []
    if summary.incomplete:
        lines.append(f"session incomplete: {summary.incomplete}")
    if summary.station_moved:
        lines.append(f"session pose: {summary.station_moved}")
    lines.extend(f"reference import: {p}" for p in summary.reference.problems)
    lines.extend(instrument_problems(summary.info))
    check = summary.aggregate.consistency
    if check is not None and check.warning:
        lines.append(f"uncertainty: {check.warning}")
    if check is not None and check.note:
        lines.append(f"uncertainty (Type A): {check.note}")
    listed = set()
    for frame in summary.frames:
        if frame.error:
            listed.add((frame.sequence, frame.timestamp_ns))
            lines.append(_frame_problem(frame.sequence, frame.error))
        if frame.measurement is not None and frame.measurement.missing_targets:
            missing = ", ".join(frame.measurement.missing_targets)
            lines.append(f"frame {frame.sequence}: targets not found: {missing}")
    aggregate = summary.aggregate
    for e in aggregate.frame_errors:
        if (e.sequence, e.timestamp_ns) not in listed:
            lines.append(_frame_problem(e.sequence, e.error))
    if aggregate.frame_errors_omitted:
        lines.append(
            f"{aggregate.frame_errors_omitted} more failed frame(s) not listed here "
            f"({aggregate.frames_failed} failed in all; every frame's status is in the recording, topic /frames)"
        )
    if summary.frames_omitted and aggregate.missing_targets:
        counts = ", ".join(f"{target} in {n}" for target, n in aggregate.missing_targets)
        lines.append(f"targets not found over all {aggregate.frames_processed} frames: {counts} frame(s)")
    for c in summary.characteristics:
        if c.n == 0:
            lines.append(f"characteristic {c.name}: measured in no frame")
    if not summary.characteristics:
        lines.append("no characteristics were evaluated")
    return lines


def frames_note(summary: SessionSummary) -> str | None:
    """Why ``frames`` does not list every frame (None when it does)."""
    omitted = summary.frames_omitted
    if not omitted:
        return None
    where = (
        "every frame's results are in the session recording (session.mcap), "
        "topics /frames, /registration, /measurement"
        if summary.info.config.session.get("record", True)
        else "the session was not recorded (session.record = false): the other rows are not kept"
    )
    return (
        f"the first {len(summary.frames)} of {summary.frames_processed} frames are listed "
        f"({omitted} left out; every aggregate covers all frames); {where}"
    )


def calibration_sha256(calibration) -> str:
    """SHA-256 (hex) of the calibration as the recording attaches it (``calibration.yml``,
    :func:`crossfield.recording.codec.calibration_yaml`), the digest the recording's
    session metadata states (``calibration_sha256``) and the audit checks."""
    from crossfield.recording.codec import calibration_yaml

    return hashlib.sha256(calibration_yaml(calibration).encode()).hexdigest()


def build_report(summary: SessionSummary) -> dict[str, Any]:
    """The content of report.json for ``summary`` (JSON-able, floats unrounded)."""
    info = summary.info
    aggregate = summary.aggregate
    return {
        "format": REPORT_FORMAT,
        "session": {
            "id": info.session_id,
            "start_time_ns": int(info.start_time_ns),
            "start_time_utc": utc_time(info.start_time_ns),
            "out_dir": str(info.out_dir),
            "parent": plain(info.parent),
        },
        "config": plain(info.config.to_dict()),
        "config_source": info.config.source,
        "plugins": {stage: plain(entry) for stage, entry in info.plugins.items()},
        "packages": plain(info.packages),
        "acquisition": plain(info.acquisition),
        "calibration": {"source": info.calibration.source, "sha256": calibration_sha256(info.calibration)},
        "plan": {"name": info.plan.name, "source": info.plan.source, "sha256": info.plan.sha256},
        "job": _job_section(summary),
        "uncertainty": _uncertainty_section(summary),
        "reference": {
            "source": summary.reference.source,
            "n_points": len(summary.reference.points),
            "problems": list(summary.reference.problems),
        },
        "frames_processed": int(aggregate.frames_processed),
        "frames_failed": int(aggregate.frames_failed),
        "frame_errors": [
            {"sequence": e.sequence, "timestamp_ns": e.timestamp_ns, "error": e.error}
            for e in aggregate.frame_errors
        ],
        "frame_errors_omitted": int(aggregate.frame_errors_omitted),
        "missing_targets": {str(target): int(n) for target, n in aggregate.missing_targets},
        "frames": [_frame_entry(f) for f in summary.frames],
        "frames_omitted": int(summary.frames_omitted),
        "frames_note": frames_note(summary),
        "registration": _registration_section(summary),
        "characteristics": [_characteristic_entry(i + 1, c) for i, c in enumerate(summary.characteristics)],
        "ground_truth_known": any(c.actual_mm is not None for c in summary.characteristics),
        "rms_error_mm": real(summary.rms_error_mm()),
        "passed": bool(summary.passed),
        "incomplete": summary.incomplete is not None,
        "incomplete_reason": summary.incomplete,
        **({"stop": _stop_section(summary.stop)} if summary.stop is not None else {}),
        "station_moved": summary.station_moved,
        "problems": problems(summary),
        **(
            {"monte_carlo": monte_carlo_section(summary.monte_carlo, int(info.config.session.get("monte_carlo", 0)))}
            if summary.monte_carlo is not None
            else {}
        ),
    }


def _stop_section(stop: Any) -> dict[str, Any]:
    """The ``stop`` section: how a session that stopped early stopped (its
    ``incomplete_reason`` says it in words)."""
    return {
        "kind": stop.kind,
        "stage": stop.stage,
        "source": stop.source,
        "frames": int(stop.frames),
        "message": stop.message,
    }


def document_of(summary: SessionSummary) -> dict[str, Any]:
    """The summary's report document: the one built at its session end
    (``summary.report``), or, for a summary made outside the runner, built now."""
    return dict(summary.report) if summary.report is not None else build_report(summary)


def with_seal(report: Mapping[str, Any], sealed: Any) -> dict[str, Any]:
    """``report`` with ``integrity``: the recording's seal (a :class:`crossfield.recording.seal.Seal`)."""
    return {**report, "integrity": sealed.to_json()}


def add_seal_to_file(path: Path, sealed: Any) -> None:
    """Add ``integrity`` (the seal) to the report.json at ``path``, written atomically
    (for a recording ended outside the runner, whose report.json was written first)."""
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise RecordingError(f"{path}: cannot add the recording's seal: {exc}") from None
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(dumps(with_seal(report, sealed)), encoding="utf-8")
        os.replace(tmp, path)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot add the recording's seal: {exc.strerror}") from None


def monte_carlo_section(results, n_draws: int, tolerance: float = 0.10) -> dict[str, Any]:
    """The ``monte_carlo`` section: the GUM-S1 check beside the linear U
    (:mod:`crossfield.uncertainty.montecarlo`); agreed: |U_MC / U - 1| <= tolerance."""
    return {
        "method": "GUM Supplement 1 (JCGM 101:2008): each draw a whole session (every kept measured frame "
        "through the session's register and measure implementations, their mean, the temperature correction), "
        "inputs drawn from the budget's distributions; probabilistically symmetric interval for "
        "p = erf(k / sqrt 2), 95.45 % for k = 2",
        "n_draws": int(n_draws),
        "tolerance": real(tolerance),
        **({"coverage": real(results[0].coverage)} if results else {}),
        "characteristics": [
            {
                "name": r.name,
                "u_mc_mm": real(r.u_mc_mm),
                "interval_mm": [real(r.interval_mm[0]), real(r.interval_mm[1])],
                "U_mc_mm": real(r.U_mc_mm),
                "U_linear_mm": real(r.U_linear_mm),
                "agreement": real(r.agreement),
                "agreement_u": real(r.agreement_u),
                "agreed": r.agreement is not None and abs(r.agreement) <= tolerance,
            }
            for r in results
        ],
    }


def dumps(report: Mapping[str, Any]) -> str:
    """report.json text: strict JSON (no NaN), floats by repr, UTF-8, indented."""
    return json.dumps(report, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def load_schema() -> dict[str, Any]:
    """The JSON Schema of report.json (``pipeline/schemas/report.schema.json``)."""
    text = resources.files("crossfield.recording").joinpath("schemas/report.schema.json").read_text(encoding="utf-8")
    return json.loads(text)


def validate(report: Mapping[str, Any]) -> None:
    """Raise ``jsonschema.ValidationError`` if ``report`` does not follow the schema. Needs the
    ``jsonschema`` package, which crossfield does not install (its ``test`` extra does)."""
    try:
        import jsonschema
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            "crossfield.report.document.validate needs the jsonschema package: pip install jsonschema"
        ) from None

    jsonschema.Draft202012Validator(load_schema()).validate(report)
