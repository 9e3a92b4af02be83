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
        """batch-report.html (``batch.html.j2``): the record header, the counts, the shift
        distribution (compare) and one row per session, worst first (:func:`sort_key`)."""
        from markupsafe import Markup

        from crossfield.report.pages import render_page

        doc = self.to_json()
        title = f"crossfield batch {self.kind}: {doc['finished']} of {doc['inputs']} session(s)"
        swapped = [f"--{k} {v}" for k, v in self.plugins.items()] + [f"--option {o}" for o in self.options]
        distribution = [
            (name, st["sessions"], st["decision_changes"], *(
                "n/a" if st[k] is None else f"{st[k]['min']:+.4g} / {st[k]['median']:+.4g} / {st[k]['max']:+.4g}"
                for k in ("shift_mm", "shift_over_U")
            ))
            for name, st in sorted((doc.get("distribution") or {}).items())
        ]
        rows = [
            {
                "path": entry["path"],
                "verdict": entry["verdict"],
                "reason": str(entry.get("reason", "")),
                "changed": _changes_decision(entry),
                "characteristics": [_characteristic_text(r) for r in entry.get("characteristics") or ()],
            }
            for entry in sorted(doc["sessions"], key=sort_key)
        ]
        svg = shift_histogram_svg(doc["sessions"]) if self.kind == "compare" else ""
        return render_page("batch.html.j2", {
            "title": title,
            "header": batch_header(doc, title),
            "doc": doc,
            "swapped": " ".join(swapped),
            "distribution": distribution,
            "rows": rows,
            "histogram": Markup(svg) if svg else "",
        })


def _characteristic_text(r: Mapping[str, Any]) -> str:
    """One characteristic of a session row: its shift in mm and in U and a decision change
    (compare), or its measured value and ISO 14253-1 decision (crossfield.report.vocabulary)."""
    from crossfield.report.vocabulary import decision_text, fixed

    if "shift_mm" in r:
        shift = "n/a" if r["shift_mm"] is None else f"{r['shift_mm']:+.4f} mm"
        ratio = "" if r.get("shift_over_U") is None else f" = {r['shift_over_U']:+.3f} U"
        words = {k: _decision_words(r.get(k)) for k in ("decision", "replayed_decision")}
        flag = f"; decision {words['decision']} \u2192 {words['replayed_decision']}" if r["decision_changed"] else ""
        return f"{r['name']}: {shift}{ratio}{flag}"
    return f"{r['name']}: {fixed(r.get('measured_mm'), 4)} mm, {decision_text(r.get('decision'), r.get('passed'))}"


def _decision_words(decision: Any) -> str:
    """A decision as compare tasks keep it: the ISO 14253-1 key, or ``passed`` (a bool) for a
    report without decisions."""
    from crossfield.report.vocabulary import DECISION_WORDS

    if isinstance(decision, bool) or decision is None:
        return "accepted" if decision else "not accepted"
    return DECISION_WORDS.get(decision, str(decision))


def batch_header(doc: Mapping[str, Any], title: str) -> Any:
    """The record header of a batch report: when it was started and updated, the software,
    where each session's seal and decision rule are (its own report), the counts as verdict."""
    from crossfield.chain.provenance import crossfield_version
    from crossfield.report.header import Fact, RecordHeader

    counts = doc["counts"]
    all_pass = doc["complete"] and counts["PASS"] == doc["inputs"]
    facts = [
        Fact("Started (UTC)", str(doc["started_utc"]), "record-date"),
        Fact("Updated (UTC)", str(doc["updated_utc"]), "record-updated"),
        Fact("Software", f"crossfield {crossfield_version()}", "record-software"),
        Fact("Seal", "per session: each recording's chain head, file SHA-256 and signature, checked by the "
             "session's task (batch-report.json)", "seal-recording"),
        Fact("Decision rule", "per session: the ISO 14253-1 rule of its plan (its report.json)", "decision-rule"),
        Fact("Sessions", f"{doc['finished']} of {doc['inputs']} finished", "record-sessions"),
    ]
    return RecordHeader(
        title=title,
        subtitle=", ".join(f"{v}: {n}" for v, n in counts.items()),
        verdict="all PASS" if all_pass else ("INCOMPLETE" if not doc["complete"] else f"{counts['PASS']} PASS"),
        verdict_class="pass" if all_pass else ("open" if not doc["complete"] else "fail"),
        facts=tuple(facts),
    )
