"""The crossfield CMM line protocol ("CFP sentences"), in three swappable layers.

The real ROMER wire protocol is not public, so crossfield documents its own
ASCII line protocol (``docs/serial-protocol.md``). One button press of the arm
gives one line::

    $CFP,<seq>,<device_time_s>,<X>,<Y>,<Z>,<I>,<J>,<K>,<probe_diameter_mm>*<CRC>\\r\\n

* ``seq``: button-press counter, a decimal integer (first press of a session = 1).
* ``device_time_s``: the arm's clock in seconds (>= 0).
* ``X, Y, Z``: probe-ball centre in mm in the arm's (global) frame.
* ``I, J, K``: unit approach direction of the probe (unitless).
* ``probe_diameter_mm``: ball diameter in mm (> 0).
* ``CRC``: CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no
  reflection, no final XOR) of the bytes between ``$`` and ``*``, as four
  hexadecimal digits. Check value: ``crc16(b"123456789") == 0x29B1``.

Numbers are plain decimals (``-?digits[.digits]``): no exponent, no NaN.
While the button is held the arm repeats the press's sentence with the
same seq; when a reader (re)connects it resends the session's sentences
(readers drop what they already have, by seq).

Layers, each replaceable on its own:

1. **transport** (:class:`Transport`, :class:`SerialTransport`): moves bytes;
   pyserial ``serial_for_url`` so any URL works (device path, ``socket://``,
   ``rfc2217://``, ``loop://``).
2. **framer** (:class:`LineFramer`): bytes -> :class:`Frame` s. Finds
   sentences from ``$`` to the line end, resynchronises after noise and
   after partial lines, ends the line in progress where the link broke
   (:meth:`LineFramer.cut`), and numbers lines as a text viewer would
   (line = 1 + number of ``\\n`` before the frame).
3. **decoder** (:class:`CfpDecoder`): one frame -> :class:`ProbeRecord` or
   :class:`Rejection` (a reason naming the line and its content); values
   outside the measuring volume are rejected (:mod:`crossfield.cmm.plausible`).
"""

from __future__ import annotations

import binascii
import math
import re
from dataclasses import dataclass
from typing import Protocol, Sequence

from crossfield.cmm.plausible import DEFAULT_VOLUME_MM, check_volume, coordinate_problem, size_problem

__all__ = [
    "MAX_LINE_BYTES",
    "NOISE",
    "OVERLONG",
    "PARTIAL",
    "POINT_FIELDS",
    "POINT_SENTENCE",
    "READ_BYTES",
    "SENTENCE",
    "UNIT_VECTOR_TOLERANCE",
    "CfpDecoder",
    "crc16",
    "Decoder",
    "encode_point",
    "Frame",
    "LineDecoder",
    "LineFramer",
    "LinkLost",
    "ProbeRecord",
    "Rejection",
    "SerialTransport",
    "show",
    "Transport",
]

# --------------------------------------------------------------------------
# Grammar constants
# --------------------------------------------------------------------------

#: Sentence type of a probed point.
POINT_SENTENCE = "CFP"
#: Fields after the sentence type: seq, time, X, Y, Z, I, J, K, diameter.
POINT_FIELDS = ("seq", "device_time_s", "X", "Y", "Z", "I", "J", "K", "probe_diameter_mm")
#: Longest line the framer accepts (a full CFP sentence is about 100 bytes).
MAX_LINE_BYTES = 200
#: How far |(I, J, K)| may be from 1 before the line is rejected.
UNIT_VECTOR_TOLERANCE = 1e-3
#: Most bytes one transport read returns (a flood arrives in blocks this size).
READ_BYTES = 65536

_NUMBER = re.compile(r"-?[0-9]+(\.[0-9]+)?\Z")
_SEQ = re.compile(r"[0-9]{1,9}\Z")
_HEX4 = re.compile(r"[0-9A-Fa-f]{4}\Z")
_WHITESPACE = b" \t\r\n"
_DOLLARS = re.compile(rb"\$+")


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF, no reflection)."""
    return binascii.crc_hqx(data, 0xFFFF)


_ESCAPES = {0x09: "\\t", 0x0A: "\\n", 0x0D: "\\r", 0x27: "\\'", 0x5C: "\\\\"}
#: How each byte value is shown: printable ASCII as is, the others escaped.
_SHOWN = tuple(_ESCAPES.get(b, chr(b) if 0x20 <= b < 0x7F else f"\\x{b:02x}") for b in range(256))


def show(data: bytes, limit: int = 100) -> str:
    """``data`` quoted for a message: printable ASCII as is, other bytes
    escaped (``\\r``, ``\\xff``), cut after ``limit`` bytes with ``...``."""
    text = "".join(map(_SHOWN.__getitem__, data[:limit]))
    return f"'{text}...'" if len(data) > limit else f"'{text}'"


# --------------------------------------------------------------------------
# Encoder (the simulated arm uses it)
# --------------------------------------------------------------------------


def _fixed(value: float, decimals: int, name: str) -> str:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return f"{value:.{decimals}f}"


def encode_point(
    seq: int,
    device_time_s: float,
    xyz: Sequence[float],
    probe_vector: Sequence[float],
    probe_diameter_mm: float,
) -> bytes:
    """One CFP sentence, ``$CFP,...*CRC\\r\\n``, as bytes.

    xyz: (3,) probe-ball centre in mm, written with 4 decimals (0.1 um).
    probe_vector: (3,) unit approach direction, written with 6 decimals.
    device_time_s written with 3 decimals, probe_diameter_mm with 3.
    """
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= 999_999_999:
        raise ValueError(f"seq must be an integer in 0..999999999, got {seq!r}")
    if len(xyz) != 3 or len(probe_vector) != 3:
        raise ValueError("xyz and probe_vector must have 3 components")
    if not float(device_time_s) >= 0:
        raise ValueError(f"device_time_s must be >= 0, got {device_time_s!r}")
    if not float(probe_diameter_mm) > 0:
        raise ValueError(f"probe_diameter_mm must be > 0, got {probe_diameter_mm!r}")
    fields = [POINT_SENTENCE, str(seq), _fixed(device_time_s, 3, "device_time_s")]
    fields += [_fixed(v, 4, "xyz") for v in xyz]
    fields += [_fixed(v, 6, "probe_vector") for v in probe_vector]
    fields.append(_fixed(probe_diameter_mm, 3, "probe_diameter_mm"))
    body = ",".join(fields).encode("ascii")
    return b"$" + body + b"*" + f"{crc16(body):04X}".encode("ascii") + b"\r\n"


# --------------------------------------------------------------------------
# Layer 1: transport
# --------------------------------------------------------------------------


class LinkLost(Exception):
    """The transport's peer went away (cable pulled, pty master closed)."""


class Transport(Protocol):
    """Moves bytes. ``read`` returns b"" when nothing arrived within the
    transport's poll interval and raises :class:`LinkLost` on disconnect."""

    name: str

    def read(self, max_bytes: int = READ_BYTES) -> bytes: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class SerialTransport:
    """A pyserial port opened with ``serial.serial_for_url``.

    url: a device path (``/dev/ttyUSB0``, ``COM3``, a pty slave) or any
    pyserial URL (``socket://host:port``, ``rfc2217://host:port``, ``loop://``).
    baudrate: bits per second (8N1). poll_s: longest a ``read`` blocks.
    Raises ``OSError`` (pyserial's ``SerialException``) if it cannot open.
    """

    def __init__(self, url: str, *, baudrate: int = 9600, poll_s: float = 0.05):
        import serial  # pyserial

        self.name = url
        self._lost: str | None = None  # a disconnect seen after some bytes were read
        self._serial_exception = serial.SerialException
        self._poll_s = poll_s
        self._serial = serial.serial_for_url(url, baudrate=baudrate, timeout=poll_s, write_timeout=poll_s)
        # pyserial's socket:// (and any other port class without a byte count) answers
        # in_waiting with 0/1; the POSIX and Windows serial ports, loop:// and rfc2217:// count
        self._counts_waiting = not type(self._serial).__module__.endswith("protocol_socket")

    def read(self, max_bytes: int = READ_BYTES) -> bytes:
        """Up to ``max_bytes`` bytes: blocks up to ``poll_s`` for the first,
        then takes whatever else has arrived, in as few calls as the port
        allows (a UART/pty says how many bytes wait; a socket does not, so it
        is read once more without waiting)."""
        if self._lost is not None:
            raise LinkLost(self._lost)
        data = b""
        try:
            data = self._serial.read(1)
            if data and max_bytes > 1:
                if self._counts_waiting:
                    waiting = self._serial.in_waiting
                    if waiting:
                        data += self._serial.read(min(waiting, max_bytes - 1))
                else:
                    data += self._read_available(max_bytes - 1)
        except (self._serial_exception, OSError) as exc:
            self._lost = f"{self.name}: {exc}"
            if not data:
                raise LinkLost(self._lost) from None
        return bytes(data)  # the disconnect, if any, is raised by the next read

    def _read_available(self, max_bytes: int) -> bytes:
        """What has arrived, without waiting (pyserial's socket:// reports
        only 1 for "some" in ``in_waiting``: read with timeout 0 instead,
        which returns after one ``recv`` of up to ``max_bytes``)."""
        self._serial.timeout = 0
        try:
            return self._serial.read(max_bytes)
        finally:
            self._serial.timeout = self._poll_s

    def write(self, data: bytes) -> None:
        try:
            self._serial.write(data)
        except (self._serial_exception, OSError) as exc:
            raise LinkLost(f"{self.name}: {exc}") from None

    def close(self) -> None:
        self._serial.close()


# --------------------------------------------------------------------------
# Layer 2: framer
# --------------------------------------------------------------------------

SENTENCE = "sentence"  # from "$" to the line end, "\r" stripped
NOISE = "noise"  # non-blank bytes outside any sentence
PARTIAL = "partial"  # a sentence cut short by a new "$" or by the end of data
OVERLONG = "overlong"  # a sentence longer than MAX_LINE_BYTES (content = its start)
CUT = "cut"  # a line cut short by a disconnect of the link (LineFramer.cut)


@dataclass(frozen=True)
class Frame:
    """One unit found by the framer.

    line: 1-based line number in the byte stream where the frame starts
    (1 + the number of ``\\n`` bytes before it). offset: byte offset of its
    first byte. data: its bytes (without the line end; for noise at most
    the first ``max_line_bytes``). kind: one of ``sentence``, ``noise``,
    ``partial``, ``overlong``, ``cut``. size: how many stream bytes from
    ``offset`` the frame stands for (its line end excluded; for an overlong
    line the first ``max_line_bytes + 1``, the rest up to the next ``$`` or
    line end is skipped with it; 0 when not known). count: how
    many partial sentences it stands for (a run of bare ``$`` bytes is one
    frame ``data=b"$"``, ``count = size`` = the run's length).
    """

    kind: str
    line: int
    offset: int
    data: bytes
    size: int = 0
    count: int = 1


class LineFramer:
    """Incremental bytes -> frames splitter; the result does not depend on
    how the stream is cut into chunks.

    A sentence starts at ``$`` and ends at ``\\n`` (a ``\\r`` before it is
    dropped). A ``$`` inside a sentence means the previous one was cut short
    (arm reset, noise): it is reported as ``partial`` and a new sentence
    starts, which is how the framer resynchronises (a run of bare ``$``
    bytes is one ``partial`` frame with a count, so a flood costs one frame).
    Bytes outside sentences are ``noise`` unless they are blank (spaces,
    tabs, ``\\r``, ``\\n``). A sentence longer than ``max_line_bytes`` is
    reported once as ``overlong`` and skipped up to the next ``$`` or line
    end. :meth:`cut` ends the current line where the link broke (a
    disconnect): what was pending is reported (``cut``, or ``noise``) and is
    never joined to the bytes after the reconnect.
    """

    _OUTSIDE, _SENTENCE, _DISCARD = range(3)

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES):
        self.max_line_bytes = max_line_bytes
        self._state = self._OUTSIDE
        self._line = 1  # line number of the next byte
        self._base = 0  # stream offset of the current chunk's first byte
        self._buf = bytearray()  # current sentence, or the first bytes of the current noise
        self._size = 0  # stream bytes of the current noise
        self._nonblank = False  # the current noise has a non-blank byte
        self._last_cr = False  # the current noise ends with "\r"
        self._start = (1, 0)  # (line, offset) where _buf began
        self._dollars = 0  # bare "$" bytes pending (each cut short by the next "$")
        self._dollars_start = (1, 0)

    def feed(self, data: bytes) -> list[Frame]:
        """Frames completed by ``data`` (bytes of any length)."""
        frames: list[Frame] = []
        pos, end = 0, len(data)
        dollar = data.find(b"$")
        newline = data.find(b"\n")
        while pos < end:
            # (each search runs once per "$" / "\n", not once per frame)
            if dollar != -1 and dollar < pos:
                dollar = data.find(b"$", pos)
            if newline != -1 and newline < pos:
                newline = data.find(b"\n", pos)
            stop = min(i for i in (dollar, newline, end) if i != -1)
            if self._state == self._OUTSIDE:
                if stop > pos:
                    if not self._size:
                        self._start = (self._line, self._base + pos)
                    self._add_noise(data, pos, stop)
                if stop != end:
                    self._emit_noise(frames, newline=stop == newline)
            elif self._state == self._SENTENCE:
                self._buf += data[pos:stop]
                if len(self._buf) > self.max_line_bytes:
                    self._flush_dollars(frames)
                    self._emit(frames, OVERLONG, self._buf[: self.max_line_bytes], self.max_line_bytes + 1)
                    self._state = self._DISCARD
                elif stop == dollar:
                    if len(self._buf) == 1:  # a bare "$"
                        if not self._dollars:
                            self._dollars_start = self._start
                        self._dollars += 1
                    else:
                        self._flush_dollars(frames)
                        self._emit(frames, PARTIAL, self._buf)
                elif stop == newline:
                    self._flush_dollars(frames)
                    text = self._buf[:-1] if self._buf.endswith(b"\r") else self._buf
                    self._emit(frames, SENTENCE, text, len(self._buf))
            if stop == end:
                break
            if stop == newline:
                self._line += 1
                self._state = self._OUTSIDE
                pos = stop + 1
            else:  # a "$" starts a sentence; in a run of "$", each but the last is bare
                run_end = _DOLLARS.match(data, stop).end()  # type: ignore[union-attr]
                if run_end - stop > 1:
                    if not self._dollars:
                        self._dollars_start = (self._line, self._base + stop)
                    self._dollars += run_end - stop - 1
                self._state = self._SENTENCE
                self._buf = bytearray(b"$")
                self._start = (self._line, self._base + run_end - 1)
                pos = run_end
        self._base += end
        return frames

    def cut(self) -> list[Frame]:
        """The link broke here (disconnect): frames left of the current
        line (a sentence in progress is ``cut``). The next byte starts a new
        frame; line numbers and offsets go on counting the same stream."""
        frames: list[Frame] = []
        self._flush_dollars(frames)
        if self._state == self._SENTENCE:
            self._emit(frames, CUT, self._buf)
        elif self._state == self._OUTSIDE:
            self._emit_noise(frames)
        self._state = self._OUTSIDE
        return frames

    def finish(self) -> list[Frame]:
        """Frames left at the end of the stream (a sentence without line end
        is ``partial``); the framer is then reset to a new stream's line 1."""
        frames: list[Frame] = []
        self._flush_dollars(frames)
        if self._state == self._SENTENCE:
            self._emit(frames, PARTIAL, self._buf)
        elif self._state == self._OUTSIDE:
            self._emit_noise(frames)
        self.__init__(self.max_line_bytes)
        return frames

    def _emit(self, frames: list[Frame], kind: str, data: bytes | bytearray, size: int | None = None) -> None:
        frames.append(Frame(kind, self._start[0], self._start[1], bytes(data), len(data) if size is None else size))
        self._buf = bytearray()

    def _flush_dollars(self, frames: list[Frame]) -> None:
        if self._dollars:
            line, offset = self._dollars_start
            frames.append(Frame(PARTIAL, line, offset, b"$", self._dollars, self._dollars))
            self._dollars = 0

    def _add_noise(self, data: bytes, pos: int, stop: int) -> None:
        room = self.max_line_bytes - len(self._buf)
        if room > 0:
            self._buf += data[pos : min(stop, pos + room)]
        self._size += stop - pos
        self._last_cr = data[stop - 1] == 0x0D
        if not self._nonblank and data[pos:stop].strip(_WHITESPACE):
            self._nonblank = True

    def _emit_noise(self, frames: list[Frame], newline: bool = False) -> None:
        if self._nonblank:
            size, data = self._size, self._buf
            if newline and self._last_cr:  # the "\r" is part of the line end, as for sentences
                size -= 1
                data = data[:size]
            frames.append(Frame(NOISE, self._start[0], self._start[1], bytes(data), size))
        self._buf = bytearray()
        self._size = 0
        self._nonblank = False


# --------------------------------------------------------------------------
# Layer 3: decoder
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ProbeRecord:
    """One decoded point sentence.

    seq: the device's button-press counter, or None for formats without one.
    xyz: (3,) mm; probe_vector: (3,) unit vector (normalised here), or None
    when the format has none; probe_diameter_mm: mm, NaN when unknown.
    line: the line number it came from; text: the line as received;
    offset, size: its bytes in the stream (set by :class:`LineDecoder`).
    """

    seq: int | None
    device_time_s: float
    xyz: tuple[float, float, float]
    probe_vector: tuple[float, float, float] | None
    probe_diameter_mm: float
    line: int
    text: bytes
    offset: int = -1
    size: int = 0

    def same_point(self, other: "ProbeRecord") -> bool:
        """Same seq, time, coordinates, vector and diameter (a retransmission)."""
        return (self.seq, self.device_time_s, self.xyz, self.probe_vector, self.probe_diameter_mm) == (
            other.seq,
            other.device_time_s,
            other.xyz,
            other.probe_vector,
            other.probe_diameter_mm,
        )


#: Kinds of :class:`Rejection` (what a flood summary counts).
REJECTION_KINDS = (
    NOISE, PARTIAL, OVERLONG, CUT, "checksum", "malformed", "implausible", "server error", "ignored point"
)


@dataclass(frozen=True)
class Rejection:
    """A frame that gave no point: ``str()`` is ``"line 7: <reason>: '<content>'"``.

    kind: one of :data:`REJECTION_KINDS`. offset, size: the stream bytes it
    stands for (set by :class:`LineDecoder`; -1, 0 when unknown). count: how
    many frames it stands for (a run of bare ``$``).
    """

    line: int
    reason: str
    text: bytes
    kind: str = "malformed"
    offset: int = -1
    size: int = 0
    count: int = 1

    def __str__(self) -> str:
        return f"line {self.line}: {self.reason}: {show(self.text)}"


class Decoder(Protocol):
    """Turns one frame into a point, a rejection, or None (nothing to report)."""

    def decode(self, frame: Frame) -> ProbeRecord | Rejection | None: ...


def _number(text: str, name: str) -> float:
    if not _NUMBER.match(text):
        raise ValueError(f"field {name} is not a decimal number: {text!r}")
    return float(text)


def frame_rejection(frame: Frame) -> Rejection | None:
    """The rejection of a frame that is not a complete line (noise, partial,
    overlong, cut), the same for every line format; None for a sentence."""
    if frame.kind == NOISE:
        return Rejection(frame.line, f"ignored {frame.size or len(frame.data)} bytes of noise", frame.data, NOISE)
    if frame.kind == PARTIAL:
        if frame.count > 1:
            reason = f"{frame.count} partial sentences (bare '$' bytes), ignored"
            return Rejection(frame.line, reason, frame.data, PARTIAL, count=frame.count)
        return Rejection(frame.line, "partial sentence (cut short), ignored", frame.data, PARTIAL)
    if frame.kind == OVERLONG:
        return Rejection(frame.line, f"line longer than {MAX_LINE_BYTES} bytes, ignored", frame.data, OVERLONG)
    if frame.kind == CUT:
        return Rejection(frame.line, "line cut short by a disconnect, ignored", frame.data, CUT)
    return None


class CfpDecoder:
    """Decodes CFP sentences (grammar in the module docstring).

    volume_mm: half-width of the measuring volume (mm): a point with some
    |X|, |Y|, |Z| above it is rejected (:mod:`crossfield.cmm.plausible`).

    Rejection reasons: ``noise``, ``partial sentence``, ``line too long``,
    ``cut short by a disconnect``, ``no checksum``, ``malformed checksum``,
    ``bad checksum: got X, computed Y``, ``not ASCII``, ``unknown sentence
    type``, wrong field count, a field that is not a number, a negative
    time, a probe vector that is not a unit vector, a diameter that is not
    positive, a coordinate outside the measuring volume.
    """

    def __init__(self, volume_mm: float = DEFAULT_VOLUME_MM):
        self.volume_mm = check_volume(volume_mm)

    def decode(self, frame: Frame) -> ProbeRecord | Rejection | None:
        if frame.kind != SENTENCE:
            return frame_rejection(frame)
        return self.decode_sentence(frame.data, frame.line)

    def decode_sentence(self, text: bytes, line: int) -> ProbeRecord | Rejection:
        """Decode one sentence ``$...*CRC`` (no line end)."""

        def reject(reason: str, kind: str = "malformed") -> Rejection:
            return Rejection(line, reason, text, kind)

        star = text.rfind(b"*")
        if not text.startswith(b"$") or star == -1:
            return reject("no checksum ('*' missing)", "checksum")
        body, given = text[1:star], text[star + 1 :]
        try:
            given_text = given.decode("ascii")
        except UnicodeDecodeError:
            given_text = ""
        if not _HEX4.match(given_text):
            return reject(f"malformed checksum {show(given)} (want 4 hex digits)", "checksum")
        computed = crc16(body)
        if int(given_text, 16) != computed:
            return reject(f"bad checksum: got {given_text.upper()}, computed {computed:04X}", "checksum")
        try:
            fields = body.decode("ascii").split(",")
        except UnicodeDecodeError:
            return reject("not ASCII")
        if fields[0] != POINT_SENTENCE:
            return reject(f"unknown sentence type {fields[0]!r} (expected {POINT_SENTENCE!r})")
        values = fields[1:]
        if len(values) != len(POINT_FIELDS):
            return reject(f"expected {len(POINT_FIELDS)} fields after {POINT_SENTENCE}, got {len(values)}")
        if not _SEQ.match(values[0]):
            return reject(f"field seq is not an integer: {values[0]!r}")
        try:
            numbers = [_number(v, name) for v, name in zip(values[1:], POINT_FIELDS[1:])]
        except ValueError as exc:
            return reject(str(exc))
        device_time_s, x, y, z, i, j, k, diameter = numbers
        if device_time_s < 0:
            return reject(f"device time must be >= 0 s, got {device_time_s}", "implausible")
        problem = coordinate_problem((x, y, z), self.volume_mm)
        if problem:
            return reject(problem, "implausible")
        norm = math.sqrt(i * i + j * j + k * k)
        if abs(norm - 1.0) > UNIT_VECTOR_TOLERANCE:
            return reject(f"probe vector ({i}, {j}, {k}) is not a unit vector (norm {norm:.6f})", "implausible")
        if not diameter > 0:
            return reject(f"probe diameter must be > 0 mm, got {diameter}", "implausible")
        problem = size_problem(diameter, "probe diameter", 2 * self.volume_mm)
        if problem:
            return reject(problem, "implausible")
        return ProbeRecord(
            seq=int(values[0]),
            device_time_s=device_time_s,
            xyz=(x, y, z),
            probe_vector=(i / norm, j / norm, k / norm),
            probe_diameter_mm=diameter,
            line=line,
            text=text,
        )


class LineDecoder:
    """Framer + decoder over a byte stream: ``feed(bytes)`` -> results.

    Results are :class:`ProbeRecord` and :class:`Rejection` in stream order
    (each rejection carries its frame's byte range); frames that the decoder
    maps to None are dropped. :meth:`cut` marks a disconnect of the link.
    """

    def __init__(self, decoder: Decoder | None = None, framer: LineFramer | None = None):
        self.decoder = decoder or CfpDecoder()
        self.framer = framer or LineFramer()

    def feed(self, data: bytes) -> list[ProbeRecord | Rejection]:
        return self._decode(self.framer.feed(data))

    def cut(self) -> list[ProbeRecord | Rejection]:
        """The link broke (disconnect) after the bytes fed so far."""
        return self._decode(self.framer.cut())

    def finish(self) -> list[ProbeRecord | Rejection]:
        return self._decode(self.framer.finish())

    def _decode(self, frames: list[Frame]) -> list[ProbeRecord | Rejection]:
        results: list[ProbeRecord | Rejection] = []
        for frame in frames:
            result = self.decoder.decode(frame)
            size = frame.size or len(frame.data)
            # (built field by field: dataclasses.replace costs as much as the decoding)
            if isinstance(result, ProbeRecord):
                r = result
                result = ProbeRecord(
                    r.seq, r.device_time_s, r.xyz, r.probe_vector, r.probe_diameter_mm, r.line, r.text,
                    frame.offset, size,
                )
            elif isinstance(result, Rejection):
                r = result
                result = Rejection(r.line, r.reason, r.text, r.kind, frame.offset, size, r.count)
            if result is not None:
                results.append(result)
        return results
