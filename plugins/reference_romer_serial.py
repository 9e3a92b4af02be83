"""Reference stage "romer-serial": CMM points from the arm's serial line.

Reads CFP sentences (``pipeline.romer_protocol``, ``docs/serial-protocol.md``)
from a pyserial port until every point of the plan's probing order has
arrived, handing every raw byte to the recorder's sink before parsing.
Points are labelled by their sequence number: the press with
``seq = first_seq + k`` is ``plan.probing_order()[k]``, so a lost or
rejected line leaves a hole at its own label instead of shifting every
later label onto the wrong element.
"""

from __future__ import annotations

import math
import time

import numpy as np

from pipeline.errors import ReferenceImportError
from pipeline.hookspecs import hookimpl
from pipeline.plan import MeasurementPlan
from pipeline.romer_protocol import (
    CfpDecoder,
    Decoder,
    LineDecoder,
    LinkLost,
    ProbeRecord,
    Rejection,
    SerialTransport,
    Transport,
)
from pipeline.stages import BytesSink
from pipeline.types import ProbedPoint, ReferenceData


def _label_list(labels: list[str], indices: list[int], first_seq: int | None) -> str:
    shown = []
    for k in indices[:12]:
        seq = f" (seq {first_seq + k})" if first_seq is not None else ""
        shown.append(f"{labels[k]}{seq}")
    more = f" and {len(indices) - 12} more" if len(indices) > 12 else ""
    return ", ".join(shown) + more


class PointCollector:
    """Labels decoded records by the plan's probing order; keeps the problems.

    labels: the plan's probing order. sigma_mm: per-coordinate standard
    uncertainty (mm) given to every point. first_seq: the seq of the first
    planned press, or None to take it from the first valid point (refused
    if a sentence was rejected before it: its label would be unknown).
    Records without a seq (formats that have none) are labelled in arrival
    order.
    """

    def __init__(self, labels: list[str], sigma_mm: float, first_seq: int | None = 1):
        self.labels = list(labels)
        self.sigma_mm = float(sigma_mm)
        self.first_seq = first_seq
        self.problems: list[str] = []
        self.points: list[ProbedPoint] = []
        self._records: dict[int, ProbeRecord] = {}  # label index -> record
        self._highest = -1  # highest label index received
        self._sentence_rejected_before_first = False

    @property
    def complete(self) -> bool:
        """The last planned point has arrived (earlier holes cannot be filled:
        the arm does not resend) or every label has its point."""
        return self._highest == len(self.labels) - 1 or len(self._records) == len(self.labels)

    def add(self, item: ProbeRecord | Rejection) -> None:
        if isinstance(item, Rejection):
            self.problems.append(str(item))
            if not self._records and item.text.startswith(b"$"):
                self._sentence_rejected_before_first = True
            return
        if item.seq is None:
            index = len(self._records)
            if index >= len(self.labels):
                self._problem(item, f"point beyond the plan's {len(self.labels)} points, ignored")
                return
        else:
            if self.first_seq is None:
                if self._sentence_rejected_before_first:
                    raise ReferenceImportError(
                        f"line {item.line}: cannot label the points: a sentence was rejected before the "
                        f"first valid point (seq {item.seq}), so its label is unknown; set the option "
                        f"first_seq to the seq of the plan's first point ({self.labels[0]}). "
                        f"Problems: {'; '.join(self.problems)}"
                    )
                self.first_seq = item.seq
            index = item.seq - self.first_seq
            if index < 0:
                self._problem(item, f"seq {item.seq} is before first_seq {self.first_seq}, ignored")
                return
            if index >= len(self.labels):
                self._problem(
                    item,
                    f"seq {item.seq} is beyond the plan's {len(self.labels)} points "
                    f"(last is {self.labels[-1]} = seq {self.first_seq + len(self.labels) - 1}), ignored",
                )
                return
        if index in self._records:
            first = self._records[index]
            if item.same_point(first):
                self._problem(item, f"duplicate of seq {item.seq} (line {first.line}), ignored")
            else:
                self._problem(
                    item,
                    f"seq {item.seq} repeated with different data (first on line {first.line}, "
                    f"kept as {self.labels[index]}), ignored",
                )
            return
        if index > self._highest + 1 and item.seq is not None:
            lost = list(range(self._highest + 1, index))
            self._problem(
                item,
                f"sequence gap: {len(lost)} point(s) missing before seq {item.seq}: "
                f"{_label_list(self.labels, lost, self.first_seq)}",
            )
        elif index < self._highest:
            after = self.first_seq + self._highest
            self._problem(item, f"seq {item.seq} arrived out of order (after seq {after})")
        self._records[index] = item
        self._highest = max(self._highest, index)
        self.points.append(self._point(self.labels[index], item))

    def missing(self) -> list[int]:
        """Label indices without a point."""
        return [k for k in range(len(self.labels)) if k not in self._records]

    def finish(self) -> None:
        """Add a problem naming the holes left in the probing order."""
        holes = [k for k in self.missing() if k < self._highest]
        if holes:
            self.problems.append(
                f"no valid point for {len(holes)} label(s): {_label_list(self.labels, holes, self.first_seq)}"
            )

    def result(self, source: str) -> ReferenceData:
        return ReferenceData(points=tuple(self.points), problems=tuple(self.problems), source=source)

    def summary(self) -> str:
        """'3 of 5 points arrived (missing C3 (seq 3), R1 (seq 4))'."""
        missing = self.missing()
        text = f"{len(self._records)} of {len(self.labels)} points arrived"
        if missing:
            text += f" (missing {_label_list(self.labels, missing, self.first_seq)})"
        if self.problems:
            text += "; problems: " + "; ".join(self.problems[:10])
            if len(self.problems) > 10:
                text += f"; and {len(self.problems) - 10} more"
        return text

    def _problem(self, item: ProbeRecord, reason: str) -> None:
        self.problems.append(str(Rejection(item.line, reason, item.text)))

    def _point(self, label: str, record: ProbeRecord) -> ProbedPoint:
        return ProbedPoint(
            label=label,
            xyz=np.array(record.xyz),
            sigma_mm=self.sigma_mm,
            device_sequence=-1 if record.seq is None else record.seq,
            device_time_s=record.device_time_s,
            probe_vector=np.zeros(3) if record.probe_vector is None else np.array(record.probe_vector),
            probe_diameter_mm=record.probe_diameter_mm,
        )


class RomerSerialReference:
    """CMM points from a ROMER-style arm speaking CFP sentences over a serial line.

    port: device path (``/dev/ttyUSB0``, ``COM3``, a pty) or pyserial URL
    (``socket://host:port``, ``rfc2217://host:port``).
    baudrate: line speed, bits per second (8N1).
    timeout_s: idle timeout in seconds. The import ends as soon as the plan's
    last point has arrived; if no new point arrives for ``timeout_s`` before
    that, the import fails naming how many of how many points arrived.
    sigma_mm: stated standard uncertainty of each coordinate of the arm, mm.
    first_seq: seq number of the plan's first point (the arm counts presses
    from 1 each session); ``"auto"`` takes it from the first valid point.
    """

    def __init__(
        self,
        *,
        port: str,
        baudrate: int = 9600,
        timeout_s: float = 60.0,
        sigma_mm: float = 0.01,
        first_seq: int | str = 1,
    ):
        if not isinstance(port, str) or not port:
            raise ValueError(f"option 'port' must be a device path or pyserial URL, got {port!r}")
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise ValueError(f"option 'baudrate' must be a positive integer, got {baudrate!r}")
        if not (isinstance(timeout_s, (int, float)) and math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"option 'timeout_s' must be a positive number of seconds, got {timeout_s!r}")
        if not (isinstance(sigma_mm, (int, float)) and math.isfinite(sigma_mm) and sigma_mm > 0):
            raise ValueError(f"option 'sigma_mm' must be a positive number of mm, got {sigma_mm!r}")
        if first_seq is None or first_seq == "auto":
            first_seq = None
        elif isinstance(first_seq, bool) or not isinstance(first_seq, int) or first_seq < 0:
            raise ValueError(f"option 'first_seq' must be an integer >= 0 or \"auto\", got {first_seq!r}")
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = float(timeout_s)
        self.sigma_mm = float(sigma_mm)
        self.first_seq = first_seq

    # -- layers (override to swap one) -------------------------------------

    def open_transport(self) -> Transport:
        """Layer 1: open the port; errors name it."""
        try:
            return SerialTransport(self.port, baudrate=self.baudrate, poll_s=min(0.05, self.timeout_s))
        except (OSError, ValueError) as exc:
            raise ReferenceImportError(f"romer-serial: cannot open port {self.port!r}: {exc}") from None

    def make_decoder(self) -> Decoder:
        """Layer 3: the sentence decoder."""
        return CfpDecoder()

    # -- ReferenceSource ----------------------------------------------------

    def _collector(self, plan: MeasurementPlan) -> PointCollector:
        labels = plan.probing_order()
        if not labels:
            name = plan.source or plan.name
            raise ReferenceImportError(f"romer-serial: plan {name!r} has nothing to probe")
        return PointCollector(labels, self.sigma_mm, self.first_seq)

    @staticmethod
    def _feed(collector: PointCollector, results: list[ProbeRecord | Rejection]) -> None:
        for item in results:
            collector.add(item)

    def acquire(self, plan: MeasurementPlan, sink: BytesSink) -> ReferenceData:
        """Read points until the plan's probing order is complete.

        Every chunk read goes to ``sink`` before it is parsed. Raises
        :class:`ReferenceImportError` if the port cannot be opened, is lost,
        or stays without a new point for ``timeout_s`` before the plan's last
        point arrived.
        """
        collector = self._collector(plan)
        stream = LineDecoder(self.make_decoder())
        transport = self.open_transport()
        ended = ""
        try:
            last_progress = time.monotonic()
            while not collector.complete:
                try:
                    data = transport.read(4096)
                except LinkLost as exc:
                    ended = f"lost the connection ({exc})"
                    break
                if data:
                    sink(data)
                    before = len(collector.points)
                    self._feed(collector, stream.feed(data))
                    if len(collector.points) > before:
                        last_progress = time.monotonic()
                elif time.monotonic() - last_progress > self.timeout_s:
                    ended = f"no new point for {self.timeout_s:g} s"
                    break
        finally:
            transport.close()
        self._feed(collector, stream.finish())
        collector.finish()
        if not collector.complete:
            raise ReferenceImportError(f"romer-serial: {self.port}: {ended}: {collector.summary()}")
        return collector.result(self.port)

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:
        """Decode recorded bytes exactly as :meth:`acquire` did (replay)."""
        collector = self._collector(plan)
        stream = LineDecoder(self.make_decoder())
        self._feed(collector, stream.feed(bytes(raw)))
        self._feed(collector, stream.finish())
        collector.finish()
        if not collector.complete:
            raise ReferenceImportError(
                f"romer-serial: {self.port}: the recorded data ends before the plan's last point: "
                f"{collector.summary()}"
            )
        return collector.result(self.port)


@hookimpl
def register_references(register):
    register("romer-serial", RomerSerialReference, "ROMER-style CMM arm over a serial line (CFP sentences)")
