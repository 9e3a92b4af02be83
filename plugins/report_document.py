"""The session report as plain JSON data (``report.json``), shared by the report writers.

:func:`build_report` turns a :class:`pipeline.session.SessionSummary` into
JSON-able data: dicts, lists, str, int, bool, None and Python floats. Floats
are never rounded; ``json.dumps`` writes them with ``repr``, the shortest
text that reads back to the same double, so an auditor can compare numbers
bit for bit. Non-finite floats (NaN for a characteristic no frame measured)
become ``null``: JSON has no NaN.

Units: mm for lengths, radians for angles. Frames: ``R_global_camera``,
``t_global_camera`` map upper-camera points into the CMM (global) frame,
``p_g = R @ p_c + t``. The format is described in ``docs/report.md`` and
fixed by ``pipeline/schemas/report.schema.json``.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from importlib import resources
from pathlib import PurePath
from typing import Any, Mapping

import numpy as np

from pipeline.session import FrameResult, SessionSummary
from pipeline.types import GroundTruth, Registration

#: Identifies the layout of report.json; bump on incompatible changes.
REPORT_FORMAT = "crossfield-report/1"

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


def number(value: Any) -> float | None:
    """``value`` as a Python float, or None when it is None or not finite."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def vector(values: Any) -> list[float | None]:
    """A 1-D array as a list of Python floats (non-finite -> None)."""
    return [number(v) for v in np.asarray(values, dtype=np.float64).ravel()]


def matrix(values: Any) -> list[list[float | None]]:
    """A 2-D array as a list of rows of Python floats."""
    return [vector(row) for row in np.asarray(values, dtype=np.float64)]


def plain(value: Any) -> Any:
    """Any config/metadata value as JSON-able data (unknown types -> str)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return number(value)
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [plain(v) for v in value]
    if isinstance(value, (_dt.datetime, _dt.date, _dt.time)):
        return value.isoformat()
    if isinstance(value, PurePath):
        return str(value)
    return str(value)


def utc_time(timestamp_ns: int) -> str | None:
    """ISO 8601 UTC time of a nanosecond Unix timestamp (None for 0 / unset)."""
    if not timestamp_ns or timestamp_ns <= 0:
        return None
    seconds, nanos = divmod(int(timestamp_ns), 1_000_000_000)
    moment = _dt.datetime.fromtimestamp(seconds, tz=_dt.timezone.utc)
    return moment.replace(microsecond=nanos // 1000).isoformat()


# --------------------------------------------------------------------------
# Rotation helpers
# --------------------------------------------------------------------------


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation (det +1) nearest to (3, 3) ``M`` in Frobenius norm.

    SVD projection ``U diag(1, 1, det(U V^T)) V^T`` (Hartley et al. 2013,
    'Rotation Averaging', Lemma/Theorem on the chordal L2 mean; the same
    step as the paper's Formula (8) with the reflection guard).
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in radians of the rotation ``R_a^T R_b``.

    From the chordal distance, ``||R_a - R_b||_F = 2 sqrt(2) sin(theta / 2)``,
    which stays accurate for tiny angles where ``arccos((tr - 1) / 2)`` does not.
    """
    chord = float(np.linalg.norm(np.asarray(R_a) - np.asarray(R_b)))
    return 2.0 * math.asin(min(1.0, chord / (2.0 * math.sqrt(2.0))))


# --------------------------------------------------------------------------
# Report sections
# --------------------------------------------------------------------------


def _registration_section(
    registrations: list[Registration], truth: GroundTruth | None
) -> dict[str, Any] | None:
    """Session-mean T_global_camera, its spread, per-frame RMS, per-control residuals."""
    if not registrations:
        return None
    rotations = np.array([r.fit.R for r in registrations])  # (F, 3, 3)
    translations = np.array([r.fit.t for r in registrations])  # (F, 3) mm
    R_mean = project_to_rotation(rotations.mean(axis=0))
    t_mean = translations.mean(axis=0)
    n = len(registrations)
    rms_per_frame = np.array([r.fit.rms_mm for r in registrations])

    # Residuals R p + t - q of each frame's own fit, gathered per control id.
    by_control: dict[str, list[np.ndarray]] = {}
    for reg in registrations:
        for control_id, residual in zip(reg.correspondence.control_ids, reg.fit.residuals):
            by_control.setdefault(control_id, []).append(np.asarray(residual, dtype=np.float64))
    controls = []
    for control_id, residuals in by_control.items():
        stack = np.array(residuals)  # (k, 3) mm
        mean_residual = stack.mean(axis=0)
        controls.append(
            {
                "id": control_id,
                "n_frames": len(residuals),
                "residual_mm": vector(mean_residual),
                "residual_norm_mm": number(np.linalg.norm(mean_residual)),
                "rms_norm_mm": number(np.sqrt(np.mean(np.sum(stack**2, axis=1)))),
                "max_norm_mm": number(np.max(np.linalg.norm(stack, axis=1))),
            }
        )

    section: dict[str, Any] = {
        "aggregate": REGISTRATION_AGGREGATE,
        "aggregate_description": REGISTRATION_AGGREGATE_TEXT,
        "n_frames": n,
        "R_global_camera": matrix(R_mean),
        "det_R": number(np.linalg.det(R_mean)),
        "t_global_camera_mm": vector(t_mean),
        "scale": number(np.mean([r.fit.scale for r in registrations])),
        "rms_mm": number(np.sqrt(np.mean(rms_per_frame**2))),
        "rotation_spread_rad": number(max(rotation_angle(R_mean, R) for R in rotations)),
        "t_std_mm": vector(translations.std(axis=0, ddof=1) if n > 1 else np.zeros(3)),
        "per_frame": [
            {
                "sequence": int(r.sequence),
                "method": r.fit.method,
                "rms_mm": number(r.fit.rms_mm),
                "n_controls": len(r.correspondence.control_ids),
                "R_global_camera": matrix(r.fit.R),
                "t_global_camera_mm": vector(r.fit.t),
                "scale": number(r.fit.scale),
                "unmatched_control": list(r.correspondence.unmatched_control),
            }
            for r in registrations
        ],
        "control_points": controls,
        "ground_truth": None,
    }
    if truth is not None:
        R_true = np.asarray(truth.R_global_camera, dtype=np.float64)
        t_true = np.asarray(truth.t_global_camera, dtype=np.float64)
        section["ground_truth"] = {
            "R_global_camera": matrix(R_true),
            "t_global_camera_mm": vector(t_true),
            "rotation_error_rad": number(rotation_angle(R_true, R_mean)),
            "translation_error_mm": vector(t_mean - t_true),
            "translation_error_norm_mm": number(np.linalg.norm(t_mean - t_true)),
        }
    return section


def _characteristic_entry(index: int, c) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "no": index,
        "name": c.name,
        "kind": c.kind,
        "elements": list(c.elements),
        "n_frames": int(c.n),
        "measured_mm": number(c.measured_mm),
        "std_mm": number(c.std_mm),
        "uncertainty_mm": number(c.uncertainty_mm),
        "nominal_mm": number(c.nominal_mm),
        "tolerance_mm": number(c.tolerance_mm),
        "deviation_mm": number(c.deviation_mm),
        "passed": bool(c.passed),
    }
    if c.actual_mm is not None:  # ground truth known (simulator)
        entry["actual_mm"] = number(c.actual_mm)
        entry["error_mm"] = number(c.error_mm)
    return entry


def _frame_entry(frame: FrameResult) -> dict[str, Any]:
    registration = frame.registration
    measurement = frame.measurement
    return {
        "sequence": int(frame.sequence),
        "timestamp_ns": int(frame.timestamp_ns),
        "error": frame.error,
        "n_camera_points": frame.n_camera_points,
        "registration_rms_mm": None if registration is None else number(registration.fit.rms_mm),
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
                "measured_mm": number(c.measured_mm),
                "uncertainty_mm": number(c.uncertainty_mm),
                "passed": bool(c.passed),
            }
            for c in measurement.characteristics
        ],
    }


def problems(summary: SessionSummary) -> list[str]:
    """Every problem of the session as one human-readable line each."""
    lines: list[str] = []
    if summary.incomplete:
        lines.append(f"session incomplete: {summary.incomplete}")
    lines.extend(f"reference import: {p}" for p in summary.reference.problems)
    for frame in summary.frames:
        if frame.error:
            lines.append(f"frame {frame.sequence}: {frame.error}")
        if frame.measurement is not None and frame.measurement.missing_targets:
            missing = ", ".join(frame.measurement.missing_targets)
            lines.append(f"frame {frame.sequence}: targets not found: {missing}")
    for c in summary.characteristics:
        if c.n == 0:
            lines.append(f"characteristic {c.name}: measured in no frame")
    if not summary.characteristics:
        lines.append("no characteristics were evaluated")
    return lines


def build_report(summary: SessionSummary) -> dict[str, Any]:
    """The content of report.json for ``summary`` (JSON-able, floats unrounded)."""
    info = summary.info
    failed = [f for f in summary.frames if f.error]
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
        "calibration": {"source": info.calibration.source},
        "plan": {"name": info.plan.name, "source": info.plan.source, "sha256": info.plan.sha256},
        "reference": {
            "source": summary.reference.source,
            "n_points": len(summary.reference.points),
            "problems": list(summary.reference.problems),
        },
        "frames_processed": len(summary.frames),
        "frames_failed": len(failed),
        "frame_errors": [
            {"sequence": int(f.sequence), "timestamp_ns": int(f.timestamp_ns), "error": f.error}
            for f in failed
        ],
        "frames": [_frame_entry(f) for f in summary.frames],
        "registration": _registration_section(summary.registrations, info.ground_truth),
        "characteristics": [_characteristic_entry(i + 1, c) for i, c in enumerate(summary.characteristics)],
        "ground_truth_known": any(c.actual_mm is not None for c in summary.characteristics),
        "rms_error_mm": number(summary.rms_error_mm()),
        "passed": bool(summary.passed),
        "incomplete": summary.incomplete is not None,
        "incomplete_reason": summary.incomplete,
        "problems": problems(summary),
    }


def dumps(report: Mapping[str, Any]) -> str:
    """report.json text: strict JSON (no NaN), floats by repr, UTF-8, indented."""
    return json.dumps(report, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def load_schema() -> dict[str, Any]:
    """The JSON Schema of report.json (``pipeline/schemas/report.schema.json``)."""
    text = resources.files("pipeline").joinpath("schemas/report.schema.json").read_text(encoding="utf-8")
    return json.loads(text)


def validate(report: Mapping[str, Any]) -> None:
    """Raise ``jsonschema.ValidationError`` if ``report`` does not follow the schema."""
    import jsonschema

    jsonschema.Draft202012Validator(load_schema()).validate(report)
