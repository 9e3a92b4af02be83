"""The integrity check of a recording (:func:`verify`): the chain recomputed from the
file's records and compared, entry by entry, with the one recorded in its
``/integrity`` records (docs/recording.md, "Integrity chain"; the chain itself:
:mod:`crossfield.recording.integrity`, the file scanner: :mod:`crossfield.recording.scan`).

A changed, removed, added or reordered record is a :class:`Problem` named by topic or
record name, sequence, time and byte offset; :class:`IntegrityResult` holds them, the
chain heads and where a cut-short file ends."""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from crossfield.recording.codec import utc_text
from crossfield.recording.integrity import (
    CHAIN_FORMATS,
    FORMATS,
    HEADER_LABEL,
    INTEGRITY_FORMAT,
    INTEGRITY_FORMAT_1,
    Entry,
    link,
)
from crossfield.recording.layout import TOPIC_INTEGRITY
from crossfield.recording.scan import FileEntry, Problem, entry_key, name_message, record_doc, scan_file


@dataclass
class IntegrityResult:
    """What :func:`verify` found.

    passed: every record is covered by an intact chain and matches it, the
    file is complete and ends with a final record. messages: messages read
    (``/integrity`` excluded); entries: all records folded (messages,
    header, schemas, channels, metadata, attachments); covered: how many
    entries the last valid record covers. chain_sha256: the chain head
    recomputed over every entry read (for a complete, intact file: the
    final record's head, the file's chain head). final_record_doc: the
    final ``/integrity`` record (its signature, if signed).
    """

    path: str
    messages: int = 0
    entries: int = 0
    records: int = 0
    covered: int = 0
    chunks: int = 0
    complete: bool = False
    final_record: bool = False
    chain_sha256: str = ""
    recorded_chain_sha256: str | None = None
    ends: str = ""
    problems: list[Problem] = field(default_factory=list)
    has_chain: bool = True
    final_record_doc: dict[str, Any] | None = None
    #: The chain layout of the file's records and what it covers ("every record";
    #: format 1: "messages only", the header, schemas, channels, metadata and
    #: attachments are not checked).
    chain_format: str = INTEGRITY_FORMAT
    covers: str = "every record"

    @property
    def coverage_note(self) -> str:
        """One line saying what the chain covers, when it is not every record ('' else)."""
        if self.chain_format != INTEGRITY_FORMAT_1:
            return ""
        return (
            "chain format 1: covers messages only (the header, schemas, channels, metadata "
            "and attachments are not checked)"
        )

    @property
    def passed(self) -> bool:
        return self.has_chain and self.complete and self.final_record and not self.problems

    def chained_text(self, topic: str = TOPIC_INTEGRITY) -> str:
        """What the chain folded, in words: every record, or (format 1) the messages only."""
        if self.chain_format == INTEGRITY_FORMAT_1:
            return f"{self.messages} messages chained in {self.records} {topic} records (chain format 1)"
        return (
            f"{self.messages} messages and {self.entries - self.messages} other records chained "
            f"in {self.records} {topic} records"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "passed": self.passed,
            "has_chain": self.has_chain,
            "chain_format": self.chain_format,
            "covers": self.covers,
            "complete": self.complete,
            "final_record": self.final_record,
            "messages": self.messages,
            "entries": self.entries,
            "covered": self.covered,
            "records": self.records,
            "chunks": self.chunks,
            "chain_sha256": self.chain_sha256,
            "recorded_chain_sha256": self.recorded_chain_sha256,
            "ends": self.ends,
            "problems": [p.to_json() for p in self.problems],
        }


def _where(entry: FileEntry | None) -> str:
    return "" if entry is None or entry.offset is None else f" (byte {entry.offset})"


def _diff_segment(listed: list[Entry], found: list[FileEntry], out: list[Problem]) -> None:
    """Name every difference between the entries a record lists and the records found."""
    a = [e[:3] for e in listed]
    b = [m.key for m in found]
    matcher = difflib.SequenceMatcher(a=a, b=b, autojunk=False)
    for op, i1, i2, j1, j2 in matcher.get_opcodes():
        if op == "equal":
            for e, m in zip(listed[i1:i2], found[j1:j2]):
                if e[3] != m.digest:
                    what = "its data differs" if m.is_message else "its content differs"
                    out.append(
                        Problem(
                            "changed",
                            f"changed: {name_message(*e[:3])}{_where(m)}: {what} from the recorded digest",
                            *e[:3],
                            m.offset,
                        )
                    )
            continue
        for e in listed[i1:i2]:
            anchor = found[j1] if j1 < len(found) else (found[-1] if found else None)
            out.append(
                Problem(
                    "removed",
                    f"removed: {name_message(*e[:3])}{_where(anchor)}",
                    *e[:3],
                    None if anchor is None else anchor.offset,
                )
            )
        for m in found[j1:j2]:
            out.append(
                Problem(
                    "added", f"added: {name_message(*m.key)}{_where(m)} is not in the chain", *m.key, m.offset
                )
            )


def _merge_moves(problems: list[Problem]) -> list[Problem]:
    """A record 'removed' at one place and 'added' at another is 'reordered'."""
    removed = {(p.topic, p.sequence, p.log_time_ns): p for p in problems if p.kind == "removed"}
    added = {(p.topic, p.sequence, p.log_time_ns): p for p in problems if p.kind == "added"}
    moved = set(removed) & set(added)
    out = []
    for p in problems:
        key = (p.topic, p.sequence, p.log_time_ns)
        if key in moved:
            if p.kind == "added":
                out.append(
                    Problem(
                        "reordered",
                        f"reordered: {name_message(*key)} (byte {p.offset}) is not where it was written",
                        *key,
                        p.offset,
                    )
                )
            continue
        out.append(p)
    return out


def detect_format(records: list[tuple[int, FileEntry]], default: str = INTEGRITY_FORMAT) -> str:
    """The chain format of the first ``/integrity`` record that names a known one
    (:data:`crossfield.recording.integrity.CHAIN_FORMATS`); ``default`` if none does."""
    for _, fe in records:
        for chain_format in CHAIN_FORMATS:
            if record_doc(fe, chain_format) is not None:
                return chain_format
    return default


def chained(
    entries: list[FileEntry], records: list[tuple[int, FileEntry]], chain_format: str
) -> tuple[list[FileEntry], list[tuple[int, FileEntry]]]:
    """The entries ``chain_format`` folds (format 1: messages only) and the records with
    their positions counted in those entries."""
    if chain_format != INTEGRITY_FORMAT_1:
        return entries, records
    before = [0]
    for e in entries:
        before.append(before[-1] + (1 if e.is_message else 0))
    return [e for e in entries if e.is_message], [(before[pos], fe) for pos, fe in records]


def verify(path: str | Path) -> IntegrityResult:
    """Check the integrity chain of a session recording (see module doc).

    Never stops at damage: every damaged, removed, added or reordered
    record is a :class:`Problem`, and the check goes on with the rest.
    """
    path = Path(path)
    scan = scan_file(path)  # digests in the hash of the format the MCAP header names
    chain_format = detect_format(scan.records, scan.chain_format)
    header_mismatch = None
    if FORMATS[chain_format].hash is not FORMATS[scan.chain_format].hash:
        # The header names another format than the records (an edited or damaged
        # header): the records decide, the file is read again with their hash.
        header_mismatch = Problem(
            "changed",
            f"changed: the MCAP header names chain format {scan.chain_format}, its {TOPIC_INTEGRITY} "
            f"records are in {chain_format}",
            HEADER_LABEL,
            0,
            0,
        )
        scan = scan_file(path, chain_format)
    result = IntegrityResult(
        str(path), messages=scan.messages, entries=len(scan.entries), chunks=scan.chunks, complete=scan.complete
    )
    problems = list(scan.problems) + ([header_mismatch] if header_mismatch else [])
    result.records = len(scan.records)
    genesis, listing, covers = CHAIN_FORMATS[chain_format]
    result.chain_format, result.covers = chain_format, covers
    entries_chained, records = chained(scan.entries, scan.records, chain_format)
    head = genesis
    heads = [genesis]
    for m in entries_chained:
        head = link(head, m.label, m.log_time_ns, m.sequence, bytes.fromhex(m.digest), chain_format)
        heads.append(head)
    result.chain_sha256 = head.hex()
    if not scan.records:
        result.has_chain = False
        problems.append(
            Problem(
                "missing",
                f"no {TOPIC_INTEGRITY} records in a known chain format: the file was recorded "
                f"without this integrity chain",
            )
        )
    listed_head = genesis
    listed_count = 0
    previous_sha: str | None = None
    previous_pos = 0
    segment_problems: list[Problem] = []
    for number, (pos, fm) in enumerate(records):
        doc = record_doc(fm, chain_format)
        where = f"{TOPIC_INTEGRITY} record at {utc_text(fm.log_time_ns)} (byte {fm.offset})"
        if doc is None:
            problems.append(
                Problem(
                    "record",
                    f"{where}: not a readable {chain_format} record",
                    fm.label,
                    fm.sequence,
                    fm.log_time_ns,
                    fm.offset,
                )
            )
            continue
        index = doc.get("index")
        where = f"{TOPIC_INTEGRITY} record #{index} (byte {fm.offset})"
        if index != number:
            problems.append(
                Problem(
                    "record",
                    f"{where} found where #{number} was expected: a record is missing or out of order",
                    fm.label,
                    fm.sequence,
                    fm.log_time_ns,
                    fm.offset,
                )
            )
        if doc.get("previous_record_sha256") != previous_sha:
            problems.append(
                Problem(
                    "record",
                    f"{where} does not link to the record before it (removed, added or edited record)",
                    fm.label,
                    fm.sequence,
                    fm.log_time_ns,
                    fm.offset,
                )
            )
        previous_sha = fm.digest
        entries: list[Entry] = []
        bad_entry = False
        for e in doc.get(listing, []) if isinstance(doc.get(listing), list) else [None]:
            key = entry_key(e)
            if key is None:
                bad_entry = True
                break
            entries.append(key)
        if bad_entry:
            problems.append(
                Problem(
                    "record", f"{where}: malformed entry", fm.label, fm.sequence, fm.log_time_ns, fm.offset
                )
            )
            continue
        # The record's own listing must reproduce its chain head (authenticates the listing).
        for label, sequence, log_time, digest in entries:
            listed_head = link(listed_head, label, log_time, sequence, bytes.fromhex(digest), chain_format)
        listed_count += len(entries)
        if listed_head.hex() != doc.get("chain_sha256") or listed_count != doc.get("count"):
            problems.append(
                Problem(
                    "record",
                    f"{where}: its entry list does not reproduce its chain head "
                    f"(the record or an earlier one was edited)",
                    fm.label,
                    fm.sequence,
                    fm.log_time_ns,
                    fm.offset,
                )
            )
            try:
                listed_head = bytes.fromhex(doc["chain_sha256"])
            except (KeyError, TypeError, ValueError):
                pass
            listed_count = doc["count"] if isinstance(doc.get("count"), int) else listed_count
        _diff_segment(entries, entries_chained[previous_pos:pos], segment_problems)
        previous_pos = pos
        if heads[pos].hex() == doc.get("chain_sha256") and pos == doc.get("count"):
            result.covered = pos
        result.recorded_chain_sha256 = doc.get("chain_sha256")
        if doc.get("final"):
            result.final_record = True
            result.final_record_doc = doc
            if number != len(records) - 1:
                problems.append(
                    Problem("record", f"{where} is marked final but more records follow it", offset=fm.offset)
                )
    problems.extend(_merge_moves(segment_problems))
    tail = entries_chained[previous_pos:]
    if tail and scan.records:
        if result.final_record:
            for m in tail:
                problems.append(
                    Problem(
                        "added",
                        f"added: {name_message(*m.key)}{_where(m)} after the final record",
                        *m.key,
                        m.offset,
                    )
                )
        else:
            first, last = tail[0], tail[-1]
            problems.append(
                Problem(
                    "uncovered",
                    f"{len(tail)} record(s) after the last {TOPIC_INTEGRITY} record are not covered by the "
                    f"chain (from {name_message(*first.key)}{_where(first)} to "
                    f"{name_message(*last.key)}{_where(last)}): the recording was cut short",
                    offset=first.offset,
                )
            )
    # The summary repeats the schemas and channels; a seeking reader uses those.
    data_section = {(e.label, e.sequence): e.digest for e in scan.entries if e.label.startswith(("#schema", "#channel"))}
    for (label, ident), digest in scan.summary_entries.items():
        if data_section.get((label, ident)) != digest:
            problems.append(
                Problem(
                    "summary",
                    f"changed: the summary's {name_message(label, ident, 0)} differs from the data section's",
                    label,
                    ident,
                    0,
                )
            )
    if scan.records and not result.final_record and scan.complete:
        problems.append(Problem("record", f"the file was finished but has no final {TOPIC_INTEGRITY} record"))
    if not scan.complete:
        last = next((e for e in reversed(scan.entries) if e.is_message), None)
        where = f"; the last message read is {name_message(*last.key)}{_where(last)}" if last else ""
        result.ends = (scan.ends or "the file has no footer: it was not finished") + where
        problems.append(Problem("truncated", f"incomplete recording: {result.ends}"))
    else:
        result.ends = "complete (footer read)"
    result.problems = problems
    return result
