"""The measured features of a session, for its QIF document (:mod:`crossfield.report.qif`).

From the session recording (``session.mcap``): the plan (attachment
``plan.toml``), the CMM points (``/reference``: control points, reference
points, the probes of the reference lines, whose axes are fitted here with
:func:`crossfield.geometry.fit_reference_element`, the fit the measurement
measured against) and the targets (``/measurement``: the mean over the
frames that found each target). Without a recording (``session.record =
false``), from report.json alone: the targets of the frames it lists, and no
CMM features.

Every coordinate is in the global (CMM) frame, mm; directions are unit vectors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crossfield.errors import RecordingError

__all__ = ["QifFeature", "features_from_recording", "features_from_report", "session_features"]

#: Roles of a feature: what measured it and what the plan says it is.
ROLES = ("target", "control", "reference_point", "reference_line")


@dataclass(frozen=True)
class QifFeature:
    """One measured feature, global (CMM) frame, mm.

    id: the plan's id (``P1``, ``C1``, ``R1``, ``L3``). kind: ``point``,
    ``line`` or ``cylinder``. role: one of :data:`ROLES`; targets are
    measured by the stereo station, the others probed by the CMM arm.
    location_mm: (3,) the point, or for a line / cylinder the foot of the
    probes' centroid on the axis. direction: (3,) unit axis direction (lines
    and cylinders; None for points). diameter_mm: cylinders only.
    form_mm: the largest minus the smallest fit residual (lines / cylinders).
    nominal_mm: (3,) the plan's nominal location (targets), else None.
    n: the number of frames (targets) or probes (CMM features) it is made of.
    """

    id: str
    kind: str
    role: str
    location_mm: tuple[float, float, float]
    direction: tuple[float, float, float] | None = None
    diameter_mm: float | None = None
    form_mm: float | None = None
    nominal_mm: tuple[float, float, float] | None = None
    n: int = 1


def _xyz(v: Any) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def _target_features(plan: Any, per_frame: Sequence[Mapping[str, Any]]) -> list[QifFeature]:
    """Targets: the mean over the frames whose ``target_points_mm`` holds them."""
    features = []
    for spec in plan.targets if plan is not None else ():
        rows = [frame[spec.id] for frame in per_frame if frame.get(spec.id) is not None]
        xyz = np.array(rows, dtype=np.float64).reshape(-1, 3)
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if not len(xyz):
            continue
        features.append(QifFeature(spec.id, "point", "target", _xyz(xyz.mean(axis=0)),
                                   nominal_mm=_xyz(spec.nominal), n=len(xyz)))
    return features


def _cmm_features(plan: Any, reference: Any) -> list[QifFeature]:
    """Control points, reference points (one probe each) and the fitted reference lines."""
    from crossfield.geometry import element_probes, fit_reference_element

    by_label = {p.label: p for p in reference.points if np.isfinite(p.xyz).all()}
    features = []
    for ids, role in ((plan.control_ids, "control"), (plan.reference_point_ids, "reference_point")):
        for pid in ids:
            if pid in by_label:
                features.append(QifFeature(pid, "point", role, _xyz(by_label[pid].xyz)))
    for spec in plan.reference_lines:
        try:
            fit = fit_reference_element(spec, reference.points)
        except ValueError:  # too few probes: the measurement refused it too
            continue
        residuals = np.asarray(fit.residuals_mm, dtype=np.float64)
        diameter = None
        if fit.radius_mm is not None:
            balls = np.array([p.probe_diameter_mm for p in element_probes(spec.id, reference.points)], dtype=float)
            ball = float(balls.mean()) if len(balls) and np.isfinite(balls).all() else 0.0
            diameter = 2.0 * float(fit.radius_mm) - ball
        features.append(QifFeature(
            spec.id,
            fit.kind,
            "reference_line",
            _xyz(fit.line.point),
            direction=_xyz(fit.line.direction),
            diameter_mm=diameter,
            form_mm=float(residuals.max() - residuals.min()) if len(residuals) else None,
            n=len(residuals),
        ))
    return features


def features_from_recording(path: str | Path, session_id: str | None = None) -> tuple[QifFeature, ...]:
    """Every measured feature of the session recorded at ``path`` (session.mcap); with
    ``session_id``, a recording of another session is a RecordingError."""
    from crossfield.recording import layout as L
    from crossfield.recording.codec import reference_data
    from crossfield.recording.facts import load_session_facts

    facts = load_session_facts(path)
    if session_id is not None and facts.session_id != session_id:
        raise RecordingError(f"{path}: the recording of session {facts.session_id!r}, "
                             f"not of the report's session {session_id!r}")
    recording = facts.recording
    reference = None
    per_frame: list[Mapping[str, Any]] = []
    try:
        for message in recording.messages([L.TOPIC_REFERENCE, L.TOPIC_MEASUREMENT]):
            doc = message.decoded
            if message.topic == L.TOPIC_REFERENCE:
                reference = reference_data(doc)
            else:
                per_frame.append(doc.get("target_points_mm") or {})
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{path}: a /reference or /measurement message is malformed: {exc!r}") from None
    features = _target_features(facts.plan, per_frame)
    if reference is not None:
        features += _cmm_features(facts.plan, reference)
    return tuple(features)


def features_from_report(report: Mapping[str, Any], plan: Any = None) -> tuple[QifFeature, ...]:
    """The targets of the frames listed in report.json (no recording at hand); nominals from ``plan``
    when given, else the target has no nominal."""
    per_frame = [f.get("target_points_mm") or {} for f in report.get("frames", ())]
    if plan is not None:
        return tuple(_target_features(plan, per_frame))
    ids = sorted({k for frame in per_frame for k in frame})
    out = []
    for tid in ids:
        xyz = np.array([frame[tid] for frame in per_frame if frame.get(tid)], dtype=np.float64).reshape(-1, 3)
        out.append(QifFeature(tid, "point", "target", _xyz(xyz.mean(axis=0)), n=len(xyz)))
    return tuple(out)


def session_features(folder: Path, report: Mapping[str, Any]) -> tuple[QifFeature, ...]:
    """From ``folder/session.mcap`` when it exists, else from report.json (:func:`features_from_report`)."""
    mcap = folder / "session.mcap"
    if mcap.is_file():
        return features_from_recording(mcap, str(report["session"]["id"]))
    return features_from_report(report)
