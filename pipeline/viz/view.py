"""``crossfield view``: a session in the Rerun viewer, in a browser, or as a picture.

    crossfield view SESSION.rrd|SESSION.mcap|SESSION_DIR       the native viewer
    crossfield view SESSION --web                              the web viewer on http://127.0.0.1:PORT
    crossfield view SESSION --screenshot out.png               render headless, write a PNG, report view errors

An MCAP recording is shown with the full logger: its recorded stage results
are fed to :class:`crossfield.viz.rerun_log.RerunLogger` (:mod:`crossfield.viz.rerun_mcap`)
into an ``.rrd`` (a temporary one unless ``--save``), which the viewer opens
with the default blueprint. A folder means its ``session.rrd``, else its
``session.mcap``.

The headless viewer (:class:`HeadlessViewer`) is the real Rerun viewer
without a window (``rerun --headless``), rendering in software with Mesa's
lavapipe on a machine without GPU or display; it is driven through
``rerun.experimental.ViewerClient`` (open, time cursor, screenshot, and each
view's error reports).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import numpy as np

from crossfield.errors import CrossfieldError

#: Environment of every viewer we start: no analytics prompt, offline, and
#: only error-level messages as pop-up notifications (they would be in the picture).
VIEWER_ENV = {"RERUN_APP_ONLY": "true", "RERUN_ANALYTICS": "0", "RUST_LOG": "error"}
DEFAULT_WINDOW_SIZE = (1600, 1000)
DEFAULT_WEB_PORT = 9090
#: Where ``crossfield run --view`` finds or starts its viewer (Rerun's default port).
LIVE_VIEWER_PORT = 9876


class ViewerError(CrossfieldError):
    """The Rerun viewer could not be started, reached or driven."""


def rerun_executable() -> str:
    """The Rerun viewer binary shipped with rerun-sdk (``rerun_cli/rerun``), else ``rerun`` on PATH.

    The binary itself rather than the ``rerun`` Python shim, so that the
    process started is the viewer (one pid to stop).
    """
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).parent / "rerun"
        if binary.exists():
            return str(binary)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if not found:
        raise ViewerError("the Rerun viewer is not installed (pip install rerun-sdk)")
    return found


def _lines(output: bytes) -> list[str]:
    """The non-empty lines of a viewer's stderr, without terminal colour codes."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", output.decode(errors="replace"))
    return [line.strip() for line in text.splitlines() if line.strip()]


def free_port() -> int:
    """An unused TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class ViewReport:
    """A warning or error that a view of the viewer reported."""

    view: str
    view_class: str
    severity: str
    summary: str
    details: str | None = None

    def __str__(self) -> str:
        text = f"{self.severity}: view {self.view!r} ({self.view_class}): {self.summary}"
        return text + (f" ({self.details})" if self.details else "")


def png_is_blank(png: bytes, *, min_distinct: int = 16) -> bool:
    """True when a PNG has fewer than ``min_distinct`` distinct colours (an empty window)."""
    import cv2

    pixels = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_COLOR)
    if pixels is None:
        return True
    return len(np.unique(pixels.reshape(-1, pixels.shape[-1]), axis=0)) < min_distinct


class HeadlessViewer:
    """A Rerun viewer without a window, on a free port of 127.0.0.1.

        with HeadlessViewer() as viewer:
            viewer.open("session.rrd")
            viewer.show_end("frame")
            viewer.screenshot("out.png")
            errors = [r for r in viewer.reports() if r.severity == "error"]

    window_size: (width, height) in logical points. startup_timeout_s: how long
    the viewer may take to answer. The viewer is stopped (by its pid) on exit.
    """

    def __init__(
        self, *, window_size: tuple[int, int] = DEFAULT_WINDOW_SIZE, startup_timeout_s: float = 30.0
    ):
        self.window_size = (int(window_size[0]), int(window_size[1]))
        self.port = free_port()
        self.startup_timeout_s = float(startup_timeout_s)
        self._process: subprocess.Popen | None = None
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 - the viewer's stderr, closed by close()
        self.client: Any = None

    @property
    def url(self) -> str:
        """The viewer's gRPC proxy: where a :class:`crossfield.viz.rerun_log.RerunLogger` streams to."""
        return f"rerun+http://127.0.0.1:{self.port}/proxy"

    def start(self) -> HeadlessViewer:
        from rerun.experimental import ViewerClient

        width, height = self.window_size
        command = [
            rerun_executable(),
            "--headless",
            "--window-size",
            f"{width}x{height}",
            "--bind",
            "127.0.0.1",
            "--port",
            str(self.port),
            "--hide-welcome-screen",
        ]
        self._process = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=self._stderr,
            env={**os.environ, **VIEWER_ENV},
        )
        deadline = time.monotonic() + self.startup_timeout_s
        while True:
            if self._process.poll() is not None:
                raise ViewerError(f"the headless Rerun viewer exited at start: {self._error_text()}")
            try:
                client = ViewerClient.connect(self.url)
                client.get_state()
                self.client = client
                return self
            except Exception as exc:  # noqa: BLE001 - not listening yet
                if time.monotonic() > deadline:
                    self.close()
                    raise ViewerError(
                        f"the headless Rerun viewer did not answer on {self.url}: {exc}"
                    ) from None
                time.sleep(0.1)

    def _error_text(self) -> str:
        self._stderr.seek(0)
        lines = _lines(self._stderr.read())
        hint = ""
        if any("graphics adapter" in line.lower() for line in lines):
            hint = " (no Vulkan adapter: apt-get install mesa-vulkan-drivers libvulkan1)"
        return ("; ".join(lines[-3:]) or "no message") + hint

    def open(self, path: str | Path, timeout_s: float = 60.0) -> list[str]:
        """Load a recording file; wait until it has arrived. Returns its store ids."""
        opened = self.client.open(str(Path(path).resolve()))
        self.wait_loaded(timeout_s)
        return list(opened.store_ids)

    def wait_loaded(self, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            state = self.client.get_state()
            if not state.loading and state.recordings:
                return
            if time.monotonic() > deadline:
                raise ViewerError(f"the viewer is still loading after {timeout_s:g} s: {state.loading}")
            time.sleep(0.1)

    def wait_for(self, condition: Callable[[], bool], timeout_s: float = 30.0, what: str = "data") -> None:
        """Poll ``condition()`` until it is true (:class:`ViewerError` after ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise ViewerError(f"the viewer did not show {what} within {timeout_s:g} s")
            time.sleep(0.2)

    def timeline_end(self, timeline: str) -> int | None:
        """The last time on ``timeline`` of the active recording (None if it has none)."""
        state = self.client.get_state()
        recordings = [r for r in state.recordings if r.store_id == state.active_recording] or state.recordings
        for recording in recordings:
            for t in recording.timelines:
                if t.name == timeline and t.end is not None:
                    return int(t.end)
        return None

    def show(self, timeline: str = "frame", sequence: int | None = None) -> None:
        """Put the time cursor on ``sequence`` of a sequence timeline (default: its end), paused."""
        if sequence is None:
            sequence = self.timeline_end(timeline)
        if sequence is None:
            self.client.set_time(timeline, play_state="paused")
        else:
            self.client.set_time(timeline, sequence=int(sequence), play_state="paused")

    def settled_png(self, timeout_s: float = 20.0) -> bytes:
        """A screenshot of the whole viewer once it has stopped changing.

        The viewer fetches, uploads and lays out data over several frames
        after a time change, and a pop-up notification fades after a few
        seconds, so screenshots are taken until two in a row are identical
        (at most ``timeout_s``; then the last one).
        """
        deadline = time.monotonic() + timeout_s
        previous = self.client.take_screenshot()
        while time.monotonic() < deadline:
            time.sleep(0.25)
            png = self.client.take_screenshot()
            if png == previous:
                return png
            previous = png
        return previous

    def screenshot(self, path: str | Path, timeout_s: float = 20.0) -> bytes:
        """Write a settled screenshot (PNG) to ``path`` (written by this process); returns it."""
        png = self.settled_png(timeout_s)
        Path(path).write_bytes(png)
        return png

    def reports(self) -> list[ViewReport]:
        """Every warning and error the views of the current blueprint reported when last shown."""
        state = self.client.get_state()
        return [
            ViewReport(v.name, v.view_class, r.severity, r.summary, r.details)
            for v in state.views
            for r in v.reports
        ]

    def reports_of_every_view(self) -> tuple[list[ViewReport], set[str]]:
        """Show every view once and return their reports and the names of the views shown.

        A view in a tab container reports only when its tab is shown, so each
        tab of each container is made the active one in turn (through the
        blueprint) and drawn; the blueprint is restored afterwards.
        """
        import copy

        def key(view_path: str) -> str:  # "/view/<uuid>" or "<uuid>" -> bare hex
            return view_path.rsplit("/", 1)[-1].replace("-", "")

        doc = self.client.get_blueprint(of="recording").blueprint
        tab_containers = [
            path
            for path, entry in doc.items()
            if entry.get("ContainerBlueprint", {}).get("container_kind") == "Tabs"
        ]
        hidden = {  # views in a tab that is not the active one
            key(tab)
            for path in tab_containers
            for tab in doc[path]["ContainerBlueprint"].get("contents", [])
            if tab != doc[path]["ContainerBlueprint"].get("active_tab")
        }
        state = self.client.get_state()
        names = {v.name for v in state.views if v.visible and key(v.view_id) not in hidden}
        reports = {(r.view, r.summary, r.severity): r for r in self.reports()}
        try:
            for path in tab_containers:
                for tab in doc[path]["ContainerBlueprint"].get("contents", []):
                    variant = copy.deepcopy(doc)
                    variant[path]["ContainerBlueprint"]["active_tab"] = tab
                    self.client.set_blueprint(variant, of="recording")
                    self.settled_png()
                    for view in self.client.get_state().views:
                        if key(view.view_id) == key(tab):
                            names.add(view.name)
                        for r in view.reports:
                            reports[(view.name, r.summary, r.severity)] = ViewReport(
                                view.name, view.view_class, r.severity, r.summary, r.details
                            )
        finally:
            self.client.set_blueprint(doc, of="recording")
        return list(reports.values()), names

    def view_names(self) -> list[str]:
        return [v.name for v in self.client.get_state().views]

    def entity_paths(self) -> list[str]:
        """Entity paths of the active recording."""
        schema = self.client.get_recording_schema(paths_only=True, max_entities=10000)
        return [e.entity_path for e in schema.entities]

    def close(self) -> None:
        """Stop the viewer process this object started (SIGTERM, then SIGKILL after 5 s)."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=5)
        self.client = None
        self._stderr.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------
# crossfield view
# --------------------------------------------------------------------------


def resolve_session_path(path: str | Path) -> Path:
    """A session file to show: ``path`` itself, or a folder's session.rrd (else session.mcap)."""
    path = Path(path)
    if path.is_dir():
        for name in ("session.rrd", "session.mcap"):
            if (path / name).is_file():
                return path / name
        raise CrossfieldError(f"{path}: no session.rrd or session.mcap in this folder")
    if not path.is_file():
        raise CrossfieldError(f"{path}: no such file")
    if path.suffix.lower() not in (".rrd", ".mcap"):
        raise CrossfieldError(f"{path}: expected a .rrd or .mcap session file (or a session folder)")
    return path


def mcap_to_rrd(mcap_path: str | Path, rrd_path: str | Path, *, image_every: int | None = None) -> Any:
    """Write the recorded session ``mcap_path`` through the full logger into ``rrd_path``.

    Returns the session summary (:func:`crossfield.viz.rerun_mcap.log_recording`).
    """
    from crossfield.viz.rerun_log import RerunLogger
    from crossfield.viz.rerun_mcap import log_recording

    if image_every is not None and image_every < 0:
        raise CrossfieldError(f"--image-every {image_every}: expected 0 (no images) or more")
    logger = RerunLogger(rrd_path, image_every=image_every)
    try:
        return log_recording(mcap_path, logger)
    finally:
        logger.close()


@contextlib.contextmanager
def session_rrd(
    path: str | Path,
    *,
    save: str | Path | None = None,
    image_every: int | None = None,
    say: Callable[[str], None] = print,
) -> Iterator[Path]:
    """The .rrd to open for ``path``: the file itself, or a .rrd made from an MCAP
    recording (``save``, else a temporary file removed afterwards)."""
    source = resolve_session_path(path)
    if source.suffix.lower() == ".rrd":
        if save is not None:
            raise CrossfieldError(f"{source}: --save applies to an MCAP recording; this is already a .rrd")
        yield source
        return
    if save is not None:
        target = Path(save)
        mcap_to_rrd(source, target, image_every=image_every)
        say(f"{source} -> {target}")
        yield target
        return
    with tempfile.TemporaryDirectory(prefix="crossfield-view-") as tmp:
        target = Path(tmp) / (source.stem + ".rrd")
        mcap_to_rrd(source, target, image_every=image_every)
        yield target


def screenshot(
    path: str | Path,
    png_path: str | Path,
    *,
    window_size: tuple[int, int] = DEFAULT_WINDOW_SIZE,
    frame: int | None = None,
    save: str | Path | None = None,
    image_every: int | None = None,
    say: Callable[[str], None] = print,
) -> list[ViewReport]:
    """Render a session headless with its default blueprint, at pair ``frame`` (default:
    the last), and write the PNG. Returns the reports (warnings and errors) of every
    view of the blueprint, those in inactive tabs included."""
    with (
        session_rrd(path, save=save, image_every=image_every, say=say) as rrd,
        HeadlessViewer(window_size=window_size) as viewer,
    ):
        viewer.open(rrd)
        viewer.show("frame", frame)
        png = viewer.screenshot(png_path)
        reports, _ = viewer.reports_of_every_view()  # after the picture: it shows the other tabs
    if png_is_blank(png):
        raise ViewerError(f"{png_path}: the viewer rendered a blank picture")
    return reports


def serve_web(rrd: Path, *, port: int = DEFAULT_WEB_PORT, say: Callable[[str], None] = print) -> int:
    """Serve the web viewer with ``rrd`` on http://127.0.0.1:port until interrupted."""
    grpc_port = free_port()
    command = [
        rerun_executable(),
        "--web-viewer",
        "--bind",
        "127.0.0.1",
        "--port",
        str(grpc_port),
        "--web-viewer-port",
        str(port),
        str(rrd),
    ]
    process = subprocess.Popen(command, env={**os.environ, **VIEWER_ENV, "RUST_LOG": "warn"})
    say(f"web viewer: http://127.0.0.1:{port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy")
    say("(Ctrl-C to stop)")

    def stop(signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)  # SIGTERM like Ctrl-C: stop the server, clean up
    try:
        return process.wait()
    except KeyboardInterrupt:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)


def open_native(rrd: Path) -> int:
    """The native viewer on ``rrd``; returns when it is closed."""
    return subprocess.call(
        [rerun_executable(), str(rrd)], env={**os.environ, **VIEWER_ENV, "RUST_LOG": "warn"}
    )


def view(
    path: str | Path,
    *,
    web: bool = False,
    port: int = DEFAULT_WEB_PORT,
    screenshot_to: str | Path | None = None,
    window_size: tuple[int, int] = DEFAULT_WINDOW_SIZE,
    frame: int | None = None,
    save: str | Path | None = None,
    image_every: int | None = None,
    say: Callable[[str], None] = print,
) -> int:
    """``crossfield view``; returns the exit status (1 when a view reports an error)."""
    if screenshot_to is not None:
        t0 = time.perf_counter()
        reports = screenshot(
            path,
            screenshot_to,
            window_size=window_size,
            frame=frame,
            save=save,
            image_every=image_every,
            say=say,
        )
        say(f"screenshot written to {screenshot_to} ({time.perf_counter() - t0:.1f} s)")
        for report in reports:
            say(str(report))
        return 1 if any(r.severity == "error" for r in reports) else 0
    if not web:
        resolve_session_path(path)  # a wrong path is the first thing to say
        require_display()
    with session_rrd(path, save=save, image_every=image_every, say=say) as rrd:
        if web:
            return serve_web(rrd, port=port, say=say)
        return open_native(rrd)


def require_display() -> None:
    """:class:`ViewerError` when the native viewer cannot open a window: on Linux,
    neither ``$DISPLAY`` (X11) nor ``$WAYLAND_DISPLAY`` is set."""
    has_display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if sys.platform.startswith("linux") and not has_display:
        raise ViewerError(
            "no display for the native viewer ($DISPLAY and $WAYLAND_DISPLAY are not set): "
            "use --web to serve the web viewer, or --screenshot PNG to render a picture headless"
        )


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def spawn_live_viewer(port: int | None = None, timeout_s: float = 15.0) -> str:
    """A native viewer listening on 127.0.0.1:``port``: the one already there, or a new
    one (detached: it stays open after the session). Returns its URL.

    :class:`ViewerError` when it cannot start (no display: use ``--view URL``
    with a viewer running elsewhere, or ``crossfield view`` afterwards).
    """
    port = LIVE_VIEWER_PORT if port is None else int(port)
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if _listening(port):
        return url
    log = tempfile.TemporaryFile()  # noqa: SIM115 - read below if the viewer dies at start
    process = subprocess.Popen(
        [
            rerun_executable(),
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--memory-limit",
            "50%",
            "--expect-data-soon",
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=log,
        env={**os.environ, **VIEWER_ENV, "RUST_LOG": "warn"},
        start_new_session=True,
    )
    deadline = time.monotonic() + timeout_s
    while not _listening(port):
        if process.poll() is not None or time.monotonic() > deadline:
            log.seek(0)
            lines = _lines(log.read())
            log.close()
            if process.poll() is None:
                process.terminate()
            raise ViewerError(
                f"could not start the Rerun viewer on port {port}: {lines[-1] if lines else 'no message'} "
                "(no display? stream to a running viewer with --view URL, or run `crossfield view` later)"
            )
        time.sleep(0.2)
    log.close()
    return url


def parse_window_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CrossfieldError(f"--window-size {text!r}: expected WIDTHxHEIGHT, e.g. 1600x1000") from None
    if width < 200 or height < 200:
        raise CrossfieldError(f"--window-size {text!r}: at least 200x200")
    return width, height
