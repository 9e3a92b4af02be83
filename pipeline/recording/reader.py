"""Read a crossfield session recording (``session.mcap``).

    with open_recording("recordings/<session>/session.mcap") as rec:
        rec.topics()                                # topic -> TopicInfo
        for m in rec.messages(["/registration"]):   # decoded, in log-time order
            print(m.sequence, m.decoded["rms_mm"])
        rec.metadata_doc("crossfield.session")      # the exact JSON document
        rec.attachment("plan.toml").data

Messages are decoded by encoding: protobuf (Foxglove schemas) into
protobuf message objects, JSON into Python data, ``/cmm/raw`` left as the
bytes read from the serial line.

A recording whose writer was killed has no summary or footer. It is still
read, sequentially, up to the last complete chunk; :attr:`Recording.complete`
is then False and :attr:`Recording.damage` says where reading stopped.
Layout of the file: ``docs/recording.md``.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap_protobuf.decoder import DecoderFactory

from crossfield.errors import RecordingError
from crossfield.recording.records import DamagedRecord, records_at

MCAP_MAGIC = b"\x89MCAP0\r\n"

#: Exceptions the mcap library raises on damaged or truncated data.
_DAMAGE = (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError)


@dataclass(frozen=True)
class TopicInfo:
    """One topic: its schema, encodings and message count."""

    topic: str
    schema_name: str | None
    schema_encoding: str | None
    message_encoding: str
    message_count: int
    channel_metadata: tuple[Mapping[str, str], ...] = ()


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded message.

    log_time_ns: the time it stands for (capture time for frames and their
    results, read time for serial bytes), ns since the Unix epoch.
    sequence: the stereo pair's sequence number (frame topics) or the read
    index (``/cmm/raw``); 0 otherwise. data: the message bytes as stored.
    decoded: the decoded message (protobuf object, JSON data or the bytes).
    """

    topic: str
    log_time_ns: int
    sequence: int
    schema_name: str | None
    message_encoding: str
    data: bytes
    decoded: Any
    channel_metadata: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class RecordedAttachment:
    name: str
    media_type: str
    data: bytes
    log_time_ns: int

    @property
    def text(self) -> str:
        return self.data.decode("utf-8")


class Recording:
    """An open session MCAP file (read-only). Use :func:`open_recording`.

    validate_crcs: check every chunk's CRC-32 while reading (a mismatch is a
    :class:`RecordingError`). The audit reads with False: it checks the CRCs
    itself (:mod:`crossfield.recording.integrity`), names the damaged
    messages and goes on comparing what the file holds.
    """

    def __init__(self, path: str | Path, *, validate_crcs: bool = True):
        self.path = Path(path)
        self.validate_crcs = validate_crcs
        self._decoders = DecoderFactory()
        self._decoder_cache: dict[tuple[int, int], Any] = {}
        self.damage: str | None = None
        self._summary = None
        with self._open() as f:
            magic = f.read(len(MCAP_MAGIC))
            if magic != MCAP_MAGIC:
                what = (
                    "empty file (0 bytes), not an MCAP recording"
                    if not magic
                    else "not an MCAP file (wrong magic bytes)"
                )
                raise RecordingError(f"{self.path}: {what}")
            try:
                self._summary = self._seeking(f).get_summary()
            except (*_DAMAGE, OSError) as exc:  # OSError: a file too short to hold a footer
                self.damage = f"no readable summary ({exc}); read sequentially"
        if self._summary is None and self.damage is None:
            self.damage = "no summary section; read sequentially"

    def _open(self):
        try:
            return open(self.path, "rb")
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot open recording: {exc.strerror}") from None

    # ---- basics ---------------------------------------------------------

    def _header(self) -> Any:
        """The file's MCAP header record, or None if it has none."""
        from mcap.records import Header

        with self._open() as f:
            try:
                for record in StreamReader(f).records:
                    return record if isinstance(record, Header) else None
            except _DAMAGE:
                return None
        return None

    @property
    def library(self) -> str:
        """The writer named in the file's MCAP header (``""`` if it has none);
        crossfield writes ``crossfield/<version> crossfield-mcap/1 mcap-python/<version>``."""
        header = self._header()
        return header.library if header is not None else ""

    @property
    def profile(self) -> str:
        """The MCAP header's profile: ``""`` for a session, else the kind of
        recording (:data:`crossfield.recording.layout.CALIBRATION_PROFILE`, ...)."""
        header = self._header()
        return header.profile if header is not None else ""

    @property
    def complete(self) -> bool:
        """True when the file was finished (summary and footer intact)."""
        return self._summary is not None

    def close(self) -> None:
        """Nothing to release: every read opens the file afresh."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _seeking(self, f: Any) -> SeekingReader:
        f.seek(0)
        return SeekingReader(f, validate_crcs=self.validate_crcs)

    # ---- sequential scan (damaged files) --------------------------------

    def _scan(self) -> Iterator[Any]:
        """Every record in file order, stopping quietly at damage."""
        with self._open() as f:
            try:
                for _, record in records_at(f, validate_crcs=self.validate_crcs):
                    yield record
            except DamagedRecord as exc:
                # the same words and byte as the audit's (crossfield.recording.records)
                self.damage = str(exc.damage)

    def _scan_channels(self) -> tuple[dict[int, Schema], dict[int, Channel], dict[int, int]]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        counts: dict[int, int] = {}
        for record in self._scan():
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
        return schemas, channels, counts

    # ---- topics and messages -------------------------------------------

    def topics(self) -> dict[str, TopicInfo]:
        """topic -> :class:`TopicInfo`, in channel order."""
        if self._summary is not None:
            schemas, channels = self._summary.schemas, self._summary.channels
            stats = self._summary.statistics
            counts = dict(stats.channel_message_counts) if stats is not None else {}
        else:
            schemas, channels, counts = self._scan_channels()
        out: dict[str, TopicInfo] = {}
        for channel_id, channel in sorted(channels.items()):
            schema = schemas.get(channel.schema_id)
            previous = out.get(channel.topic)
            count = counts.get(channel_id, 0) + (previous.message_count if previous else 0)
            meta = (previous.channel_metadata if previous else ()) + (dict(channel.metadata),)
            out[channel.topic] = TopicInfo(
                channel.topic,
                schema.name if schema else None,
                schema.encoding if schema else None,
                channel.message_encoding,
                count,
                meta,
            )
        return out

    def _decode(self, schema: Schema | None, channel: Channel, message: Message) -> Any:
        encoding = channel.message_encoding
        if encoding == "json":
            try:
                return json.loads(message.data)
            except (ValueError, UnicodeDecodeError) as exc:
                raise RecordingError(
                    f"{self.path}: {channel.topic} message at {message.log_time}: not valid JSON: {exc}"
                ) from None
        if encoding == "protobuf":
            key = (channel.id, channel.schema_id)
            decoder = self._decoder_cache.get(key)
            if decoder is None:
                decoder = self._decoders.decoder_for(encoding, schema)
                if decoder is None:
                    raise RecordingError(
                        f"{self.path}: {channel.topic}: protobuf channel without a protobuf schema"
                    )
                self._decoder_cache[key] = decoder
            try:
                return decoder(message.data)
            except Exception as exc:  # noqa: BLE001 - protobuf raises several types
                raise RecordingError(
                    f"{self.path}: {channel.topic} message at {message.log_time}: cannot decode "
                    f"{schema.name if schema else 'protobuf'}: {exc}"
                ) from None
        return message.data

    def messages(
        self, topics: str | Iterable[str] | None = None, *, decode: bool = True, file_order: bool = False
    ) -> Iterator[RecordedMessage]:
        """Messages of ``topics`` (all when None) in log-time order, or in the
        order they were written when ``file_order`` (replay: the processing order).

        In file order the file is streamed one chunk at a time, so memory does
        not grow with the recording's length (replay and audit read this way).
        On a damaged recording: the messages before the damage, in file order.
        """
        if isinstance(topics, str):
            topics = [topics]
        wanted = None if topics is None else set(topics)
        if self._summary is not None and file_order and self._summary.chunk_indexes:
            yield from self._chunk_by_chunk(wanted, decode)
            return
        if self._summary is not None:
            with self._open() as f:
                reader = self._seeking(f)
                selected = None if wanted is None else list(wanted)
                try:
                    for schema, channel, message in reader.iter_messages(
                        topics=selected, log_time_order=not file_order
                    ):
                        yield self._recorded(schema, channel, message, decode)
                except _DAMAGE as exc:
                    raise RecordingError(f"{self.path}: damaged recording: {exc}") from None
            return
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for record in self._scan():
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None or (wanted is not None and channel.topic not in wanted):
                    continue
                yield self._recorded(schemas.get(channel.schema_id), channel, record, decode)

    def _chunk_by_chunk(self, wanted: set[str] | None, decode: bool) -> Iterator[RecordedMessage]:
        """Messages in file order, reading one chunk at a time (the mcap library's
        own file-order iteration reads every chunk before it yields a message)."""
        summary = self._summary
        channels = summary.channels
        wanted_ids = None if wanted is None else {i for i, c in channels.items() if c.topic in wanted}
        with self._open() as f:
            try:
                for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
                    if wanted_ids is not None and index.message_index_offsets:
                        if not wanted_ids & set(index.message_index_offsets):
                            continue  # no wanted message in this chunk: not read
                    f.seek(index.chunk_start_offset + 1 + 8)
                    chunk = Chunk.read(ReadDataStream(f))
                    for record in breakup_chunk(chunk, validate_crc=self.validate_crcs):
                        if not isinstance(record, Message):
                            continue
                        channel = channels.get(record.channel_id)
                        if channel is None or (wanted_ids is not None and record.channel_id not in wanted_ids):
                            continue
                        schema = summary.schemas.get(channel.schema_id) if channel.schema_id else None
                        yield self._recorded(schema, channel, record, decode)
            except _DAMAGE as exc:
                raise RecordingError(f"{self.path}: damaged recording: {exc}") from None

    def _recorded(
        self, schema: Schema | None, channel: Channel, message: Message, decode: bool
    ) -> RecordedMessage:
        return RecordedMessage(
            topic=channel.topic,
            log_time_ns=message.log_time,
            sequence=message.sequence,
            schema_name=schema.name if schema else None,
            message_encoding=channel.message_encoding,
            data=message.data,
            decoded=self._decode(schema, channel, message) if decode else None,
            channel_metadata=dict(channel.metadata),
        )

    def schema(self, topic: str) -> bytes | None:
        """The schema data of ``topic`` (a FileDescriptorSet or JSON Schema text)."""
        if self._summary is not None:
            schemas, channels = self._summary.schemas, self._summary.channels
        else:
            schemas, channels, _ = self._scan_channels()
        for channel in channels.values():
            if channel.topic == topic:
                schema = schemas.get(channel.schema_id)
                return schema.data if schema else None
        raise RecordingError(f"{self.path}: no topic {topic!r}")

    # ---- metadata and attachments --------------------------------------

    def metadata(self) -> dict[str, dict[str, str]]:
        """name -> record (str -> str) of every metadata record."""
        if self._summary is not None:
            try:
                with self._open() as f:
                    records = list(self._seeking(f).iter_metadata())
            except _DAMAGE as exc:
                raise RecordingError(f"{self.path}: damaged recording: {exc}") from None
        else:
            records = [r for r in self._scan() if isinstance(r, Metadata)]
        return {r.name: dict(r.metadata) for r in records}

    def metadata_doc(self, name: str) -> Any:
        """The exact JSON document of a ``crossfield.*`` metadata record (its ``json`` key)."""
        record = self.metadata().get(name)
        if record is None:
            raise RecordingError(f"{self.path}: no metadata record {name!r}")
        if "json" not in record:
            return dict(record)
        try:
            return json.loads(record["json"])
        except ValueError as exc:
            raise RecordingError(
                f"{self.path}: metadata {name!r}: key 'json' is not valid JSON: {exc}"
            ) from None

    def attachments(self) -> dict[str, RecordedAttachment]:
        """name -> attachment."""
        if self._summary is not None:
            try:
                with self._open() as f:
                    records = list(self._seeking(f).iter_attachments())
            except _DAMAGE as exc:
                raise RecordingError(f"{self.path}: damaged recording: {exc}") from None
        else:
            records = [r for r in self._scan() if isinstance(r, Attachment)]
        return {r.name: RecordedAttachment(r.name, r.media_type, r.data, r.log_time) for r in records}

    def attachment(self, name: str) -> RecordedAttachment:
        found = self.attachments().get(name)
        if found is None:
            raise RecordingError(f"{self.path}: no attachment {name!r}")
        return found


def open_recording(path: str | Path, *, validate_crcs: bool = True) -> Recording:
    """Open a session MCAP for reading; :class:`RecordingError` if it is none."""
    return Recording(path, validate_crcs=validate_crcs)
