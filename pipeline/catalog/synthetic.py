"""Small synthetic session folders for the catalog's tests and benchmark (no pipeline run).

Each folder is shaped as ``crossfield run`` writes one: a real (tiny) crossfield MCAP
``session.mcap`` written by crossfield's own file sink (so its chain head, seal sidecar
and signature are genuine), holding the ``crossfield.session`` and ``crossfield.machine``
metadata, and a ``report.json`` with the session, job, plan, characteristics (with U, k,
decision and a budget), registration and consistency sections the catalog reads. The
measured values are the caller's; nothing else is simulated.
"""

from __future__ import annotations

import datetime as _dt
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from crossfield.recording import layout as L


def write_session(
    parent: str | Path,
    session_id: str,
    start_time_ns: int,
    measured_mm: Mapping[str, float],
    *,
    nominal_mm: Mapping[str, float] | None = None,
    tolerance_mm: float = 0.1,
    u_mm: float = 0.016,
    hostname: str = "station-a",
    registration_rms_mm: float = 0.018,
    operator: str = "",
    signing_key: str | Path | None = None,
    note: str = "",
) -> Path:
    """Write ``parent/session_id/`` and return it. ``measured_mm``: characteristic name ->
    measured length (mm), in plan order; ``nominal_mm`` default: the measured values
    rounded to 0.1 mm. ``note`` goes into the recording (a different note: a different file)."""
    from crossfield.recording.writer import McapFileSink

    folder = Path(parent) / session_id
    folder.mkdir(parents=True)
    utc = (_dt.datetime(1970, 1, 1) + _dt.timedelta(microseconds=start_time_ns // 1000)).isoformat() + "+00:00"
    facts = {
        "session_id": session_id, "start_time_ns": start_time_ns, "start_time_utc": utc,
        "crossfield_version": "0.1.0", "recording_format": L.RECORDING_FORMAT, "out_dir": str(folder),
        "plan_name": "synthetic", "calibration_source": "synthetic", "calibration_sha256": "0" * 64,
        "simulated": True, "parent": None, "note": note,
    }
    machine = {"hostname": hostname}
    sink = McapFileSink(folder / "session.mcap", writer_thread=False, signing_key=signing_key)
    for name, doc in ((L.META_SESSION, facts), (L.META_MACHINE, machine)):
        sink.metadata(name, {**{k: str(v) for k, v in doc.items()}, L.META_JSON: json.dumps(doc)})
    sink.close()
    assert sink.seal is not None
    nominal = nominal_mm or {k: round(v, 1) for k, v in measured_mm.items()}
    chars: list[dict[str, Any]] = []
    for i, (name, value) in enumerate(measured_mm.items()):
        dev = value - nominal[name]
        chars.append({
            "no": i + 1, "name": name, "kind": "point_line", "measured_mm": value, "nominal_mm": nominal[name],
            "tolerance_mm": tolerance_mm, "upper_tol_mm": tolerance_mm, "lower_tol_mm": tolerance_mm,
            "deviation_mm": dev, "expanded_uncertainty_mm": u_mm, "coverage_factor": 2.0,
            "decision": "conforms" if abs(dev) <= tolerance_mm - u_mm else "not_proven",
            "decision_rule": "simple", "budget": [{"source": "camera", "u_mm": u_mm / 2}],
        })
    report = {
        "format": "crossfield-report/2",
        "session": {"id": session_id, "start_time_ns": start_time_ns, "start_time_utc": utc,
                    "out_dir": str(folder), "parent": None},
        "plugins": {"acquire": {"name": "synthetic"}},
        "packages": {"crossfield": "0.1.0"},
        "calibration": {"source": "synthetic"},
        "plan": {"name": "synthetic", "sha256": "1" * 64},
        "job": {"part": "P-1", "serial": session_id, "operator": operator, "order": "", "instruments": []},
        "uncertainty": {"consistency": {"birge_ratio": 1.0, "p_value": 0.5, "warning": None, "cmm_inflation": 1.0}},
        "frames_processed": 3, "frames_failed": 0,
        "frames": [{"sequence": k, "timestamp_ns": start_time_ns + k * 70_000_000} for k in range(3)],
        "registration": {"rms_mm": registration_rms_mm, "rotation_spread_rad": 5e-5},
        "characteristics": chars,
        "passed": True, "incomplete": False, "problems": [],
        "integrity": sink.seal.to_json(),
    }
    (folder / "report.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    return folder
