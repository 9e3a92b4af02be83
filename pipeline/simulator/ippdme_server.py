"""A simulated I++ DME server for a manual CMM arm, over real TCP.

``with SimulatedIppDmeServer(probes).serve() as url:`` listens on
127.0.0.1 (``url`` is ``socket://127.0.0.1:<port>``, what the reference
plugin opens with ``format = "ippdme"``). It speaks the part of I++ DME a
manual arm needs: ``StartSession()``, ``EnableUser()``,
``OnPtMeasReport(...)``, ``EndSession()`` are acknowledged (``&``) and
completed (``%``); anything else gets an ``! Error(...)``. Once a session is
started and the user enabled, each probe is reported as the unsolicited
event ``E0000 # PtMeas(X(..), Y(..), Z(..), IJK(..), R(..))``.

Faults: ``drop_after={index, ...}`` closes the connection (gracefully:
what was sent is still delivered) after that probe's event; the client
reconnects and starts a new session, and the server continues with the
next probe. ``cut_after={index: n}`` drops the connection the same way
after that probe's event and the first ``n`` bytes of the next one (a
line cut by the disconnect; the next probe is reported whole after the
reconnect). ``bursts={index: n}`` repeats a probe ``n`` times with small
jitter (a held button).
"""

from __future__ import annotations

import contextlib
import re
import socket
import threading
import time
from typing import Iterable, Iterator, Mapping, Sequence

import numpy as np

from crossfield.cmm.formats import encode_ippdme_event

_COMMAND = re.compile(r"(?P<tag>[0-9]{5}|E[0-9]{4})\s+(?P<name>[A-Za-z][A-Za-z0-9.]*)\((?P<args>.*)\)\s*")
_ACCEPTED = {"StartSession", "EnableUser", "OnPtMeasReport", "EndSession", "DisableUser"}


class SimulatedIppDmeServer:
    """I++ DME server reporting ``probes`` (objects with ``label``, ``xyz``
    (3,) mm, ``probe_vector`` (3,), ``probe_diameter_mm``) as manual points.

    line_delay_s: pause between two probes (s). drop_after: probe indices
    after which the connection is closed. cut_after: probe index -> bytes
    of the next event sent before the connection is closed. bursts: probe index -> repeats.
    ``written`` holds every byte sent; ``commands`` every command line
    received; ``connections`` the number of accepted connections.
    """

    def __init__(
        self,
        probes: Sequence[object],
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        line_delay_s: float = 0.0,
        drop_after: Iterable[int] = (),
        cut_after: Mapping[int, int] | None = None,
        bursts: Mapping[int, int] | None = None,
        burst_jitter_mm: float = 0.01,
    ):
        self.probes = list(probes)
        self.host, self.port = host, port
        self.line_delay_s = float(line_delay_s)
        self.drop_after = set(drop_after)
        self.cut_after = dict(cut_after or {})
        self.bursts = dict(bursts or {})
        self.burst_jitter_mm = float(burst_jitter_mm)
        self.written = bytearray()
        self.commands: list[str] = []
        self.connections = 0
        self.error: BaseException | None = None
        self._next = 0
        self._connected = False
        self._done = threading.Event()
        self._stop = threading.Event()

    def event(self, index: int, repeat: int = 0) -> bytes:
        """The PtMeas event of probe ``index`` (repeat > 0: a held-button repeat)."""
        probe = self.probes[index]
        xyz = np.asarray(probe.xyz, dtype=np.float64)
        if repeat:
            xyz = xyz + np.random.default_rng([index, repeat]).normal(0.0, self.burst_jitter_mm, 3)
        vector = np.asarray(probe.probe_vector, dtype=np.float64)
        return encode_ippdme_event(xyz, vector, probe.probe_diameter_mm)

    def wait_done(self, timeout: float | None = None) -> bool:
        """Wait until every probe has been reported."""
        return self._done.wait(timeout)

    def client_connected(self) -> bool:
        """A client connection is open."""
        return self._connected

    @contextlib.contextmanager
    def serve(self) -> Iterator[str]:
        """Listen, serve from a background thread, yield the pyserial URL."""
        listener = socket.create_server((self.host, self.port))
        listener.settimeout(0.05)
        host, port = listener.getsockname()[:2]
        thread = threading.Thread(target=self._run, args=(listener,), name=f"I++ DME {port}", daemon=True)
        thread.start()
        try:
            yield f"socket://{host}:{port}"
        finally:
            self._stop.set()
            thread.join(5.0)
            listener.close()
        if self.error is not None:
            raise RuntimeError(f"simulated I++ DME server failed: {self.error!r}") from self.error

    # -- server thread --------------------------------------------------------------

    def _run(self, listener: socket.socket) -> None:
        try:
            while not self._stop.is_set():
                try:
                    connection, _ = listener.accept()
                except TimeoutError:
                    continue
                self.connections += 1
                self._connected = True
                try:
                    with connection:
                        self._session(connection)
                finally:
                    self._connected = False
        except BaseException as exc:  # reported by serve()
            self.error = exc

    def _send(self, connection: socket.socket, data: bytes) -> None:
        connection.sendall(data)
        self.written += data

    def _session(self, connection: socket.socket) -> None:
        connection.settimeout(0.01)
        pending = b""
        session = enabled = False
        last_event = 0.0
        while not self._stop.is_set():
            try:
                data = connection.recv(4096)
                if not data:
                    return  # the client closed
                pending += data
            except TimeoutError:
                pass
            except OSError:
                return
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                text = line.decode("ascii", "replace").strip()
                if not text:
                    continue
                self.commands.append(text)
                match = _COMMAND.fullmatch(text)
                if match is None:
                    self._send(connection, b'00000 ! Error(3, 0001, "", "Cannot parse command")\r\n')
                    continue
                tag, name = match.group("tag"), match.group("name")
                if name not in _ACCEPTED or (name != "StartSession" and not session):
                    error = f'{tag} ! Error(3, 0500, "{name}", "Not supported in this state")\r\n'
                    self._send(connection, f"{tag} &\r\n".encode() + error.encode())
                    continue
                self._send(connection, f"{tag} &\r\n{tag} %\r\n".encode())
                if name == "StartSession":
                    session = True
                elif name == "EnableUser":
                    enabled = True
                elif name == "DisableUser":
                    enabled = False
                elif name == "EndSession":
                    return
            if enabled and self._next < len(self.probes):
                if time.monotonic() - last_event < self.line_delay_s:
                    continue
                index = self._next
                events = b"".join(self.event(index, r) for r in range(self.bursts.get(index, 0) + 1))
                self._send(connection, events)
                self._next += 1
                last_event = time.monotonic()
                if self._next == len(self.probes):
                    self._done.set()
                if index in self.cut_after and self._next < len(self.probes):
                    self._send(connection, self.event(self._next)[: self.cut_after[index]])
                    self._drop(connection)
                    return
                if index in self.drop_after:
                    self._drop(connection)
                    return

    def _drop(self, connection: socket.socket) -> None:
        """Close gracefully: what was sent is delivered, then EOF."""
        with contextlib.suppress(OSError):
            connection.shutdown(socket.SHUT_WR)
            connection.settimeout(1.0)
            while connection.recv(4096):
                pass
