"""Compare two recorded sessions side by side (``crossfield compare A.mcap B.mcap``).

Read from each recording (its recorded results: comparing them is the point):

* the plugins that ran (``crossfield.plugins``);
* every characteristic of the report (``/report``): measured value, its
  standard deviation and uncertainty, deviation from nominal, pass/fail,
  and for simulated sessions the error against ground truth;
* the registration: the session's ``T_global_camera`` (R, t), RMS, and
  per stereo pair R, t, RMS and the residual of every control point
  (``/registration``);
* centroid statistics per camera (``/centroids/<camera>``): count, mean
  sigma, area, roundness, rejected blobs, and how far the two sessions'
  centroids of the same pair lie apart.

Every compared value that differs (bit for bit: floats are compared
exactly) is one entry of ``differences``: ``{"path", "a", "b", "delta"}``
with ``delta = b - a`` (numbers, element-wise for vectors; for a rotation
matrix the angle of ``R_a^T R_b`` in radians; for centroid positions the
largest shift in pixels). No entry means the two sessions agree in every
compared value. Units: mm, rad, px.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crossfield import rigid
from crossfield.chain.registry import STAGES
from crossfield.recording import layout as L
from crossfield.recording.facts import require_session
from crossfield.recording.reader import Recording, open_recording
from crossfield.report.vocabulary import decision_text, expanded_heading, verdict_word
from crossfield.types import CAMERAS

#: Per-characteristic values compared (report.json keys).
CHARACTERISTIC_KEYS = (
    "n_frames",
    "measured_mm",
    "std_mm",
    "uncertainty_mm",
    "expanded_uncertainty_mm",
    "decision",
    "deviation_mm",
    "passed",
    "actual_mm",
    "error_mm",
    "coverage_factor",
)
#: Session-level report values compared.
SUMMARY_KEYS = ("passed", "frames_processed", "frames_failed", "rms_error_mm", "incomplete")
#: Centroid statistics per camera (see :func:`centroid_stats`).
CENTROID_STATS = (
    "frames",
    "centroids",
    "mean_per_frame",
    "mean_sigma_u_px",
    "mean_sigma_v_px",
    "mean_area_px",
    "mean_roundness",
    "rejected",
)


@dataclass
class SessionView:
    """What compare reads from one recording."""

    path: Path
    session_id: str
    complete: bool
    damage: str | None
    parent: Any
    plugins: Mapping[str, Any]
    report: Mapping[str, Any] | None
    registrations: dict[int, Mapping[str, Any]] = field(default_factory=dict)
    centroids: dict[str, dict[int, Mapping[str, Any]]] = field(default_factory=dict)
    frames: dict[int, Mapping[str, Any]] = field(default_factory=dict)


def read_view(path: str | Path) -> SessionView:
    """Read the recorded results of a session (``RecordingError`` if it is not one)."""
    path = Path(path)
    rec: Recording = open_recording(path)
    meta = require_session(rec)
    session = rec.metadata_doc(L.META_SESSION)
    plugins = rec.metadata_doc(L.META_PLUGINS) if L.META_PLUGINS in meta else {}
    view = SessionView(
        path,
        str(session.get("session_id", "")),
        rec.complete,
        rec.damage,
        session.get("parent"),
        plugins,
        None,
    )
    view.centroids = {camera: {} for camera in CAMERAS}
    topics = [L.TOPIC_REPORT, L.TOPIC_REGISTRATION, *L.CENTROID_TOPICS, L.TOPIC_FRAMES]
    for m in rec.messages(topics, file_order=True):
        if m.topic == L.TOPIC_REPORT:
            view.report = m.decoded
        elif m.topic == L.TOPIC_REGISTRATION:
            view.registrations[int(m.decoded["sequence"])] = m.decoded
        elif m.topic == L.TOPIC_FRAMES:
            view.frames[int(m.decoded["sequence"])] = m.decoded
        else:
            view.centroids[L.CAMERA_OF_TOPIC[m.topic]][int(m.decoded["sequence"])] = m.decoded
    return view


# --------------------------------------------------------------------------
# Value helpers
# --------------------------------------------------------------------------


def _same(a: Any, b: Any) -> bool:
    """Exact equality; NaN/None equal to themselves."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _delta(a: Any, b: Any) -> Any:
    if isinstance(a, bool) or isinstance(b, bool):
        return None
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return b - a
    numbers = isinstance(a, list) and isinstance(b, list) and len(a) == len(b)
    if numbers and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in a + b):
        return [y - x for x, y in zip(a, b)]
    return None


def rotation_angle(Ra: Any, Rb: Any) -> float | None:
    """Angle (rad) of the rotation R_a^T R_b between two rotation matrices read from
    report.json (:func:`crossfield.rigid.rotation_angle`); None when either is missing."""
    try:
        A, B = np.asarray(Ra, dtype=np.float64), np.asarray(Rb, dtype=np.float64)
        if A.shape != (3, 3) or B.shape != (3, 3):
            return None
        return rigid.rotation_angle(A, B)
    except (TypeError, ValueError):
        return None


def _norm(v: Any) -> float | None:
    try:
        return float(np.linalg.norm(np.asarray(v, dtype=np.float64)))
    except (TypeError, ValueError):
        return None


def centroid_stats(docs: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Statistics of one camera's centroids over a session (px)."""
    counts = [int(d.get("count", 0)) for d in docs.values()]
    sig = [
        np.asarray(d["sigma_uv"], dtype=np.float64).reshape(-1, 2) for d in docs.values() if d.get("sigma_uv")
    ]
    sig = np.vstack(sig) if sig else np.zeros((0, 2))
    area = [v for d in docs.values() for v in d.get("area_px", []) if v is not None]
    rnd = [v for d in docs.values() for v in d.get("roundness", []) if v is not None]

    def mean(values: Any) -> float | None:
        values = np.asarray(values, dtype=np.float64)
        values = values[np.isfinite(values)]
        return float(values.mean()) if values.size else None

    return {
        "frames": len(docs),
        "centroids": int(sum(counts)),
        "mean_per_frame": (sum(counts) / len(counts)) if counts else None,
        "mean_sigma_u_px": mean(sig[:, 0]),
        "mean_sigma_v_px": mean(sig[:, 1]),
        "mean_area_px": mean(area),
        "mean_roundness": mean(rnd),
        "rejected": int(sum(len(d.get("rejected", [])) for d in docs.values())),
    }


def centroid_shift(a: Mapping[str, Any], b: Mapping[str, Any], radius_px: float = 3.0) -> dict[str, Any]:
    """Mutual nearest centroids of the same pair within ``radius_px``: how far apart (px)."""
    A = np.asarray([p for p in a.get("uv", []) if None not in p], dtype=np.float64).reshape(-1, 2)
    B = np.asarray([p for p in b.get("uv", []) if None not in p], dtype=np.float64).reshape(-1, 2)
    if not len(A) or not len(B):
        return {"matched": 0, "only_a": len(A), "only_b": len(B), "rms_px": None, "max_px": None}
    d = np.linalg.norm(A[:, None, :] - B[None, :, :], axis=2)
    ab, ba = d.argmin(axis=1), d.argmin(axis=0)
    pairs = [(i, j) for i, j in enumerate(ab) if ba[j] == i and d[i, j] <= radius_px]
    shifts = np.array([d[i, j] for i, j in pairs])
    return {
        "matched": len(pairs),
        "only_a": len(A) - len(pairs),
        "only_b": len(B) - len(pairs),
        "rms_px": float(np.sqrt(np.mean(shifts**2))) if len(shifts) else None,
        "max_px": float(shifts.max()) if len(shifts) else None,
    }


# --------------------------------------------------------------------------
# The comparison
# --------------------------------------------------------------------------


def compare(a: str | Path | SessionView, b: str | Path | SessionView) -> dict[str, Any]:
    """Compare two recordings; JSON-able result (see module doc)."""
    va = a if isinstance(a, SessionView) else read_view(a)
    vb = b if isinstance(b, SessionView) else read_view(b)
    diffs: list[dict[str, Any]] = []

    def diff(path: str, x: Any, y: Any, delta: Any = "auto") -> None:
        if not _same(x, y):
            diffs.append({"path": path, "a": x, "b": y, "delta": _delta(x, y) if delta == "auto" else delta})

    def side(v: SessionView) -> dict[str, Any]:
        return {
            "path": str(v.path),
            "session_id": v.session_id,
            "complete": v.complete,
            "damage": v.damage,
            "parent": v.parent,
        }

    out: dict[str, Any] = {"a": side(va), "b": side(vb)}

    # ---- plugins
    plugins = []
    for stage in STAGES:
        pa, pb = va.plugins.get(stage) or {}, vb.plugins.get(stage) or {}
        na = f"{pa.get('name')} {pa.get('version', '')}".strip() if pa else None
        nb = f"{pb.get('name')} {pb.get('version', '')}".strip() if pb else None
        plugins.append({"stage": stage, "a": na, "b": nb, "same": na == nb})
        diff(f"plugins.{stage}", na, nb, None)
    out["plugins"] = plugins

    # ---- summary and characteristics
    ra, rb = va.report or {}, vb.report or {}
    out["reports"] = {"a": va.report is not None, "b": vb.report is not None}
    if va.report is None or vb.report is None:
        missing = [x for x, r in (("a", va.report), ("b", vb.report)) if r is None]
        diffs.append(
            {"path": "report", "a": va.report is not None, "b": vb.report is not None, "delta": None}
        )
        out["note"] = (
            f"no /report in {' and '.join(missing)} (incomplete recording?): characteristics not compared"
        )
    summary = []
    for key in SUMMARY_KEYS:
        x, y = ra.get(key), rb.get(key)
        summary.append({"key": key, "a": x, "b": y, "delta": _delta(x, y)})
        if va.report is not None and vb.report is not None:
            diff(f"summary.{key}", x, y)
    out["summary"] = summary
    chars_a = {c["name"]: c for c in ra.get("characteristics", [])}
    chars_b = {c["name"]: c for c in rb.get("characteristics", [])}
    names = list(chars_a) + [n for n in chars_b if n not in chars_a]
    characteristics = []
    for name in names:
        ca, cb = chars_a.get(name), chars_b.get(name)
        row: dict[str, Any] = {"name": name, "kind": (ca or cb or {}).get("kind"), "a": None, "b": None}
        if ca is None or cb is None:
            diff(f"characteristics.{name}", ca is not None, cb is not None, None)
        for which, c in (("a", ca), ("b", cb)):
            if c is not None:
                row[which] = {k: c.get(k) for k in CHARACTERISTIC_KEYS}
                row[which]["nominal_mm"] = c.get("nominal_mm")
                row[which]["tolerance_mm"] = c.get("tolerance_mm")
        if ca is not None and cb is not None:
            for k in CHARACTERISTIC_KEYS + ("nominal_mm", "tolerance_mm"):
                diff(f"characteristics.{name}.{k}", ca.get(k), cb.get(k))
            row["delta_mm"] = _delta(ca.get("measured_mm"), cb.get("measured_mm"))
        characteristics.append(row)
    out["characteristics"] = characteristics

    # ---- registration
    out["registration"] = _compare_registration(va, vb, ra, rb, diff)

    # ---- centroids
    centroids = {}
    for camera in ("upper", "lower"):
        da, db = va.centroids.get(camera, {}), vb.centroids.get(camera, {})
        sa, sb = centroid_stats(da), centroid_stats(db)
        for key in CENTROID_STATS:
            diff(f"centroids.{camera}.{key}", sa[key], sb[key])
        per_frame = []
        for seq in sorted(set(da) | set(db)):
            if seq not in da or seq not in db:
                diff(f"centroids.{camera}[{seq}]", seq in da, seq in db, None)
                continue
            shift = centroid_shift(da[seq], db[seq])
            shift["sequence"] = seq
            per_frame.append(shift)
            if da[seq].get("uv") != db[seq].get("uv") or da[seq].get("sigma_uv") != db[seq].get("sigma_uv"):
                diffs.append(
                    {
                        "path": f"centroids.{camera}[{seq}].uv",
                        "a": f"{da[seq].get('count')} centroids",
                        "b": f"{db[seq].get('count')} centroids",
                        "delta": shift["max_px"],
                    }
                )
        shifts = [f["max_px"] for f in per_frame if f["max_px"] is not None]
        rms = [f["rms_px"] for f in per_frame if f["rms_px"] is not None]
        centroids[camera] = {
            "a": sa,
            "b": sb,
            "shift_px": {
                "rms": float(np.sqrt(np.mean(np.square(rms)))) if rms else None,
                "max": max(shifts) if shifts else None,
                "only_a": sum(f["only_a"] for f in per_frame),
                "only_b": sum(f["only_b"] for f in per_frame),
            },
            "per_frame": per_frame,
        }
    out["centroids"] = centroids

    # ---- frame errors
    for seq in sorted(set(va.frames) | set(vb.frames)):
        fa, fb = va.frames.get(seq), vb.frames.get(seq)
        if fa is None or fb is None:
            diff(f"frames[{seq}]", fa is not None, fb is not None, None)
        else:
            diff(f"frames[{seq}].error", fa.get("error"), fb.get("error"), None)

    out["differences"] = diffs
    out["identical"] = not diffs
    return out


def _compare_registration(
    va: SessionView, vb: SessionView, ra: Mapping, rb: Mapping, diff: Any
) -> dict[str, Any]:
    rega, regb = ra.get("registration") or {}, rb.get("registration") or {}
    session = {
        "a": {k: rega.get(k) for k in ("R_global_camera", "t_global_camera_mm", "rms_mm", "scale")},
        "b": {k: regb.get(k) for k in ("R_global_camera", "t_global_camera_mm", "rms_mm", "scale")},
        "rotation_diff_rad": rotation_angle(rega.get("R_global_camera"), regb.get("R_global_camera"))
        if rega.get("R_global_camera") and regb.get("R_global_camera")
        else None,
        "translation_diff_mm": _norm(_delta(rega.get("t_global_camera_mm"), regb.get("t_global_camera_mm")))
        if rega.get("t_global_camera_mm") and regb.get("t_global_camera_mm")
        else None,
    }
    if rega and regb:
        diff(
            "registration.R_global_camera",
            rega.get("R_global_camera"),
            regb.get("R_global_camera"),
            session["rotation_diff_rad"],
        )
        diff(
            "registration.t_global_camera_mm", rega.get("t_global_camera_mm"), regb.get("t_global_camera_mm")
        )
        diff("registration.rms_mm", rega.get("rms_mm"), regb.get("rms_mm"))
        diff("registration.scale", rega.get("scale"), regb.get("scale"))
    per_frame = []
    for seq in sorted(set(va.registrations) | set(vb.registrations)):
        xa, xb = va.registrations.get(seq), vb.registrations.get(seq)
        if xa is None or xb is None:
            diff(f"registration[{seq}]", xa is not None, xb is not None, None)
            per_frame.append({"sequence": seq, "a": xa is not None, "b": xb is not None})
            continue
        res_a = {r["control_id"]: r for r in xa.get("residuals", [])}
        res_b = {r["control_id"]: r for r in xb.get("residuals", [])}
        angle = rotation_angle(xa["R_global_camera"], xb["R_global_camera"])
        row = {
            "sequence": seq,
            "rms_mm": {
                "a": xa.get("rms_mm"),
                "b": xb.get("rms_mm"),
                "delta": _delta(xa.get("rms_mm"), xb.get("rms_mm")),
            },
            "R_global_camera": {"a": xa["R_global_camera"], "b": xb["R_global_camera"], "angle_rad": angle},
            "t_global_camera_mm": {
                "a": xa["t_global_camera_mm"],
                "b": xb["t_global_camera_mm"],
                "delta": _delta(xa["t_global_camera_mm"], xb["t_global_camera_mm"]),
            },
            "residuals": [
                {
                    "control_id": cid,
                    "a_mm": (res_a.get(cid) or {}).get("residual_mm"),
                    "b_mm": (res_b.get(cid) or {}).get("residual_mm"),
                    "a_norm_mm": (res_a.get(cid) or {}).get("norm_mm"),
                    "b_norm_mm": (res_b.get(cid) or {}).get("norm_mm"),
                }
                for cid in list(res_a) + [c for c in res_b if c not in res_a]
            ],
        }
        per_frame.append(row)
        diff(f"registration[{seq}].R_global_camera", xa["R_global_camera"], xb["R_global_camera"], angle)
        diff(f"registration[{seq}].t_global_camera_mm", xa["t_global_camera_mm"], xb["t_global_camera_mm"])
        diff(f"registration[{seq}].rms_mm", xa.get("rms_mm"), xb.get("rms_mm"))
        diff(f"registration[{seq}].scale", xa.get("scale"), xb.get("scale"))
        for r in row["residuals"]:
            diff(f"registration[{seq}].residual.{r['control_id']}", r["a_mm"], r["b_mm"])
        diff(
            f"registration[{seq}].unmatched_control",
            xa.get("unmatched_control"),
            xb.get("unmatched_control"),
            None,
        )
    controls_a = {c["id"]: c for c in rega.get("control_points", [])}
    controls_b = {c["id"]: c for c in regb.get("control_points", [])}
    controls = []
    for cid in list(controls_a) + [c for c in controls_b if c not in controls_a]:
        x = (controls_a.get(cid) or {}).get("rms_norm_mm")
        y = (controls_b.get(cid) or {}).get("rms_norm_mm")
        controls.append({"id": cid, "a_rms_norm_mm": x, "b_rms_norm_mm": y, "delta": _delta(x, y)})
    return {"session": session, "per_frame": per_frame, "controls": controls}


# --------------------------------------------------------------------------
# Terminal table
# --------------------------------------------------------------------------


def _decision(c: Mapping[str, Any]) -> str:
    """A side's ISO 14253-1 decision of a characteristic (crossfield.report.vocabulary); - when absent."""
    return decision_text(c.get("decision"), c.get("passed")) if c else "-"


def _verdict(passed: Any) -> str:
    """A side's session verdict, PASS or FAIL; - without a report."""
    return "-" if passed is None else verdict_word(bool(passed))


def _f(value: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return verdict_word(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return f"{value:.{digits}f}"
    return str(value)


def _d(value: Any, digits: int = 4) -> str:
    """A difference: '0' when exactly zero, else signed with enough digits to show it."""
    if value is None:
        return "-"
    if isinstance(value, list):
        return "[" + ", ".join(_d(v, digits) for v in value) + "]"
    if value == 0:
        return "0"
    if abs(value) < 10**-digits:
        return f"{value:+.2e}"
    return f"{value:+.{digits}f}"


def format_table(result: Mapping[str, Any]) -> str:
    """The comparison as text for the terminal."""
    lines = []
    for which in ("a", "b"):
        s = result[which]
        state = "" if s["complete"] else "  (INCOMPLETE recording)"
        parent = s.get("parent") or {}
        origin = f"  replay of {parent.get('session_id')}" if parent else ""
        lines.append(f"{which.upper()}: {s['path']}  session {s['session_id']}{origin}{state}")
    lines.append("")
    lines.append("Plugins")
    for p in result["plugins"]:
        mark = "" if p["same"] else "   <- differs"
        lines.append(f"  {p['stage']:<12} {p['a']!s:<22} {p['b']!s:<22}{mark}")
    lines.append("")
    if result.get("note"):
        lines.append(result["note"])
    else:
        chars = result["characteristics"]
        k = next((s.get("coverage_factor") for c in chars for s in (c["a"], c["b"]) if s), None)
        U = expanded_heading(k)
        lines.append(f"Characteristics (mm; {U}: expanded uncertainty; decision: ISO 14253-1)")
        lines.append(
            f"  {'name':<10} {'A measured':>12} {'B measured':>12} {'B - A':>10} "
            f"{'A dev':>9} {'B dev':>9} {'A ' + U:>13} {'B ' + U:>13}  {'A decision':<17} B decision"
        )
        for c in chars:
            a, b = c["a"] or {}, c["b"] or {}
            lines.append(
                f"  {c['name']:<10} {_f(a.get('measured_mm')):>12} {_f(b.get('measured_mm')):>12} "
                f"{_d(c.get('delta_mm')):>10} {_f(a.get('deviation_mm')):>9} {_f(b.get('deviation_mm')):>9} "
                f"{_f(a.get('expanded_uncertainty_mm')):>13} {_f(b.get('expanded_uncertainty_mm')):>13}  "
                f"{_decision(a):<17} {_decision(b)}"
            )
        for row in result["summary"]:
            if row["key"] == "passed":
                lines.append(f"  {'verdict':<10} {_verdict(row['a']):>12} {_verdict(row['b']):>12}")
            elif row["key"] == "rms_error_mm":
                lines.append(
                    f"  {row['key']:<10} {_f(row['a']):>12} {_f(row['b']):>12} {_d(row['delta']):>10}"
                )
    lines.append("")
    reg = result["registration"]
    s = reg["session"]
    lines.append("Registration (T_global_camera; mm, rad)")
    if s["a"].get("rms_mm") is not None or s["b"].get("rms_mm") is not None:
        lines.append(
            f"  session    RMS A {_f(s['a'].get('rms_mm'))}  B {_f(s['b'].get('rms_mm'))}  "
            f"rotation B vs A {_d(s['rotation_diff_rad'], 6)} rad  "
            f"translation {_d(s['translation_diff_mm'])} mm"
        )
    Ra, Rb = s["a"].get("R_global_camera"), s["b"].get("R_global_camera")
    ta, tb = s["a"].get("t_global_camera_mm"), s["b"].get("t_global_camera_mm")
    if Ra and Rb and ta and tb:
        lines.append(f"  {'':<10} {'R A':<30} {'t A (mm)':>11}    {'R B':<30} {'t B (mm)':>11}")
        for k in range(3):
            row_a = " ".join(f"{v:>9.6f}" for v in Ra[k])
            row_b = " ".join(f"{v:>9.6f}" for v in Rb[k])
            lines.append(f"  {'':<10} {row_a:<30} {ta[k]:>11.4f}    {row_b:<30} {tb[k]:>11.4f}")
    lines.append(
        f"  {'pair':<8} {'RMS A':>8} {'RMS B':>8} {'B - A':>10} {'rot B vs A':>12} {'|t B - A|':>10}"
    )
    for f in reg["per_frame"]:
        if "rms_mm" not in f:
            lines.append(f"  {f['sequence']:<8} registered in A: {f['a']}, in B: {f['b']}")
            continue
        lines.append(
            f"  {f['sequence']:<8} {_f(f['rms_mm']['a']):>8} {_f(f['rms_mm']['b']):>8} "
            f"{_d(f['rms_mm']['delta']):>10} {_d(f['R_global_camera']['angle_rad'], 6):>12} "
            f"{_d(_norm(f['t_global_camera_mm']['delta'])):>10}"
        )
    if reg["controls"]:
        lines.append(f"  {'control':<8} {'|res| A':>8} {'|res| B':>8} {'B - A':>10}   (RMS over pairs)")
        for c in reg["controls"]:
            lines.append(
                f"  {c['id']:<8} {_f(c['a_rms_norm_mm']):>8} {_f(c['b_rms_norm_mm']):>8} {_d(c['delta']):>10}"
            )
    lines.append("")
    lines.append("Centroids (px)")
    for camera, c in result["centroids"].items():
        lines.append(f"  {camera}")
        for key in CENTROID_STATS:
            x, y = c["a"][key], c["b"][key]
            lines.append(f"    {key:<16} {_f(x):>10} {_f(y):>10} {_d(_delta(x, y)):>10}")
        sh = c["shift_px"]
        lines.append(
            f"    {'shift B vs A':<16} RMS {_f(sh['rms'])}  max {_f(sh['max'])}  "
            f"unmatched A {sh['only_a']}  B {sh['only_b']}"
        )
    lines.append("")
    diffs = result["differences"]
    if not diffs:
        lines.append("No differences: the sessions agree in every compared value (bit for bit).")
    else:
        lines.append(f"{len(diffs)} difference(s):")
        for d in diffs[:40]:
            lines.append(f"  {d['path']}: A {_short(d['a'])}  B {_short(d['b'])}  delta {_short(d['delta'])}")
        if len(diffs) > 40:
            lines.append(f"  ... and {len(diffs) - 40} more (see --json)")
    return "\n".join(lines)


def _short(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list):
        text = "[" + ", ".join(_short(v) for v in value) + "]"
        return text if len(text) < 80 else text[:77] + "..."
    return str(value)
