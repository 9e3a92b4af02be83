"""What one batch task does with one session: audit it, replay it, or replay it with
other plugins and compare the replay with the original.

Each task runs on a Dask worker and returns its archive-report entry, a JSON-able
dict with at least ``path``, ``verdict`` (PASS, FAIL, INCOMPLETE or ERROR) and
``reason``. Everything a task writes goes into its own folder
``<out>/sessions/<index>-<name>/``: made under a temporary name, then renamed in one
step (``os.rename`` of a folder is atomic on a POSIX file system). A task whose worker
was lost is run again by Dask on another worker; the retry makes its own temporary
folder, and if an earlier attempt finished its rename before its worker was lost, the
retry returns that attempt's entry instead of writing a second copy. So each session
appears once in the report and once on disk (idempotent tasks).

A task never raises for a bad session: a file that is not a crossfield recording,
or fails while being read, is an ERROR entry with the reason (the rest of the batch
goes on). Memory: one session per task, its frames streamed by the replay
(:class:`crossfield.replay.RecordingSource`); a worker runs one task at a time
(one thread per worker).

Units: mm for measured values, shifts and uncertainties; ``shift_over_U`` is a ratio.
"""

from __future__ import annotations

import functools
import json
import math
import os
import re
import shutil
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from crossfield.errors import CrossfieldError

__all__ = [
    "VERDICTS",
    "KINDS",
    "warm_up",
    "noop",
    "task_folder_name",
    "run_task",
    "audit_entry",
    "replay_entry",
    "compare_entry",
    "characteristic_shifts",
    "expanded_uncertainty",
    "decision",
]

VERDICTS = ("PASS", "FAIL", "INCOMPLETE", "ERROR")
KINDS = ("audit", "replay", "compare")
#: The file each task folder holds its entry in (written last, before the rename).
ENTRY_FILE = "entry.json"
#: Integrity findings that mean "cut short", not "altered" (as :class:`crossfield.audit.report.AuditReport`).
TRUNCATION = {"truncated", "uncovered"}
#: Findings named in a reason (the rest are counted; all are in the task's audit.json).
REASON_ITEMS = 3


@functools.lru_cache(maxsize=1)
def _plugin_manager() -> Any:
    """One plugin manager per worker process: built-in plugins and installed ones (entry points)."""
    from crossfield.chain.registry import make_plugin_manager

    return make_plugin_manager(entry_points=True)


def warm_up(path: str | None = None) -> None:
    """Import what a task needs and build this process's plugin manager (a worker does it
    on its first task; ``Client.run(warm_up)`` does it ahead, e.g. before timing); with
    ``path``, also audit that session once into a temporary folder (what the first
    replay in a process initialises: plugin modules, caches)."""
    import tempfile

    import crossfield.audit  # noqa: F401
    import crossfield.compare  # noqa: F401
    import crossfield.replay  # noqa: F401

    _plugin_manager()
    if path is not None:
        with tempfile.TemporaryDirectory(prefix="crossfield-warm-") as tmp:
            audit_entry(path, Path(tmp))


def noop(*args: Any) -> None:
    """A task that does nothing: the engine's own cost per task (bench/bench_batch.py)."""
    return None


def task_folder_name(index: int, path: str) -> str:
    """``<index>-<name>``: the session folder's name (``.../<name>/session.mcap``) or the
    file's stem, reduced to letters, digits, ``.``, ``_`` and ``-`` (a name from the
    archive is data, never a path)."""
    p = Path(path)
    name = p.parent.name if p.name == "session.mcap" else p.stem
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "session"
    return f"{index:05d}-{name[:80]}"


def _read_entry(folder: Path) -> dict[str, Any]:
    return json.loads((folder / ENTRY_FILE).read_text(encoding="utf-8"))


def in_own_folder(root: Path, name: str, work: Callable[[Path, Path], dict[str, Any]]) -> dict[str, Any]:
    """Run ``work(tmp, final)`` in a fresh temporary folder under ``root`` and rename it to
    ``root/name``; ``work`` writes its files into ``tmp`` and names them by ``final``.
    If ``root/name`` already holds an entry (an earlier attempt finished), that entry is
    returned and nothing is written."""
    final = root / name
    if (final / ENTRY_FILE).exists():
        return _read_entry(final)
    root.mkdir(parents=True, exist_ok=True)
    tmp = root / f".{name}.tmp-{uuid.uuid4().hex}"
    tmp.mkdir()
    try:
        entry = work(tmp, final)
        entry["folder"] = str(final)
        (tmp / ENTRY_FILE).write_text(json.dumps(entry, indent=2, allow_nan=False, default=str), encoding="utf-8")
        try:
            os.rename(tmp, final)
        except OSError:
            if (final / ENTRY_FILE).exists():  # another attempt renamed first
                shutil.rmtree(tmp, ignore_errors=True)
                return _read_entry(final)
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return entry


def _error_entry(path: str, exc: BaseException) -> dict[str, Any]:
    reason = str(exc) if isinstance(exc, CrossfieldError) else f"{type(exc).__name__}: {exc}"
    return {"path": path, "verdict": "ERROR", "reason": reason}


def run_task(
    kind: str,
    index: int,
    path: str,
    out_dir: str,
    plugins: Mapping[str, str | None] | None = None,
    options: Sequence[str] = (),
) -> dict[str, Any]:
    """The Dask task: ``kind`` (audit, replay, compare) of the session at ``path`` (absolute),
    written into ``<out_dir>/sessions/<index>-<name>/``. Returns the report entry
    (with ``index``); an exception of the session is an ERROR entry."""
    if kind not in KINDS:
        raise ValueError(f"batch task {kind!r}: one of {', '.join(KINDS)}")
    name = task_folder_name(index, path)
    root = Path(out_dir) / "sessions"

    def guarded(tmp: Path, final: Path) -> dict[str, Any]:
        try:
            if kind == "audit":
                return audit_entry(path, tmp)
            work = replay_entry if kind == "replay" else compare_entry
            return work(path, tmp, final, plugins or {}, options)
        except (CrossfieldError, OSError, ValueError, KeyError) as exc:  # a bad session, not a bad batch
            return _error_entry(path, exc)

    entry = in_own_folder(root, name, guarded)
    entry["index"] = index
    return entry


# --------------------------------------------------------------------------
# audit
# --------------------------------------------------------------------------


def audit_entry(path: str, folder: Path) -> dict[str, Any]:
    """Audit one session (:func:`crossfield.audit.audit`, the same checks as
    ``crossfield audit``); its full report is ``audit.json`` in ``folder``.

    PASS: integrity, provenance and reproduction pass. INCOMPLETE: the recording
    was cut short but what it holds is intact and reproduces. FAIL: any other
    finding (named in the reason)."""
    from crossfield.audit import audit, to_json

    report = audit(path, _plugin_manager())
    (folder / "audit.json").write_text(to_json(report), encoding="utf-8")
    findings: list[str] = []
    altered = [p for p in report.integrity.problems if p.kind not in TRUNCATION]
    if not report.integrity.has_chain:
        findings.append("integrity: the recording has no integrity chain")
    findings += [f"integrity: {p}" for p in altered[:REASON_ITEMS]]
    if len(altered) > REASON_ITEMS:
        findings.append(f"integrity: {len(altered) - REASON_ITEMS} more finding(s)")
    findings += [f"provenance: {p}" for p in report.provenance.get("problems", [])]
    repro = report.reproduction
    if not repro.get("passed"):
        if repro.get("error"):
            findings.append(f"reproduction: {repro['error']}")
        else:
            n = repro.get("differences_total", 0)
            first = (repro.get("differences") or [{}])[0]
            where = f" (first: {first.get('topic')} sequence {first.get('sequence')} {first.get('path')})" if n else ""
            findings.append(
                f"reproduction: {n} difference(s){where}, {len(repro.get('only_recorded', []))} recorded "
                f"message(s) not reproduced"
            )
    if findings:
        verdict, reason = "FAIL", "; ".join(findings)
    elif not report.complete:
        verdict, reason = "INCOMPLETE", f"{'; '.join(report.notes)}; intact and reproduced up to where it ends"
    elif (report.provenance.get("result") or {}).get("incomplete"):  # stopped early (Ctrl-C, a source error)
        stopped = report.provenance["result"]["incomplete"]
        verdict, reason = "INCOMPLETE", f"the session ended INCOMPLETE: {stopped}; its recording is intact and reproduced"
    else:
        verdict, reason = "PASS", "integrity, provenance and reproduction pass"
    return {
        "path": path,
        "verdict": verdict,
        "reason": reason,
        "file_sha256": report.file_sha256,
        "complete": report.complete,
        "intact": report.intact,
        "integrity_passed": report.integrity.passed,
        "provenance_passed": bool(report.provenance.get("passed")),
        "reproduction_passed": bool(repro.get("passed")),
        "audit": "audit.json",
    }


# --------------------------------------------------------------------------
# replay
# --------------------------------------------------------------------------


def _replay(path: str, tmp: Path, plugins: Mapping[str, str | None], options: Sequence[str]) -> Any:
    from crossfield.replay import replay_session

    return replay_session(
        path, _plugin_manager(), plugins=plugins, options=list(options), output=tmp / "replay.mcap", rerun=False
    )


def _replay_verdict(summary: Any) -> tuple[str, str]:
    from crossfield.report.document import problems

    if summary.incomplete:
        return "INCOMPLETE", summary.incomplete
    if summary.passed:
        return "PASS", f"{summary.frames_processed} stereo pair(s), every characteristic passes"
    found = problems(summary)
    failing = [c.name for c in summary.characteristics if not c.passed]
    if failing:
        found.insert(0, f"characteristic(s) not passing: {', '.join(failing)}")
    return "FAIL", "; ".join(found[: REASON_ITEMS + 1]) or "the session does not pass"


def replay_entry(
    path: str, tmp: Path, final: Path, plugins: Mapping[str, str | None], options: Sequence[str]
) -> dict[str, Any]:
    """Replay one session (:func:`crossfield.replay.replay_session`, as ``crossfield replay``
    with the same plugin flags); the replay is ``replay.mcap`` with its report files in
    ``replay/``. PASS / FAIL: the replayed session passes or not (the reason names what
    fails); INCOMPLETE: the recording was cut short (where it ends)."""
    summary = _replay(path, tmp, plugins, options)
    verdict, reason = _replay_verdict(summary)
    return {
        "path": path,
        "verdict": verdict,
        "reason": reason,
        "replay": str(final / "replay.mcap"),
        "changed": (summary.info.parent or {}).get("changed"),
        "frames_processed": summary.frames_processed,
        "characteristics": [
            {"name": c.name, "measured_mm": _real(c.measured_mm), "decision": c.decision, "passed": bool(c.passed)}
            for c in summary.characteristics
        ],
    }


# --------------------------------------------------------------------------
# compare
# --------------------------------------------------------------------------


def _real(value: Any) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def expanded_uncertainty(characteristic: Mapping[str, Any]) -> tuple[float | None, str]:
    """(U in mm, where it comes from) for one characteristic of a report.json:
    ``expanded_uncertainty_mm`` when the report gives it, else 2 x ``uncertainty_mm``
    (the standard uncertainty with the default coverage factor k = 2, GUM 6.2.1)."""
    U = _real(characteristic.get("expanded_uncertainty_mm"))
    if U is not None:
        return U, "expanded_uncertainty_mm"
    u = _real(characteristic.get("uncertainty_mm"))
    return (None if u is None else 2.0 * u), "2 x uncertainty_mm"


def decision(characteristic: Mapping[str, Any]) -> Any:
    """The characteristic's conformance decision: ``decision`` when the report gives one
    (ISO 14253-1), else ``passed``."""
    return characteristic.get("decision", characteristic.get("passed"))


def characteristic_shifts(original: Mapping[str, Any], replayed: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per characteristic of two report.json documents: the shift of the measured value
    (replayed - original, mm), the original's U (mm, :func:`expanded_uncertainty`), the
    shift relative to it, and whether the decision changes. A characteristic in one
    report only has no shift and counts as a changed decision."""
    a = {c["name"]: c for c in original.get("characteristics", [])}
    b = {c["name"]: c for c in replayed.get("characteristics", [])}
    rows = []
    for name in list(a) + [n for n in b if n not in a]:
        ca, cb = a.get(name), b.get(name)
        row: dict[str, Any] = {"name": name, "kind": (ca or cb or {}).get("kind")}
        if ca is None or cb is None:
            row.update(
                measured_mm=None, replayed_mm=None, shift_mm=None, U_mm=None, U_source=None, shift_over_U=None,
                decision=None if ca is None else decision(ca), replayed_decision=None if cb is None else decision(cb),
                decision_changed=True, note=f"only in the {'replay' if ca is None else 'original'}",
            )
            rows.append(row)
            continue
        ma, mb = _real(ca.get("measured_mm")), _real(cb.get("measured_mm"))
        shift = None if ma is None or mb is None else mb - ma
        U, source = expanded_uncertainty(ca)
        row.update(
            measured_mm=ma,
            replayed_mm=mb,
            shift_mm=shift,
            U_mm=U,
            U_source=source,
            shift_over_U=None if shift is None or not U else shift / U,
            decision=decision(ca),
            replayed_decision=decision(cb),
            decision_changed=decision(ca) != decision(cb),
        )
        rows.append(row)
    return rows


def compare_entry(
    path: str, tmp: Path, final: Path, plugins: Mapping[str, str | None], options: Sequence[str]
) -> dict[str, Any]:
    """Replay one session with the given plugins (as :func:`replay_entry`) and compare the
    replay with the original (:func:`crossfield.compare.compare`, as ``crossfield compare``;
    ``compare.json``). PASS: no characteristic changes its decision; FAIL: at least one
    does (named, with shift / U); INCOMPLETE: the original or the replay is incomplete
    or has no report."""
    from crossfield.compare import compare, read_view

    summary = _replay(path, tmp, plugins, options)
    original = read_view(path)
    replayed = read_view(tmp / "replay.mcap")
    result = compare(original, replayed)
    (tmp / "compare.json").write_text(json.dumps(result, indent=2, allow_nan=False, default=str), encoding="utf-8")
    replay_verdict, _ = _replay_verdict(summary)
    entry: dict[str, Any] = {
        "path": path,
        "replay": str(final / "replay.mcap"),
        "compare": "compare.json",
        "changed": (summary.info.parent or {}).get("changed"),
        "identical": bool(result["identical"]),
        "differences": len(result["differences"]),
        "replay_verdict": replay_verdict,
        "original_passed": (original.report or {}).get("passed"),
        "characteristics": [],
    }
    if original.report is None or replayed.report is None or summary.incomplete:
        missing = "the original" if original.report is None else "the replay"
        entry.update(
            verdict="INCOMPLETE",
            reason=summary.incomplete or f"{missing} has no report (cut short): characteristics not compared",
        )
        return entry
    rows = characteristic_shifts(original.report, replayed.report)
    entry["characteristics"] = rows
    changed = [r for r in rows if r["decision_changed"]]
    if changed:
        named = ", ".join(
            f"{r['name']} ({r['decision']} -> {r['replayed_decision']}"
            + (f", shift {r['shift_mm']:+.4f} mm = {r['shift_over_U']:+.2f} U" if r["shift_over_U"] is not None else "")
            + ")"
            for r in changed
        )
        entry.update(verdict="FAIL", reason=f"{len(changed)} characteristic(s) change their decision: {named}")
    else:
        largest = max((abs(r["shift_over_U"]) for r in rows if r["shift_over_U"] is not None), default=None)
        entry.update(
            verdict="PASS",
            reason="no characteristic changes its decision"
            + (f"; largest |shift| = {largest:.3f} U" if largest is not None else ""),
        )
    return entry
