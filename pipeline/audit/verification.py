"""Audit a verification recording (``crossfield audit VERIFY.mcap``; docs/replay-and-audit.md).

The checks of a session audit (:mod:`crossfield.audit.session`), for a
``crossfield verify --record`` file (:mod:`crossfield.verification.procedure`):

* **integrity**: the hash chain over every record (the session's chain);
* **provenance**: the ``crossfield.verification.procedure`` record can be read, the
  attached calibration file's SHA-256 is the recorded one, package versions
  recorded against those installed (notes);
* **reproduction**: the recorded pairs are evaluated again with the recorded
  stage plugins, the attached calibration, the recorded bar and MPE, and
  every ``/verification/position`` message and the ``/verification/result``
  message rebuilt and compared with the recorded one **bit for bit**: the
  same pixels through the same single-threaded centroid and triangulation
  code give the same floats, so there is no tolerance to state;
* **seal**: as a session's (:func:`crossfield.audit.report.seal_check`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from crossfield.audit.report import (
    AuditReport,
    audit_recording,
    format_checks,
    json_differences,
    recording_provenance,
)
from crossfield.camera.calibration_io import stereo_calibration_from_yaml
from crossfield.errors import CrossfieldError, RecordingError
from crossfield.recording import layout as L
from crossfield.recording.codec import dump_json
from crossfield.recording.reader import open_recording
from crossfield.verification.procedure import create_stages, evaluate
from crossfield.verification.record import (
    POSITION_CHANNEL,
    RESULT_CHANNEL,
    position_doc,
    read_verification_recording,
)

__all__ = ["audit_verification", "format_verification_report"]


def _reproduction(path: Path, *, limit: int = 500) -> dict[str, Any]:
    try:
        recorded = read_verification_recording(path, validate_crcs=False)
        rec = open_recording(path, validate_crcs=False)
        topics = [POSITION_CHANNEL.topic, RESULT_CHANNEL.topic]
        messages = {(m.topic, m.sequence): m for m in rec.messages(topics, decode=False, file_order=True)}
    except RecordingError as exc:
        return {"passed": False, "error": f"the verification cannot be read back: {exc}", "differences": []}
    try:
        first = recorded.named_frames[0][1][0]
        sizes = tuple((im.shape[1], im.shape[0]) for im in (first.upper, first.lower))
        source = recorded.metadata.get("calibration_source", L.ATTACHMENT_CALIBRATION)
        calibration = stereo_calibration_from_yaml(recorded.calibration_text, source, image_sizes=sizes)
        stages = create_stages(recorded.stages, str(path))
        result = evaluate(
            recorded.named_frames,
            calibration,
            stages["centroid"],
            stages["triangulate"],
            certified_mm=recorded.certified_mm,
            certified_u_mm=recorded.certified_u_mm,
            mpe_mm=recorded.mpe_mm,
        )
    except (CrossfieldError, IndexError) as exc:
        return {
            "passed": False,
            "error": f"the verification cannot be evaluated again: {exc}",
            "differences": [],
        }
    rebuilt = {
        (POSITION_CHANNEL.topic, k): dump_json(position_doc(k, p, [f.sequence for f in frames]))
        for k, (p, (_, frames)) in enumerate(zip(result.positions, recorded.named_frames))
    }
    rebuilt[(RESULT_CHANNEL.topic, 0)] = dump_json(result.to_dict())
    differences: list[dict[str, Any]] = []
    identical = 0
    for key, data in rebuilt.items():
        m = messages.get(key)
        if m is None:
            continue
        if m.data == data:
            identical += 1
            continue
        try:
            found = json_differences(json.loads(m.data), json.loads(data))
        except ValueError:
            found = [("<data>", f"<{len(m.data)} bytes>", f"<{len(data)} bytes>")]
        differences += [
            {
                "topic": m.topic,
                "sequence": m.sequence,
                "log_time_ns": m.log_time_ns,
                "path": p,
                "recorded": a,
                "replayed": b,
                "tolerance": "exact",
            }
            for p, a, b in found
        ]
    missing = [f"{t} sequence {s}" for t, s in rebuilt if (t, s) not in messages]
    extra = [f"{t} sequence {s}" for t, s in messages if (t, s) not in rebuilt]
    return {
        "passed": not differences and not missing and not extra,
        "positions_replayed": len(result.positions),
        "pairs_replayed": sum(len(frames) for _, frames in recorded.named_frames),
        "messages_compared": len(rebuilt) - len(missing),
        "messages_identical": identical,
        "differences": differences[:limit],
        "differences_total": len(differences),
        "missing": missing,
        "only_recorded": extra,
        "replayed": {"max_abs_error_mm": result.max_abs_error_mm, "passed": result.passed},
    }


def audit_verification(
    path: str | Path,
    *,
    reproduce: bool = True,
    expect_head: str | None = None,
    public_key: str | Path | None = None,
) -> AuditReport:
    """Audit the verification recording ``path`` (module docstring); ``RecordingError`` if it
    is not one. ``expect_head`` / ``public_key`` as :func:`crossfield.audit.audit`."""

    def provenance(p: Path) -> dict[str, Any]:
        return recording_provenance(p, L.VERIFICATION_METADATA, "calibration_source")

    return audit_recording(
        path,
        "verification",
        L.VERIFICATION_PROFILE,
        provenance,
        _reproduction,
        RESULT_CHANNEL.topic,
        reproduce=reproduce,
        expect_head=expect_head,
        public_key=public_key,
    )


def format_verification_report(report: AuditReport, *, limit: int = 40) -> str:
    """The verification audit as text for the terminal (:func:`crossfield.audit.report.format_checks`)."""
    record = report.provenance.get("record") or {}
    repro = report.reproduction
    header = [
        f"Audit of verification recording {report.path}",
        f"  file SHA-256 {report.file_sha256}",
        f"  source {record.get('source')}",
        f"  scale bar {record.get('certified_length_mm')} mm, MPE {record.get('mpe_mm')} mm",
        f"  writer {report.provenance.get('writer')}",
    ]
    summary = ""
    if "positions_replayed" in repro:
        summary = (
            f"{repro['messages_identical']} of {repro['messages_compared']} recorded results identical "
            f"({repro['pairs_replayed']} pairs of {repro['positions_replayed']} positions evaluated again "
            f"with the recorded plugins and the attached calibration; bit for bit)"
        )
    return format_checks(report, header, summary, replayed="evaluated again", limit=limit)
