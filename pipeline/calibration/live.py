"""Calibration pairs from live cameras: a key, a timer or a trigger takes a pair; a live coverage view.

``crossfield calibrate --source basler|opencv`` (``docs/calibration.md``,
"Calibrating from live cameras"). The cameras are opened by the acquire
plugin itself (its ``create()`` and ``frames()``), exactly as ``crossfield
run`` opens them; this module only decides when a pair is taken:

* ``key``: Enter on the terminal (a line; ``q`` then Enter ends), or space
  in the OpenCV window when one can be shown (``q`` / Esc end);
* ``every``: a pair every ``every_s`` seconds (Enter takes one more);
* ``trigger``: every pair the source delivers (the basler source with
  ``trigger = "hardware"``: each trigger pulse; the opencv source: each
  frame of a file or externally triggered camera).

How a pair is pulled: from an on-demand source (the basler source with its
software trigger, the opencv source reading a file) the next pair is
requested when it is taken, so the software trigger fires at the key press.
A free-running source (a camera triggered by a line, an opencv device
index) keeps delivering; a reader thread keeps only its latest pair
(:class:`LatestPair`) and a key press takes the first pair that arrives
after it, never one buffered before.

After every pair the coverage of each image by the board points so far
(:mod:`crossfield.calibration.coverage`) is printed as one line and, when
asked, logged to Rerun (:class:`CoverageLog`). Ctrl-C, ``q``, the end of the
source, the end of the terminal input (key mode) or ``pairs`` taken pairs
end the capture; what was taken is returned.
"""

from __future__ import annotations

import os
import queue
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np

from crossfield.calibration.boards import Board
from crossfield.calibration.coverage import CameraCoverage, camera_coverage, coverage_line, coverage_picture
from crossfield.calibration.detect import BoardDetection, BoardDetector, to_uint8
from crossfield.errors import ConfigError, RecordingError
from crossfield.types import CAMERAS, StereoFrame

__all__ = [
    "MODES",
    "CoverageLog",
    "KeyEvents",
    "LatestPair",
    "LivePair",
    "LivePairs",
    "capture_live",
    "window_available",
    "write_provisional_calibration",
]

#: How pairs are taken (module docstring).
MODES: tuple[str, ...] = ("key", "every", "trigger")

TAKE, QUIT, END = "take", "quit", "end of input"


def write_provisional_calibration(path: str | Path) -> Path:
    """A placeholder calibration for the acquire plugins, which need one to open the cameras.

    fx = fy = 1000 px, principal point 0, no distortion, R = I, T = (-1, 0, 0) mm,
    and no image size (the cameras report theirs). It is never used to measure:
    the calibration being made replaces it.
    """
    path = Path(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise ConfigError(f"{path}: cannot write the provisional calibration")
    fs.writeComment("crossfield calibrate: provisional calibration to open the cameras; not for measuring")
    K = np.array([[1000.0, 0, 0], [0, 1000.0, 0], [0, 0, 1]])
    for key, value in (("M1", K), ("D1", np.zeros((1, 5))), ("M2", K), ("D2", np.zeros((1, 5))),
                       ("R", np.eye(3)), ("T", np.array([[-1.0], [0.0], [0.0]]))):  # fmt: skip
        fs.write(key, value)
    fs.release()
    return path


# ---- when to take a pair -------------------------------------------------------------------------


class KeyEvents:
    """Key presses as events (``take``, ``quit``, ``end of input``) from the terminal and the window.

    Terminal: a reader thread takes ``stream`` line by line: an empty line
    (Enter) or any text but ``q`` is ``take``; ``q`` is ``quit``; the end of
    the stream is ``end of input``. ``on_quit`` is called on ``quit`` (from
    that thread; :func:`capture_live` sets it when the source is not asked
    for pairs by keys): it stops the source so that a wait for a trigger ends.
    """

    def __init__(self, stream: TextIO | None = None, on_quit: Callable[[], None] | None = None):
        self.events: queue.Queue[str] = queue.Queue()
        self.on_quit = on_quit
        self.stream = stream
        self.quit_requested = False
        if stream is not None:
            threading.Thread(target=self._read, name="calibrate-keys", daemon=True).start()

    def _read(self) -> None:
        assert self.stream is not None
        for line in iter(self.stream.readline, ""):
            self.put(QUIT if line.strip().lower() in ("q", "quit") else TAKE)
        self.put(END)

    def put(self, event: str) -> None:
        """Post an event (the window's keys come this way)."""
        if event == QUIT:
            self.quit_requested = True
            if self.on_quit is not None:
                self.on_quit()
        self.events.put(event)

    def get(self, timeout: float | None, idle: Callable[[], None] | None = None) -> str | None:
        """The next event, or None when none came within ``timeout`` s (None = wait for one).

        ``idle`` (e.g. the window's event loop) is called every 50 ms while waiting."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            step = remaining if idle is None else min(0.05, 0.05 if remaining is None else remaining)
            try:
                return self.events.get(timeout=step) if step is None or step > 0 else self.events.get_nowait()
            except queue.Empty:
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                if idle is not None:
                    idle()


def window_available() -> bool:
    """Whether an OpenCV window can be shown (a display, and an OpenCV built with a GUI)."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return False
    try:
        cv2.namedWindow("crossfield calibrate", cv2.WINDOW_NORMAL)
    except cv2.error:  # opencv-python-headless: "The function is not implemented"
        return False
    return True


class LatestPair:
    """The latest pair of a free-running source: a reader thread consumes ``frames``.

    :meth:`take` returns the first pair that arrives after the call (None
    when the source ends first), so a pair is never one buffered before the
    key press.
    """

    def __init__(self, frames: Iterator[StereoFrame]):
        self._frames = frames
        self._cond = threading.Condition()
        self._latest: StereoFrame | None = None
        self._count = 0
        self._ended = False
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="calibrate-latest", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            for frame in self._frames:
                with self._cond:
                    self._latest, self._count = frame, self._count + 1
                    self._cond.notify_all()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller of take()
            self.error = exc
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()

    def take(self, timeout_s: float | None = None) -> StereoFrame | None:
        """The first pair delivered after this call (waits up to ``timeout_s``; None = for ever)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            seen = self._count
            while self._count == seen and not self._ended:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(0.1 if remaining is None else min(remaining, 0.1))
            if self.error is not None:
                raise self.error
            return self._latest if self._count > seen else None

    def join(self, timeout_s: float = 5.0) -> None:
        """Wait for the reader to end (after the source was stopped)."""
        self._thread.join(timeout_s)


# ---- the capture -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class LivePair:
    """One taken pair: index (0, 1, ...), the source's frame, the board found per camera (None = not)."""

    index: int
    frame: StereoFrame
    detections: Mapping[str, BoardDetection | None]


@dataclass(frozen=True)
class LivePairs:
    """What a live capture took.

    images: per pair camera -> (H, W) uint16 image (``bit_depth`` bits);
    names: ``live pair <k> (frame <sequence>)``; coverage: per camera after
    the last pair; ended_by: ``pairs``, ``quit``, ``interrupt``, ``source
    ended`` or ``end of input``.
    """

    images: tuple[dict[str, np.ndarray], ...]
    names: tuple[str, ...]
    bit_depth: int
    coverage: Mapping[str, CameraCoverage]
    ended_by: str


def capture_live(
    frames: Iterator[StereoFrame],
    board: Board,
    events: KeyEvents,
    *,
    mode: str = "key",
    every_s: float = 2.0,
    pairs: int = 0,
    free_running: bool = False,
    min_points: int = 6,
    on_pair: Callable[[LivePair, Mapping[str, CameraCoverage]], None] | None = None,
    idle: Callable[[], None] | None = None,
    stop: Callable[[], None] = lambda: None,
) -> LivePairs:
    """Take pairs from ``frames`` (a source's :meth:`frames` iterator) until the capture ends.

    mode: ``key``, ``every`` (``every_s`` seconds apart) or ``trigger``
    (module docstring); pairs: end after this many (0 = until ``q``, Ctrl-C
    or the end of the source); free_running: the source delivers without
    being asked (:class:`LatestPair`); min_points: fewest board points for a
    view to count as detected (as :func:`crossfield.calibration.solve.calibrate_images`).
    ``on_pair(pair, coverage)`` is called after every pair (the live view),
    ``idle()`` while waiting for a key (the window's event loop); ``stop()``
    (the source's :meth:`stop`) ends a free-running source's reader at the end.
    """
    if mode not in MODES:
        raise ConfigError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    detector = BoardDetector(board, min_points=min_points)
    latest = LatestPair(frames) if free_running and mode != "trigger" else None
    if mode == "trigger" or latest is not None:
        # Pairs are not asked for by keys: a quit must end the wait for the next pair at once.
        # (Otherwise it is taken in turn, after the keys typed before it.)
        events.on_quit = stop
    taken: list[LivePair] = []
    coverage: dict[str, CameraCoverage] = {}

    def pull() -> StereoFrame | None:
        if latest is not None:  # a quit stops the source, which ends the wait
            return latest.take()
        return next(frames, None)

    def take(frame: StereoFrame) -> None:
        found = {cam: detector.detect(frame.image(cam), frame.bit_depth) for cam in CAMERAS}
        pair = LivePair(len(taken), frame, found)
        taken.append(pair)
        for cam in CAMERAS:
            h, w = frame.image(cam).shape
            coverage[cam] = camera_coverage(cam, [p.detections[cam] for p in taken], (w, h))
        if on_pair is not None:
            on_pair(pair, dict(coverage))

    ended_by = "pairs"
    try:
        if mode == "trigger":
            ended_by = "source ended"
            for frame in frames:
                take(frame)
                if pairs and len(taken) >= pairs:
                    ended_by = "pairs"
                    break
                if events.get(0, idle) == QUIT or events.quit_requested:
                    ended_by = "quit"
                    break
        else:
            next_at = time.monotonic() + every_s
            while not pairs or len(taken) < pairs:
                if mode == "key":
                    event = events.get(None, idle)
                else:
                    event = events.get(max(0.0, next_at - time.monotonic()), idle) or TAKE
                    if event == END:
                        continue  # no terminal input: the timer goes on
                    if event == TAKE:
                        next_at = time.monotonic() + every_s
                if event in (QUIT, END):
                    ended_by = event
                    break
                frame = pull()
                if frame is None:
                    ended_by = "quit" if events.quit_requested else "source ended"
                    break
                take(frame)
        if ended_by == "source ended" and events.quit_requested:  # the quit stopped the source
            ended_by = "quit"
    except KeyboardInterrupt:
        ended_by = "interrupt"
    finally:
        if latest is not None:
            stop()
            latest.join()
    images = tuple({cam: np.asarray(p.frame.image(cam)) for cam in CAMERAS} for p in taken)
    bit_depth = taken[0].frame.bit_depth if taken else 0
    names = tuple(f"live pair {p.index} (frame {p.frame.sequence})" for p in taken)
    return LivePairs(images, names, bit_depth, coverage, ended_by)


# ---- the live view ---------------------------------------------------------------------------------


def print_pair(pair: LivePair, coverage: Mapping[str, CameraCoverage], stream: TextIO | None = None) -> None:
    """The terminal's live view: one line per pair (points found, then :func:`coverage_line`)."""
    def found_in(cam: str, d: BoardDetection | None) -> str:
        if d is not None:
            return f"{cam} {len(d)} points"
        peak, full = int(np.max(pair.frame.image(cam))), (1 << pair.frame.bit_depth) - 1
        dark = f" (peak {peak} of {full}: dark, or set the source's bit_depth)" if peak < full / 8 else ""
        return f"{cam}: board not found{dark}"

    found = ", ".join(found_in(cam, d) for cam, d in pair.detections.items())
    print(f"pair {pair.index + 1} (frame {pair.frame.sequence}): {found} | {coverage_line(coverage)}",
          file=sys.stdout if stream is None else stream, flush=True)  # fmt: skip


class CoverageLog:
    """The live coverage view in Rerun: per camera the :func:`coverage_picture` over the latest
    image (``calibration/<camera>/coverage``), the covered share (``calibration/<camera>/covered``,
    Scalars) and the terminal's line (``calibration/log``, TextLog), on the timeline ``pair``.

    rrd_path: save to a file; viewer: a viewer's URL (``rerun+http://HOST:PORT/proxy``); either or both.
    """

    def __init__(self, rrd_path: str | Path | None = None, *, viewer: str | None = None):
        import rerun as rr

        if rrd_path is None and not viewer:
            raise ValueError("CoverageLog needs an .rrd path, a viewer URL or both")
        self.rr = rr
        self.rec = rr.RecordingStream("crossfield-calibrate", recording_id=uuid.uuid4())
        sinks: list[Any] = []
        try:
            if rrd_path is not None:
                sinks.append(rr.FileSink(str(rrd_path)))
            if viewer:
                sinks.append(rr.GrpcSink(viewer))
            self.rec.set_sinks(*sinks)
        except Exception as exc:  # noqa: BLE001 - rerun raises several types
            where = rrd_path if rrd_path is not None else viewer
            raise RecordingError(f"{where}: cannot write the Rerun live view: {exc}") from None

    def __call__(self, pair: LivePair, coverage: Mapping[str, CameraCoverage]) -> None:
        rr = self.rr
        self.rec.set_time("pair", sequence=pair.index)
        for cam, c in coverage.items():
            d = pair.detections.get(cam)
            image = to_uint8(np.asarray(pair.frame.image(cam)), pair.frame.bit_depth)
            picture = coverage_picture(c, None if d is None else d.image_points, image)
            self.rec.log(f"calibration/{cam}/coverage", rr.Image(picture))
            self.rec.log(f"calibration/{cam}/covered", rr.Scalars(c.fraction))
        self.rec.log("calibration/log", rr.TextLog(coverage_line(coverage)))

    def close(self) -> None:
        """Flush and end the recording / stream."""
        self.rec.flush()
        self.rec.disconnect()


class CoverageWindow:
    """The OpenCV window (when :func:`window_available`): the upper and lower coverage pictures
    side by side; space takes a pair, ``q`` or Esc ends (posted to ``events``)."""

    NAME = "crossfield calibrate"

    def __init__(self, events: KeyEvents):
        self.events = events
        self.picture: np.ndarray | None = None

    def __call__(self, pair: LivePair, coverage: Mapping[str, CameraCoverage]) -> None:
        tiles = []
        for cam, c in coverage.items():
            d = pair.detections.get(cam)
            image = to_uint8(np.asarray(pair.frame.image(cam)), pair.frame.bit_depth)
            tiles.append(coverage_picture(c, None if d is None else d.image_points, image, scale=0.4))
        height = min(t.shape[0] for t in tiles)
        self.picture = np.hstack([t[:height] for t in tiles])
        cv2.imshow(self.NAME, cv2.cvtColor(self.picture, cv2.COLOR_RGB2BGR))
        self.poll()

    def close(self) -> None:
        cv2.destroyWindow(self.NAME)

    def poll(self) -> None:
        """Pass the window's key presses on (call regularly: OpenCV handles its events here)."""
        key = cv2.waitKey(30) & 0xFF
        if key == ord(" "):
            self.events.put(TAKE)
        elif key in (ord("q"), 27):
            self.events.put(QUIT)
