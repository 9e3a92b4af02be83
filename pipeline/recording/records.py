"""An MCAP file's records in file order with the byte offset each starts at, and the one
description of where a damaged or cut-short file stops being readable.

Both readers of a damaged file use this: the recording reader
(:class:`crossfield.recording.reader.Recording`, which replay reads through) and the
integrity scanner (:func:`crossfield.recording.scan.scan_file`, which audit reads
through), so a file cut in the middle of a chunk is named by the same byte in
``crossfield replay``'s INCOMPLETE line and in ``crossfield audit``'s: the offset of the
first record that cannot be read whole (a chunk's start, not the end of the bytes the
mcap library happened to read before it gave up).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

from mcap.exceptions import McapError
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk

#: What the mcap library raises on damaged or truncated data.
DAMAGE = (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError, MemoryError)


@dataclass(frozen=True)
class Damage:
    """Where reading stopped. offset: byte offset of the first record (a chunk: the
    chunk record) that cannot be read whole; size: the file's size (bytes); reason:
    the exception, as ``Type: message``."""

    offset: int
    size: int
    reason: str

    def __str__(self) -> str:
        return f"the file ends in damage or is cut short at byte {self.offset} of {self.size} ({self.reason})"


class DamagedRecord(Exception):
    """Raised by :func:`records_at` where the file's records stop being readable."""

    def __init__(self, damage: Damage) -> None:
        super().__init__(str(damage))
        self.damage = damage


def reason_of(exc: BaseException) -> str:
    """``Type: message`` (``Type`` alone when the message is empty)."""
    return type(exc).__name__ + (f": {exc}" if str(exc) else "")


def file_size(f: BinaryIO) -> int:
    """Size of the open file ``f`` in bytes (its position is kept)."""
    here = f.tell()
    try:
        return f.seek(0, 2)
    finally:
        f.seek(here)


def records_at(
    f: BinaryIO, *, validate_crcs: bool = False, emit_chunks: bool = False, skip_magic: bool = False
) -> Iterator[tuple[int, Any]]:
    """``(offset, record)`` for every record from ``f``'s position on, in file order.

    offset: byte offset where the record starts; a record inside a chunk gets its
    chunk's offset. emit_chunks: yield each :class:`~mcap.records.Chunk` itself
    instead of the records inside it. validate_crcs: check each chunk's CRC-32 (a
    mismatch is damage at the chunk's offset). skip_magic: ``f`` is not at the start
    of the file (resume after damage). At the first record that cannot be read whole
    raises :class:`DamagedRecord` with :class:`Damage` (offset of that record).
    """
    size = file_size(f)
    reader = StreamReader(f, skip_magic=skip_magic, emit_chunks=True, validate_crcs=False)
    offset = f.tell() + (0 if skip_magic else 8)  # the first record follows the 8 magic bytes
    try:
        for record in reader.records:
            if isinstance(record, Chunk) and not emit_chunks:
                for inner in breakup_chunk(record, validate_crc=validate_crcs):
                    yield offset, inner
            else:
                yield offset, record
            offset = f.tell()
    except DAMAGE as exc:
        raise DamagedRecord(Damage(offset, size, reason_of(exc))) from exc
