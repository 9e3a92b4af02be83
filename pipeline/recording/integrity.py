"""The integrity chain of a session recording: written while recording, checked by audit.

Every record of the file's data section is folded, in file order, into a
running hash chain (``docs/recording.md``, "Integrity chain"): the
header, every schema and channel record, every message, every metadata
record and every attachment. Each record is one *entry* ``(label,
sequence, log_time, digest)``; with ``H`` the format's hash (format 3,
written since issue 25: BLAKE3, 32-byte output; format 2: SHA-256)::

    h_0 = H("crossfield-integrity/3")
    h_k = H(h_{k-1} || u32 len(label) || label || u64 log_time || u32 sequence || digest_k)

(integers little-endian). For a message, ``label`` is its topic,
``sequence`` and ``log_time`` its own and ``digest = H(data)``. For
the other records ``label`` names the record (``#header``, ``#schema
<name>``, ``#channel <topic>``, ``#metadata <name>``, ``#attachment
<name>``), ``sequence`` is the schema / channel id (else 0), ``log_time``
the attachment's log time (else 0), and ``digest`` the ``H`` of the
canonical JSON of all its fields (data fields by their ``H``, hex): see
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

Checking (:func:`crossfield.audit.chain.verify`) reads the file in file order without trusting
its CRCs, recomputes the chain and compares every entry with the one
recorded, so a changed, removed, added or reordered record is named (topic
or record name, sequence, time, byte offset). The records themselves are
authenticated by the chain (recomputed from their entries) and by the link
to their predecessor (the SHA-256 of that record's JSON, in every format).

Formats: every function takes ``chain_format`` (default: the format written
now, :data:`INTEGRITY_FORMAT`); :data:`CHAIN_FORMATS` lists the readable ones.
Format 3 differs from format 2 only in ``H`` (BLAKE3 instead of SHA-256: ~5x
less CPU per 4 MB image here, and the ``blake3`` package releases the GIL while
it hashes, so the writer thread hashes an image while the pipeline thread
goes on with the next pair); the record keys keep their names
(``chain_sha256`` holds the format's chain head). Format 1 is format 2's link
over messages only.

What this proves (docs/replay-and-audit.md, "What the audit proves"): the
file is self-consistent. Someone who edits the data and rewrites every
record with this code produces another self-consistent file with another
chain head; that is caught only by comparing the head with one kept
outside the file (``crossfield audit --expect-head``) or by a signature
(:mod:`crossfield.recording.seal`).
"""

from __future__ import annotations

import hashlib
import json
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import blake3

#: Identifies the chain layout written now; in every ``/integrity`` record.
INTEGRITY_FORMAT_3 = "crossfield-integrity/3"
#: The layout written before issue 25 (SHA-256): still audited.
INTEGRITY_FORMAT_2 = "crossfield-integrity/2"
#: The first chain layout (recordings made before the chain covered every record):
#: format 2's link over **messages only**, listed under ``"messages"`` in each record;
#: metadata and attachments were listed by a digest this code no longer checks.
INTEGRITY_FORMAT_1 = "crossfield-integrity/1"
INTEGRITY_FORMAT = INTEGRITY_FORMAT_3


@dataclass(frozen=True)
class ChainFormat:
    """One chain layout. hash: ``H`` (bytes-like -> hash object with ``digest()``,
    ``hexdigest()``, ``update()``); genesis: ``h_0 = H(name)``; listing: the record key
    listing its entries; covers: what the chain covers, in words."""

    name: str
    hash: Callable[..., Any]
    listing: str
    covers: str

    @property
    def genesis(self) -> bytes:
        return self.hash(self.name.encode()).digest()


#: The readable chain layouts by name.
FORMATS: dict[str, ChainFormat] = {
    INTEGRITY_FORMAT_3: ChainFormat(INTEGRITY_FORMAT_3, blake3.blake3, "entries", "every record"),
    INTEGRITY_FORMAT_2: ChainFormat(INTEGRITY_FORMAT_2, hashlib.sha256, "entries", "every record"),
    INTEGRITY_FORMAT_1: ChainFormat(INTEGRITY_FORMAT_1, hashlib.sha256, "messages", "messages only"),
}
GENESIS = FORMATS[INTEGRITY_FORMAT].genesis
GENESIS_2 = FORMATS[INTEGRITY_FORMAT_2].genesis
GENESIS_1 = FORMATS[INTEGRITY_FORMAT_1].genesis

#: Per chain format: (genesis h_0, the record key listing its entries, what the chain covers).
CHAIN_FORMATS: dict[str, tuple[bytes, str, str]] = {
    name: (f.genesis, f.listing, f.covers) for name, f in FORMATS.items()
}

#: Entry labels of the records that are not messages.
HEADER_LABEL = "#header"
_SCHEMA = "#schema "
_CHANNEL = "#channel "
_METADATA = "#metadata "
_ATTACHMENT = "#attachment "

_U64_U32 = struct.Struct("<QI")

#: An entry: (label, sequence, log_time_ns, digest hex).
Entry = tuple[str, int, int, str]


def _hash(chain_format: str) -> Callable[..., Any]:
    return FORMATS[chain_format].hash


def data_digest(data: bytes | memoryview, chain_format: str = INTEGRITY_FORMAT) -> bytes:
    """``H(data)`` of a message's data (32 bytes): BLAKE3 in format 3 (the GIL released
    while it runs), SHA-256 in formats 1 and 2."""
    return _hash(chain_format)(data).digest()


def link(
    previous: bytes, label: str, log_time_ns: int, sequence: int, digest: bytes, chain_format: str = INTEGRITY_FORMAT
) -> bytes:
    """One step of the chain: h_k from h_{k-1} and the k-th entry (see module doc)."""
    t = label.encode("utf-8")
    h = _hash(chain_format)(previous)
    h.update(len(t).to_bytes(4, "little"))
    h.update(t)
    h.update(_U64_U32.pack(int(log_time_ns) & 0xFFFFFFFFFFFFFFFF, int(sequence) & 0xFFFFFFFF))
    h.update(digest)
    return h.digest()


def _canonical(fields: Any, chain_format: str) -> bytes:
    return _hash(chain_format)(
        json.dumps(fields, ensure_ascii=False, separators=(",", ":"), sort_keys=True).encode("utf-8")
    ).digest()


def header_digest(profile: str, library: str, chain_format: str = INTEGRITY_FORMAT) -> bytes:
    """Digest of the MCAP header: ``H`` of the canonical JSON ``["header", profile, library]``."""
    return _canonical(["header", profile, library], chain_format)


def schema_digest(schema_id: int, name: str, encoding: str, data: bytes, chain_format: str = INTEGRITY_FORMAT) -> bytes:
    """Digest of a schema record: ``["schema", id, name, encoding, H(data) hex]``."""
    data_hex = _hash(chain_format)(data).hexdigest()
    return _canonical(["schema", int(schema_id), name, encoding, data_hex], chain_format)


def channel_digest(
    channel_id: int,
    topic: str,
    message_encoding: str,
    schema_id: int,
    metadata: Mapping[str, str],
    chain_format: str = INTEGRITY_FORMAT,
) -> bytes:
    """Digest of a channel record: ``["channel", id, topic, encoding, schema_id, {metadata}]``."""
    fields = ["channel", int(channel_id), topic, message_encoding, int(schema_id), dict(metadata)]
    return _canonical(fields, chain_format)


def metadata_digest(name: str, record: Mapping[str, str], chain_format: str = INTEGRITY_FORMAT) -> bytes:
    """Digest of a metadata record: ``["metadata", name, {key: value}]``."""
    return _canonical(["metadata", name, dict(record)], chain_format)


def attachment_digest(
    name: str, media_type: str, log_time: int, create_time: int, data: bytes, chain_format: str = INTEGRITY_FORMAT
) -> bytes:
    """Digest of an attachment: ``["attachment", name, media_type, log_time, create_time, H(data) hex]``."""
    data_hex = _hash(chain_format)(data).hexdigest()
    return _canonical(["attachment", name, media_type, int(log_time), int(create_time), data_hex], chain_format)


def header_entry(profile: str, library: str, chain_format: str = INTEGRITY_FORMAT) -> Entry:
    return (HEADER_LABEL, 0, 0, header_digest(profile, library, chain_format).hex())


def schema_entry(schema_id: int, name: str, encoding: str, data: bytes, chain_format: str = INTEGRITY_FORMAT) -> Entry:
    return (_SCHEMA + name, int(schema_id), 0, schema_digest(schema_id, name, encoding, data, chain_format).hex())


def channel_entry(
    channel_id: int,
    topic: str,
    message_encoding: str,
    schema_id: int,
    metadata: Mapping[str, str],
    chain_format: str = INTEGRITY_FORMAT,
) -> Entry:
    digest = channel_digest(channel_id, topic, message_encoding, schema_id, metadata, chain_format)
    return (_CHANNEL + topic, int(channel_id), 0, digest.hex())


def metadata_entry(name: str, record: Mapping[str, str], chain_format: str = INTEGRITY_FORMAT) -> Entry:
    return (_METADATA + name, 0, 0, metadata_digest(name, record, chain_format).hex())


def attachment_entry(
    name: str, media_type: str, log_time: int, create_time: int, data: bytes, chain_format: str = INTEGRITY_FORMAT
) -> Entry:
    digest = attachment_digest(name, media_type, log_time, create_time, data, chain_format)
    return (_ATTACHMENT + name, 0, int(log_time), digest.hex())


def message_entry(
    topic: str, sequence: int, log_time: int, data: bytes | memoryview, chain_format: str = INTEGRITY_FORMAT
) -> Entry:
    return (topic, int(sequence) & 0xFFFFFFFF, int(log_time), data_digest(data, chain_format).hex())


# --------------------------------------------------------------------------
# Writing side (used by the recorder's writer thread)
# --------------------------------------------------------------------------


class IntegrityChain:
    """The running chain while recording; :meth:`record` gives the next ``/integrity`` document.

    The writer calls ``add_*`` for every record in the order it lands in the
    file. head: the chain head so far (32 bytes); count: entries folded.
    chain_format: the layout written (the current one; an older one only to make
    test recordings in it).
    """

    def __init__(self, chain_format: str = INTEGRITY_FORMAT) -> None:
        if chain_format not in FORMATS or FORMATS[chain_format].listing != "entries":
            raise ValueError(f"cannot write chain format {chain_format!r}")
        self.chain_format = chain_format
        self.head = FORMATS[chain_format].genesis
        self.count = 0
        self.index = 0
        self.previous_record_sha256: str | None = None
        self.latest_time_ns = 0
        self._entries: list[list[Any]] = []

    def add(self, entry: Entry) -> None:
        label, sequence, log_time, digest = entry
        self.head = link(self.head, label, log_time, sequence, bytes.fromhex(digest), self.chain_format)
        self.count += 1
        self._entries.append([label, sequence, log_time, digest])

    def add_message(self, topic: str, log_time_ns: int, sequence: int, data: bytes | memoryview) -> None:
        self.add(message_entry(topic, sequence, log_time_ns, data, self.chain_format))
        self.latest_time_ns = max(self.latest_time_ns, int(log_time_ns))

    def add_header(self, profile: str, library: str) -> None:
        self.add(header_entry(profile, library, self.chain_format))

    def add_schema(self, schema_id: int, name: str, encoding: str, data: bytes) -> None:
        self.add(schema_entry(schema_id, name, encoding, data, self.chain_format))

    def add_channel(
        self, channel_id: int, topic: str, message_encoding: str, schema_id: int, metadata: Mapping[str, str]
    ) -> None:
        self.add(channel_entry(channel_id, topic, message_encoding, schema_id, metadata, self.chain_format))

    def add_metadata(self, name: str, record: Mapping[str, str]) -> None:
        self.add(metadata_entry(name, record, self.chain_format))

    def add_attachment(self, name: str, media_type: str, log_time: int, create_time: int, data: bytes) -> None:
        self.add(attachment_entry(name, media_type, log_time, create_time, data, self.chain_format))

    @property
    def pending(self) -> bool:
        """Something was written since the last record."""
        return bool(self._entries)

    def record(self, final: bool = False, extra: Mapping[str, Any] | None = None) -> bytes:
        """The next ``/integrity`` record (JSON bytes); resets the pending list.
        ``extra``: more keys (the final record's signature)."""
        doc = {
            "format": self.chain_format,
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


def file_sha256(path: str | Path, *, block: int = 1 << 22) -> str:
    """SHA-256 (hex) of a whole file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()
