"""Reference stage "romer-serial": CMM points from the arm's serial line.

Reads points from a pyserial port (or any pyserial URL: ``socket://`` for
TCP) until every point of the plan's probing order has arrived, handing
every raw byte to the recorder's sink before parsing. Line formats
(``docs/serial-protocol.md``): ``cfp`` (crossfield's CFP sentences, the
default), ``pcdmis`` (PC-DMIS generic ``X..,Y..,Z..`` lines, mm or inch),
``ippdme`` (I++ DME manual-point events over TCP).

CFP points are labelled by their sequence number: the press with
``seq = first_seq + k`` is ``plan.probing_order()[k]``, so a lost or
rejected line leaves a hole at its own label instead of shifting every
later label onto the wrong element. Formats without a sequence number are
labelled in arrival order.

Production behaviour: a held probe button (a burst of repeats of one
press) gives one point; points resent after a reconnect are recognised and
dropped; a lost link is reopened until the idle timeout; implausible
values (non-finite, outside ``measuring_volume_mm``) are rejected naming
the line; between two accepted points at most :data:`LISTED_PROBLEMS`
problems are listed, the rest summarised by kind (a noise flood costs
bounded output); degenerate control sets are reported.

Each disconnect and reconnect is handed to the sink as a
:class:`crossfield.stages.LinkEvent` between the chunks of bytes (the
recorder keeps it on ``/cmm/raw`` in order with them), and the line in
progress is cut there: never joined to the first line after the
reconnect; ``decode(raw, plan, link_events=...)`` splits the same way on
replay. The plugin also reports them as they happen through its ``log`` callback (connected
by the session runner to ``pm.hook.on_log`` through :meth:`connect_log`, the :class:`crossfield.stages.ReportsIncidents` side channel; the recorder writes them to
``/log``): each disconnect (``link down at <time>: <reason>``), each
reconnect (``link up again after X s ...``), the idle timeout, and each
rejected line. Without ``log`` they go to the Python logger
``crossfield.reference.romer-serial``; outages are also kept in
:attr:`RomerSerialReference.outages`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np

from crossfield.plugin_api import (
    DEFAULT_VOLUME_MM,
    FORMATS,
    READ_BYTES,
    UNITS,
    BytesSink,
    Decoder,
    LineDecoder,
    LineFormat,
    LinkEvent,
    LinkLost,
    MeasurementPlan,
    ProbedPoint,
    ProbeRecord,
    ReferenceData,
    ReferenceImportError,
    ReferenceSource,
    Register,
    Rejection,
    SerialTransport,
    Transport,
    check_volume,
    control_problems,
    hookimpl,
)


def _label_list(labels: list[str], indices: list[int], first_seq: int | None) -> str:
    """'C3 (seq 3), R1 (seq 4)'; without first_seq: 'C3, R1'."""
    shown = []
    for k in indices[:12]:
        seq = f" (seq {first_seq + k})" if first_seq is not None else ""
        shown.append(f"{labels[k]}{seq}")
    more = f" and {len(indices) - 12} more" if len(indices) > 12 else ""
    return ", ".join(shown) + more


def _lines(first: int, last: int) -> str:
    return f"line {first}" if first == last else f"lines {first}-{last}"


def _distance(a: ProbeRecord, b: ProbeRecord) -> float:
    return math.dist(a.xyz, b.xyz)


class _Run:
    """Consecutive ignored repeats of one kind, reported as one problem."""

    def __init__(self, kind: str, label: str, item: ProbeRecord):
        self.kind, self.label = kind, label
        self.first_line = self.last_line = item.line
        self.count = 1
        self.labels = [label]

    def extend(self, label: str, item: ProbeRecord) -> None:
        self.last_line = item.line
        self.count += 1
        if label not in self.labels:
            self.labels.append(label)

    def __str__(self) -> str:
        where = _lines(self.first_line, self.last_line)
        if self.kind == "held":
            return f"{where}: held button: {self.count} repeat(s) of {self.label} ignored, first point kept"
        shown = ", ".join(self.labels[:12]) + (" ..." if len(self.labels) > 12 else "")
        return f"{where}: {self.count} resent point(s) already received ({shown}), ignored"


#: Problems listed one by one between two accepted points; further ones are
#: counted by kind in one summary line (a noise flood costs bounded output).
LISTED_PROBLEMS = 5


class _Flood:
    """Problems beyond :data:`LISTED_PROBLEMS` since the last accepted point:
    counts by kind, their lines and byte range."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.first_line = self.last_line = 0
        self.first_byte = self.end_byte = -1

    def add(self, kind: str, count: int, line: int, offset: int, size: int) -> None:
        if not self.counts:
            self.first_line = line
        self.counts[kind] = self.counts.get(kind, 0) + count
        self.last_line = max(self.last_line, line)
        if offset >= 0:
            if self.first_byte < 0:
                self.first_byte = offset
            self.end_byte = max(self.end_byte, offset + max(size, 1))

    def __str__(self) -> str:
        total = sum(self.counts.values())
        where = _lines(self.first_line, self.last_line)
        if self.first_byte >= 0:
            where += f", bytes {self.first_byte}-{self.end_byte - 1}"
        kinds = ", ".join(f"{n} {kind}" for kind, n in sorted(self.counts.items(), key=lambda kv: -kv[1]))
        return f"{where}: {total} more problem(s), not listed one by one: {kinds}"


class PointCollector:
    """Labels decoded records by the plan's probing order; keeps the problems.

    labels: the plan's probing order. sigma_mm: per-coordinate standard
    uncertainty (mm) given to every point. first_seq: the seq of the first
    planned press, or None to take it from the first valid point (refused
    if a sentence was rejected before it: its label would be unknown).
    burst_radius_mm: repeats of a press within this distance of its first
    point are a held button (mm). numbered: the format has sequence
    numbers (else labels are named without seq in messages).

    With seq: a repeat of a received seq is *resent* if identical, *held*
    if within ``burst_radius_mm``, else a conflict. Without seq (arrival
    order): a point identical to a received one is *resent*; a point within
    ``burst_radius_mm`` of the last accepted one is *held*. Either way the
    first point is kept.

    Between two accepted points at most :data:`LISTED_PROBLEMS` problems
    are listed one by one; the others are counted by kind in one summary
    (lines, byte range, counts), so the problems of a noise flood are
    bounded by the plan's size, not by the input's.
    """

    def __init__(
        self,
        labels: list[str],
        sigma_mm: float,
        first_seq: int | None = 1,
        burst_radius_mm: float = 0.5,
        numbered: bool = True,
    ):
        self.labels = list(labels)
        self.numbered = numbered
        self.sigma_mm = float(sigma_mm)
        self.first_seq = first_seq
        self.burst_radius_mm = float(burst_radius_mm)
        self.problems: list[str] = []
        self.points: list[ProbedPoint] = []
        self._records: dict[int, ProbeRecord] = {}  # label index -> record
        self._by_content: dict[tuple, int] = {}  # (xyz, probe_vector) -> label index
        self._last: tuple[int, ProbeRecord] | None = None  # last accepted (index, record)
        self._highest = -1  # highest label index received
        self._sentence_rejected_before_first = False
        self._run: _Run | None = None
        self._listed = 0  # problems listed since the last accepted point
        self._flood: _Flood | None = None

    @property
    def complete(self) -> bool:
        """The last planned point has arrived (earlier holes are not waited
        for) or every label has its point."""
        return self._highest == len(self.labels) - 1 or len(self._records) == len(self.labels)

    def add(self, item: ProbeRecord | Rejection) -> None:
        if isinstance(item, Rejection):
            self._flush_run()
            self._emit(item.__str__, item.kind, item.count, item.line, item.offset, item.size)
            if not self._records and item.text.startswith(b"$"):
                self._sentence_rejected_before_first = True
            return
        if item.seq is None:
            self._add_unnumbered(item)
        else:
            self._add_numbered(item)

    def _add_numbered(self, item: ProbeRecord) -> None:
        assert item.seq is not None
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
                self._repeat("resent", index, item)
            elif _distance(item, first) <= self.burst_radius_mm:
                self._repeat("held", index, item)
            else:
                self._problem(
                    item,
                    f"seq {item.seq} repeated {_distance(item, first):.3f} mm away from its first point "
                    f"(line {first.line}, kept as {self.labels[index]}), ignored",
                )
            return
        if index > self._highest + 1:
            lost = list(range(self._highest + 1, index))
            self._problem(
                item,
                f"sequence gap: {len(lost)} point(s) missing before seq {item.seq}: "
                f"{_label_list(self.labels, lost, self.first_seq)}",
                listed=True,
            )
        elif index < self._highest:
            after = self.first_seq + self._highest
            self._problem(item, f"seq {item.seq} arrived out of order (after seq {after})", listed=True)
        self._accept(index, item)

    def _add_unnumbered(self, item: ProbeRecord) -> None:
        known = self._by_content.get((item.xyz, item.probe_vector))
        if known is not None:
            self._repeat("resent", known, item)
            return
        if self._last is not None and _distance(item, self._last[1]) <= self.burst_radius_mm:
            self._repeat("held", self._last[0], item)
            return
        index = len(self._records)
        if index >= len(self.labels):
            self._problem(item, f"point beyond the plan's {len(self.labels)} points, ignored")
            return
        self._accept(index, item)

    def _accept(self, index: int, item: ProbeRecord) -> None:
        self._flush_run()
        self._flush_flood()
        self._listed = 0
        self._records[index] = item
        self._by_content.setdefault((item.xyz, item.probe_vector), index)
        self._last = (index, item)
        self._highest = max(self._highest, index)
        self.points.append(self._point(self.labels[index], item))

    def _repeat(self, kind: str, index: int, item: ProbeRecord) -> None:
        label = self.labels[index]
        run = self._run
        if run is not None and run.kind == kind and (kind == "resent" or run.label == label):
            run.extend(label, item)
        else:
            self._flush_run()
            self._run = _Run(kind, label, item)

    def _flush_run(self) -> None:
        if self._run is not None:
            run, self._run = self._run, None
            self._emit(run.__str__, "repeat", run.count, run.first_line)

    def _emit(
        self, text: Callable[[], str], kind: str, count: int = 1, line: int = 0, offset: int = -1, size: int = 0
    ) -> None:
        """One problem: listed (``text()``) while fewer than LISTED_PROBLEMS were
        since the last accepted point, else counted in the pending flood summary
        (its text is never made: a flood costs no formatting)."""
        if self._listed < LISTED_PROBLEMS:
            self.problems.append(text())
            self._listed += 1
            return
        if self._flood is None:
            self._flood = _Flood()
        self._flood.add(kind, count, line, offset, size)

    def _flush_flood(self) -> None:
        if self._flood is not None:
            self.problems.append(str(self._flood))
            self._flood = None

    @property
    def _seq_base(self) -> int | None:
        return self.first_seq if self.numbered else None

    def missing(self) -> list[int]:
        """Label indices without a point."""
        return [k for k in range(len(self.labels)) if k not in self._records]

    def finish(self) -> None:
        """Report a pending run and flood, and the holes left in the probing order."""
        self._flush_run()
        self._flush_flood()
        holes = [k for k in self.missing() if k < self._highest]
        if holes:
            self.problems.append(
                f"no valid point for {len(holes)} label(s): {_label_list(self.labels, holes, self._seq_base)}"
            )

    def result(self, source: str) -> ReferenceData:
        return ReferenceData(points=tuple(self.points), problems=tuple(self.problems), source=source)

    def summary(self) -> str:
        """'3 of 5 points arrived (missing C3 (seq 3), R1 (seq 4))'."""
        missing = self.missing()
        text = f"{len(self._records)} of {len(self.labels)} points arrived"
        if missing:
            text += f" (missing {_label_list(self.labels, missing, self._seq_base)})"
        if self.problems:
            text += "; problems: " + "; ".join(self.problems[:10])
            if len(self.problems) > 10:
                text += f"; and {len(self.problems) - 10} more"
        return text

    def _problem(self, item: ProbeRecord, reason: str, listed: bool = False) -> None:
        """A problem with a decoded point; ``listed``: always listed (a gap or
        reordering, reported just before the point is kept)."""
        self._flush_run()
        rejection = Rejection(item.line, reason, item.text)
        if listed:
            self._flush_flood()
            self.problems.append(str(rejection))
        else:
            self._emit(rejection.__str__, "ignored point", 1, item.line, item.offset, item.size)

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


#: ``log(level=..., message=..., timestamp_ns=...)``, as ``pm.hook.on_log``.
LogCallable = Callable[..., Any]

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}


def wall_clock(timestamp_ns: int) -> str:
    """Local time with UTC offset and milliseconds: '2024-06-11T14:03:12.345+02:00'."""
    return datetime.fromtimestamp(timestamp_ns / 1e9).astimezone().isoformat(timespec="milliseconds")


@dataclass
class LinkOutage:
    """One interruption of the link.

    down_ns / up_ns: host time (ns since the epoch) when the disconnect was
    detected / when the port was open again (None: it never came back).
    reason: what the transport reported. points_before: points received
    before the link went down.
    """

    down_ns: int
    reason: str
    points_before: int
    up_ns: int | None = None

    @property
    def duration_s(self) -> float | None:
        return None if self.up_ns is None else (self.up_ns - self.down_ns) / 1e9


def _stated_sigma(sigma_mm: float | None, arm_model: str) -> tuple[float, str]:
    """The arm's stated per-coordinate sigma (mm) and where it came from: the option
    ``sigma_mm`` when given, else the ``arm_model``'s specification (:data:`ARM_MODELS`)."""
    if not isinstance(arm_model, str) or arm_model not in ARM_MODELS:
        raise ValueError(f"option 'arm_model' must be one of {', '.join(ARM_MODELS)}, got {arm_model!r}")
    if sigma_mm is None:
        return ARM_MODELS[arm_model], f"the {arm_model} arm model's specification (option arm_model)"
    return _positive(sigma_mm, "sigma_mm", "mm"), "option sigma_mm"


def _positive(value, name: str, unit: str) -> float:
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and value > 0):
        raise ValueError(f"option {name!r} must be a positive number of {unit}, got {value!r}")
    return float(value)


#: Per-coordinate standard uncertainty (mm) of each arm model this source knows, the
#: documented default of ``sigma_mm`` (docs/serial-protocol.md). "simulated": the arm
#: of crossfield's simulator (``crossfield.simulator.arm``, ``romer-sim --sigma``
#: default). A real arm: give ``sigma_mm`` from its calibration certificate.
ARM_MODELS: dict[str, float] = {"simulated": 0.01}


class RomerSerialReference:
    """CMM points from a ROMER-style arm over a serial line (or TCP).

    port: device path (``/dev/ttyUSB0``, ``COM3``, a pty) or pyserial URL
    (``socket://host:port``, ``rfc2217://host:port``).
    baudrate: line speed, bits per second (8N1).
    timeout_s: idle timeout in seconds. The import ends as soon as the plan's
    last point has arrived; if no new point arrives for ``timeout_s`` before
    that (the link may drop and come back meanwhile), the import fails
    naming how many of how many points arrived.
    sigma_mm: stated standard uncertainty of each coordinate of the arm, mm;
    unset: the ``arm_model``'s specification (:data:`ARM_MODELS`).
    arm_model: the arm whose specification ``sigma_mm`` defaults to
    (``"simulated"``). ``sigma_origin`` (attribute): where the stated sigma
    came from, in words; the consistency check names it when the scatter
    disagrees.
    first_seq: seq number of the plan's first point (the arm counts presses
    from 1 each session); ``"auto"`` takes it from the first valid point.
    format: ``"cfp"``, ``"pcdmis"`` or ``"ippdme"``.
    units: ``"mm"`` or ``"inch"`` (``pcdmis`` only; converted to mm).
    burst_radius_mm: repeats of one press within this distance are a held
    button and give one point (mm).
    measuring_volume_mm: half-width of the measuring volume (mm): a point
    with |X|, |Y| or |Z| above it (or not finite) is rejected, naming its line.

    ``log`` (attribute, not an option; default None; set by
    :meth:`connect_log`): a callable receiving ``level``, ``message`` and
    ``timestamp_ns`` keyword arguments, called
    as things happen during :meth:`acquire` (link down / up, timeout,
    each rejected line); without it they go to the Python logger
    ``crossfield.reference.romer-serial``. ``outages``: the
    :class:`LinkOutage` s of the last :meth:`acquire`.
    """

    def __init__(
        self,
        *,
        port: str,
        baudrate: int = 9600,
        timeout_s: float = 60.0,
        sigma_mm: float | None = None,
        arm_model: str = "simulated",
        first_seq: int | str = 1,
        format: str = "cfp",
        units: str = "mm",
        burst_radius_mm: float = 0.5,
        measuring_volume_mm: float = DEFAULT_VOLUME_MM,
    ):
        if not isinstance(port, str) or not port:
            raise ValueError(f"option 'port' must be a device path or pyserial URL, got {port!r}")
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise ValueError(f"option 'baudrate' must be a positive integer, got {baudrate!r}")
        if first_seq is None or first_seq == "auto":
            first_seq = None
        elif isinstance(first_seq, bool) or not isinstance(first_seq, int) or first_seq < 0:
            raise ValueError(f"option 'first_seq' must be an integer >= 0 or \"auto\", got {first_seq!r}")
        if not isinstance(format, str) or format not in FORMATS:
            raise ValueError(f"option 'format' must be one of {', '.join(FORMATS)}, got {format!r}")
        if not isinstance(units, str) or units not in UNITS:
            raise ValueError(f"option 'units' must be one of {', '.join(UNITS)}, got {units!r}")
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = _positive(timeout_s, "timeout_s", "seconds")
        self.sigma_mm, self.sigma_origin = _stated_sigma(sigma_mm, arm_model)
        self.arm_model = arm_model
        self.first_seq = first_seq
        self.format: LineFormat = FORMATS[format]
        self.units = units
        self.burst_radius_mm = _positive(burst_radius_mm, "burst_radius_mm", "mm")
        self.measuring_volume_mm = check_volume(measuring_volume_mm)
        try:
            self.make_decoder()
        except ValueError as exc:
            raise ValueError(f"option 'units': {exc}") from None
        self.log: LogCallable | None = None
        self.outages: list[LinkOutage] = []
        self._logger = logging.getLogger("crossfield.reference.romer-serial")

    def connect_log(self, log: LogCallable) -> None:
        """Report incidents through ``log`` from now on
        (:class:`crossfield.stages.ReportsIncidents`; the runner passes ``on_log``)."""
        self.log = log

    def _report(self, level: str, message: str, timestamp_ns: int | None = None) -> None:
        """One incident: to ``log`` if set, else to the Python logger (not
        both: the session's log observers already print it)."""
        text = f"romer-serial {self.port}: {message}"
        if self.log is None:
            self._logger.log(_LEVELS[level], text)
        else:
            when = time.time_ns() if timestamp_ns is None else timestamp_ns
            self.log(level=level, message=text, timestamp_ns=when)

    def _report_problems(self, collector: PointCollector, reported: int) -> int:
        """Report the collector's problems from index ``reported`` on; returns the new count."""
        for problem in collector.problems[reported:]:
            self._report("warning", problem)
        return len(collector.problems)

    # -- layers (override one to swap it) ------------------------------------

    def open_transport(self) -> Transport:
        """Layer 1: open the port (``OSError`` if it cannot)."""
        return SerialTransport(self.port, baudrate=self.baudrate, poll_s=min(0.05, self.timeout_s))

    def make_stream(self) -> LineDecoder:
        """Layers 2 and 3: the format's framer and decoder."""
        return LineDecoder(self.make_decoder(), self.format.framer())

    def make_decoder(self) -> Decoder:
        return self.format.decoder(self.units, self.measuring_volume_mm)

    # -- ReferenceSource ----------------------------------------------------

    def _collector(self, plan: MeasurementPlan) -> PointCollector:
        labels = plan.probing_order()
        if not labels:
            name = plan.source or plan.name
            raise ReferenceImportError(f"romer-serial: plan {name!r} has nothing to probe")
        return PointCollector(
            labels, self.sigma_mm, self.first_seq, self.burst_radius_mm, numbered=self.format.has_seq
        )

    @staticmethod
    def _feed(collector: PointCollector, results: list[ProbeRecord | Rejection]) -> None:
        for item in results:
            collector.add(item)

    def _connect(self) -> Transport:
        """Open the port and start the format's session (I++ DME)."""
        transport = self.open_transport()
        if self.format.session:
            try:
                transport.write(self.format.session)
            except LinkLost:
                transport.close()
                raise
        return transport

    def _close(self, transport: Transport) -> None:
        if self.format.end:
            try:
                transport.write(self.format.end)
            except LinkLost:
                pass
        transport.close()

    def acquire(self, plan: MeasurementPlan, sink: BytesSink) -> ReferenceData:
        """Read points until the plan's probing order is complete.

        Every chunk read goes to ``sink`` before it is parsed. A lost link is
        reopened (every 0.1 s) until the idle timeout; each outage is
        reported through ``log`` when it starts and when it ends, and kept
        in :attr:`outages`. Raises :class:`ReferenceImportError` if the port
        cannot be opened at the start, or no new point arrives for
        ``timeout_s`` before the plan's last point.
        """
        collector = self._collector(plan)
        stream = self.make_stream()
        self.outages = []
        try:
            transport: Transport | None = self._connect()
        except (OSError, ValueError, LinkLost) as exc:
            raise ReferenceImportError(f"romer-serial: cannot open port {self.port!r}: {exc}") from None
        self._report(
            "info",
            f"reading {self.format.name} from {self.port} ({self.baudrate} baud): "
            f"{len(collector.labels)} points expected",
        )
        ended = ""
        lost = ""
        reported = 0  # problems already passed to log
        last_progress = time.monotonic()
        received_since_point = 0  # bytes read since the last new point
        try:
            while not collector.complete:
                idle = time.monotonic() - last_progress > self.timeout_s
                if transport is None:
                    if idle:
                        ended = (
                            f"lost the connection ({lost}) and it did not come back "
                            f"within {self.timeout_s:g} s"
                        )
                        break
                    time.sleep(0.1)
                    try:
                        transport = self._connect()
                    except (OSError, ValueError, LinkLost):
                        transport = None
                        continue
                    sink(LinkEvent("up"))
                    outage = self.outages[-1]
                    outage.up_ns = time.time_ns()
                    self._report(
                        "info",
                        f"link up again after {outage.duration_s:.2f} s (down since "
                        f"{wall_clock(outage.down_ns)}); {len(collector.points)} of "
                        f"{len(collector.labels)} points so far",
                        outage.up_ns,
                    )
                    continue
                try:
                    data = transport.read(READ_BYTES)
                except LinkLost as exc:
                    lost = str(exc)
                    transport.close()
                    transport = None
                    sink(LinkEvent("down", lost))
                    outage = LinkOutage(time.time_ns(), lost, len(collector.points))
                    self.outages.append(outage)
                    self._report(
                        "warning",
                        f"link down at {wall_clock(outage.down_ns)}: {lost}; {outage.points_before} of "
                        f"{len(collector.labels)} points so far; reopening every 0.1 s for up to "
                        f"{self.timeout_s:g} s",
                        outage.down_ns,
                    )
                    # the line in progress ends here: never joined to the bytes after the reconnect
                    self._feed(collector, stream.cut())
                    reported = self._report_problems(collector, reported)
                    continue
                if data:
                    sink(data)
                    before = len(collector.points)
                    self._feed(collector, stream.feed(data))
                    reported = self._report_problems(collector, reported)
                    if len(collector.points) > before:
                        last_progress = time.monotonic()
                        received_since_point = 0
                        continue
                    received_since_point += len(data)
                if idle:  # bytes that bring no point (a noise flood) do not hold the import open
                    ended = f"no new point for {self.timeout_s:g} s"
                    if received_since_point:
                        ended += f" ({received_since_point} bytes arrived meanwhile, none a new point)"
                    break
        finally:
            if transport is not None:
                self._close(transport)
        self._feed(collector, stream.finish())
        collector.finish()
        reported = self._report_problems(collector, reported)
        if not collector.complete:
            self._report("error", f"{ended}: {collector.summary()}")
            raise ReferenceImportError(f"romer-serial: {self.port}: {ended}: {collector.summary()}")
        result = self._result(collector, plan)
        for problem in result.problems[len(collector.problems) :]:
            self._report("warning", problem)
        summary = (
            f"{len(collector.points)} of {len(collector.labels)} points imported, "
            f"{len(result.problems)} problem(s)"
        )
        if self.outages:
            down = sum(o.duration_s or 0.0 for o in self.outages)
            summary += f"; the link was down {len(self.outages)} time(s), {down:.2f} s in all"
        self._report("info", summary)
        return result

    def decode(
        self, raw: bytes, plan: MeasurementPlan, link_events: Sequence[tuple[int, LinkEvent]] = ()
    ) -> ReferenceData:
        """Decode recorded bytes exactly as :meth:`acquire` did (replay).

        link_events: ``(offset, LinkEvent)`` pairs in order, offset = bytes
        of ``raw`` before the event (replay reads them from the recording):
        at each ``down`` the line in progress is cut, as it was live.
        """
        collector = self._collector(plan)
        stream = self.make_stream()
        data = bytes(raw)
        pos = 0
        for offset, event in link_events:
            if not (isinstance(offset, int) and pos <= offset <= len(data)):
                raise ReferenceImportError(
                    f"romer-serial: {self.port}: link event {event!r} at byte {offset!r} is outside the "
                    f"recorded bytes {pos}..{len(data)}"
                )
            self._feed(collector, stream.feed(data[pos:offset]))
            pos = offset
            if event.kind == "down":
                self._feed(collector, stream.cut())
        self._feed(collector, stream.feed(data[pos:]))
        self._feed(collector, stream.finish())
        collector.finish()
        if not collector.complete:
            raise ReferenceImportError(
                f"romer-serial: {self.port}: the recorded data ends before the plan's last point: "
                f"{collector.summary()}"
            )
        return self._result(collector, plan)

    def _result(self, collector: PointCollector, plan: MeasurementPlan) -> ReferenceData:
        """The collected points and problems, and those of a degenerate control set."""
        result = collector.result(self.port)
        degenerate = control_problems(result.points, plan)
        if not degenerate:
            return result
        return dataclasses.replace(result, problems=result.problems + tuple(degenerate))


@hookimpl
def register_references(register: Register[ReferenceSource]) -> None:
    register(
        "romer-serial",
        RomerSerialReference,
        "CMM arm over a serial line or TCP (CFP sentences, PC-DMIS generic lines, I++ DME events)",
    )
