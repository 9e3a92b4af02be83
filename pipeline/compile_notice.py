"""Say so when the numeric kernels compile (numba, first run only).

The compiled kernels (``crossfield.imaging``: blob runs, the disc-model fit, the
eccentricity terms) are ``numba.njit(cache=True)``: compiled on their first call
and kept in numba's cache (``__pycache__`` beside the source, or numba's user
cache for a read-only install), so only the first run of an installation pays
the 20-60 s. numba fires its ``numba:compile`` event only when it really compiles
(a cache miss), not when it loads a cached kernel: the first such event prints
:data:`MESSAGE` once, on a terminal, above any progress bar
(:func:`crossfield.progress.note`: the same rule as the bars, nothing on a pipe or
under ``-q``)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from numba.core import event

from crossfield import progress

__all__ = ["MESSAGE", "announced"]

MESSAGE = "crossfield: compiling the numeric kernels (first run only, cached afterwards; about 20-60 s) ..."


class _FirstCompile(event.Listener):
    """Prints :data:`MESSAGE` at the start of the first compilation it sees."""

    def __init__(self) -> None:
        self.said = False

    def on_start(self, ev: event.Event) -> None:
        if not self.said:
            self.said = True
            progress.note(MESSAGE)

    def on_end(self, ev: event.Event) -> None:
        pass


@contextlib.contextmanager
def announced() -> Iterator[None]:
    """While the block runs, the first kernel compilation is announced (once)."""
    with event.install_listener("numba:compile", _FirstCompile()):
        yield
