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
  is (also while it writes its report): the recorders are still closed on
  the way out, so the recording stays readable, but no report may be written;
* a third and later one while that cleanup runs: ignored, so that the
  recording can be closed.
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

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        self.count += 1
        if self.count == 1:
            if self._deferring:
                self.requested = True
                return
            raise KeyboardInterrupt
        if self.count == 2:
            raise InterruptedAgain(
                "interrupted again while the session was finishing: the recording is closed without "
                "its result record (replay and audit call it INCOMPLETE); the report may be missing"
            )
        # third and later: ignored while the recording is closed

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """A first Ctrl-C inside this block only sets :attr:`requested`."""
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False


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
