"""The MCAP session recorder: an observer plugin writing one ``session.mcap``.

Layout (``docs/recording.md``, :mod:`crossfield.recording.layout`): raw
inputs (both camera images, the exact serial bytes), every stage output,
the log, and the session's facts (config, plugins, packages, plan,
calibration) in one MCAP file. Where a Foxglove schema exists it is used
with protobuf encoding, so Foxglove and Rerun (``rerun session.mcap``,
``rerun mcap convert``) display the data without code of ours; the stage
results are JSON with a JSON Schema (``pipeline/recording/schemas/``).

This module is only the observer: each hook hands its stage output to a
:class:`crossfield.recording.writer.SessionWriter`, which builds the
messages (:mod:`crossfield.recording.codec`) and gives them to a sink
(:class:`~crossfield.recording.writer.McapFileSink` for a file,
:class:`~crossfield.recording.writer.MemorySink` for the audit).
"""

from __future__ import annotations

import atexit
from pathlib import Path
from typing import Any, Self

from crossfield.errors import RecordingError
from crossfield.hookspecs import hookimpl
from crossfield.recording.seal import Seal
from crossfield.recording.writer import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_COMPRESSION,
    McapFileSink,
    SessionWriter,
    Sink,
)
from crossfield.report.document import REPORT_JSON, add_seal_to_file


class SessionRecorder:
    """Observer plugin: feeds every session hook to a :class:`SessionWriter` on ``sink``.

    Register an instance with the session's plugin manager; the sink is
    closed on ``on_session_end`` (or :meth:`close`).
    """

    def __init__(self, sink: Sink) -> None:
        self.sink = sink
        self.writer = SessionWriter(sink)

    @property
    def closed(self) -> bool:
        return self.sink.closed

    def flush(self) -> None:
        """Hand everything recorded so far on (closes the open chunk of a file)."""
        self.writer.flush()

    def close(self) -> None:
        """Finish the recording. Idempotent."""
        self.writer.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @hookimpl
    def on_session_start(self, session: Any) -> None:
        self.writer.session_start(session)

    @hookimpl
    def on_frame(self, frame: Any) -> None:
        self.writer.frame(frame)

    @hookimpl
    def on_serial_bytes(self, data: bytes, timestamp_ns: int, source: str) -> None:
        self.writer.serial_bytes(data, timestamp_ns, source)

    @hookimpl
    def on_serial_event(self, kind: str, detail: str, timestamp_ns: int, source: str) -> None:
        self.writer.serial_event(kind, detail, timestamp_ns, source)

    @hookimpl
    def on_reference(self, reference: Any) -> None:
        self.writer.reference(reference)

    @hookimpl
    def on_centroids(self, centroids: Any) -> None:
        self.writer.centroids(centroids)

    @hookimpl
    def on_camera_points(self, points: Any) -> None:
        self.writer.camera_points(points)

    @hookimpl
    def on_registration(self, registration: Any) -> None:
        self.writer.registration(registration)

    @hookimpl
    def on_measurement(self, measurement: Any) -> None:
        self.writer.measurement(measurement)

    @hookimpl
    def on_frame_done(self, result: Any) -> None:
        self.writer.frame_done(result)

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        self.writer.log(level, message, timestamp_ns)

    @hookimpl
    def on_session_stop(self, stop: Any) -> None:
        self.writer.session_stop(stop)

    def end_session(self, summary: Any) -> Seal | None:
        """Record the session's end (``/report``, the result record) and close
        the recording; the runner calls this before any report is written.
        Returns the seal (None for a sink that has none). Idempotent."""
        try:
            self.writer.session_end(summary)
        finally:
            self.close()
        return None

    @hookimpl
    def on_session_end(self, summary: Any) -> None:
        self.end_session(summary)


class McapRecorder(SessionRecorder):
    """Observer plugin: records one session into ``path`` (``session.mcap``).

    Register an instance with the session's plugin manager; it writes as
    the hooks fire and closes the file on ``on_session_end`` (or
    :meth:`close`; also at interpreter exit if neither ran).

    Options as :class:`crossfield.recording.writer.McapFileSink`: overwrite,
    chunk_size (bytes), writer_thread, queue_size, flush_interval_s (s),
    compression, signing_key (a PEM Ed25519 private key file). When the file
    is finished its seal (chain head, file SHA-256, signature) is written
    next to it (:mod:`crossfield.recording.seal`). The runner ends the
    recording with :meth:`end_session` *before* it writes the reports, which
    then carry the seal (``report.json`` key ``integrity``): no report exists
    while the recording is open or unchecked. An error writing the file is
    raised as :class:`crossfield.errors.RecordingError` from the next hook
    call (and from :meth:`close` and :meth:`end_session`).
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
    ):
        sink = McapFileSink(
            path,
            overwrite=overwrite,
            chunk_size=chunk_size,
            writer_thread=writer_thread,
            queue_size=queue_size,
            flush_interval_s=flush_interval_s,
            compression=compression,
            signing_key=signing_key,
        )
        super().__init__(sink)
        self.path = sink.path
        atexit.register(self.close)

    @property
    def seal(self) -> Seal | None:
        """The recording's seal once it is closed (None before, or if it failed)."""
        return self.sink.seal

    def close(self) -> None:
        """Finish the MCAP file (summary, indexes, footer), close it and seal it. Idempotent."""
        atexit.unregister(self.close)
        super().close()

    def end_session(self, summary: Any) -> Seal:
        """Record the session's end, close and seal the file, then check it:
        the file reads back complete (summary and footer) and its seal was
        computed from the bytes on disk. Returns the seal; any failure is a
        :class:`RecordingError` saying what failed (the part of the file
        already written stays readable: a reader sees an INCOMPLETE recording)."""
        if not self.closed:
            super().end_session(summary)
        return check_closed(self.path, self.seal)

    @hookimpl
    def on_session_end(self, summary: Any) -> None:
        """For use outside the runner: end the recording, then add the seal to
        the report.json the summary names (the runner ends the recording first
        and writes report.json with the seal itself)."""
        if self.closed:
            return
        sealed = self.end_session(summary)
        for path in summary.report_files:
            if Path(path).name == REPORT_JSON:
                add_seal_to_file(Path(path), sealed)


def check_closed(path: Path, sealed: Seal | None) -> Seal:
    """``sealed`` if the closed recording at ``path`` reads back complete and was
    sealed; else a :class:`RecordingError` naming the file and what is wrong."""
    from crossfield.recording.reader import open_recording

    if sealed is None:
        raise RecordingError(f"{path}: the recording was closed but not sealed")
    with open_recording(path) as rec:
        if not rec.complete:
            raise RecordingError(f"{path}: the recording does not read back complete: {rec.damage}")
    return sealed
