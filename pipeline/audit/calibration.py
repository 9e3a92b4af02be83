"""Audit a calibration recording (``crossfield audit CAL.mcap``; docs/replay-and-audit.md).

A calibration is audited like a measurement session (:mod:`crossfield.audit.session`):

* **integrity**: the recording's hash chain (:func:`crossfield.audit.chain.verify`),
  the same chain a session has; a changed, removed or reordered image,
  detection, result, metadata record or attachment is named;
* **provenance**: the recorded board, solver settings, bit depth and view
  names can be read; the attached calibration file's SHA-256 is the recorded
  one; OpenCV and package versions recorded against those installed (notes);
* **reproduction**: the calibration is solved again from the recorded raw
  images with the recorded board and settings
  (:func:`crossfield.calibration.solve.calibrate_images`) and compared with
  what was recorded: the result message (``report_dict``: parameters, their
  standard deviations, RMS errors, per-view errors, dropped and held-out
  views, coverage, predicted 3-D uncertainty), the detections of every view,
  and the attached calibration file (M1 D1 M2 D2 R T, rms keys);
* **seal**: chain head and file SHA-256 against the sidecar, ``--expect-head``,
  ``--public-key`` (:func:`crossfield.audit.report.seal_check`).

Tolerances (the re-solve is not bit for bit): OpenCV's Levenberg-Marquardt
solvers do not give bit-identical results on the same detections (measured
on 10 station views, also with ``cv2.setNumThreads(1)``: parameters agree to
1e-8 relative, 5e-9 of their standard deviation). Every calibration parameter (fx fy cx cy,
distortion, rotation vector of R, T) must therefore agree within
:data:`PARAMETER_TOLERANCE_STD` of its own standard deviation, a difference
three orders of magnitude below anything the calibration can resolve; every
standard deviation and predicted uncertainty within :data:`STD_RELATIVE_TOLERANCE`
relative (a standard deviation estimated from ~1000 residuals is itself
uncertain by ~2 %; OpenCV's per-camera ``stdDeviationsIntrinsics`` were
measured to vary by 1e-5 between identical runs); every other number within
:data:`RELATIVE_TOLERANCE` relative (measured: <= 3e-10); detected corners
within :data:`CORNER_TOLERANCE_PX`; ids, view lists, statuses, board and
settings exactly.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossfield.audit.report import (
    AuditReport,
    audit_recording,
    format_checks,
    json_differences,
    recording_provenance,
)
from crossfield.calibration.record import (
    ATTACHMENT_CALIBRATION,
    METADATA_NAME,
    PROFILE,
    TOPIC_DETECTIONS,
    TOPIC_RESULT,
    detection_doc,
    open_calibration_recording,
    read_calibration_recording,
)
from crossfield.calibration.report import report_dict
from crossfield.calibration.solve import CalibrationResult, calibrate_images
from crossfield.camera.calibration_io import stereo_calibration_from_yaml
from crossfield.errors import CrossfieldError, RecordingError
from crossfield.types import CAMERAS, StereoCalibration

__all__ = [
    "CORNER_TOLERANCE_PX",
    "PARAMETER_TOLERANCE_STD",
    "RELATIVE_TOLERANCE",
    "STD_RELATIVE_TOLERANCE",
    "audit_calibration",
    "format_calibration_report",
    "parameter_vector",
]

#: A re-solved calibration parameter may differ from the recorded one by this
#: fraction of its standard deviation (module docstring).
PARAMETER_TOLERANCE_STD = 1e-3
#: Relative tolerance of a recorded standard deviation or predicted uncertainty
#: (module docstring).
STD_RELATIVE_TOLERANCE = 1e-3
#: Relative tolerance of every other recorded number (RMS px, coverage, mm).
RELATIVE_TOLERANCE = 1e-6
#: Tolerance of a re-detected board corner (px).
CORNER_TOLERANCE_PX = 1e-6


def parameter_vector(calibration: StereoCalibration, n_dist: int) -> np.ndarray:
    """The calibration in the solver's parameter order
    (:func:`crossfield.calibration.covariance.camera_param_names`): per camera
    fx fy cx cy (px) and ``n_dist`` distortion coefficients, then the rotation
    vector of R (rad, Rodrigues) and T (mm), ``p_lower = R p_upper + T``."""
    out: list[float] = []
    for cam in CAMERAS:
        intr = calibration.camera(cam)
        K = np.asarray(intr.camera_matrix, dtype=np.float64)
        D = np.zeros(n_dist)
        d = np.asarray(intr.dist_coeffs, dtype=np.float64).ravel()[:n_dist]
        D[: len(d)] = d
        out += [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *D]
    rvec = cv2.Rodrigues(np.asarray(calibration.R_lower_upper, dtype=np.float64))[0].ravel()
    out += [*rvec, *np.asarray(calibration.t_lower_upper, dtype=np.float64).ravel()]
    return np.array(out)


def _number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _close(a: Any, b: Any, tolerance: float | None = None, relative: float = RELATIVE_TOLERANCE) -> bool:
    """Numbers within ``tolerance`` (absolute), else within ``relative`` of the larger."""
    if not (_number(a) and _number(b)):
        return False
    if tolerance is None:
        tolerance = relative * max(abs(a), abs(b))
    return math.isfinite(a) and math.isfinite(b) and abs(a - b) <= tolerance


def _provenance(path: Path) -> dict[str, Any]:
    prov = recording_provenance(path, METADATA_NAME, "source")
    recorded_cv = prov["record"].get("opencv_version")
    if recorded_cv and recorded_cv != cv2.__version__:
        prov["notes"].append(
            f"recorded with OpenCV {recorded_cv}, installed {cv2.__version__}: another solver build may "
            f"reproduce the parameters only to its own rounding"
        )
    return prov


# --------------------------------------------------------------------------
# Reproduction
# --------------------------------------------------------------------------


def _difference(
    topic: str, sequence: int, log_time: int, path: str, recorded: Any, replayed: Any, tol: Any
) -> dict:
    return {
        "topic": topic,
        "sequence": sequence,
        "log_time_ns": log_time,
        "path": path,
        "recorded": recorded,
        "replayed": replayed,
        "tolerance": tol,
    }


def _compare_result(recorded: dict, replayed: dict, std: dict[str, float]) -> list[tuple[str, Any, Any, Any]]:
    """Differences (path, recorded, replayed, tolerance) beyond the tolerances (module docstring)."""
    names = [p.get("name") for p in recorded.get("parameters", [])] if isinstance(recorded, dict) else []
    out = []
    for path, a, b in json_differences(recorded, replayed):
        tol: Any = "exact"
        if path.startswith("parameters[") and path.endswith("].value"):
            k = int(path[len("parameters[") : -len("].value")])
            name = names[k] if k < len(names) else None
            if name in std:
                tol = PARAMETER_TOLERANCE_STD * std[name]
                if _close(a, b, tol):
                    continue
                path = f"{path} ({name})"
        else:
            uncertain = "std" in path or path.startswith("uncertainty_3d")
            relative = STD_RELATIVE_TOLERANCE if uncertain else RELATIVE_TOLERANCE
            if _close(a, b, relative=relative):
                continue
            if _number(a):
                tol = f"relative {relative:g}"
        out.append((path, a, b, tol))
    return out


def _attachment_differences(text: str, result: CalibrationResult) -> list[tuple[str, Any, Any, Any]]:
    """The attached calibration file against the re-solved result: M1 D1 M2 D2 R T
    (as parameters, within :data:`PARAMETER_TOLERANCE_STD` sigma) and the rms keys."""

    n_dist = (len(result.param_names) - 6) // 2 - 4  # p = 2 (4 + n_dist) + 6
    try:
        attached = stereo_calibration_from_yaml(text, ATTACHMENT_CALIBRATION)
    except CrossfieldError as exc:
        return [("<file>", "unreadable", str(exc), "exact")]
    out = []
    for cam, key in (("upper", "D1"), ("lower", "D2")):
        n = len(np.asarray(attached.camera(cam).dist_coeffs).ravel())
        if n != n_dist:
            out.append((key, f"{n} coefficients", f"{n_dist} coefficients", "exact"))
    a, b, std = parameter_vector(attached, n_dist), result.params, result.std
    keys = {"upper": "M1/D1", "lower": "M2/D2", "rig": "R/T"}
    for name, x, y, s in zip(result.param_names, a, b, std):
        tol = PARAMETER_TOLERANCE_STD * float(s)
        if not _close(float(x), float(y), tol):
            out.append((f"{keys[name.split('.')[0]]} {name}", float(x), float(y), tol))
    fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    try:
        for key, value in (
            ("rms_px_upper", result.cameras["upper"].rms_px),
            ("rms_px_lower", result.cameras["lower"].rms_px),
            ("rms_px_stereo", result.rms_stereo_px),
        ):
            node = fs.getNode(key)
            found = None if node.empty() else float(node.real())
            if found is None or not _close(found, float(value)):
                out.append((key, found, float(value), f"relative {RELATIVE_TOLERANCE:g}"))
    finally:
        fs.release()
    return out


def _detection_differences(recorded: dict, replayed: dict) -> list[tuple[str, Any, Any, Any]]:
    out = []
    if recorded.get("ids") != replayed.get("ids"):
        out.append(("ids", recorded.get("ids"), replayed.get("ids"), "exact"))
        return out
    a = np.asarray(recorded.get("image_points_px", []), dtype=float).reshape(-1, 2)
    b = np.asarray(replayed.get("image_points_px", []), dtype=float).reshape(-1, 2)
    if a.shape != b.shape:
        out.append(("image_points_px", f"{len(a)} points", f"{len(b)} points", "exact"))
    elif len(a):
        d = np.abs(a - b).max(axis=1)
        worst = int(np.argmax(d))
        if not d[worst] <= CORNER_TOLERANCE_PX:
            out.append(
                (f"image_points_px[{worst}]", a[worst].tolist(), b[worst].tolist(), CORNER_TOLERANCE_PX)
            )
    return out


def _reproduction(path: Path, *, limit: int = 500) -> dict[str, Any]:
    try:
        recorded = read_calibration_recording(path, validate_crcs=False)
        rec = open_calibration_recording(path, validate_crcs=False)
        messages = list(rec.messages([TOPIC_RESULT, TOPIC_DETECTIONS], decode=False, file_order=True))
    except RecordingError as exc:
        return {"passed": False, "error": f"the calibration cannot be read back: {exc}", "differences": []}
    try:
        result = calibrate_images(
            recorded.images,
            recorded.board,
            recorded.bit_depth,
            recorded.settings,
            names=recorded.names,
            source=recorded.source,
        )
    except CrossfieldError as exc:
        return {"passed": False, "error": f"the calibration cannot be solved again: {exc}", "differences": []}
    differences: list[dict[str, Any]] = []
    compared = identical = 0
    results = [m for m in messages if m.topic == TOPIC_RESULT]
    detections = {}
    for m in messages:
        if m.topic == TOPIC_DETECTIONS:
            try:
                doc = json.loads(m.data)
                detections[(int(doc["view"]), str(doc["camera"]))] = (m, doc)
            except (ValueError, KeyError, TypeError) as exc:
                differences.append(
                    _difference(
                        m.topic, m.sequence, m.log_time_ns, "<data>", f"not a detection: {exc}", None, "exact"
                    )
                )
    missing: list[str] = []
    if len(results) != 1:
        missing.append(f"{len(results)} {TOPIC_RESULT} messages, expected 1")
    else:
        m = results[0]
        compared += 1
        try:
            doc = json.loads(m.data)
        except ValueError as exc:
            found = [("<data>", f"not JSON: {exc}", None, "exact")]
        else:
            found = _compare_result(doc, report_dict(result), result.std_by_name())
        identical += not found
        differences += [_difference(m.topic, m.sequence, m.log_time_ns, *f) for f in found]
    for k, view in enumerate(result.detections):
        for cam in CAMERAS:
            if (k, cam) not in detections:
                missing.append(f"{TOPIC_DETECTIONS} of view {k} {cam}")
                continue
            m, doc = detections.pop((k, cam))
            compared += 1
            found = _detection_differences(doc, detection_doc(k, cam, view[cam]))
            identical += not found
            differences += [_difference(m.topic, m.sequence, m.log_time_ns, *f) for f in found]
    extra = [f"{TOPIC_DETECTIONS} of view {k} {cam} (no such view)" for k, cam in detections]
    found = _attachment_differences(recorded.calibration_yaml, result) if recorded.calibration_yaml else []
    if not recorded.calibration_yaml:
        missing.append(f"attachment {ATTACHMENT_CALIBRATION}")
    else:
        compared += 1
        identical += not found
    differences += [
        {"attachment": ATTACHMENT_CALIBRATION, "path": p, "recorded": a, "replayed": b, "tolerance": t}
        for p, a, b, t in found
    ]
    return {
        "passed": not differences and not missing and not extra,
        "views_replayed": len(recorded.images),
        "settings": {k: getattr(recorded.settings, k) for k in recorded.settings.__dataclass_fields__},
        "messages_compared": compared,
        "messages_identical": identical,
        "differences": differences[:limit],
        "differences_total": len(differences),
        "missing": missing,
        "only_recorded": extra,
        "tolerances": {
            "parameters_std": PARAMETER_TOLERANCE_STD,
            "relative": RELATIVE_TOLERANCE,
            "std_relative": STD_RELATIVE_TOLERANCE,
            "corners_px": CORNER_TOLERANCE_PX,
        },
        "replayed": {
            "rms_px": {
                "upper": result.cameras["upper"].rms_px,
                "lower": result.cameras["lower"].rms_px,
                "stereo": result.rms_stereo_px,
            },
            "baseline_mm": result.baseline_mm,
        },
    }


# --------------------------------------------------------------------------
# The audit
# --------------------------------------------------------------------------


def audit_calibration(
    path: str | Path,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> AuditReport:
    """Audit the calibration recording ``path`` (module docstring); ``RecordingError``
    if it is not one. ``expect_head`` / ``public_key`` as :func:`crossfield.audit.audit`."""
    return audit_recording(
        path,
        "calibration",
        PROFILE,
        _provenance,
        _reproduction,
        TOPIC_RESULT,
        reproduce=reproduce,
        expect_head=expect_head,
        public_key=public_key,
    )


def format_calibration_report(report: AuditReport, *, limit: int = 40) -> str:
    """The calibration audit as text for the terminal (:func:`crossfield.audit.report.format_checks`)."""
    record = report.provenance.get("record") or {}
    repro = report.reproduction
    header = [
        f"Audit of calibration recording {report.path}",
        f"  file SHA-256 {report.file_sha256}",
        f"  source {record.get('source')}  recorded {record.get('recorded_utc')}",
        f"  OpenCV {record.get('opencv_version')}",
        f"  writer {report.provenance.get('writer')}",
    ]
    summary = ""
    if "tolerances" in repro:
        tol = repro["tolerances"]
        summary = (
            f"{repro['messages_identical']} of {repro['messages_compared']} recorded results reproduced "
            f"({repro['views_replayed']} views solved again; parameters within {tol['parameters_std']:g} "
            f"sigma, standard deviations {tol['std_relative']:g} and other numbers {tol['relative']:g} "
            f"relative, corners {tol['corners_px']:g} px)"
        )
    return format_checks(report, header, summary, replayed="solved again", limit=limit)
