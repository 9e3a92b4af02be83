"""Other CMM line formats, as framer + decoder pairs for the reference stage.

Besides crossfield's own CFP sentences (:mod:`crossfield.cmm.protocol`),
the ``romer-serial`` reference plugin reads (``docs/serial-protocol.md``):

* ``pcdmis``: PC-DMIS "Generic CMM" style lines, one point per line, either
  prefixed ``X100.000,Y200.000,Z300.000`` (optionally ``,I0,J0,K1``) or
  plain ``100.000,200.000,300.000``; in mm or inch. No sequence number, no
  checksum.
* ``ippdme``: I++ DME (the DMIS server protocol over TCP): after the client
  has started a session and enabled the user (manual probing), the server
  reports each point picked by hand as an unsolicited event
  ``E0000 # PtMeas(X(..), Y(..), Z(..), IJK(..), R(..))``.

Both are line formats without a start character, so they use
:class:`PlainLineFramer` (every non-blank line is one frame).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Callable, Sequence

from crossfield.cmm.plausible import DEFAULT_VOLUME_MM, check_volume, coordinate_problem, size_problem
from crossfield.cmm.protocol import (
    CUT,
    MAX_LINE_BYTES,
    OVERLONG,
    PARTIAL,
    SENTENCE,
    CfpDecoder,
    Decoder,
    Frame,
    LineFramer,
    ProbeRecord,
    Rejection,
    frame_rejection,
)

__all__ = [
    "FORMATS",
    "IPPDME_END",
    "IPPDME_PORT",
    "IPPDME_SESSION",
    "MM_PER_INCH",
    "UNITS",
    "IppDmeDecoder",
    "LineFormat",
    "PcDmisDecoder",
    "PlainLineFramer",
    "encode_ippdme_event",
    "encode_pcdmis",
]

MM_PER_INCH = 25.4
UNITS = {"mm": 1.0, "inch": MM_PER_INCH}

_BLANK_LINES = re.compile(rb"(?:[ \t\r]*\n)+")


class PlainLineFramer:
    """Bytes -> one frame per non-blank line (``\\r`` and surrounding blanks
    stripped), for formats without a start character. Lines longer than
    ``max_line_bytes`` are reported once as ``overlong``; a last line without
    line end is ``partial``; :meth:`cut` ends the current line where the
    link broke (``cut``: never joined to the bytes after the reconnect).
    Independent of chunking; line numbers as in
    :class:`crossfield.cmm.protocol.LineFramer`. A frame's ``offset`` is its
    line's first byte and ``size`` the line's length without the ``\\n``.
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES):
        self.max_line_bytes = max_line_bytes
        self._line = 1
        self._base = 0
        self._buf = bytearray()
        self._size = 0  # bytes of the current line so far
        self._start = 0
        self._overlong = False

    def feed(self, data: bytes) -> list[Frame]:
        frames: list[Frame] = []
        pos = 0
        end = len(data)
        while pos < end:
            if not self._size:
                # a run of blank lines costs one regex match, not one loop per line
                blank = _BLANK_LINES.match(data, pos)
                if blank is not None and blank.end() > pos:
                    self._line += data.count(b"\n", pos, blank.end())
                    pos = blank.end()
                    continue
            newline = data.find(b"\n", pos)
            stop = end if newline == -1 else newline
            if not self._size:
                self._start = self._base + pos
            self._size += stop - pos
            if not self._overlong:
                self._buf += data[pos:stop]
                if len(self._buf) > self.max_line_bytes:
                    head = bytes(self._buf[: self.max_line_bytes])
                    frames.append(Frame(OVERLONG, self._line, self._start, head, self.max_line_bytes + 1))
                    self._buf = bytearray()
                    self._overlong = True
            if newline == -1:
                break
            self._end_line(frames, SENTENCE)
            self._line += 1
            pos = newline + 1
        self._base += end
        return frames

    def cut(self) -> list[Frame]:
        """The link broke here: the line in progress is a ``cut`` frame."""
        frames: list[Frame] = []
        self._end_line(frames, CUT)
        return frames

    def finish(self) -> list[Frame]:
        frames: list[Frame] = []
        self._end_line(frames, PARTIAL)
        self.__init__(self.max_line_bytes)
        return frames

    def _end_line(self, frames: list[Frame], kind: str) -> None:
        text = bytes(self._buf).strip()
        if text and not self._overlong:
            frames.append(Frame(kind, self._line, self._start, text, self._size))
        self._buf = bytearray()
        self._size = 0
        self._overlong = False


# ---- PC-DMIS "Generic CMM" lines ----------------------------------------------

_PC_NUMBER = r"[+-]?[0-9]+(?:\.[0-9]+)?"
_PREFIXED = re.compile(
    rf"X({_PC_NUMBER})\s*,\s*Y({_PC_NUMBER})\s*,\s*Z({_PC_NUMBER})"
    rf"(?:\s*,\s*I({_PC_NUMBER})\s*,\s*J({_PC_NUMBER})\s*,\s*K({_PC_NUMBER}))?",
    re.IGNORECASE,
)
_PLAIN = re.compile(rf"({_PC_NUMBER})\s*,\s*({_PC_NUMBER})\s*,\s*({_PC_NUMBER})")


def encode_pcdmis(xyz: Sequence[float], *, units: str = "mm", prefixed: bool = True) -> bytes:
    """One PC-DMIS generic line for ``xyz`` (3,) given in mm, written in
    ``units`` (3 decimals for mm, 4 for inch)."""
    scale = UNITS[units]
    decimals = 3 if units == "mm" else 4
    values = [f"{float(v) / scale:.{decimals}f}" for v in xyz]
    if prefixed:
        values = [f"{axis}{v}" for axis, v in zip("XYZ", values)]
    return (",".join(values) + "\r\n").encode("ascii")


class PcDmisDecoder:
    """``X..,Y..,Z..[,I..,J..,K..]`` or ``x,y,z`` lines (whole line must match).

    units: ``"mm"`` or ``"inch"`` (coordinates are converted to mm).
    volume_mm: half-width of the measuring volume (mm); points outside it
    (or not finite) are rejected.
    Without a checksum a damaged line can still look valid (e.g. a lost
    line end joining ``100`` and ``3.000,...`` into ``1003.000,...``): prefer
    CFP where the device allows it. (A line cut by a disconnect is not
    joined to the next: the framer reports it as ``cut``.)
    """

    def __init__(self, units: str = "mm", volume_mm: float = DEFAULT_VOLUME_MM):
        if units not in UNITS:
            raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
        self.units = units
        self.scale = UNITS[units]
        self.volume_mm = check_volume(volume_mm)

    def decode(self, frame: Frame) -> ProbeRecord | Rejection | None:
        if frame.kind != SENTENCE:
            return frame_rejection(frame)
        try:
            text = frame.data.decode("ascii")
        except UnicodeDecodeError:
            return Rejection(frame.line, "not ASCII", frame.data)
        match = _PREFIXED.fullmatch(text) or _PLAIN.fullmatch(text)
        if match is None:
            return Rejection(
                frame.line, "not a point line (want 'X..,Y..,Z..[,I..,J..,K..]' or 'x,y,z')", frame.data
            )
        groups = match.groups()
        xyz = tuple(float(v) * self.scale for v in groups[:3])
        problem = coordinate_problem(xyz, self.volume_mm)
        if problem:
            return Rejection(frame.line, problem, frame.data, "implausible")
        vector = None
        if len(groups) == 6 and groups[3] is not None:
            ijk = [float(v) for v in groups[3:]]
            norm = math.sqrt(sum(v * v for v in ijk))
            if not abs(norm - 1.0) <= 1e-3:
                reason = f"I,J,K ({', '.join(groups[3:])}) is not a unit vector"
                return Rejection(frame.line, reason, frame.data, "implausible")
            vector = tuple(v / norm for v in ijk)
        return ProbeRecord(
            seq=None,
            device_time_s=float("nan"),
            xyz=xyz,  # type: ignore[arg-type]
            probe_vector=vector,  # type: ignore[arg-type]
            probe_diameter_mm=float("nan"),
            line=frame.line,
            text=frame.data,
        )


# ---- I++ DME -------------------------------------------------------------------

#: Default TCP port of an I++ DME server.
IPPDME_PORT = 1294
#: What the client sends after connecting: start a session, enable manual
#: probing, and ask for centre, normal and radius in every point report.
IPPDME_SESSION = (
    b"00001 StartSession()\r\n"
    b"00002 EnableUser()\r\n"
    b"00003 OnPtMeasReport(X(), Y(), Z(), IJK(), R())\r\n"
)
IPPDME_END = b"00004 EndSession()\r\n"

_IPP_NUMBER = r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[Ee][+-]?[0-9]{1,3})?"
_IPP_LINE = re.compile(r"(?P<tag>[0-9]{5}|E[0-9]{4})\s+(?P<kind>[&%#!])\s*(?P<data>.*)")
_IPP_GROUP = re.compile(r"\s*([A-Za-z][A-Za-z0-9.]*)\(([^()]*)\)\s*(?:,|$)")


def encode_ippdme_event(
    xyz: Sequence[float], probe_vector: Sequence[float], probe_diameter_mm: float
) -> bytes:
    """The server's manual-point event: ``E0000 # PtMeas(X(..), Y(..), Z(..),
    IJK(..), R(..))``. xyz (3,) mm ball centre; IJK is the surface normal,
    i.e. minus the approach direction ``probe_vector``; R the ball radius."""
    x, y, z = (float(v) for v in xyz)
    i, j, k = (-float(v) for v in probe_vector)
    return (
        f"E0000 # PtMeas(X({x:.4f}), Y({y:.4f}), Z({z:.4f}), IJK({i:.6f}, {j:.6f}, {k:.6f}), "
        f"R({probe_diameter_mm / 2.0:.4f}))\r\n"
    ).encode("ascii")


def _groups(text: str) -> dict[str, list[str]] | None:
    """``X(1), IJK(0,0,1)`` -> {"X": ["1"], "IJK": ["0", "0", "1"]}; None if malformed."""
    out: dict[str, list[str]] = {}
    pos = 0
    while pos < len(text):
        match = _IPP_GROUP.match(text, pos)
        if match is None or match.end() == pos:
            return None
        out[match.group(1)] = [a.strip() for a in match.group(2).split(",")] if match.group(2).strip() else []
        pos = match.end()
    return out


class IppDmeDecoder:
    """Reads the server's side of an I++ DME session.

    ``&`` (acknowledged) and ``%`` (completed) responses, other events
    (``KeyPress``, clearance ``GoTo``) and data answers to other commands
    give nothing; ``! Error(...)`` gives a rejection naming the error;
    ``E0000 # PtMeas(...)`` gives a point. X, Y, Z are the ball centre in mm;
    the approach direction is minus IJK; the diameter is 2 R. Non-finite
    values (``1e999``), points outside the measuring volume (``volume_mm``,
    mm) and negative radii are rejected.
    """

    def __init__(self, volume_mm: float = DEFAULT_VOLUME_MM):
        self.volume_mm = check_volume(volume_mm)

    def decode(self, frame: Frame) -> ProbeRecord | Rejection | None:
        if frame.kind != SENTENCE:
            return frame_rejection(frame)
        try:
            text = frame.data.decode("ascii")
        except UnicodeDecodeError:
            return Rejection(frame.line, "not ASCII", frame.data)
        match = _IPP_LINE.fullmatch(text)
        if match is None:
            return Rejection(frame.line, "not an I++ DME response (want '<tag> &|%|#|! ...')", frame.data)
        tag, kind, data = match.group("tag"), match.group("kind"), match.group("data").strip()
        if kind == "!":
            return Rejection(frame.line, f"server error for command {tag}", frame.data, "server error")
        if kind != "#" or tag != "E0000" or not data.startswith("PtMeas("):
            return None
        if not data.endswith(")"):
            return Rejection(frame.line, "malformed PtMeas event", frame.data)
        groups = _groups(data[len("PtMeas(") : -1])
        if groups is None:
            return Rejection(frame.line, "malformed PtMeas event", frame.data)
        number = re.compile(_IPP_NUMBER)

        def values(name: str, count: int) -> list[float] | None:
            args = groups.get(name)
            if args is None:
                return None
            if len(args) != count or not all(number.fullmatch(a) for a in args):
                raise ValueError(f"{name}({', '.join(args)}) is not {count} number(s)")
            return [float(a) for a in args]

        try:
            coords = [values(axis, 1) for axis in "XYZ"]
            ijk = values("IJK", 3)
            radius = values("R", 1)
        except ValueError as exc:
            return Rejection(frame.line, f"malformed PtMeas event: {exc}", frame.data)
        if any(c is None for c in coords):
            return Rejection(frame.line, "PtMeas event without X, Y and Z", frame.data)
        xyz = tuple(c[0] for c in coords)  # type: ignore[index]
        problem = coordinate_problem(xyz, self.volume_mm)
        if problem:
            return Rejection(frame.line, problem, frame.data, "implausible")
        vector = None
        if ijk is not None:
            if not all(math.isfinite(v) for v in ijk):
                return Rejection(frame.line, "IJK is not finite", frame.data, "implausible")
            norm = math.sqrt(sum(v * v for v in ijk))
            if not norm > 0:
                return Rejection(frame.line, "IJK is a zero vector", frame.data, "implausible")
            vector = tuple(-v / norm for v in ijk)
        if radius is not None:
            problem = size_problem(radius[0], "probe radius R", self.volume_mm, allow_zero=True)
            if problem:
                return Rejection(frame.line, problem, frame.data, "implausible")
        return ProbeRecord(
            seq=None,
            device_time_s=float("nan"),
            xyz=xyz,  # type: ignore[arg-type]
            probe_vector=vector,  # type: ignore[arg-type]
            probe_diameter_mm=2.0 * radius[0] if radius else float("nan"),
            line=frame.line,
            text=frame.data,
        )


# ---- the formats the reference plugin knows ----------------------------------------


@dataclass(frozen=True)
class LineFormat:
    """A framer + decoder pair (decoder: ``(units, volume_mm)`` -> Decoder). session: bytes the client writes after each
    (re)connect; end: bytes it writes before closing. has_seq: its points
    carry sequence numbers."""

    name: str
    framer: Callable[[], LineFramer | PlainLineFramer]
    decoder: Callable[[str, float], Decoder]  # (units, volume_mm) -> decoder
    has_seq: bool
    session: bytes = b""
    end: bytes = b""


def _cfp_decoder(units: str, volume_mm: float = DEFAULT_VOLUME_MM) -> Decoder:
    if units != "mm":
        raise ValueError(f"format 'cfp' is defined in mm; units must be 'mm', got {units!r}")
    return CfpDecoder(volume_mm)


def _ippdme_decoder(units: str, volume_mm: float = DEFAULT_VOLUME_MM) -> Decoder:
    if units != "mm":
        raise ValueError(
            f"format 'ippdme' reads mm (the protocol's default); units must be 'mm', got {units!r}"
        )
    return IppDmeDecoder(volume_mm)


FORMATS: dict[str, LineFormat] = {
    "cfp": LineFormat("cfp", LineFramer, _cfp_decoder, has_seq=True),
    "pcdmis": LineFormat("pcdmis", PlainLineFramer, PcDmisDecoder, has_seq=False),
    "ippdme": LineFormat(
        "ippdme", PlainLineFramer, _ippdme_decoder, has_seq=False, session=IPPDME_SESSION, end=IPPDME_END
    ),
}
