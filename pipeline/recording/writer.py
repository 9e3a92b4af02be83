"""Writing a session recording: message building apart from where messages go.

:class:`SessionWriter` turns the session's facts and every stage output
into the recording's messages, metadata records and attachments (layout:
:mod:`crossfield.recording.layout`, encodings: :mod:`crossfield.recording.codec`)
and hands them to a :class:`Sink`:

* :class:`McapFileSink` writes one MCAP file, in a background thread by
  default, with the integrity chain (:mod:`crossfield.recording.integrity`);
* :class:`MemorySink` keeps the messages in memory (the audit rebuilds a
  session's messages with it and compares them with the recorded ones).

The observer plugin that feeds a writer from the pipeline's hooks is
:class:`crossfield.recording.recorder.McapRecorder`.

Speed and crash safety (file sink): images are written uncompressed
(lossless ``mono16``, little-endian) with one copy into the protobuf
message; the MCAP writer runs in a background thread so that its copies,
CRCs and the file write overlap with the pipeline. Each image closes its
chunk, and the open chunk is flushed to the file at the end of every frame
and at least every ``flush_interval_s``, so a killed session loses at most
the frame in progress (and the messages still queued for the writer, at
most ``queue_size``).
"""

from __future__ import annotations

import functools
import hashlib
import json
import queue
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, Protocol, Self

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.writer import CompressionType, Writer

from crossfield.chain.provenance import crossfield_version, machine_info
from crossfield.covariance import global_sigma
from crossfield.errors import RecordingError
from crossfield.jsonable import plain, real, reals
from crossfield.recording import layout as L
from crossfield.recording import seal
from crossfield.recording.codec import (
    FramePose,
    SchemaSpec,
    calibration_yaml,
    camera_calibration_message,
    camera_points_doc,
    centroids_doc,
    dump_json,
    frame_status_doc,
    frame_transforms_message,
    ground_truth_doc,
    json_schema,
    log_message,
    measurement_doc,
    metadata_record,
    point_cloud_message,
    protobuf_schema,
    raw_image_message,
    reference_doc,
    registration_doc,
    toml_text,
    upper_to_lower_pose,
    utc_text,
)
from crossfield.recording.foxglove_overlay import FoxgloveOverlay
from crossfield.recording.hashed_stream import HashedStream
from crossfield.recording.integrity import INTEGRITY_FORMAT, IntegrityChain
from crossfield.report.document import document_of
from crossfield.types import CAMERAS, CameraPoints

#: Chunk compression by name (lossless; ``[session] compression``). lz4 (the mcap
#: library's frame defaults) is the default since issue 27: a simulated 12-bit image
#: shrinks to 0.70 of its size at ~10 ms of CPU per 4 MB image in the writer thread
#: (zstd level 3: 0.42 at ~25-27 ms), enough for the 14 Hz cameras; "none" where the rate
#: matters more than the disk, "zstd" where the disk matters most (bench/bench_recording.py,
#: docs/recording.md).
COMPRESSIONS = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}
#: The compression of a recording unless told otherwise.
DEFAULT_COMPRESSION = "lz4"

#: The integrity chain format written (integrity.py; the tests set an older one to make
#: recordings in it and check that they are still audited).
CHAIN_FORMAT = INTEGRITY_FORMAT

#: Each image (4 MB for 1626 x 1236 mono16) is larger than this, so it closes
#: its chunk: chunks stay small (crash safety) and the writer never re-grows a
#: multi-image buffer (measured: 16 MiB chunks cost 2x the CPU of 1 MiB ones).
DEFAULT_CHUNK_SIZE = 1 << 20


# --------------------------------------------------------------------------
# Channels
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ChannelSpec:
    """A channel: topic, message encoding, schema and channel metadata (hashable)."""

    topic: str
    message_encoding: str
    schema: SchemaSpec | None
    metadata: tuple[tuple[str, str], ...] = ()


@functools.lru_cache(maxsize=256)
def protobuf_channel(topic: str, message_class: Any, metadata_: tuple[tuple[str, str], ...] = ()) -> ChannelSpec:
    """The channel of a Foxglove protobuf topic."""
    return ChannelSpec(topic, "protobuf", protobuf_schema(message_class), metadata_)


@functools.lru_cache(maxsize=256)
def json_channel(topic: str, schema_name: str) -> ChannelSpec:
    """The channel of a JSON topic with the JSON schema ``schema_name``."""
    return ChannelSpec(topic, "json", json_schema(schema_name))


def raw_channel(source: str) -> ChannelSpec:
    """The ``/cmm/raw`` channel of one serial source (schema-less bytes)."""
    return ChannelSpec(L.TOPIC_CMM_RAW, L.RAW_ENCODING, None, ((L.CHANNEL_SOURCE, str(source)),))


def link_event_channel(source: str) -> ChannelSpec:
    """The ``/cmm/raw`` channel of one source's link events (its own channel, so
    that no byte sequence on the line can pass for an event)."""
    return ChannelSpec(
        L.TOPIC_CMM_RAW, L.RAW_ENCODING, None, ((L.CHANNEL_SOURCE, str(source)), (L.CHANNEL_CONTENT, L.LINK_EVENTS))
    )


INTEGRITY_CHANNEL = json_channel(L.TOPIC_INTEGRITY, L.SCHEMA_INTEGRITY)


# --------------------------------------------------------------------------
# Sinks
# --------------------------------------------------------------------------


class Sink(Protocol):
    """Where a :class:`SessionWriter` puts what it builds.

    ``message``: one message (log time ns, MCAP sequence); ``metadata``: a
    metadata record (str -> str); ``attachment``: a file (log time ns);
    ``flush``: hand everything so far on (end of a frame); ``close``: finish
    (idempotent). Errors are :class:`RecordingError`.
    """

    @property
    def closed(self) -> bool: ...

    def message(self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int) -> None: ...

    def metadata(self, name: str, record: dict[str, str]) -> None: ...

    def attachment(self, name: str, media_type: str, data: bytes, log_time: int) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


class MemorySink:
    """A sink that keeps what it is given in memory.

    messages: ``(topic, log_time_ns, sequence, data)`` in write order (the
    sequence as MCAP stores it, 32 bits), topics in ``skip_topics`` left out
    (the audit skips the raw images). metadata: ``(name, record)``;
    attachments: ``(name, media_type, data, log_time_ns)``.
    """

    def __init__(self, skip_topics: Iterable[str] = ()) -> None:
        self.messages: list[tuple[str, int, int, bytes]] = []
        self.metadata_records: list[tuple[str, dict[str, str]]] = []
        self.attachments: list[tuple[str, str, bytes, int]] = []
        self._skip = frozenset(skip_topics)
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def _check(self) -> None:
        if self._closed:
            raise RecordingError("the message capture is closed")

    def message(self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int) -> None:
        self._check()
        if spec.topic not in self._skip:
            self.messages.append((spec.topic, int(log_time), int(sequence) & 0xFFFFFFFF, bytes(data)))

    def metadata(self, name: str, record: dict[str, str]) -> None:
        self._check()
        self.metadata_records.append((name, dict(record)))

    def attachment(self, name: str, media_type: str, data: bytes, log_time: int) -> None:
        self._check()
        self.attachments.append((name, media_type, bytes(data), int(log_time)))

    def flush(self) -> None:
        self._check()

    def close(self) -> None:
        self._closed = True


class _McapFile:
    """Owns the ``mcap`` Writer and the integrity chain; every method is called from one thread."""

    def __init__(
        self,
        stream: Any,
        chunk_size: int,
        flush_interval_s: float,
        library: str,
        compression: CompressionType,
        profile: str = "",
    ):
        self.stream = stream
        self.writer = Writer(stream, chunk_size=chunk_size, compression=compression)
        self.writer.start(profile=profile, library=library)
        self.schemas: dict[SchemaSpec, int] = {}
        self.channels: dict[ChannelSpec, int] = {}
        self.flush_interval_s = flush_interval_s
        self.last_flush = time.monotonic()
        # Every record is chained in the order it lands in the file (integrity.py).
        self.chain = IntegrityChain(CHAIN_FORMAT)
        self.chain.add_header(profile, library)

    def _channel_id(self, spec: ChannelSpec) -> int:
        channel_id = self.channels.get(spec)
        if channel_id is None:
            schema_id = 0
            if spec.schema is not None:
                schema_id = self.schemas.get(spec.schema, 0)
                if not schema_id:
                    schema_id = self.writer.register_schema(
                        spec.schema.name, spec.schema.encoding, spec.schema.data
                    )
                    self.schemas[spec.schema] = schema_id
                    self.chain.add_schema(schema_id, spec.schema.name, spec.schema.encoding, spec.schema.data)
            channel_id = self.writer.register_channel(
                spec.topic, spec.message_encoding, schema_id, dict(spec.metadata)
            )
            self.channels[spec] = channel_id
            self.chain.add_channel(channel_id, spec.topic, spec.message_encoding, schema_id, dict(spec.metadata))
        return channel_id

    def message(self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int) -> None:
        sequence = int(sequence) & 0xFFFFFFFF
        self.writer.add_message(self._channel_id(spec), int(log_time), data, int(log_time), sequence)
        self.chain.add_message(spec.topic, int(log_time), sequence, data)
        if time.monotonic() - self.last_flush > self.flush_interval_s:
            self.flush()

    def metadata(self, name: str, record: dict[str, str]) -> None:
        # Metadata and attachments are written outside chunks: finish the open
        # chunk first, so that the file order is the order of the chain.
        self.writer.flush()
        self.writer.add_metadata(name, record)
        self.chain.add_metadata(name, record)

    def attachment(self, name: str, media_type: str, data: bytes, log_time: int) -> None:
        self.writer.flush()
        self.writer.add_attachment(int(log_time), int(log_time), name, media_type, data)
        self.chain.add_attachment(name, media_type, int(log_time), int(log_time), data)

    def _integrity_record(self, final: bool, signing_key: Any = None) -> None:
        """Write the next /integrity record into the open chunk (:mod:`crossfield.recording.integrity`);
        the final one signed with ``signing_key`` when given (:mod:`crossfield.recording.seal`)."""
        t = self.chain.latest_time_ns or time.time_ns()
        index = self.chain.index
        channel_id = self._channel_id(INTEGRITY_CHANNEL)  # chained before the record that covers it
        extra = None
        if final and signing_key is not None:
            extra = {"signature": seal.sign(signing_key, seal.head_statement(self.chain.head.hex()))}
        data = self.chain.record(final, extra)
        self.writer.add_message(channel_id, t, data, t, index & 0xFFFFFFFF)

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (no fsync). The
        chunk ends with an /integrity record covering everything written so far."""
        if self.chain.pending:
            self._integrity_record(final=False)
        self.writer.flush()
        self.last_flush = time.monotonic()

    def finish(self, signing_key: Any = None) -> str:
        """Write the final record and the summary; returns the file's chain head (hex)."""
        self._integrity_record(final=True, signing_key=signing_key)
        self.writer.finish()
        self.stream.flush()
        return self.chain.head.hex()


_CLOSE = object()


class McapFileSink:
    """A sink writing one MCAP file (``session.mcap``) with the integrity chain.

    path: the file to create; an existing file is an error unless
    ``overwrite``. chunk_size: MCAP chunk size in bytes. writer_thread: run
    the MCAP writer in a background thread (callers only queue the message
    bytes). queue_size: items the queue holds before callers wait for the
    writer. flush_interval_s: longest time a message stays in the open
    chunk. compression: one of :data:`COMPRESSIONS` (lossless in every case).
    profile: the MCAP header's profile ("" for a session; a calibration or
    verification recording names its kind, :mod:`crossfield.recording.layout`).

    An error writing the file is raised as :class:`RecordingError` from the
    next call (and from :meth:`close`).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        overwrite: bool = False,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        writer_thread: bool = True,
        queue_size: int = 8,
        flush_interval_s: float = 1.0,
        compression: str = DEFAULT_COMPRESSION,
        signing_key: str | Path | None = None,
        profile: str = "",
    ):
        self.path = Path(path)
        #: The seal (chain head, file SHA-256, signature, sidecar) once closed.
        self.seal: seal.Seal | None = None
        self._signing_key = seal.load_private_key(signing_key) if signing_key else None
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        try:
            raw = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115 - held until close()
        except FileExistsError:
            raise RecordingError(f"{self.path}: a recording already exists there (not overwritten)") from None
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create the recording: {exc.strerror}") from None
        # The file's SHA-256 (the seal) is computed on a thread while the file is written.
        self._stream = HashedStream(raw)
        # The header names the chain format (its hash: crossfield.recording.scan.library_chain_format).
        library = (
            f"crossfield/{crossfield_version()} {L.RECORDING_FORMAT} {CHAIN_FORMAT} "
            f"mcap-python/{metadata.version('mcap')}"
        )
        self._file = _McapFile(
            self._stream, chunk_size, flush_interval_s, library, COMPRESSIONS[compression], profile
        )
        self._closed = False
        self._error: BaseException | None = None
        self._lock = threading.Lock()
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if writer_thread:
            self._queue = queue.Queue(maxsize=max(1, int(queue_size)))
            self._thread = threading.Thread(
                target=self._run_writer, name=f"mcap-writer {self.path.name}", daemon=True
            )
            self._thread.start()

    @property
    def closed(self) -> bool:
        return self._closed

    def _run_writer(self) -> None:
        assert self._queue is not None
        while True:
            item = self._queue.get()
            if item is _CLOSE:
                return
            if self._error is None:
                try:
                    method, args = item
                    getattr(self._file, method)(*args)
                except BaseException as exc:  # noqa: BLE001 - reported to the producer
                    self._error = exc

    def _submit(self, method: str, *args: Any) -> None:
        if self._error is not None:
            raise RecordingError(f"{self.path}: recording failed: {self._error}") from self._error
        if self._closed:
            raise RecordingError(f"{self.path}: the recording is closed")
        if self._queue is not None:
            self._queue.put((method, args))
        else:
            try:
                getattr(self._file, method)(*args)
            except Exception as exc:
                self._error = exc
                raise RecordingError(f"{self.path}: recording failed: {exc}") from exc

    def message(self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int) -> None:
        self._submit("message", spec, log_time, data, sequence)

    def metadata(self, name: str, record: dict[str, str]) -> None:
        self._submit("metadata", name, record)

    def attachment(self, name: str, media_type: str, data: bytes, log_time: int) -> None:
        self._submit("attachment", name, media_type, data, log_time)

    def flush(self) -> None:
        """Hand everything recorded so far to the OS (closes the open chunk)."""
        self._submit("flush")

    def close(self) -> None:
        """Finish the MCAP file (summary, indexes, footer) and close it. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._thread is not None and self._queue is not None:
            self._queue.put(_CLOSE)
            self._thread.join()
        head = None
        try:
            if self._error is None:
                head = self._file.finish(self._signing_key)
        except Exception as exc:  # noqa: BLE001 - reported below as RecordingError
            self._error = exc
        finally:
            self._stream.close()
        if self._error is not None:
            raise RecordingError(f"{self.path}: recording failed: {self._error}") from self._error
        if head is not None:
            self._seal(head)

    def _seal(self, head: str) -> None:
        """The chain head and the file's SHA-256 leave the file: the sidecar (signed
        with the station key when there is one)."""
        digest = self._stream.hexdigest()  # of every byte written (hashed_stream.py)
        signature = None
        if self._signing_key is not None:
            signature = seal.sign(self._signing_key, seal.seal_statement(head, digest))
        sealed = seal.Seal(self.path, head, digest, signature)
        try:
            sidecar = seal.write_sidecar(sealed)
        except seal.SealError as exc:
            raise RecordingError(f"{self.path}: the recording is finished but not sealed: {exc}") from None
        self.seal = seal.Seal(self.path, head, digest, signature, sidecar)


# --------------------------------------------------------------------------
# Message building
# --------------------------------------------------------------------------


def write_provenance(sink: Sink) -> None:
    """The ``crossfield.packages`` (installed versions now) and ``crossfield.machine``
    records, for a recording that is not a session (calibration, verification)."""
    from crossfield.chain.provenance import package_versions

    sink.metadata(L.META_PACKAGES, {str(k): str(v) for k, v in package_versions().items()})
    sink.metadata(L.META_MACHINE, metadata_record(machine_info()))


def global_points(points: CameraPoints, registration: Any) -> tuple[np.ndarray, np.ndarray]:
    """Camera points of a frame in the global frame, with propagated sigmas (mm).

    ``p_g = scale * R @ p_c + t`` (the registration, Formulas (5)-(9)); the
    sigmas are the diagonal of ``A diag(sigma_c^2) A^T``, ``A = scale R``
    (:func:`crossfield.covariance.global_sigma`; the registration's own
    uncertainty is not included).
    """
    fit = registration.fit
    xyz = fit.apply(points.xyz).reshape(-1, 3)
    A = float(fit.scale) * np.asarray(fit.R, dtype=np.float64)
    return xyz, global_sigma(A, points.sigma_xyz)


class SessionWriter:
    """Builds a session's messages, metadata and attachments and gives them to ``sink``.

    One method per event of a session, in the order the pipeline emits them
    (:meth:`session_start`, then per stereo pair :meth:`frame`,
    :meth:`centroids`, :meth:`camera_points`, :meth:`registration`,
    :meth:`measurement`, :meth:`frame_done`; :meth:`serial_bytes`,
    :meth:`reference` and :meth:`log` when they happen; :meth:`session_end`).
    Every message's log time is the time it stands for: the capture time of
    its stereo pair, the read time of serial bytes; session-level results
    get the latest time recorded so far.
    """

    def __init__(self, sink: Sink) -> None:
        self.sink = sink
        self._frame_times: dict[int, int] = {}
        self._camera_points: dict[int, CameraPoints] = {}
        self._latest_time_ns = 0
        self._static_time_ns: int | None = None
        self._session: Any = None
        self._serial_counts: dict[str, int] = {}
        self._overlay = FoxgloveOverlay()  # /camera/*/annotations, /scene (foxglove_overlay.py)

    # ---- plumbing -------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self.sink.closed

    def _message(
        self, spec: ChannelSpec, log_time: int, data: bytes, sequence: int = 0, *, advances_clock: bool = True
    ) -> None:
        log_time = int(log_time)
        if advances_clock:
            self._latest_time_ns = max(self._latest_time_ns, log_time)
        self.sink.message(spec, log_time, data, sequence)

    def _json(self, topic: str, schema_name: str, doc: Any, log_time: int, sequence: int = 0) -> None:
        self._message(json_channel(topic, schema_name), log_time, dump_json(doc), sequence)

    def _now(self) -> int:
        """Time for a session-level result with no timestamp of its own: the
        latest time recorded so far (it sorts after the data it derives
        from), or the wall clock before anything was recorded."""
        return self._latest_time_ns or time.time_ns()

    def _frame_time(self, sequence: int) -> int:
        return self._frame_times.get(int(sequence)) or self._now()

    def flush(self) -> None:
        self.sink.flush()

    def close(self) -> None:
        self.sink.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- session start: facts, attachments, static data ----------------

    def session_start(self, session: Any) -> None:
        """The session facts (metadata records), attachments and static data."""
        self._session = session
        self._overlay.plan = session.plan
        start = int(session.start_time_ns or time.time_ns())
        self._latest_time_ns = max(self._latest_time_ns, start)
        version = crossfield_version(session.packages)
        calibration_text = calibration_yaml(session.calibration).encode()
        session_doc = {
            "session_id": session.session_id,
            "start_time_ns": start,
            "start_time_utc": utc_text(start),
            "crossfield_version": version,
            "recording_format": L.RECORDING_FORMAT,
            "out_dir": str(session.out_dir),
            "config_source": session.config.source,
            "plan_name": session.plan.name,
            "plan_source": session.plan.source,
            "plan_sha256": session.plan.sha256,
            "calibration_source": session.calibration.source,
            "calibration_sha256": hashlib.sha256(calibration_text).hexdigest(),
            # the calibration file(s) themselves, attached below (recording/calibration_files.py)
            "calibration_files": [f.entry() for f in session.calibration_files or ()],
            "simulated": session.ground_truth is not None,
            "parent": plain(session.parent),
            "units": "JSON messages: mm, rad, px; foxglove PointCloud and FrameTransforms: m",
        }
        sink = self.sink
        sink.metadata(L.META_SESSION, metadata_record(session_doc))
        config = session.config.to_dict()
        config_record = {"source": session.config.source, L.META_JSON: json.dumps(plain(config), allow_nan=False)}
        try:
            config_record["toml"] = toml_text(config)
        except TypeError as exc:  # a value TOML cannot hold: the JSON stays exact
            config_record["toml_error"] = str(exc)
        sink.metadata(L.META_CONFIG, config_record)
        sink.metadata(L.META_PLUGINS, metadata_record(session.plugins))
        sink.metadata(L.META_PACKAGES, {str(k): str(v) for k, v in session.packages.items()})
        sink.metadata(L.META_ACQUISITION, metadata_record(session.acquisition))
        sink.metadata(L.META_MACHINE, metadata_record(machine_info()))

        sink.attachment(L.ATTACHMENT_PLAN, "application/toml", session.plan.text.encode("utf-8"), start)
        sink.attachment(L.ATTACHMENT_CALIBRATION, "application/yaml", calibration_text, start)
        for copy in session.calibration_files or ():
            sink.attachment(copy.attachment, copy.media_type, copy.data, start)
        if session.ground_truth is not None:
            sink.attachment(
                L.ATTACHMENT_GROUND_TRUTH,
                "application/json",
                json.dumps(ground_truth_doc(session.ground_truth), indent=1, allow_nan=False).encode(),
                start,
            )
        self._write_static(start)
        self.flush()

    def _write_static(self, timestamp_ns: int) -> None:
        """Calibrations and the upper -> lower transform, at ``timestamp_ns``."""
        calibration = self._session.calibration
        self._static_time_ns = int(timestamp_ns)
        for camera in CAMERAS:
            self._message(
                protobuf_channel(L.calibration_topic(camera), CameraCalibration),
                timestamp_ns,
                camera_calibration_message(calibration.camera(camera), camera, timestamp_ns),
            )
        self._message(
            protobuf_channel(L.TOPIC_TF, FrameTransforms),
            timestamp_ns,
            frame_transforms_message([upper_to_lower_pose(calibration)], timestamp_ns),
        )

    # ---- raw inputs -----------------------------------------------------

    def frame(self, frame: Any) -> None:
        """Both raw images of a stereo pair (lossless), at its capture time."""
        t = int(frame.timestamp_ns)
        seq = int(frame.sequence)
        self._frame_times[seq] = t
        if len(self._frame_times) > 256:
            self._frame_times.pop(next(iter(self._frame_times)))
        if self._session is not None and self._static_time_ns is not None and t < self._static_time_ns:
            # A source stamping frames with its own clock, earlier than the
            # session start: repeat the static data so that viewers find the
            # calibration at every frame.
            self._write_static(t)
        for camera in CAMERAS:
            image = frame.image(camera)
            spec = protobuf_channel(
                L.image_topic(camera), RawImage, ((L.CHANNEL_BIT_DEPTH, str(int(frame.bit_depth))),)
            )
            self._message(spec, t, raw_image_message(image, camera, t), seq)

    def serial_bytes(self, data: bytes, timestamp_ns: int, source: str) -> None:
        """The exact bytes of one read from the CMM line (sequence: the read index per source)."""
        source = str(source)
        count = self._serial_counts.get(source, 0)
        self._serial_counts[source] = count + 1
        self._message(raw_channel(source), timestamp_ns, bytes(data), count)

    def serial_event(self, kind: str, detail: str, timestamp_ns: int, source: str) -> None:
        """A link event of the CMM line (down/up), in file order with its bytes."""
        key = f"{source}\n{L.LINK_EVENTS}"
        count = self._serial_counts.get(key, 0)
        self._serial_counts[key] = count + 1
        doc = {"event": str(kind), "detail": str(detail)}
        self._message(link_event_channel(str(source)), timestamp_ns, dump_json(doc), count)

    # ---- stage outputs --------------------------------------------------

    def reference(self, reference: Any) -> None:
        t = self._now()
        xyz = np.array([p.xyz for p in reference.points], dtype=np.float64).reshape(-1, 3)
        self._message(
            protobuf_channel(L.TOPIC_POINTS_REFERENCE, PointCloud),
            t,
            point_cloud_message(xyz, L.FRAME_GLOBAL, t),
        )
        twin = {
            "frame": L.FRAME_GLOBAL,
            "units": "mm",
            "count": len(reference.points),
            "ids": [p.label for p in reference.points],
            "xyz_mm": reals(xyz),
            "sigma_mm": [real(p.sigma_mm) for p in reference.points],
        }
        self._json(L.TOPIC_POINTS_REFERENCE_JSON, L.SCHEMA_REFERENCE_POINTS, twin, t)
        self._json(L.TOPIC_REFERENCE, L.SCHEMA_REFERENCE, reference_doc(reference), t)
        self._message(protobuf_channel(L.TOPIC_SCENE, SceneUpdate), t, self._overlay.reference(reference, t))
        self.flush()

    def centroids(self, centroids: Any) -> None:
        t = self._frame_time(centroids.sequence)
        for camera in CAMERAS:
            cs = getattr(centroids, camera)
            self._json(L.centroids_topic(camera), L.SCHEMA_CENTROIDS, centroids_doc(cs), t, cs.sequence)

    def camera_points(self, points: Any) -> None:
        seq = int(points.sequence)
        t = self._frame_time(seq)
        self._camera_points[seq] = points
        while len(self._camera_points) > 8:
            self._camera_points.pop(next(iter(self._camera_points)))
        self._message(
            protobuf_channel(L.TOPIC_POINTS_CAMERA, PointCloud),
            t,
            point_cloud_message(points.xyz, L.FRAME_CAMERA, t),
            seq,
        )
        self._json(L.TOPIC_POINTS_CAMERA_JSON, L.SCHEMA_CAMERA_POINTS, camera_points_doc(points), t, seq)

    def registration(self, registration: Any) -> None:
        seq = int(registration.sequence)
        t = self._frame_time(seq)
        fit = registration.fit
        pose = FramePose(L.FRAME_GLOBAL, L.FRAME_CAMERA, np.asarray(fit.R), np.asarray(fit.t))
        self._message(
            protobuf_channel(L.TOPIC_TF, FrameTransforms), t, frame_transforms_message([pose], t), seq
        )
        self._json(L.TOPIC_REGISTRATION, L.SCHEMA_REGISTRATION, registration_doc(registration), t, seq)
        points = self._camera_points.get(seq)
        if points is not None:
            xyz, sigma = global_points(points, registration)
            ids: list[str | None] = [None] * len(points)
            for index, cid in zip(
                registration.correspondence.camera_index, registration.correspondence.control_ids
            ):
                if 0 <= int(index) < len(ids):
                    ids[int(index)] = str(cid)
            self._message(
                protobuf_channel(L.TOPIC_POINTS_GLOBAL, PointCloud),
                t,
                point_cloud_message(xyz, L.FRAME_GLOBAL, t),
                seq,
            )
            twin = {
                "sequence": seq,
                "frame": L.FRAME_GLOBAL,
                "units": "mm",
                "count": len(points),
                "ids": ids,
                "camera_index": list(range(len(points))),
                "xyz_mm": reals(xyz),
                "sigma_xyz_mm": reals(sigma),
            }
            self._json(L.TOPIC_POINTS_GLOBAL_JSON, L.SCHEMA_GLOBAL_POINTS, twin, t, seq)

    def measurement(self, measurement: Any) -> None:
        seq = int(measurement.sequence)
        self._json(
            L.TOPIC_MEASUREMENT, L.SCHEMA_MEASUREMENT, measurement_doc(measurement), self._frame_time(seq), seq
        )

    def frame_done(self, result: Any) -> None:
        seq = int(result.sequence)
        t = int(result.timestamp_ns) or self._frame_time(seq)
        self._json(L.TOPIC_FRAMES, L.SCHEMA_FRAME_STATUS, frame_status_doc(result), t, seq)
        for camera, data in self._overlay.annotations(result, t).items():
            self._message(protobuf_channel(L.annotations_topic(camera), ImageAnnotations), t, data, seq)
        self._message(protobuf_channel(L.TOPIC_SCENE, SceneUpdate), t, self._overlay.frame(result, t), seq)
        self._camera_points.pop(seq, None)
        self.flush()

    def log(self, level: str, message: str, timestamp_ns: int) -> None:
        t = int(timestamp_ns) or self._now()
        # Device events (link down, dropped frame) are logged at wall-clock
        # times a replay cannot know: they must not move the time stamps of
        # the results, which a replay reproduces from the data's own times.
        self._message(protobuf_channel(L.TOPIC_LOG, Log), t, log_message(level, message, t), advances_clock=False)

    def session_stop(self, stop: Any) -> None:
        """Why the session stopped early (``/session/stop``, :mod:`crossfield.recording.stop`),
        at the time it stopped; like a log line it does not move the results' time stamps."""
        from crossfield.recording.stop import stop_doc

        t = int(stop.timestamp_ns) or self._now()
        self._message(
            json_channel(L.TOPIC_SESSION_STOP, L.SCHEMA_SESSION_STOP), t, dump_json(stop_doc(stop)),
            advances_clock=False,
        )
        self.flush()

    def session_end(self, summary: Any) -> None:
        """The session report (``/report``) and result record; then the sink is closed."""
        if self.sink.closed:
            return
        t = self._now()
        try:
            report = document_of(summary)
        except Exception as exc:  # noqa: BLE001 - the recording must still be finished
            self._message(
                protobuf_channel(L.TOPIC_LOG, Log), t, log_message("error", f"recorder: no /report: {exc}", t)
            )
        else:
            self._json(L.TOPIC_REPORT, L.SCHEMA_REPORT, report, t)
        result = {
            "passed": bool(summary.passed),
            "incomplete": summary.incomplete,
            "frames": summary.frames_processed,
            "frames_failed": summary.frames_failed,
            "rms_error_mm": real(summary.rms_error_mm()),
            "report_files": [str(p) for p in summary.report_files],
        }
        self.sink.metadata(L.META_RESULT, metadata_record(result))
        self.close()
