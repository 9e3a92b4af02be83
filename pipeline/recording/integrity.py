"""The integrity chain of a session recording: written while recording, checked by audit.

Every message is folded, in the order it is written, into a running
SHA-256 chain (``docs/recording.md``, "Integrity chain")::

    h_0 = SHA256("crossfield-integrity/1")
    h_k = SHA256(h_{k-1} || u32 len(topic) || topic || u64 log_time || u32 sequence || SHA256(data))

(integers little-endian; ``sequence`` is the MCAP message sequence, 32 bits).
Whenever the recorder hands a chunk to the operating system (end of every
frame, session start, reference import, at least every ``flush_interval_s``)
it first writes a JSON record on the ``/integrity`` channel into that chunk:
the chain head ``h_k``, the message count ``k``, one entry ``[topic,
sequence, log_time_ns, sha256(data)]`` per message since the previous
record, the digests of the metadata records and attachments written since
then, and the SHA-256 of the previous ``/integrity`` record. A last record
with ``"final": true`` is written when the file is finished. A crash
therefore leaves every complete chunk covered up to its last record.

Checking (:func:`verify`) reads the file in file order without trusting
its CRCs, recomputes the chain and compares every message with its entry,
so a changed, removed, added or reordered message is named by topic,
sequence and time. The records themselves are authenticated by the chain
(recomputed from their entries) and by the link to their predecessor. The
chain detects accidental and casual changes; someone who rewrites every
record after editing the data is not stopped by it (keep the final chain
head, which ``crossfield audit`` prints, outside the file to guard against
that).
"""

from __future__ import annotations

import difflib
import hashlib
import json
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from crossfield.recording.layout import TOPIC_INTEGRITY

#: Identifies this chain layout; written into every ``/integrity`` record.
INTEGRITY_FORMAT = "crossfield-integrity/1"
GENESIS = hashlib.sha256(INTEGRITY_FORMAT.encode()).digest()

_U64_U32 = struct.Struct("<QI")


def data_digest(data: bytes | memoryview) -> bytes:
    """SHA-256 of a message's data (32 bytes)."""
    return hashlib.sha256(data).digest()


def link(previous: bytes, topic: str, log_time_ns: int, sequence: int, digest: bytes) -> bytes:
    """One step of the chain: h_k from h_{k-1} and the k-th message (see module doc)."""
    t = topic.encode("utf-8")
    h = hashlib.sha256(previous)
    h.update(len(t).to_bytes(4, "little"))
    h.update(t)
    h.update(_U64_U32.pack(int(log_time_ns) & 0xFFFFFFFFFFFFFFFF, int(sequence) & 0xFFFFFFFF))
    h.update(digest)
    return h.digest()


def metadata_digest(name: str, record: Mapping[str, str]) -> str:
    """SHA-256 (hex) of a metadata record: canonical JSON of ``[name, {key: value}]``."""
    text = json.dumps([name, dict(sorted(record.items()))], ensure_ascii=False, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def attachment_digest(name: str, media_type: str, data: bytes) -> str:
    """SHA-256 (hex) of an attachment: its name, media type and data."""
    h = hashlib.sha256(json.dumps([name, media_type], ensure_ascii=False).encode("utf-8"))
    h.update(hashlib.sha256(data).digest())
    return h.hexdigest()


# --------------------------------------------------------------------------
# Writing side (used by the recorder's writer thread)
# --------------------------------------------------------------------------


class IntegrityChain:
    """The running chain while recording; :meth:`record` gives the next ``/integrity`` document."""

    def __init__(self) -> None:
        self.head = GENESIS
        self.count = 0
        self.index = 0
        self.previous_record_sha256: str | None = None
        self.latest_time_ns = 0
        self._messages: list[list[Any]] = []
        self._metadata: list[dict[str, str]] = []
        self._attachments: list[dict[str, str]] = []

    def add_message(self, topic: str, log_time_ns: int, sequence: int, data: bytes) -> None:
        digest = data_digest(data)
        sequence = int(sequence) & 0xFFFFFFFF
        self.head = link(self.head, topic, log_time_ns, sequence, digest)
        self.count += 1
        self.latest_time_ns = max(self.latest_time_ns, int(log_time_ns))
        self._messages.append([topic, sequence, int(log_time_ns), digest.hex()])

    def add_metadata(self, name: str, record: Mapping[str, str]) -> None:
        self._metadata.append({"name": name, "sha256": metadata_digest(name, record)})

    def add_attachment(self, name: str, media_type: str, data: bytes) -> None:
        self._attachments.append(
            {"name": name, "media_type": media_type, "sha256": attachment_digest(name, media_type, data)}
        )

    @property
    def pending(self) -> bool:
        """Something was written since the last record."""
        return bool(self._messages or self._metadata or self._attachments)

    def record(self, final: bool = False) -> bytes:
        """The next ``/integrity`` record (JSON bytes); resets the pending lists."""
        doc = {
            "format": INTEGRITY_FORMAT,
            "index": self.index,
            "final": bool(final),
            "previous_record_sha256": self.previous_record_sha256,
            "count": self.count,
            "chain_sha256": self.head.hex(),
            "messages": self._messages,
            "metadata": self._metadata,
            "attachments": self._attachments,
        }
        data = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
        self.index += 1
        self.previous_record_sha256 = hashlib.sha256(data).hexdigest()
        self._messages, self._metadata, self._attachments = [], [], []
        return data


# --------------------------------------------------------------------------
# Checking side
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class FileMessage:
    """A message as found in the file (file order)."""

    topic: str
    sequence: int
    log_time_ns: int
    digest: str  # hex SHA-256 of the data
    data: bytes | None  # kept only for /integrity records
    chunk_offset: int | None  # byte offset of the chunk holding it (None: not in a chunk)

    @property
    def key(self) -> tuple[str, int, int]:
        return (self.topic, self.sequence, self.log_time_ns)


@dataclass(frozen=True)
class Problem:
    """One integrity finding. kind: changed, removed, added, reordered, crc, unreadable,
    record, metadata, attachment, uncovered, truncated, missing."""

    kind: str
    detail: str
    topic: str | None = None
    sequence: int | None = None
    log_time_ns: int | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "topic": self.topic,
            "sequence": self.sequence,
            "log_time_ns": self.log_time_ns,
            "detail": self.detail,
        }

    def __str__(self) -> str:
        return self.detail


@dataclass
class IntegrityResult:
    """What :func:`verify` found.

    passed: every message, metadata record and attachment is covered by an
    intact chain and matches it, the file is complete and ends with a final
    record. messages: messages read (``/integrity`` excluded); covered: how
    many of them the last valid record covers. chain_sha256: the chain head
    recomputed over every message read.
    """

    path: str
    messages: int = 0
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

    @property
    def passed(self) -> bool:
        return self.has_chain and self.complete and self.final_record and not self.problems

    def to_json(self) -> dict[str, Any]:
        return {
            "passed": self.passed,
            "has_chain": self.has_chain,
            "complete": self.complete,
            "final_record": self.final_record,
            "messages": self.messages,
            "covered": self.covered,
            "records": self.records,
            "chunks": self.chunks,
            "chain_sha256": self.chain_sha256,
            "recorded_chain_sha256": self.recorded_chain_sha256,
            "ends": self.ends,
            "problems": [p.to_json() for p in self.problems],
        }


def utc(timestamp_ns: int) -> str:
    """ISO 8601 UTC text of a time in ns since the Unix epoch (to the ns)."""
    import datetime as _dt

    seconds, nanos = divmod(int(timestamp_ns), 1_000_000_000)
    moment = _dt.datetime.fromtimestamp(seconds, tz=_dt.UTC)
    return moment.strftime("%Y-%m-%dT%H:%M:%S") + f".{nanos:09d}Z"


def name_message(topic: str, sequence: int, log_time_ns: int) -> str:
    """'<topic> sequence 1 at 2026-...Z (1795... ns)'."""
    return f"{topic} sequence {sequence} at {utc(log_time_ns)} ({log_time_ns} ns)"


@dataclass
class _Scan:
    messages: list[FileMessage] = field(default_factory=list)  # /integrity excluded
    records: list[tuple[int, FileMessage]] = field(default_factory=list)  # (messages before it, record)
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    attachments: list[tuple[str, str, bytes]] = field(default_factory=list)
    chunks: int = 0
    problems: list[Problem] = field(default_factory=list)
    complete: bool = False
    ends: str = ""


def _scan_file(path: Path) -> _Scan:
    """Read every record in file order, checking chunk CRCs ourselves so that a
    bad chunk is reported and its messages still compared."""
    from mcap.exceptions import McapError
    from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata
    from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

    scan = _Scan()
    channels: dict[int, str] = {}

    def take(record: Any, chunk_offset: int | None) -> None:
        if isinstance(record, Channel):
            channels[record.id] = record.topic
        elif isinstance(record, Message):
            topic = channels.get(record.channel_id)
            if topic is None:
                scan.problems.append(
                    Problem(
                        "unreadable",
                        f"a message on unknown channel {record.channel_id} at {utc(record.log_time)}",
                        None,
                        record.sequence,
                        record.log_time,
                    )
                )
                return
            digest = hashlib.sha256(record.data).hexdigest()
            if topic == TOPIC_INTEGRITY:
                fm = FileMessage(
                    topic, record.sequence, record.log_time, digest, bytes(record.data), chunk_offset
                )
                scan.records.append((len(scan.messages), fm))
            else:
                scan.messages.append(
                    FileMessage(topic, record.sequence, record.log_time, digest, None, chunk_offset)
                )

    with open(path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True, validate_crcs=False)
        offset = 8
        try:
            for record in reader.records:
                if isinstance(record, Chunk):
                    scan.chunks += 1
                    crc = zlib.crc32(_chunk_bytes(record, get_chunk_data_stream))
                    records = None
                    try:
                        records = breakup_chunk(record, validate_crc=False)
                    except Exception as exc:  # noqa: BLE001 - a damaged chunk is a finding
                        scan.problems.append(
                            Problem(
                                "unreadable", f"chunk at byte {offset}: its records cannot be read ({exc})"
                            )
                        )
                    bad_crc = record.uncompressed_crc != 0 and crc != record.uncompressed_crc
                    if records is not None:
                        first = len(scan.messages)
                        for r in records:
                            take(r, offset)
                        if bad_crc:
                            inside = scan.messages[first:]
                            what = ", ".join(
                                name_message(m.topic, m.sequence, m.log_time_ns) for m in inside[:4]
                            )
                            more = f" and {len(inside) - 4} more" if len(inside) > 4 else ""
                            scan.problems.append(
                                Problem(
                                    "crc",
                                    f"chunk at byte {offset} has a bad CRC-32 "
                                    f"(stored {record.uncompressed_crc:08x}, "
                                    f"computed {crc:08x}); it holds {what or 'no message'}{more}",
                                )
                            )
                    elif bad_crc:
                        scan.problems.append(Problem("crc", f"chunk at byte {offset} has a bad CRC-32"))
                else:
                    take(record, None)
                    if isinstance(record, Metadata):
                        scan.metadata.append((record.name, dict(record.metadata)))
                    elif isinstance(record, Attachment):
                        scan.attachments.append((record.name, record.media_type, bytes(record.data)))
                    elif isinstance(record, Footer):
                        scan.complete = True
                offset = f.tell()
        except (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError, MemoryError) as exc:
            size = path.stat().st_size
            reason = type(exc).__name__ + (f": {exc}" if str(exc) else "")
            scan.ends = f"the file ends in damage or is cut short at byte {offset} of {size} ({reason})"
    return scan


def _chunk_bytes(chunk: Any, get_chunk_data_stream: Any) -> bytes:
    """The uncompressed records of a chunk (the bytes its CRC-32 covers)."""
    if chunk.compression == "":
        return chunk.data
    stream, length = get_chunk_data_stream(chunk, validate_crc=False)
    return stream.read(length)


def _record_doc(fm: FileMessage) -> dict[str, Any] | None:
    try:
        doc = json.loads(fm.data or b"")
    except ValueError:
        return None
    if not isinstance(doc, dict) or doc.get("format") != INTEGRITY_FORMAT:
        return None
    return doc


def _entry_key(entry: Any) -> tuple[str, int, int, str] | None:
    if not (isinstance(entry, list) and len(entry) == 4):
        return None
    topic, sequence, log_time, digest = entry
    if not (
        isinstance(topic, str)
        and isinstance(sequence, int)
        and isinstance(log_time, int)
        and isinstance(digest, str)
    ):
        return None
    return (topic, sequence, log_time, digest)


def _diff_segment(
    listed: list[tuple[str, int, int, str]], found: list[FileMessage], out: list[Problem]
) -> None:
    """Name every difference between the messages a record lists and those found."""
    a = [e[:3] for e in listed]
    b = [m.key for m in found]
    matcher = difflib.SequenceMatcher(a=a, b=b, autojunk=False)
    for op, i1, i2, j1, j2 in matcher.get_opcodes():
        if op == "equal":
            for e, m in zip(listed[i1:i2], found[j1:j2]):
                if e[3] != m.digest:
                    out.append(
                        Problem(
                            "changed",
                            f"changed: {name_message(*e[:3])}: its data differs from the recorded digest",
                            *e[:3],
                        )
                    )
            continue
        for e in listed[i1:i2]:
            out.append(Problem("removed", f"removed: {name_message(*e[:3])}", *e[:3]))
        for m in found[j1:j2]:
            out.append(Problem("added", f"added: {name_message(*m.key)} is not in the chain", *m.key))


def _merge_moves(problems: list[Problem]) -> list[Problem]:
    """A message 'removed' at one place and 'added' at another is 'reordered'."""
    removed = {(p.topic, p.sequence, p.log_time_ns): p for p in problems if p.kind == "removed"}
    added = {(p.topic, p.sequence, p.log_time_ns): p for p in problems if p.kind == "added"}
    moved = set(removed) & set(added)
    out = []
    for p in problems:
        key = (p.topic, p.sequence, p.log_time_ns)
        if key in moved:
            if p.kind == "removed":
                out.append(
                    Problem("reordered", f"reordered: {name_message(*key)} is not where it was written", *key)
                )
            continue
        out.append(p)
    return out


def verify(path: str | Path) -> IntegrityResult:
    """Check the integrity chain of a session recording (see module doc)."""
    path = Path(path)
    scan = _scan_file(path)
    result = IntegrityResult(
        str(path), messages=len(scan.messages), chunks=scan.chunks, complete=scan.complete
    )
    problems = list(scan.problems)
    result.records = len(scan.records)
    head = GENESIS
    heads = [GENESIS]
    for m in scan.messages:
        head = link(head, m.topic, m.log_time_ns, m.sequence, bytes.fromhex(m.digest))
        heads.append(head)
    result.chain_sha256 = head.hex()
    if not scan.records:
        result.has_chain = False
        problems.append(
            Problem("missing", "no /integrity records: the file was recorded without the integrity chain")
        )
    listed_head = GENESIS
    listed_count = 0
    previous_sha: str | None = None
    previous_pos = 0
    listed_metadata: dict[str, list[str]] = {}
    listed_attachments: dict[str, list[str]] = {}
    segment_problems: list[Problem] = []
    for number, (pos, fm) in enumerate(scan.records):
        doc = _record_doc(fm)
        where = f"{TOPIC_INTEGRITY} record at {utc(fm.log_time_ns)}"
        if doc is None:
            problems.append(
                Problem(
                    "record",
                    f"{where}: not a readable {INTEGRITY_FORMAT} record",
                    fm.topic,
                    fm.sequence,
                    fm.log_time_ns,
                )
            )
            continue
        index = doc.get("index")
        where = f"{TOPIC_INTEGRITY} record #{index}"
        if index != number:
            problems.append(
                Problem(
                    "record",
                    f"{where} found where #{number} was expected: a record is missing or out of order",
                    fm.topic,
                    fm.sequence,
                    fm.log_time_ns,
                )
            )
        if doc.get("previous_record_sha256") != previous_sha:
            problems.append(
                Problem(
                    "record",
                    f"{where} does not link to the record before it (removed, added or edited record)",
                    fm.topic,
                    fm.sequence,
                    fm.log_time_ns,
                )
            )
        previous_sha = fm.digest
        entries = []
        bad_entry = False
        for e in doc.get("messages", []):
            key = _entry_key(e)
            if key is None:
                bad_entry = True
                break
            entries.append(key)
        if bad_entry:
            problems.append(
                Problem("record", f"{where}: malformed message entry", fm.topic, fm.sequence, fm.log_time_ns)
            )
            continue
        # The record's own listing must reproduce its chain head (authenticates the listing).
        for topic, sequence, log_time, digest in entries:
            listed_head = link(listed_head, topic, log_time, sequence, bytes.fromhex(digest))
        listed_count += len(entries)
        if listed_head.hex() != doc.get("chain_sha256") or listed_count != doc.get("count"):
            problems.append(
                Problem(
                    "record",
                    f"{where}: its message list does not reproduce its chain head "
                    f"(the record or an earlier one was edited)",
                    fm.topic,
                    fm.sequence,
                    fm.log_time_ns,
                )
            )
            listed_head = (
                bytes.fromhex(doc["chain_sha256"])
                if isinstance(doc.get("chain_sha256"), str)
                else listed_head
            )
            listed_count = (
                doc.get("count", listed_count) if isinstance(doc.get("count"), int) else listed_count
            )
        _diff_segment(entries, scan.messages[previous_pos:pos], segment_problems)
        previous_pos = pos
        for m in doc.get("metadata", []):
            listed_metadata.setdefault(str(m.get("name")), []).append(str(m.get("sha256")))
        for a in doc.get("attachments", []):
            listed_attachments.setdefault(str(a.get("name")), []).append(str(a.get("sha256")))
        if heads[pos].hex() == doc.get("chain_sha256") and pos == doc.get("count"):
            result.covered = pos
        result.recorded_chain_sha256 = doc.get("chain_sha256")
        if doc.get("final"):
            result.final_record = True
            if number != len(scan.records) - 1:
                problems.append(Problem("record", f"{where} is marked final but more records follow it"))
    problems.extend(_merge_moves(segment_problems))
    tail = scan.messages[previous_pos:]
    if tail and scan.records:
        if result.final_record:
            for m in tail:
                problems.append(
                    Problem("added", f"added: {name_message(*m.key)} after the final record", *m.key)
                )
        else:
            first, last = tail[0], tail[-1]
            problems.append(
                Problem(
                    "uncovered",
                    f"{len(tail)} message(s) after the last /integrity record are not covered by the chain "
                    f"(from {name_message(*first.key)} to {name_message(*last.key)}): "
                    f"the recording was cut short",
                )
            )
    # Metadata and attachments: every one found must be listed, every listed one found.
    _check_named(
        "metadata",
        [(n, metadata_digest(n, r)) for n, r in scan.metadata],
        listed_metadata,
        result.final_record,
        problems,
    )
    _check_named(
        "attachment",
        [(n, attachment_digest(n, t, d)) for n, t, d in scan.attachments],
        listed_attachments,
        result.final_record,
        problems,
    )
    if scan.records and not result.final_record and scan.complete:
        problems.append(Problem("record", "the file was finished but has no final /integrity record"))
    if not scan.complete:
        last = scan.messages[-1] if scan.messages else None
        where = f"; the last message read is {name_message(*last.key)}" if last else ""
        result.ends = (scan.ends or "the file has no footer: it was not finished") + where
        problems.append(Problem("truncated", f"incomplete recording: {result.ends}"))
    else:
        result.ends = "complete (footer read)"
    result.problems = problems
    return result


def _check_named(
    kind: str,
    found: list[tuple[str, str]],
    listed: dict[str, list[str]],
    final: bool,
    problems: list[Problem],
) -> None:
    remaining = {name: list(digests) for name, digests in listed.items()}
    for name, digest in found:
        digests = remaining.get(name)
        if digests and digest in digests:
            digests.remove(digest)
        elif digests:
            digests.pop(0)
            problems.append(Problem(kind, f"changed: {kind} {name!r} differs from its recorded digest"))
        elif final:
            problems.append(Problem(kind, f"added: {kind} {name!r} is not in the chain"))
        else:
            problems.append(
                Problem(
                    "uncovered",
                    f"{kind} {name!r} is not covered by the chain (written after the last record)",
                )
            )
    for name, digests in remaining.items():
        for _ in digests:
            problems.append(
                Problem(kind, f"removed: {kind} {name!r} is listed in the chain but not in the file")
            )


def file_sha256(path: str | Path, *, block: int = 1 << 22) -> str:
    """SHA-256 (hex) of a whole file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()
