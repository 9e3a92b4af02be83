"""The integrity chain of a session recording: written while recording, checked by audit.

Every record of the file's data section is folded, in file order, into a
running SHA-256 chain (``docs/recording.md``, "Integrity chain"): the
header, every schema and channel record, every message, every metadata
record and every attachment. Each record is one *entry* ``(label,
sequence, log_time, digest)``::

    h_0 = SHA256("crossfield-integrity/2")
    h_k = SHA256(h_{k-1} || u32 len(label) || label || u64 log_time || u32 sequence || digest_k)

(integers little-endian). For a message, ``label`` is its topic,
``sequence`` and ``log_time`` its own and ``digest = SHA256(data)``. For
the other records ``label`` names the record (``#header``, ``#schema
<name>``, ``#channel <topic>``, ``#metadata <name>``, ``#attachment
<name>``), ``sequence`` is the schema / channel id (else 0), ``log_time``
the attachment's log time (else 0), and ``digest`` the SHA-256 of the
canonical JSON of all its fields (data fields by their SHA-256): see
:func:`header_digest`, :func:`schema_digest`, :func:`channel_digest`,
:func:`metadata_digest`, :func:`attachment_digest`. So an edited channel
record (e.g. its ``bit_depth``), schema, metadata record or attachment
changes the chain exactly as an edited message does. The summary section
repeats the schemas and channels; the check requires them to equal the
data section's (a reader that seeks uses the summary's).

Whenever the recorder hands a chunk to the operating system (end of every
frame, session start, reference import, at least every ``flush_interval_s``)
it first writes a JSON record on the ``/integrity`` channel into that chunk:
the chain head ``h_k``, the entry count ``k``, the entries since the
previous record, and the SHA-256 of the previous ``/integrity`` record. A
last record with ``"final": true`` is written when the file is finished;
its chain head is the **chain head of the file**. The ``/integrity``
messages themselves are not entries (they carry the chain). A crash
therefore leaves every complete chunk covered up to its last record.

Checking (:func:`verify`) reads the file in file order without trusting
its CRCs, recomputes the chain and compares every entry with the one
recorded, so a changed, removed, added or reordered record is named (topic
or record name, sequence, time, byte offset). The records themselves are
authenticated by the chain (recomputed from their entries) and by the link
to their predecessor.

What this proves (docs/replay-and-audit.md, "What the audit proves"): the
file is self-consistent. Someone who edits the data and rewrites every
record with this code produces another self-consistent file with another
chain head; that is caught only by comparing the head with one kept
outside the file (``crossfield audit --expect-head``) or by a signature
(:mod:`crossfield.recording.seal`).
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
INTEGRITY_FORMAT = "crossfield-integrity/2"
GENESIS = hashlib.sha256(INTEGRITY_FORMAT.encode()).digest()

#: Entry labels of the records that are not messages.
HEADER_LABEL = "#header"
_SCHEMA = "#schema "
_CHANNEL = "#channel "
_METADATA = "#metadata "
_ATTACHMENT = "#attachment "

_U64_U32 = struct.Struct("<QI")

#: An entry: (label, sequence, log_time_ns, digest hex).
Entry = tuple[str, int, int, str]


def data_digest(data: bytes | memoryview) -> bytes:
    """SHA-256 of a message's data (32 bytes)."""
    return hashlib.sha256(data).digest()


def link(previous: bytes, label: str, log_time_ns: int, sequence: int, digest: bytes) -> bytes:
    """One step of the chain: h_k from h_{k-1} and the k-th entry (see module doc)."""
    t = label.encode("utf-8")
    h = hashlib.sha256(previous)
    h.update(len(t).to_bytes(4, "little"))
    h.update(t)
    h.update(_U64_U32.pack(int(log_time_ns) & 0xFFFFFFFFFFFFFFFF, int(sequence) & 0xFFFFFFFF))
    h.update(digest)
    return h.digest()


def _canonical(fields: Any) -> bytes:
    return hashlib.sha256(
        json.dumps(fields, ensure_ascii=False, separators=(",", ":"), sort_keys=True).encode("utf-8")
    ).digest()


def header_digest(profile: str, library: str) -> bytes:
    """Digest of the MCAP header: canonical JSON ``["header", profile, library]``."""
    return _canonical(["header", profile, library])


def schema_digest(schema_id: int, name: str, encoding: str, data: bytes) -> bytes:
    """Digest of a schema record: ``["schema", id, name, encoding, sha256(data)]``."""
    return _canonical(["schema", int(schema_id), name, encoding, hashlib.sha256(data).hexdigest()])


def channel_digest(
    channel_id: int, topic: str, message_encoding: str, schema_id: int, metadata: Mapping[str, str]
) -> bytes:
    """Digest of a channel record: ``["channel", id, topic, encoding, schema_id, {metadata}]``."""
    return _canonical(["channel", int(channel_id), topic, message_encoding, int(schema_id), dict(metadata)])


def metadata_digest(name: str, record: Mapping[str, str]) -> bytes:
    """Digest of a metadata record: ``["metadata", name, {key: value}]``."""
    return _canonical(["metadata", name, dict(record)])


def attachment_digest(name: str, media_type: str, log_time: int, create_time: int, data: bytes) -> bytes:
    """Digest of an attachment: ``["attachment", name, media_type, log_time, create_time, sha256(data)]``."""
    return _canonical(
        ["attachment", name, media_type, int(log_time), int(create_time), hashlib.sha256(data).hexdigest()]
    )


def header_entry(profile: str, library: str) -> Entry:
    return (HEADER_LABEL, 0, 0, header_digest(profile, library).hex())


def schema_entry(schema_id: int, name: str, encoding: str, data: bytes) -> Entry:
    return (_SCHEMA + name, int(schema_id), 0, schema_digest(schema_id, name, encoding, data).hex())


def channel_entry(
    channel_id: int, topic: str, message_encoding: str, schema_id: int, metadata: Mapping[str, str]
) -> Entry:
    digest = channel_digest(channel_id, topic, message_encoding, schema_id, metadata)
    return (_CHANNEL + topic, int(channel_id), 0, digest.hex())


def metadata_entry(name: str, record: Mapping[str, str]) -> Entry:
    return (_METADATA + name, 0, 0, metadata_digest(name, record).hex())


def attachment_entry(name: str, media_type: str, log_time: int, create_time: int, data: bytes) -> Entry:
    digest = attachment_digest(name, media_type, log_time, create_time, data)
    return (_ATTACHMENT + name, 0, int(log_time), digest.hex())


def message_entry(topic: str, sequence: int, log_time: int, data: bytes) -> Entry:
    return (topic, int(sequence) & 0xFFFFFFFF, int(log_time), data_digest(data).hex())


# --------------------------------------------------------------------------
# Writing side (used by the recorder's writer thread)
# --------------------------------------------------------------------------


class IntegrityChain:
    """The running chain while recording; :meth:`record` gives the next ``/integrity`` document.

    The writer calls ``add_*`` for every record in the order it lands in the
    file. head: the chain head so far (32 bytes); count: entries folded.
    """

    def __init__(self) -> None:
        self.head = GENESIS
        self.count = 0
        self.index = 0
        self.previous_record_sha256: str | None = None
        self.latest_time_ns = 0
        self._entries: list[list[Any]] = []

    def add(self, entry: Entry) -> None:
        label, sequence, log_time, digest = entry
        self.head = link(self.head, label, log_time, sequence, bytes.fromhex(digest))
        self.count += 1
        self._entries.append([label, sequence, log_time, digest])

    def add_message(self, topic: str, log_time_ns: int, sequence: int, data: bytes) -> None:
        self.add(message_entry(topic, sequence, log_time_ns, data))
        self.latest_time_ns = max(self.latest_time_ns, int(log_time_ns))

    def add_header(self, profile: str, library: str) -> None:
        self.add(header_entry(profile, library))

    def add_schema(self, schema_id: int, name: str, encoding: str, data: bytes) -> None:
        self.add(schema_entry(schema_id, name, encoding, data))

    def add_channel(
        self, channel_id: int, topic: str, message_encoding: str, schema_id: int, metadata: Mapping[str, str]
    ) -> None:
        self.add(channel_entry(channel_id, topic, message_encoding, schema_id, metadata))

    def add_metadata(self, name: str, record: Mapping[str, str]) -> None:
        self.add(metadata_entry(name, record))

    def add_attachment(self, name: str, media_type: str, log_time: int, create_time: int, data: bytes) -> None:
        self.add(attachment_entry(name, media_type, log_time, create_time, data))

    @property
    def pending(self) -> bool:
        """Something was written since the last record."""
        return bool(self._entries)

    def record(self, final: bool = False, extra: Mapping[str, Any] | None = None) -> bytes:
        """The next ``/integrity`` record (JSON bytes); resets the pending list.
        ``extra``: more keys (the final record's signature)."""
        doc = {
            "format": INTEGRITY_FORMAT,
            "index": self.index,
            "final": bool(final),
            "previous_record_sha256": self.previous_record_sha256,
            "count": self.count,
            "chain_sha256": self.head.hex(),
            "entries": self._entries,
            **dict(extra or {}),
        }
        data = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
        self.index += 1
        self.previous_record_sha256 = hashlib.sha256(data).hexdigest()
        self._entries = []
        return data


# --------------------------------------------------------------------------
# Checking side
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class FileEntry:
    """A record as found in the file (file order): its entry and where it is.

    offset: byte offset of the record, or of the chunk holding it.
    """

    label: str
    sequence: int
    log_time_ns: int
    digest: str  # hex
    data: bytes | None  # kept only for /integrity records
    offset: int | None

    @property
    def key(self) -> tuple[str, int, int]:
        return (self.label, self.sequence, self.log_time_ns)

    @property
    def is_message(self) -> bool:
        return not self.label.startswith("#")


# Old name, kept for readers of the earlier API.
FileMessage = FileEntry


@dataclass(frozen=True)
class Problem:
    """One integrity finding. kind: changed, removed, added, reordered, crc, unreadable,
    record, summary, uncovered, truncated, missing.

    topic: the message's topic or the record's label (``#channel /log``);
    offset: byte offset of the record or of the chunk holding it (None if unknown).
    """

    kind: str
    detail: str
    topic: str | None = None
    sequence: int | None = None
    log_time_ns: int | None = None
    offset: int | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "topic": self.topic,
            "sequence": self.sequence,
            "log_time_ns": self.log_time_ns,
            "offset": self.offset,
            "detail": self.detail,
        }

    def __str__(self) -> str:
        return self.detail


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
            "entries": self.entries,
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
    """'<topic> sequence 1 at 2026-...Z (1795... ns)'; for a record that is not a
    message: 'channel <topic> (id 3)', 'metadata record <name>', ..."""
    if topic.startswith("#"):
        kind, _, name = topic[1:].partition(" ")
        if kind in ("schema", "channel"):
            return f"{kind} {name} (id {sequence})"
        if kind == "metadata":
            return f"metadata record {name!r}"
        if kind == "attachment":
            return f"attachment {name!r}"
        return "the MCAP header"
    return f"{topic} sequence {sequence} at {utc(log_time_ns)} ({log_time_ns} ns)"


def _where(entry: FileEntry | None) -> str:
    return "" if entry is None or entry.offset is None else f" (byte {entry.offset})"


@dataclass
class _Scan:
    entries: list[FileEntry] = field(default_factory=list)  # /integrity messages excluded
    records: list[tuple[int, FileEntry]] = field(default_factory=list)  # (entries before it, record)
    summary_entries: dict[tuple[str, int], str] = field(default_factory=dict)  # (label, id) -> digest
    chunks: int = 0
    problems: list[Problem] = field(default_factory=list)
    complete: bool = False
    ends: str = ""

    @property
    def messages(self) -> int:
        return sum(1 for e in self.entries if e.is_message)


def _scan_file(path: Path) -> _Scan:
    """Read every record in file order, checking chunk CRCs ourselves so that a
    bad chunk is reported and its records still compared."""
    from mcap.exceptions import McapError
    from mcap.records import (
        Attachment,
        Channel,
        Chunk,
        DataEnd,
        Footer,
        Header,
        Message,
        Metadata,
        Schema,
    )
    from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

    scan = _Scan()
    channels: dict[int, str] = {}
    in_summary = False

    def take(record: Any, offset: int) -> None:
        if in_summary:
            if isinstance(record, Schema):
                e = schema_entry(record.id, record.name, record.encoding, record.data)
                scan.summary_entries[(e[0], e[1])] = e[3]
            elif isinstance(record, Channel):
                e = channel_entry(
                    record.id, record.topic, record.message_encoding, record.schema_id, record.metadata
                )
                scan.summary_entries[(e[0], e[1])] = e[3]
            elif isinstance(record, Footer):
                scan.complete = True
            return
        entry: Entry | None = None
        if isinstance(record, Header):
            entry = header_entry(record.profile, record.library)
        elif isinstance(record, Schema):
            entry = schema_entry(record.id, record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            channels[record.id] = record.topic
            entry = channel_entry(
                record.id, record.topic, record.message_encoding, record.schema_id, record.metadata
            )
        elif isinstance(record, Metadata):
            entry = metadata_entry(record.name, record.metadata)
        elif isinstance(record, Attachment):
            entry = attachment_entry(
                record.name, record.media_type, record.log_time, record.create_time, record.data
            )
        elif isinstance(record, Message):
            topic = channels.get(record.channel_id)
            if topic is None:
                scan.problems.append(
                    Problem(
                        "unreadable",
                        f"a message on unknown channel {record.channel_id} at {utc(record.log_time)} "
                        f"(byte {offset})",
                        None,
                        record.sequence,
                        record.log_time,
                        offset,
                    )
                )
                return
            if topic == TOPIC_INTEGRITY:
                digest = hashlib.sha256(record.data).hexdigest()
                fe = FileEntry(topic, record.sequence, record.log_time, digest, bytes(record.data), offset)
                scan.records.append((len(scan.entries), fe))
                return
            entry = message_entry(topic, record.sequence, record.log_time, record.data)
        if entry is not None:
            scan.entries.append(FileEntry(*entry, None, offset))

    size = path.stat().st_size
    damage = (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError, MemoryError)
    with open(path, "rb") as f:
        offset = 8
        at_start = True
        while True:
            reader = StreamReader(f, skip_magic=not at_start, emit_chunks=True, validate_crcs=False)
            at_start = False
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
                                    "unreadable",
                                    f"chunk at byte {offset}: its records cannot be read ({exc})",
                                    offset=offset,
                                )
                            )
                        bad_crc = record.uncompressed_crc != 0 and crc != record.uncompressed_crc
                        if records is not None:
                            first = len(scan.entries)
                            for r in records:
                                take(r, offset)
                            if bad_crc:
                                inside = [e for e in scan.entries[first:] if e.is_message]
                                what = ", ".join(name_message(*m.key) for m in inside[:4])
                                more = f" and {len(inside) - 4} more" if len(inside) > 4 else ""
                                scan.problems.append(
                                    Problem(
                                        "crc",
                                        f"chunk at byte {offset} has a bad CRC-32 "
                                        f"(stored {record.uncompressed_crc:08x}, "
                                        f"computed {crc:08x}); it holds {what or 'no message'}{more}",
                                        offset=offset,
                                    )
                                )
                        elif bad_crc:
                            scan.problems.append(
                                Problem("crc", f"chunk at byte {offset} has a bad CRC-32", offset=offset)
                            )
                    else:
                        take(record, offset)
                        if isinstance(record, DataEnd):
                            in_summary = True
                        elif isinstance(record, Footer):
                            scan.complete = True
                    offset = f.tell()
                break
            except damage as exc:
                reason = type(exc).__name__ + (f": {exc}" if str(exc) else "")
                resume = None if in_summary else _next_chunk(f, offset, size, get_chunk_data_stream)
                if resume is None:
                    scan.ends = f"the file ends in damage or is cut short at byte {offset} of {size} ({reason})"
                    break
                # Go on after the damage: the next intact chunk (its CRC-32 matches).
                scan.problems.append(
                    Problem(
                        "unreadable",
                        f"bytes {offset}..{resume} cannot be read as MCAP records ({reason}); "
                        f"reading goes on at the next intact chunk, byte {resume}",
                        offset=offset,
                    )
                )
                f.seek(resume)
                offset = resume
    return scan


def _next_chunk(f: Any, after: int, size: int, get_chunk_data_stream: Any, *, block: int = 1 << 22) -> int | None:
    """Byte offset of the next intact chunk record after ``after`` (opcode 0x06, a
    length inside the file and a matching CRC-32), or None."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk

    position = after + 1
    while position < size:
        f.seek(position)
        data = f.read(block + 9)
        if not data:
            return None
        at = data.find(b"\x06")
        while 0 <= at < min(len(data), block):
            start = position + at
            header = data[at : at + 9]
            if len(header) < 9:
                f.seek(start)
                header = f.read(9)
            length = int.from_bytes(header[1:9], "little") if len(header) == 9 else -1
            if 40 <= length <= size - start - 9:
                f.seek(start + 9)
                try:
                    chunk = Chunk.read(ReadDataStream(f))
                    if chunk.uncompressed_crc and zlib.crc32(_chunk_bytes(chunk, get_chunk_data_stream)) == (
                        chunk.uncompressed_crc
                    ):
                        return start
                except Exception:  # noqa: BLE001 - not a chunk here: look further
                    pass
            at = data.find(b"\x06", at + 1)
        position += block
    return None


def _chunk_bytes(chunk: Any, get_chunk_data_stream: Any) -> bytes:
    """The uncompressed records of a chunk (the bytes its CRC-32 covers)."""
    if chunk.compression == "":
        return chunk.data
    stream, length = get_chunk_data_stream(chunk, validate_crc=False)
    return stream.read(length)


def _record_doc(fe: FileEntry) -> dict[str, Any] | None:
    try:
        doc = json.loads(fe.data or b"")
    except ValueError:
        return None
    if not isinstance(doc, dict) or doc.get("format") != INTEGRITY_FORMAT:
        return None
    return doc


def _entry_key(entry: Any) -> Entry | None:
    if not (isinstance(entry, list) and len(entry) == 4):
        return None
    label, sequence, log_time, digest = entry
    if not (
        isinstance(label, str)
        and isinstance(sequence, int)
        and isinstance(log_time, int)
        and isinstance(digest, str)
        and len(digest) == 64
    ):
        return None
    try:
        bytes.fromhex(digest)
    except ValueError:
        return None
    return (label, sequence, log_time, digest)


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


def verify(path: str | Path) -> IntegrityResult:
    """Check the integrity chain of a session recording (see module doc).

    Never stops at damage: every damaged, removed, added or reordered
    record is a :class:`Problem`, and the check goes on with the rest.
    """
    path = Path(path)
    scan = _scan_file(path)
    result = IntegrityResult(
        str(path), messages=scan.messages, entries=len(scan.entries), chunks=scan.chunks, complete=scan.complete
    )
    problems = list(scan.problems)
    result.records = len(scan.records)
    head = GENESIS
    heads = [GENESIS]
    for m in scan.entries:
        head = link(head, m.label, m.log_time_ns, m.sequence, bytes.fromhex(m.digest))
        heads.append(head)
    result.chain_sha256 = head.hex()
    if not scan.records:
        result.has_chain = False
        problems.append(
            Problem(
                "missing",
                f"no {TOPIC_INTEGRITY} records in the {INTEGRITY_FORMAT} format: the file was recorded "
                f"without this integrity chain",
            )
        )
    listed_head = GENESIS
    listed_count = 0
    previous_sha: str | None = None
    previous_pos = 0
    segment_problems: list[Problem] = []
    for number, (pos, fm) in enumerate(scan.records):
        doc = _record_doc(fm)
        where = f"{TOPIC_INTEGRITY} record at {utc(fm.log_time_ns)} (byte {fm.offset})"
        if doc is None:
            problems.append(
                Problem(
                    "record",
                    f"{where}: not a readable {INTEGRITY_FORMAT} record",
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
        for e in doc.get("entries", []) if isinstance(doc.get("entries"), list) else [None]:
            key = _entry_key(e)
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
            listed_head = link(listed_head, label, log_time, sequence, bytes.fromhex(digest))
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
        _diff_segment(entries, scan.entries[previous_pos:pos], segment_problems)
        previous_pos = pos
        if heads[pos].hex() == doc.get("chain_sha256") and pos == doc.get("count"):
            result.covered = pos
        result.recorded_chain_sha256 = doc.get("chain_sha256")
        if doc.get("final"):
            result.final_record = True
            result.final_record_doc = doc
            if number != len(scan.records) - 1:
                problems.append(
                    Problem("record", f"{where} is marked final but more records follow it", offset=fm.offset)
                )
    problems.extend(_merge_moves(segment_problems))
    tail = scan.entries[previous_pos:]
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


def file_sha256(path: str | Path, *, block: int = 1 << 22) -> str:
    """SHA-256 (hex) of a whole file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()
