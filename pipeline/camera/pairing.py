"""Stereo pairing checks shared by the camera sources (``docs/cameras.md``).

A camera source must never hand out a pair whose two images belong to
different exposures. This module holds the bookkeeping that lets it refuse
one:

* :class:`Incident` / :class:`IncidentLog`: every dropped, late, failed or
  mismatched frame is recorded (kind, camera, sequence, message, host time),
  counted, written to Python logging and passed to an optional ``log``
  callable with the keyword arguments of the ``on_log`` observer hook
  (``level``, ``message``, ``timestamp_ns``);
* :class:`BlockCounter`: the frame-counter check under software triggering
  (each accepted trigger consumes exactly one block/frame id);
* :class:`ArrivalPairer`: pairing by time when the cameras are triggered
  externally (hardware line), where the source cannot know which pulse a
  frame answers.

Nothing here imports a camera SDK, so the logic is tested with synthetic
frame events (``tests/acquire/test_basler.py``).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass
from typing import Any, Callable, Iterator

import numpy as np

__all__ = [
    "INCIDENT_KINDS",
    "ArrivalPairer",
    "BlockCounter",
    "GrabbedFrame",
    "Incident",
    "IncidentLog",
    "LogCallable",
    "pair_skew_ns",
]

#: ``log(level=..., message=..., timestamp_ns=...)``, e.g. ``pm.hook.on_log``.
LogCallable = Callable[..., Any]

INCIDENT_KINDS: tuple[str, ...] = (
    "timeout",  # no frame within timeout_ms of the trigger / of the partner frame
    "grab_failed",  # the SDK delivered a failed (e.g. incomplete) buffer
    "late_frame",  # a frame of an earlier trigger arrived after its pair was given up
    "unexpected_frame",  # a frame arrived that no trigger of ours asked for
    "counter_mismatch",  # the camera's frame counter skipped ids: frames were lost
    "skew",  # the two frames are further apart in time than max_skew_ms
    "not_ready",  # a camera was not ready for a software trigger (none was sent)
    "no_partner",  # (external trigger) a frame whose partner never came
    "stream_ended",  # (video source) one stream ended before the other
    "stopped",  # acquisition gave up (too many consecutive drops, reader error)
)


@dataclass(frozen=True)
class Incident:
    """One detected acquisition problem.

    kind: one of :data:`INCIDENT_KINDS`. camera: ``upper``, ``lower`` or
    ``both``. sequence: the trigger / read index the problem belongs to
    (-1 when it belongs to none). host_ns: host time (ns since the epoch)
    at which it was detected.
    """

    kind: str
    camera: str
    sequence: int
    message: str
    host_ns: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class IncidentLog:
    """The incidents of one acquisition, in detection order.

    log: optional callable receiving ``level``, ``message`` and
    ``timestamp_ns`` as keyword arguments for each incident (the session
    runner passes ``pm.hook.on_log``). Every incident also goes to the
    Python logger ``crossfield.acquire.<source>``.
    """

    def __init__(self, source: str, log: LogCallable | None = None):
        self.source = source
        self.log = log
        self.items: list[Incident] = []
        self._logger = logging.getLogger(f"crossfield.acquire.{source}")

    def add(self, kind: str, camera: str, sequence: int, message: str, level: str = "warning") -> Incident:
        if kind not in INCIDENT_KINDS:
            raise ValueError(f"unknown incident kind {kind!r}")
        incident = Incident(kind, camera, int(sequence), message, time.time_ns())
        self.items.append(incident)
        text = f"{self.source}: {kind}: {message}"
        self._logger.log(logging.ERROR if level == "error" else logging.WARNING, text)
        if self.log is not None:
            self.log(level=level, message=text, timestamp_ns=incident.host_ns)
        return incident

    def counts(self) -> dict[str, int]:
        return dict(Counter(i.kind for i in self.items))

    def as_dicts(self) -> list[dict[str, Any]]:
        return [i.to_dict() for i in self.items]

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self) -> Iterator[Incident]:
        return iter(self.items)


# --------------------------------------------------------------------------
# Frame counters (software trigger)
# --------------------------------------------------------------------------


class BlockCounter:
    """Expected frame (block) ids of one camera under software triggering.

    Model: every trigger sent while the camera reports itself ready for a
    frame trigger makes it expose one frame, which consumes the next block
    id even when the frame is then lost or arrives late, and pylon delivers
    the frames in order (grab strategy OneByOne). So the frame answering
    trigger ``t`` (0-based) carries ``base + t``. The first frame received
    answers the first trigger sent, whenever it arrives, which fixes
    ``base``. After trigger ``t`` a frame carrying less than ``base + t`` is
    a late frame of an earlier trigger; one carrying more means ids were
    consumed by frames we never received, and it is not trusted (the counter
    resynchronises on it).

    modulus: ids compare modulo this number (GigE Vision 1.x block ids are
    16 bit and skip 0 when they wrap, so they repeat every 65535); None =
    plain integers (USB3 Vision, camera emulation). Differences are taken
    as signed, so a wrap between two frames is harmless.
    """

    OK, STALE, AHEAD = "ok", "stale", "ahead"

    def __init__(self, modulus: int | None = None):
        self.modulus = modulus
        self.triggers = 0  # triggers sent so far
        self.base: int | None = None  # block id of the frame answering trigger 0

    @property
    def expected(self) -> int | None:
        """Block id the frame answering the latest trigger must carry (None = not known yet)."""
        if self.base is None or self.triggers == 0:
            return None
        return self.base + self.triggers - 1

    def difference(self, block_id: int, reference: int) -> int:
        """Signed ``block_id - reference`` (modulo ``modulus`` if set)."""
        d = int(block_id) - int(reference)
        if self.modulus:
            d %= self.modulus
            if d > self.modulus // 2:
                d -= self.modulus
        return d

    def trigger_sent(self) -> None:
        """A trigger was sent to the (ready) camera."""
        self.triggers += 1

    def classify(self, block_id: int) -> str:
        """Classify a frame received after the latest trigger was sent.

        Returns :attr:`OK` (it answers the latest trigger), :attr:`STALE`
        (it answers an earlier trigger) or :attr:`AHEAD` (ids were skipped;
        the counter resynchronises on this frame, which is not trusted).
        """
        if self.triggers == 0:
            raise ValueError("classify() before any trigger was sent")
        if self.base is None:
            self.base = int(block_id)  # the first frame answers the first trigger
        d = self.difference(block_id, self.expected)
        if d == 0:
            return self.OK
        if d < 0:
            return self.STALE
        self.base = int(block_id) - (self.triggers - 1)
        return self.AHEAD

    def unsolicited(self, block_id: int) -> bool:
        """A frame arrived before the next trigger was sent, so it cannot answer
        that trigger. Returns False if it is a late frame of an earlier trigger,
        True if the camera exposed without a trigger of ours (its id is at or
        past the next trigger's); the counter then skips past it."""
        if self.triggers == 0:
            return True
        if self.base is None:
            self.base = int(block_id)  # the first frame answers the first trigger
            return False
        if self.difference(block_id, self.base + self.triggers) >= 0:
            self.base = int(block_id) + 1 - self.triggers
            return True
        return False


# --------------------------------------------------------------------------
# Frame events and time skew
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class GrabbedFrame:
    """One result delivered by a camera.

    camera: ``upper`` or ``lower``. ok: the buffer is complete. index: the
    0-based count of results this camera delivered in this acquisition.
    block_id: the camera's frame counter. camera_ns: the camera's own
    timestamp converted to ns (0 = the camera gives none, e.g. pylon's
    emulation). host_ns: host time (ns since the epoch) when the result was
    retrieved, taken by a reader thread per camera. image: (H, W) uint16 or
    None when not ok. error: the SDK's error text when not ok.
    """

    camera: str
    ok: bool
    index: int
    block_id: int
    camera_ns: int
    host_ns: int
    image: np.ndarray | None = None
    error: str = ""


def pair_skew_ns(
    upper: GrabbedFrame, lower: GrabbedFrame, previous: tuple[GrabbedFrame, GrabbedFrame] | None
) -> tuple[int, str]:
    """Signed time offset ``upper - lower`` (ns) of two frames, and its basis.

    With camera clocks on both cameras and a previous accepted pair, the
    offset is the difference of the intervals each camera measured since
    that pair (the two clocks need not be synchronised, only steady): it
    compares exposure times. Otherwise it is the difference of the host
    arrival times (which also contains transfer time differences).
    """
    if previous is not None and all(f.camera_ns for f in (upper, lower, *previous)):
        du = upper.camera_ns - previous[0].camera_ns
        dl = lower.camera_ns - previous[1].camera_ns
        return du - dl, "camera clock"
    return upper.host_ns - lower.host_ns, "host arrival"


class ArrivalPairer:
    """Pair the frames of two externally triggered cameras by time.

    Frames are pushed as they arrive. The head frames of the two cameras
    form a pair when their skew (:func:`pair_skew_ns`) is within
    ``max_skew_ns``; otherwise the older one can have no partner any more
    and is dropped (``no_partner`` incident). A head frame whose partner
    has not come within ``timeout_ns`` of its arrival is dropped too.
    Failed buffers are dropped on arrival (``grab_failed``).

    Sequence numbers: the upper camera's frame index (so a pair lost to a
    missed trigger leaves a gap).
    """

    def __init__(self, max_skew_ns: int, timeout_ns: int, incidents: IncidentLog):
        self.max_skew_ns = int(max_skew_ns)
        self.timeout_ns = int(timeout_ns)
        self.incidents = incidents
        self.pending: dict[str, deque[GrabbedFrame]] = {"upper": deque(), "lower": deque()}
        self.previous: tuple[GrabbedFrame, GrabbedFrame] | None = None

    def push(self, frame: GrabbedFrame, now_ns: int) -> list[tuple[GrabbedFrame, GrabbedFrame]]:
        """Add an arrived frame; return the pairs that became complete."""
        if not frame.ok:
            self.incidents.add(
                "grab_failed", frame.camera, frame.index,
                f"{frame.camera} frame {frame.index} (block {frame.block_id}) failed: {frame.error}; dropped",
            )
        else:
            self.pending[frame.camera].append(frame)
        return self.poll(now_ns)

    def poll(self, now_ns: int) -> list[tuple[GrabbedFrame, GrabbedFrame]]:
        """Match head frames and expire lonely ones; return the complete pairs."""
        pairs = []
        upper, lower = self.pending["upper"], self.pending["lower"]
        while upper and lower:
            u, l = upper[0], lower[0]
            skew, basis = pair_skew_ns(u, l, self.previous)
            if abs(skew) <= self.max_skew_ns:
                upper.popleft()
                lower.popleft()
                self._check_counters(u, l)
                self.previous = (u, l)
                pairs.append((u, l))
                continue
            older = upper if skew < 0 else lower
            dropped = older.popleft()
            self.incidents.add(
                "no_partner", dropped.camera, dropped.index,
                f"{dropped.camera} frame {dropped.index} (block {dropped.block_id}) has no partner: "
                f"the other camera's next frame is {abs(skew) / 1e6:.3f} ms away by {basis} (max_skew_ms "
                f"{self.max_skew_ns / 1e6:g}); dropped",
            )
        for queue in (upper, lower):
            while queue and now_ns - queue[0].host_ns > self.timeout_ns:
                dropped = queue.popleft()
                self.incidents.add(
                    "timeout", dropped.camera, dropped.index,
                    f"{dropped.camera} frame {dropped.index} (block {dropped.block_id}): no partner frame "
                    f"within timeout_ms {self.timeout_ns / 1e6:g}; dropped",
                )
        return pairs

    def _check_counters(self, u: GrabbedFrame, l: GrabbedFrame) -> None:
        """Report frames a camera numbered but never delivered between two accepted
        pairs (lost in transport). Frames that arrived and were dropped are already
        reported; the pair itself is vouched for by its time skew."""
        if self.previous is not None:
            for now, before in ((u, self.previous[0]), (l, self.previous[1])):
                unseen = (now.block_id - before.block_id) - (now.index - before.index)
                if unseen:
                    self.incidents.add(
                        "counter_mismatch", now.camera, u.index,
                        f"{now.camera}: the frame counter advanced by {now.block_id - before.block_id} "
                        f"since the previous pair but {now.index - before.index} frames arrived: "
                        f"{unseen} frame(s) lost in transport (this pair matches in time and is kept)",
                    )
