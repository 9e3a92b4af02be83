"""The simulated ROMER arm: speaks a CMM line format on a real pseudo-terminal.

``with SimulatedArm(probes).serve_pty() as port:`` opens a pty pair and
yields a stable path to its slave (a symlink, like udev's
``/dev/serial/by-id/...``), which the serial plugin opens with pyserial
exactly like a real port. A background thread waits until a client has
opened and configured the slave (pyserial flushes the input queue when it
opens a port, as a real UART would lose what was sent before), then writes
one line per probe in ``format`` (``cfp``, ``pcdmis``, ``pcdmis-plain``),
optionally paced like a real line (``baudrate``) and spaced like button
presses (``line_delay_s``).

Production behaviour: ``bursts={index: n}`` holds the button on a probe
(``n`` repeats: same seq, slightly different coordinates);
``unplug_after={index: downtime_s}`` pulls the cable after that probe (the
pty closes, the path disappears, a new pty appears behind the same path
after the downtime); whenever a client (re)connects, the arm first resends
every point it has sent in this session (``resend_on_connect``), so points
in flight when the link dropped are not lost; the reader drops the
duplicates.

Faults for tests: ``faults={index: transform}`` rewrites the bytes of the
probe at ``index`` (0-based) before they are written; see
:func:`bad_checksum`, :func:`with_noise`, :func:`truncated`,
:func:`repeated`, :func:`dropped`. ``preamble`` is written before the first
sentence (line noise at connect).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import shutil
import tempfile
import termios
import threading
import time
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np

from crossfield.cmm.formats import encode_pcdmis
from crossfield.cmm.protocol import encode_point
from crossfield.simulator.scene import ArmProbe  # noqa: F401  (re-exported for the tools that build probes)

__all__ = [
    "FORMATS",
    "ArmProbe",
    "Fault",
    "SimulatedArm",
    "bad_checksum",
    "dropped",
    "probes_from_points",
    "repeated",
    "truncated",
    "with_noise",
]

#: termios speed set on the slave before a client opens it; pyserial's
#: open() replaces it, which tells the arm that the port is configured.
_MARKER_SPEED = termios.B50

Fault = Callable[[bytes], bytes]


def probes_from_points(
    labels: Sequence[str],
    xyz: np.ndarray,
    rng: np.random.Generator,
    sigma_mm: float = 0.01,
    probe_diameter_mm: float = 6.0,
) -> list[ArmProbe]:
    """Arm probes for true points ``xyz`` (N, 3) mm: Gaussian noise of
    ``sigma_mm`` per coordinate and a random approach direction within 30
    degrees of -Z."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(labels) != len(xyz):
        raise ValueError(f"{len(labels)} labels for {len(xyz)} points")
    probes = []
    for label, point in zip(labels, xyz):
        tilt = np.deg2rad(30.0) * np.sqrt(rng.uniform())
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        vector = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)])
        probes.append(ArmProbe(label, point + rng.normal(0.0, sigma_mm, 3), vector, probe_diameter_mm))
    return probes


# ---- fault transforms -------------------------------------------------------


def bad_checksum(sentence: bytes) -> bytes:
    """The sentence with its CRC digits altered (the data stays readable)."""
    star = sentence.rindex(b"*")
    digits = sentence[star + 1 : star + 5]
    wrong = f"{int(digits, 16) ^ 0x5A5A:04X}".encode()
    return sentence[: star + 1] + wrong + sentence[star + 5 :]


def with_noise(noise: bytes) -> Fault:
    """Write ``noise`` just before the sentence (same line)."""
    return lambda sentence: noise + sentence


def truncated(keep: int = 30) -> Fault:
    """Only the first ``keep`` bytes of the sentence, no line end (the
    next sentence's ``$`` cuts it short)."""
    return lambda sentence: sentence[:keep]


def repeated(times: int = 2) -> Fault:
    """The sentence sent ``times`` times (a retransmission)."""
    return lambda sentence: sentence * times


def dropped(sentence: bytes) -> bytes:
    """Nothing is written (the press is lost: a sequence gap)."""
    return b""


# ---- the arm ------------------------------------------------------------------

FORMATS = ("cfp", "pcdmis", "pcdmis-plain")


class SimulatedArm:
    """A ROMER-style arm that sends one line per probe.

    probes: objects with ``label``, ``xyz`` (3,) mm, ``probe_vector`` (3,),
    ``probe_diameter_mm`` in probing order. format: ``cfp`` (default),
    ``pcdmis`` (``X..,Y..,Z..``) or ``pcdmis-plain`` (``x,y,z``); units
    ``mm`` or ``inch`` (pcdmis only). line_delay_s: pause between two
    probes (s). baudrate: if set, bytes are paced at 10 bits per byte (8N1)
    like a real line; None writes as fast as the pty accepts.
    first_seq: seq of the first probe. time_origin_s, press_interval_s:
    device clock of the first press and between presses (s).
    faults: probe index -> transform of its line's bytes. preamble: bytes
    written before the first line. bursts: probe index -> number of repeats
    sent while the button is held (jitter ``burst_jitter_mm`` per axis,
    device time + 0.05 s each). unplug_after: probe index -> seconds the
    cable stays out after that probe. cut_after: probe index -> n: before
    that unplug, the first n bytes of the next probe's line go out (the
    reader gets them), so the cable is pulled in the middle of a line.
    resend_on_connect: on every
    (re)connection resend the clean lines of the probes already sent.
    hang_up_when_done: close the pty once everything is written (the arm is
    switched off: the reader sees the link drop and no return).

    ``written`` holds every byte the pty accepted (resends included).
    """

    def __init__(
        self,
        probes: Sequence[object],
        *,
        format: str = "cfp",
        units: str = "mm",
        line_delay_s: float = 0.0,
        baudrate: int | None = None,
        first_seq: int = 1,
        time_origin_s: float = 10.0,
        press_interval_s: float = 2.0,
        faults: Mapping[int, Fault] | None = None,
        preamble: bytes = b"",
        bursts: Mapping[int, int] | None = None,
        burst_jitter_mm: float = 0.01,
        unplug_after: Mapping[int, float] | None = None,
        cut_after: Mapping[int, int] | None = None,
        resend_on_connect: bool = True,
        settle_s: float = 0.02,
        hang_up_when_done: bool = False,
    ):
        if format not in FORMATS:
            raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {format!r}")
        if format == "cfp" and units != "mm":
            raise ValueError("the cfp format is in mm")
        self.probes = list(probes)
        self.format = format
        self.units = units
        self.line_delay_s = float(line_delay_s)
        self.baudrate = baudrate
        self.first_seq = int(first_seq)
        self.time_origin_s = float(time_origin_s)
        self.press_interval_s = float(press_interval_s)
        self.faults = dict(faults or {})
        self.preamble = bytes(preamble)
        self.bursts = dict(bursts or {})
        self.burst_jitter_mm = float(burst_jitter_mm)
        self.unplug_after = dict(unplug_after or {})
        self.cut_after = dict(cut_after or {})
        if set(self.cut_after) - set(self.unplug_after):
            raise ValueError("cut_after needs an unplug_after at the same probe index")
        self.resend_on_connect = resend_on_connect
        self.settle_s = float(settle_s)
        self.hang_up_when_done = hang_up_when_done
        self.written = bytearray()
        self.connections = 0  # how many times a client has (re)connected
        self.error: BaseException | None = None
        self._master: int | None = None
        self._poller: select.poll | None = None
        self._link: str | None = None
        self.pty_path = ""  # the latest /dev/pts/N behind the stable path
        self._sent: list[int] = []  # probe indices whose line was written
        self._done = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._line_free_at = 0.0

    # -- what is sent ------------------------------------------------------------

    def sentence(self, index: int, repeat: int = 0) -> bytes:
        """The clean line of probe ``index`` (``repeat`` > 0: the repeat
        number ``repeat`` of a held button)."""
        probe = self.probes[index]
        xyz = np.asarray(probe.xyz, dtype=np.float64)
        if repeat:
            jitter = np.random.default_rng([index, repeat]).normal(0.0, self.burst_jitter_mm, 3)
            xyz = xyz + jitter
        if self.format != "cfp":
            return encode_pcdmis(xyz, units=self.units, prefixed=self.format == "pcdmis")
        return encode_point(
            self.first_seq + index,
            self.time_origin_s + index * self.press_interval_s + 0.05 * repeat,
            xyz,
            np.asarray(probe.probe_vector, dtype=np.float64),
            float(probe.probe_diameter_mm),
        )

    def probe_bytes(self, index: int) -> bytes:
        """What the arm writes for probe ``index``: its line after its fault
        transform, then the repeats of a held button."""
        sentence = self.sentence(index)
        fault = self.faults.get(index)
        out = fault(sentence) if fault else sentence
        for repeat in range(1, self.bursts.get(index, 0) + 1):
            out += self.sentence(index, repeat)
        return out

    def messages(self) -> list[bytes]:
        """What the arm writes without reconnections, in order: preamble (if
        any), then :meth:`probe_bytes` of each probe."""
        out = [self.preamble] if self.preamble else []
        return out + [self.probe_bytes(index) for index in range(len(self.probes))]

    def expected_bytes(self) -> bytes:
        return b"".join(self.messages())

    def wait_done(self, timeout: float | None = None) -> bool:
        """Wait until every message has been written; True if so."""
        return self._done.wait(timeout)

    def client_connected(self) -> bool:
        """A reader has the pty open."""
        with self._lock:
            if self._master is None:
                return False
            poller = select.poll()
            poller.register(self._master, select.POLLOUT)
            return not any(flags & select.POLLHUP for _, flags in poller.poll(0))

    # -- the pty -----------------------------------------------------------------

    @contextlib.contextmanager
    def serve_pty(self) -> Iterator[str]:
        """Open a pty, serve the probes from a background thread, yield the
        stable path of its slave; on exit stop the thread and close the pty."""
        directory = tempfile.mkdtemp(prefix="crossfield-arm-")
        self._link = os.path.join(directory, "romer-arm")
        self._plug_in()
        thread = threading.Thread(target=self._run, name=f"SimulatedArm {self._link}", daemon=True)
        thread.start()
        try:
            yield self._link
        finally:
            self._stop.set()
            thread.join(5.0)
            self._hang_up()
            shutil.rmtree(directory, ignore_errors=True)
        if self.error is not None:
            raise RuntimeError(f"simulated arm on {self._link} failed: {self.error!r}") from self.error

    def _plug_in(self) -> None:
        """A new pty behind the stable path; the slave's speed is set to a
        marker that the client's configuration replaces."""
        master, slave = os.openpty()
        attrs = termios.tcgetattr(slave)
        attrs[4] = attrs[5] = _MARKER_SPEED
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        path = self.pty_path = os.ttyname(slave)
        os.close(slave)  # the master now sees POLLHUP until a client opens the slave
        os.set_blocking(master, False)
        poller = select.poll()
        poller.register(master, select.POLLOUT)
        with self._lock:
            self._master, self._poller = master, poller
        assert self._link is not None
        temporary = self._link + ".new"
        os.symlink(path, temporary)
        os.replace(temporary, self._link)

    def _hang_up(self) -> None:
        """Close the pty (the client's reads fail) and remove the stable path."""
        with self._lock:
            if self._master is not None:
                os.close(self._master)
                self._master = self._poller = None
        if self._link:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._link)

    # -- writer thread ----------------------------------------------------------

    def _run(self) -> None:
        try:
            if not self._connect():
                return
            if self.preamble and not self._send(self.preamble):
                return
            for index in range(len(self.probes)):
                if index and self.line_delay_s > 0 and self._stop.wait(self.line_delay_s):
                    return
                if not self._send(self.probe_bytes(index)):
                    return
                self._sent.append(index)
                if index in self.unplug_after:
                    keep = self.cut_after.get(index, 0)
                    if keep and index + 1 < len(self.probes):
                        # the start of the next line, then the cable goes (once the reader has it)
                        if not self._write(self.sentence(index + 1)[:keep]):
                            return
                        time.sleep(0.1)
                    self._hang_up()
                    if self._stop.wait(self.unplug_after[index]):
                        return
                    self._plug_in()
                    if not self._connect():
                        return
            if self.hang_up_when_done:
                time.sleep(0.05)  # let the reader drain the pty first
                self._hang_up()
            self._done.set()
        except BaseException as exc:  # reported by serve_pty
            self.error = exc

    def _client_present(self) -> bool:
        assert self._poller is not None
        events = self._poller.poll(0)
        return not any(flags & select.POLLHUP for _, flags in events)

    def _connect(self) -> bool:
        """Wait for a client (see :meth:`_wait_for_client`), then resend the
        lines already sent in this session. False if stopped."""
        while True:
            if not self._wait_for_client():
                return False
            self.connections += 1
            if not (self.resend_on_connect and self._sent):
                return True
            resend = b"".join(self.sentence(index) for index in self._sent)
            if self._write(resend):
                return True
            if self._stop.is_set():
                return False

    def _wait_for_client(self) -> bool:
        """Block until a client has opened the slave and set its speed (or
        0.5 s after it opened it), then let its input flush pass."""
        opened_at = None
        while not self._stop.is_set():
            if self._client_present():
                opened_at = opened_at or time.monotonic()
                assert self._master is not None
                configured = termios.tcgetattr(self._master)[4] != _MARKER_SPEED
                if configured or time.monotonic() - opened_at > 0.5:
                    return not self._stop.wait(self.settle_s)
            else:
                opened_at = None
            time.sleep(0.002)
        return False

    def _send(self, data: bytes) -> bool:
        """Write ``data``; if the client goes away meanwhile, wait for it to
        come back (it gets the session's lines again), then write ``data``
        again from its start. False if stopped."""
        while not self._write(data):
            if self._stop.is_set() or not self._connect():
                return False
        return True

    def _write(self, data: bytes) -> bool:
        """Write all of ``data`` (paced if baudrate is set); False if stopped
        or the client went away."""
        step = 16 if self.baudrate else 4096
        for start in range(0, len(data), step):
            chunk = data[start : start + step]
            if self.baudrate and not self._pace(len(chunk)):
                return False
            if not self._write_all(chunk):
                return False
        return True

    def _pace(self, n: int) -> bool:
        """Wait until ``n`` more bytes have crossed the line (10 bits each,
        8N1); the line clock restarts after the line was idle for 5 ms."""
        now = time.monotonic()
        if self._line_free_at < now - 0.005:
            self._line_free_at = now
        self._line_free_at += n * 10.0 / self.baudrate
        delay = self._line_free_at - time.monotonic()
        return not (delay > 0 and self._stop.wait(delay))

    def _write_all(self, chunk: bytes) -> bool:
        while chunk:
            if self._stop.is_set():
                return False
            assert self._poller is not None and self._master is not None
            if not self._poller.poll(50):
                continue
            if not self._client_present():
                return False
            try:
                n = os.write(self._master, chunk)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:
                    continue
                raise
            self.written += chunk[:n]
            chunk = chunk[n:]
        return True
