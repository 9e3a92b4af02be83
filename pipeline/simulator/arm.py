"""The simulated ROMER arm: speaks CFP sentences on a real pseudo-terminal.

``with SimulatedArm(probes).serve_pty() as port:`` opens a pty pair; the
slave's path (``/dev/pts/N``) is what the serial plugin opens with pyserial,
exactly like a real port. A background thread waits until a client has
opened and configured the slave (pyserial flushes the input queue when it
opens a port, as a real UART would lose what was sent before), then writes
one sentence per probe, optionally paced like a real line (``baudrate``)
and spaced like button presses (``line_delay_s``).

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
import termios
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np

from pipeline.romer_protocol import encode_point

#: termios speed set on the slave before a client opens it; pyserial's
#: open() replaces it, which tells the arm that the port is configured.
_MARKER_SPEED = termios.B50

Fault = Callable[[bytes], bytes]


@dataclass(frozen=True)
class ArmProbe:
    """One button press: label (plan label), xyz (3,) measured probe-ball
    centre in mm (noise already added), probe_vector (3,) unit approach
    direction, probe_diameter_mm in mm."""

    label: str
    xyz: np.ndarray
    probe_vector: np.ndarray
    probe_diameter_mm: float


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


class SimulatedArm:
    """A ROMER-style arm that sends one CFP sentence per probe.

    probes: objects with ``label``, ``xyz`` (3,) mm, ``probe_vector`` (3,),
    ``probe_diameter_mm`` in probing order. line_delay_s: pause between two
    sentences (s). baudrate: if set, bytes are paced at 10 bits per byte
    (8N1) like a real line; None writes as fast as the pty accepts.
    first_seq: seq of the first probe. time_origin_s, press_interval_s:
    device clock of the first press and between presses (s).
    faults: probe index -> transform of its sentence bytes. preamble:
    bytes written before the first sentence. hang_up_when_done: close the
    pty once everything is written (the arm is switched off: the reader
    sees the link drop).

    After (or during) serving, ``written`` holds every byte the pty accepted.
    """

    def __init__(
        self,
        probes: Sequence[object],
        *,
        line_delay_s: float = 0.0,
        baudrate: int | None = None,
        first_seq: int = 1,
        time_origin_s: float = 10.0,
        press_interval_s: float = 2.0,
        faults: Mapping[int, Fault] | None = None,
        preamble: bytes = b"",
        settle_s: float = 0.02,
        hang_up_when_done: bool = False,
    ):
        self.probes = list(probes)
        self.line_delay_s = float(line_delay_s)
        self.baudrate = baudrate
        self.first_seq = int(first_seq)
        self.time_origin_s = float(time_origin_s)
        self.press_interval_s = float(press_interval_s)
        self.faults = dict(faults or {})
        self.preamble = bytes(preamble)
        self.settle_s = float(settle_s)
        self.hang_up_when_done = hang_up_when_done
        self._master: int | None = None
        self.written = bytearray()
        self.error: BaseException | None = None
        self._done = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._line_free_at = 0.0

    def sentence(self, index: int) -> bytes:
        """The clean sentence of probe ``index`` (before any fault)."""
        probe = self.probes[index]
        return encode_point(
            self.first_seq + index,
            self.time_origin_s + index * self.press_interval_s,
            np.asarray(probe.xyz, dtype=np.float64),
            np.asarray(probe.probe_vector, dtype=np.float64),
            float(probe.probe_diameter_mm),
        )

    def messages(self) -> list[bytes]:
        """What the arm writes, in order: preamble (if any), then each
        probe's sentence after its fault transform."""
        out = [self.preamble] if self.preamble else []
        for index in range(len(self.probes)):
            sentence = self.sentence(index)
            fault = self.faults.get(index)
            out.append(fault(sentence) if fault else sentence)
        return out

    def expected_bytes(self) -> bytes:
        return b"".join(self.messages())

    def wait_done(self, timeout: float | None = None) -> bool:
        """Wait until every message has been written; True if so."""
        return self._done.wait(timeout)

    @contextlib.contextmanager
    def serve_pty(self) -> Iterator[str]:
        """Open a pty, serve the probes from a background thread, yield the
        slave path; on exit stop the thread and close the pty."""
        master, slave = os.openpty()
        path = os.ttyname(slave)
        attrs = termios.tcgetattr(slave)
        attrs[4] = attrs[5] = _MARKER_SPEED
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.close(slave)  # the master now sees POLLHUP until a client opens the slave
        os.set_blocking(master, False)
        self._master = master
        thread = threading.Thread(target=self._run, args=(master,), name=f"SimulatedArm {path}", daemon=True)
        thread.start()
        try:
            yield path
        finally:
            self._stop.set()
            thread.join(5.0)
            self._hang_up()
        if self.error is not None:
            raise RuntimeError(f"simulated arm on {path} failed: {self.error!r}") from self.error

    # -- writer thread ----------------------------------------------------------

    def _run(self, master: int) -> None:
        try:
            poller = select.poll()
            poller.register(master, select.POLLOUT)
            if not self._wait_for_client(master, poller):
                return
            for k, message in enumerate(self.messages()):
                if k and self.line_delay_s > 0 and self._stop.wait(self.line_delay_s):
                    return
                if not self._write(master, poller, message):
                    return
            if self.hang_up_when_done:
                time.sleep(0.05)  # let the reader drain the pty first
                self._hang_up()
            self._done.set()
        except BaseException as exc:  # reported by serve_pty
            self.error = exc

    def _hang_up(self) -> None:
        with self._lock:
            if self._master is not None:
                os.close(self._master)
                self._master = None

    def _client_present(self, poller: select.poll) -> bool:
        events = poller.poll(0)
        return not any(flags & select.POLLHUP for _, flags in events)

    def _wait_for_client(self, master: int, poller: select.poll) -> bool:
        """Block until a client has opened the slave and set its speed (or
        0.5 s after it opened it), then let its input flush pass."""
        opened_at = None
        while not self._stop.is_set():
            if self._client_present(poller):
                opened_at = opened_at or time.monotonic()
                configured = termios.tcgetattr(master)[4] != _MARKER_SPEED
                if configured or time.monotonic() - opened_at > 0.5:
                    return not self._stop.wait(self.settle_s)
            else:
                opened_at = None
            time.sleep(0.002)
        return False

    def _write(self, master: int, poller: select.poll, data: bytes) -> bool:
        """Write all of ``data`` (paced if baudrate is set); False if stopped."""
        step = 16 if self.baudrate else 4096
        for start in range(0, len(data), step):
            chunk = data[start : start + step]
            if self.baudrate and not self._pace(len(chunk)):
                return False
            if not self._write_all(master, poller, chunk):
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

    def _write_all(self, master: int, poller: select.poll, chunk: bytes) -> bool:
        while chunk:
            if self._stop.is_set():
                return False
            if not poller.poll(50):
                continue
            if not self._client_present(poller):
                # the client closed the port: wait for it to come back
                if not self._wait_for_client(master, poller):
                    return False
                continue
            try:
                n = os.write(master, chunk)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:
                    continue
                raise
            self.written += chunk[:n]
            chunk = chunk[n:]
        return True
