"""Progress on a terminal (tqdm): a bar with a count, a rate and an ETA for every
step that can take more than a second (docs/user-guide.md, "Progress").

One rule for every command: a bar is drawn only when

* the command line turned progress on (:func:`shown`: every ``crossfield``
  command does, except under ``-q``), or a caller asked for it
  (``Progress(enabled=True)``, ``crossfield.run(progress=True)``), and
* the stream (stderr) is a terminal.

Otherwise nothing is drawn, not even a last line: a pipe or a log file gets the
command's results and its log lines only. Bars are transient (erased when their
step ends), so a finished command leaves its results on the screen, not bars.
One bar at a time: a bar opened while another is drawn (a prediction inside a
sweep, the replay inside an audit step) stays silent, the outer step's bar counts.

:func:`bar` is the one constructor of the steps (``calibrate``, ``verify``,
``audit``, the Monte Carlo check, ``plan --sweep``, ``batch``); :class:`Progress`
is the observer of a session (``run``, ``replay``, the audit's reproduction)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterable, Iterator
from typing import Any, TextIO, TypeVar

from tqdm import tqdm

from crossfield.hookspecs import hookimpl

__all__ = ["Progress", "bar", "drawing", "note", "shown"]

T = TypeVar("T")

_shown = False  # set by the command line (shown()); a process-wide switch, as the terminal is
_drawn = 0  # bars being drawn now (0 or 1: an inner bar is silent)


class _Bar(tqdm):
    """tqdm that gives the terminal back (:data:`_drawn`) when it closes."""

    holds_terminal = False

    def close(self) -> None:
        global _drawn
        if self.holds_terminal:
            self.holds_terminal = False
            _drawn -= 1
        super().close()


@contextlib.contextmanager
def shown(on: bool = True) -> Iterator[None]:
    """While the block runs, :func:`bar` and :class:`Progress` draw on a terminal
    (``on``); ``crossfield``'s :func:`~crossfield.cli.main` sets it to ``not -q``."""
    global _shown
    previous, _shown = _shown, on
    try:
        yield
    finally:
        _shown = previous


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a closed or fd-less stream
        return False


def drawing(enabled: bool | None = None, stream: TextIO | None = None) -> bool:
    """Whether a bar would be drawn: ``enabled`` (None: the :func:`shown` switch) and
    ``stream`` (default stderr) a terminal."""
    return (_shown if enabled is None else enabled) and _is_terminal(stream or sys.stderr)


def bar(
    iterable: Iterable[T] | None = None,
    *,
    desc: str,
    total: int | None = None,
    unit: str = "it",
    enabled: bool | None = None,
    stream: TextIO | None = None,
    unit_scale: bool = False,
) -> Any:
    """A tqdm bar on ``stream`` (stderr) labelled ``desc``, counting ``unit`` (``unit_scale``:
    with k/M/G prefixes, e.g. bytes); drawn as :func:`drawing` says, else a silent
    pass-through (tqdm's ``disable``). Use it as tqdm: iterate it, or
    ``with bar(total=n, desc=...) as b: ... b.update()``."""
    global _drawn
    stream = stream or sys.stderr
    draw = drawing(enabled, stream) and _drawn == 0
    b = _Bar(
        iterable, desc=desc, total=total, unit=unit, unit_scale=unit_scale, file=stream, leave=False,
        dynamic_ncols=True, mininterval=0.2, disable=not draw,
    )
    if draw:
        b.holds_terminal = True
        _drawn += 1
    return b


def note(text: str, enabled: bool | None = None, stream: TextIO | None = None) -> None:
    """One line on a terminal (as :func:`drawing` says), above any bar being drawn."""
    stream = stream or sys.stderr
    if drawing(enabled, stream):
        tqdm.write(text, file=stream)


class Progress:
    """Observer of a session: a bar of the stereo pairs done (of ``total`` if known),
    with the latest registration RMS (mm) and the failed pairs, drawn as :func:`drawing`
    says (``enabled``: None follows :func:`shown`). ``log``: also print the session's
    warning and error log lines (``warning: ...``) to the stream, terminal or not."""

    def __init__(
        self,
        total: int | None = None,
        stream: TextIO | None = None,
        *,
        desc: str = "pairs",
        enabled: bool | None = None,
        log: bool = True,
    ) -> None:
        self.total = total
        self.stream = stream or sys.stderr
        self.desc = desc
        self.enabled = enabled
        self.log = log
        self.done = 0
        self.failed = 0
        self._bar: Any = None

    def _open(self) -> Any:
        if self._bar is None:
            self._bar = bar(desc=self.desc, total=self.total, unit="pair", enabled=self.enabled, stream=self.stream)
        return self._bar

    @hookimpl
    def on_session_start(self, session) -> None:
        self._open()  # 0/N at once: the first pair may take a while (the kernels' first compile)

    @hookimpl
    def on_frame_done(self, result) -> None:
        self.done += 1
        self.failed += result.error is not None
        if self.total is not None and self.done > self.total:
            return  # more pairs than announced: the bar closed at the total
        b = self._open()
        rms = result.registration.fit.rms_mm if result.registration is not None else float("nan")
        b.set_postfix_str(f"RMS {rms:.4f} mm" + (f", {self.failed} failed" if self.failed else ""), refresh=False)
        if not b.update():  # tqdm draws at most every 0.2 s: every pair drawn all the same
            b.refresh()
        if self.total is not None and self.done >= self.total:
            self._close()  # the pairs are done: the session end's steps (Monte Carlo check) show theirs

    @hookimpl
    def on_log(self, level: str, message: str, timestamp_ns: int) -> None:
        if self.log and level in ("warning", "error"):
            if drawing(self.enabled, self.stream):
                tqdm.write(f"{level}: {message}", file=self.stream)
            else:
                self.stream.write(f"{level}: {message}\n")

    def _close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    @hookimpl
    def on_session_end(self, summary) -> None:
        self._close()
        self.stream.flush()
