"""Ctrl-C (SIGINT) during a session: the first one ends the session as INCOMPLETE.

The runner (:func:`crossfield.chain.runner.run_session`) installs
:class:`OperatorInterrupts` as the SIGINT handler for the length of a
session (main thread only, and only over Python's default handler: an
application that installed its own keeps it). What a Ctrl-C does then
depends on where the session is (``docs/faults.md``, "Interrupted runs"):

* while a stereo pair is being processed (:meth:`OperatorInterrupts.deferred`):
  nothing at once; the pair is finished (its every result recorded, as a
  replay will compute it), then the session stops taking pairs;
* while waiting for the source (the next pair, the CMM import): a
  :class:`KeyboardInterrupt` there at once, which the runner takes as the
  stop;
* the second Ctrl-C: :class:`InterruptedAgain` at once, wherever the session
  is (also while it writes its report), except while a recording is ended and
  closed (:meth:`OperatorInterrupts.shielded`): there it waits until the file
  is whole. The recorders are still closed on the way out, so the recording
  stays readable, but no report may be written;
* a third and later one: ignored, so that the recording can be closed.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType

__all__ = ["InterruptedAgain", "OperatorInterrupts", "operator_interrupts"]


class InterruptedAgain(KeyboardInterrupt):
    """A second Ctrl-C: stop now. The recording is closed on the way out (readable;
    replay and audit call it INCOMPLETE: it has no result record); the report may be missing."""


class OperatorInterrupts:
    """The session's SIGINT handler (see the module doc). ``count``: SIGINTs received;
    ``requested``: a first one arrived while a pair was processed (the runner
    stops after that pair)."""

    def __init__(self) -> None:
        self.count = 0
        self.requested = False
        self._deferring = False
        self._shielded = False
        self._pending = False

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.count += 1
        if self.count >= 3:
            return  # ignored while the recording is closed
        if self._shielded:
            self._pending = True
            return
        if self.count == 1 and self._deferring:
            self.requested = True
            return
        raise self._interrupt()

    def _interrupt(self) -> KeyboardInterrupt:
        if self.count == 1:
            return KeyboardInterrupt()
        return InterruptedAgain(
            "interrupted again while the session was finishing: the recording is closed (replay and "
            "audit read it); the report may be missing"
        )

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """A first Ctrl-C inside this block only sets :attr:`requested`."""
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False

    @contextlib.contextmanager
    def shielded(self) -> Iterator[None]:
        """No Ctrl-C interrupts this block (ending and closing a recording: a file
        half-closed would lose its index and footer); one that arrived meanwhile is
        raised when the block ends normally."""
        outer = self._shielded
        self._shielded = True
        try:
            yield
        finally:
            self._shielded = outer
        if self._pending and not outer:
            self._pending = False
            raise self._interrupt()


@contextlib.contextmanager
def operator_interrupts() -> Iterator[OperatorInterrupts | None]:
    """Install an :class:`OperatorInterrupts` as the SIGINT handler for the block and
    restore the previous one after it; yields None (and installs nothing) off the main
    thread or when SIGINT is not Python's default handler (ignored, or the
    application's own)."""
    if threading.current_thread() is not threading.main_thread():
        yield None
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is not signal.default_int_handler:
        yield None
        return
    handler = OperatorInterrupts()
    signal.signal(signal.SIGINT, handler)
    try:
        yield handler
    finally:
        signal.signal(signal.SIGINT, previous)
