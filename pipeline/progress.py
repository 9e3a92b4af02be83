"""Progress display: an observer that shows frames done on stderr."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from crossfield.hookspecs import hookimpl


class Progress:
    """Prints ``frame k/N`` with the latest registration RMS; one line, redrawn
    in place on a terminal, every ``every`` frames otherwise."""

    def __init__(self, total: int | None = None, stream: TextIO | None = None, every: int = 10) -> None:
        self.total = total
        self.stream = stream or sys.stderr
        self.every = every
        self.done = 0
        self.failed = 0
        self.started = time.perf_counter()

    @hookimpl
    def on_frame_done(self, result) -> None:
        self.done += 1
        self.failed += result.error is not None
        tty = self.stream.isatty()
        if not tty and self.done % self.every and self.done != self.total:
            return
        rms = result.registration.fit.rms_mm if result.registration is not None else float("nan")
        rate = self.done / max(time.perf_counter() - self.started, 1e-9)
        of = f"/{self.total}" if self.total else ""
        text = f"frame {self.done}{of}  registration RMS {rms:.4f} mm  {rate:.1f} pairs/s"
        if self.failed:
            text += f"  ({self.failed} failed)"
        self.stream.write(("\r" + text) if tty else text + "\n")
        self.stream.flush()

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        if level in ("warning", "error"):
            if self.stream.isatty():
                self.stream.write("\n")
            self.stream.write(f"{level}: {message}\n")

    @hookimpl
    def on_session_end(self, summary) -> None:
        if self.stream.isatty():
            self.stream.write("\n")
        self.stream.flush()
