"""The archive report of a batch: ``batch-report.json`` and ``batch-report.html``.

``batch-report.json``::

    {"format": "crossfield.batch-report/1", "kind": "audit" | "replay" | "compare",
     "complete": bool,            # false while running and after an interruption
     "started_utc", "updated_utc", "inputs": N, "finished": n,
     "counts": {"PASS": .., "FAIL": .., "INCOMPLETE": .., "ERROR": ..},
     "plugins": {...}, "options": [...],            # what a replay / compare swaps
     "uncertainty": "...",                          # compare: where U comes from
     "decision_changes": n, "distribution": {name: {...}},   # compare: over the archive
     "sessions": [{"path", "verdict", "reason", ...}, ...],   # input order
     "not_finished": [path, ...]}                   # inputs without an entry yet

The file is rewritten (to a temporary file, then ``os.replace``: readers never see
half a file) each time a session finishes, so an interrupted batch leaves a report
of what finished with ``complete: false``. The HTML page is written with it at the
end (and on interruption): the sessions that change their decision first, then
FAIL / ERROR / INCOMPLETE, then PASS; for a comparison the plot of shifts
(:mod:`crossfield.batch.plot`) and per characteristic the shift in mm and in U.
"""

from __future__ import annotations

import html
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from crossfield.batch.inputs import SessionInput
from crossfield.batch.plot import shift_histogram_svg
from crossfield.batch.tasks import VERDICTS
from crossfield.recording.codec import utc_text

__all__ = [
    "REPORT_FORMAT", "JSON_NAME", "HTML_NAME", "BatchReport", "shift_distribution", "sort_key", "write_atomic"
]

REPORT_FORMAT = "crossfield.batch-report/1"
JSON_NAME = "batch-report.json"
HTML_NAME = "batch-report.html"


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and ``os.replace``."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _changes_decision(entry: Mapping[str, Any]) -> bool:
    return any(r.get("decision_changed") for r in entry.get("characteristics") or ())


def sort_key(entry: Mapping[str, Any]) -> tuple[int, int, float]:
    """Sessions that change a decision first, then FAIL, ERROR, INCOMPLETE, PASS; within
    each, the largest |shift / U| first."""
    order = {"FAIL": 1, "ERROR": 2, "INCOMPLETE": 3, "PASS": 4}
    largest = max(
        (abs(r["shift_over_U"]) for r in entry.get("characteristics") or () if r.get("shift_over_U") is not None),
        default=0.0,
    )
    return (0 if _changes_decision(entry) else 1, order.get(entry.get("verdict", ""), 5), -largest)


def shift_distribution(entries: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per characteristic over the archive: how many sessions have a shift, how many change
    their decision, and the min / median / max / RMS of ``shift_mm`` (mm) and ``shift_over_U``."""
    import numpy as np

    rows: dict[str, list[Mapping[str, Any]]] = {}
    for entry in entries:
        for r in entry.get("characteristics") or ():
            if "shift_mm" in r:
                rows.setdefault(r["name"], []).append(r)
    out: dict[str, dict[str, Any]] = {}
    for name, found in rows.items():
        stats: dict[str, Any] = {
            "sessions": len(found), "decision_changes": sum(1 for r in found if r["decision_changed"])
        }
        for key in ("shift_mm", "shift_over_U"):
            v = np.array([r[key] for r in found if r.get(key) is not None], dtype=float)
            stats[key] = None if v.size == 0 else {
                "min": float(v.min()), "median": float(np.median(v)), "max": float(v.max()),
                "rms": float(np.sqrt(np.mean(v**2))),
            }
        out[name] = stats
    return out


class BatchReport:
    """The report of one batch, kept on disk as results arrive.

    inputs: every input (readable or not); ``add(position, entry)`` records the entry
    of input ``position`` once (a second entry for the same input, which a retried task
    cannot produce but a buggy one could, is refused)."""

    def __init__(
        self,
        out_dir: Path,
        kind: str,
        inputs: Sequence[SessionInput],
        *,
        plugins: Mapping[str, Any] | None = None,
        options: Sequence[str] = (),
    ) -> None:
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.kind = kind
        self.inputs = list(inputs)
        self.plugins = {k: v for k, v in (plugins or {}).items() if v}
        self.options = list(options)
        self.entries: dict[int, dict[str, Any]] = {}
        self.started_ns = time.time_ns()
        self.complete = False

    @property
    def json_path(self) -> Path:
        return self.out_dir / JSON_NAME

    @property
    def html_path(self) -> Path:
        return self.out_dir / HTML_NAME

    def add(self, position: int, entry: Mapping[str, Any], *, write: bool = True) -> None:
        if position in self.entries:
            raise ValueError(f"{self.inputs[position].path}: a second entry for one session")
        entry = dict(entry)
        entry["path"] = self.inputs[position].path
        if entry.get("verdict") not in VERDICTS:
            entry = {"path": entry["path"], "verdict": "ERROR", "reason": f"no verdict in the task's result: {entry}"}
        self.entries[position] = entry
        if write:
            self.write_json()

    def sessions(self) -> list[dict[str, Any]]:
        """The entries in input order."""
        return [self.entries[i] for i in sorted(self.entries)]

    def to_json(self) -> dict[str, Any]:
        sessions = self.sessions()
        counts = {v: sum(1 for e in sessions if e["verdict"] == v) for v in VERDICTS}
        doc: dict[str, Any] = {
            "format": REPORT_FORMAT,
            "kind": self.kind,
            "complete": self.complete,
            "started_utc": utc_text(self.started_ns),
            "updated_utc": utc_text(time.time_ns()),
            "inputs": len(self.inputs),
            "finished": len(sessions),
            "counts": counts,
            "plugins": self.plugins,
            "options": self.options,
            "sessions": sessions,
            "not_finished": [s.path for i, s in enumerate(self.inputs) if i not in self.entries],
        }
        if self.kind == "compare":
            doc["uncertainty"] = (
                "U of each characteristic is the original session's expanded_uncertainty_mm when its "
                "report.json gives one, else 2 x uncertainty_mm (k = 2); per row: U_source"
            )
            doc["decision_changes"] = sum(1 for e in sessions if _changes_decision(e))
            doc["distribution"] = shift_distribution(sessions)
        return doc

    def write_json(self) -> None:
        write_atomic(self.json_path, json.dumps(self.to_json(), indent=2, allow_nan=False, default=str))

    def finish(self, complete: bool) -> None:
        """Write both files; ``complete``: every input has its entry."""
        self.complete = complete and len(self.entries) == len(self.inputs)
        self.write_json()
        write_atomic(self.html_path, self.html())

    # ---- HTML ------------------------------------------------------------------

    def html(self) -> str:
        doc = self.to_json()
        esc = html.escape
        title = f"crossfield batch {self.kind}: {doc['finished']} of {doc['inputs']} session(s)"
        parts = [
            "<!DOCTYPE html><html><head><meta charset='utf-8'>",
            f"<title>{esc(title)}</title><style>",
            "body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%;vertical-align:top}"
            ".PASS{color:#185c18}.FAIL{color:#a01010}.ERROR{color:#a01010}.INCOMPLETE{color:#a06000}"
            ".changed{background:#fde8e8}",
            "</style></head><body>",
            f"<h1>{esc(title)}</h1>",
        ]
        if not doc["complete"]:
            parts.append(
                f"<p><b>INCOMPLETE report</b>: {len(doc['not_finished'])} session(s) not finished "
                "(the batch was interrupted or is still running).</p>"
            )
        parts.append(
            "<p>" + ", ".join(f"{v}: {n}" for v, n in doc["counts"].items()) + f". Started {esc(doc['started_utc'])}.</p>"
        )
        if self.plugins or self.options:
            swapped = [f"--{k} {v}" for k, v in self.plugins.items()] + [f"--option {o}" for o in self.options]
            parts.append(f"<p>Replayed with {esc(' '.join(swapped))}.</p>")
        if self.kind == "compare":
            parts.append(f"<p>{doc['decision_changes']} session(s) change a decision. {esc(doc['uncertainty'])}.</p>")
            svg = shift_histogram_svg(doc["sessions"])
            if svg:
                parts.append(f"<figure>{svg}<figcaption>Shift of each measured value over the session's U, "
                             "per characteristic, over the archive.</figcaption></figure>")
        if doc.get("distribution"):
            parts.append(
                "<table><tr><th>characteristic</th><th>sessions</th><th>decision changes</th>"
                "<th>shift mm (min / median / max)</th><th>shift / U (min / median / max)</th></tr>"
            )
            for name, st in sorted(doc["distribution"].items()):
                cells = [
                    "n/a" if st[k] is None else f"{st[k]['min']:+.4g} / {st[k]['median']:+.4g} / {st[k]['max']:+.4g}"
                    for k in ("shift_mm", "shift_over_U")
                ]
                parts.append(
                    f"<tr><td>{esc(name)}</td><td>{st['sessions']}</td><td>{st['decision_changes']}</td>"
                    f"<td>{cells[0]}</td><td>{cells[1]}</td></tr>"
                )
            parts.append("</table><p></p>")
        parts.append("<table><tr><th>session</th><th>verdict</th><th>reason</th><th>characteristics</th></tr>")
        for entry in sorted(doc["sessions"], key=sort_key):
            rows = []
            for r in entry.get("characteristics") or ():
                if "shift_mm" in r:
                    shift = "n/a" if r["shift_mm"] is None else f"{r['shift_mm']:+.4f} mm"
                    ratio = "" if r.get("shift_over_U") is None else f" = {r['shift_over_U']:+.3f} U"
                    flag = f" decision {r['decision']} -> {r['replayed_decision']}" if r["decision_changed"] else ""
                    rows.append(f"{esc(r['name'])}: {shift}{ratio}{esc(flag)}")
                else:
                    rows.append(f"{esc(r['name'])}: {r.get('measured_mm')} mm, passed {r.get('passed')}")
            css = " class='changed'" if _changes_decision(entry) else ""
            parts.append(
                f"<tr{css}><td>{esc(entry['path'])}</td><td class='{esc(entry['verdict'])}'>{esc(entry['verdict'])}</td>"
                f"<td>{esc(str(entry.get('reason', '')))}</td><td>{'<br>'.join(rows)}</td></tr>"
            )
        for path in doc["not_finished"]:
            parts.append(f"<tr><td>{esc(path)}</td><td>not finished</td><td></td><td></td></tr>")
        parts.append("</table></body></html>")
        return "\n".join(parts)
