"""Reading an MCAP file's records in file order without trusting it: the scanner the
integrity check (:func:`crossfield.audit.chain.verify`) recomputes the chain from.

:func:`scan_file` walks the data section record by record (a chunk whose CRC fails is
still read, a cut-short file up to its last whole record), giving every entry of the
integrity chain (:mod:`crossfield.recording.integrity`) with its byte offset
(:class:`FileEntry`), the ``/integrity`` records, and where the file ends."""

from __future__ import annotations

import hashlib
import json
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from crossfield.progress import bar
from crossfield.recording.codec import utc_text
from crossfield.recording.integrity import (
    FORMATS,
    INTEGRITY_FORMAT,
    INTEGRITY_FORMAT_2,
    Entry,
    attachment_entry,
    channel_entry,
    header_entry,
    message_entry,
    metadata_entry,
    schema_entry,
)
from crossfield.recording.layout import TOPIC_INTEGRITY
from crossfield.recording.records import DamagedRecord, records_at


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
    return f"{topic} sequence {sequence} at {utc_text(log_time_ns)} ({log_time_ns} ns)"


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


@dataclass
class FileScan:
    entries: list[FileEntry] = field(default_factory=list)  # /integrity messages excluded
    records: list[tuple[int, FileEntry]] = field(default_factory=list)  # (entries before it, record)
    summary_entries: dict[tuple[str, int], str] = field(default_factory=dict)  # (label, id) -> digest
    chunks: int = 0
    problems: list[Problem] = field(default_factory=list)
    complete: bool = False
    ends: str = ""
    #: the chain format whose hash the digests were computed with
    chain_format: str = INTEGRITY_FORMAT_2

    @property
    def messages(self) -> int:
        return sum(1 for e in self.entries if e.is_message)


def library_chain_format(library: str) -> str:
    """The chain format a writer's header names (``crossfield/... crossfield-integrity/3 ...``,
    since format 3); format 2 when it names none (its hash is also format 1's)."""
    return next((word for word in library.split() if word in FORMATS), INTEGRITY_FORMAT_2)


def scan_file(path: Path, chain_format: str | None = None) -> FileScan:
    """Read every record in file order, checking chunk CRCs ourselves so that a
    bad chunk is reported and its records still compared. The digests are those of
    ``chain_format`` (by default the one the MCAP header names,
    :func:`library_chain_format`; ``scan.chain_format`` says which)."""
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
    from mcap.stream_reader import breakup_chunk, get_chunk_data_stream

    scan = FileScan()
    if chain_format is not None:
        scan.chain_format = chain_format
    channels: dict[int, str] = {}
    in_summary = False

    def take(record: Any, offset: int) -> None:
        fmt = scan.chain_format
        if in_summary:
            if isinstance(record, Schema):
                e = schema_entry(record.id, record.name, record.encoding, record.data, fmt)
                scan.summary_entries[(e[0], e[1])] = e[3]
            elif isinstance(record, Channel):
                e = channel_entry(
                    record.id, record.topic, record.message_encoding, record.schema_id, record.metadata, fmt
                )
                scan.summary_entries[(e[0], e[1])] = e[3]
            elif isinstance(record, Footer):
                scan.complete = True
            return
        entry: Entry | None = None
        if isinstance(record, Header):
            if chain_format is None:
                fmt = scan.chain_format = library_chain_format(record.library)
            entry = header_entry(record.profile, record.library, fmt)
        elif isinstance(record, Schema):
            entry = schema_entry(record.id, record.name, record.encoding, record.data, fmt)
        elif isinstance(record, Channel):
            channels[record.id] = record.topic
            entry = channel_entry(
                record.id, record.topic, record.message_encoding, record.schema_id, record.metadata, fmt
            )
        elif isinstance(record, Metadata):
            entry = metadata_entry(record.name, record.metadata, fmt)
        elif isinstance(record, Attachment):
            entry = attachment_entry(
                record.name, record.media_type, record.log_time, record.create_time, record.data, fmt
            )
        elif isinstance(record, Message):
            topic = channels.get(record.channel_id)
            if topic is None:
                scan.problems.append(
                    Problem(
                        "unreadable",
                        f"a message on unknown channel {record.channel_id} at {utc_text(record.log_time)} "
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
            entry = message_entry(topic, record.sequence, record.log_time, record.data, fmt)
        if entry is not None:
            scan.entries.append(FileEntry(*entry, None, offset))

    size = path.stat().st_size
    with open(path, "rb") as f, bar(desc="integrity check", total=size, unit="B", unit_scale=True) as read:
        at_start = True
        while True:
            try:
                for offset, record in records_at(f, emit_chunks=True, skip_magic=not at_start):
                    at_start = False
                    if isinstance(record, Chunk):
                        scan.chunks += 1
                        records = crc = None
                        try:
                            # a compressed chunk whose bytes are damaged may not decompress at all
                            crc = zlib.crc32(_chunk_bytes(record, get_chunk_data_stream))
                            records = breakup_chunk(record, validate_crc=False)
                        except Exception as exc:  # noqa: BLE001 - a damaged chunk is a finding
                            scan.problems.append(
                                Problem(
                                    "unreadable",
                                    f"chunk at byte {offset} ({record.compression or 'uncompressed'}): its "
                                    f"records cannot be read ({exc})",
                                    offset=offset,
                                )
                            )
                        bad_crc = crc is not None and record.uncompressed_crc != 0 and crc != record.uncompressed_crc
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
                    read.update(f.tell() - read.n)
                break
            except DamagedRecord as exc:
                at_start = False
                damage = exc.damage
                resume = None if in_summary else _next_chunk(f, damage.offset, size, get_chunk_data_stream)
                if resume is None:
                    scan.ends = str(damage)
                    break
                # Go on after the damage: the next intact chunk (its CRC-32 matches).
                scan.problems.append(
                    Problem(
                        "unreadable",
                        f"bytes {damage.offset}..{resume} cannot be read as MCAP records ({damage.reason}); "
                        f"reading goes on at the next intact chunk, byte {resume}",
                        offset=damage.offset,
                    )
                )
                f.seek(resume)
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


def record_doc(fe: FileEntry, chain_format: str = INTEGRITY_FORMAT) -> dict[str, Any] | None:
    """The JSON of an ``/integrity`` record in ``chain_format`` (None: unreadable or another format)."""
    try:
        doc = json.loads(fe.data or b"")
    except ValueError:
        return None
    if not isinstance(doc, dict) or doc.get("format") != chain_format:
        return None
    return doc


def entry_key(entry: Any) -> Entry | None:
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
