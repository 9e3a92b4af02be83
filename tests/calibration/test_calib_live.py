"""``crossfield calibrate --source basler|opencv``: live pairs from the real acquire plugins.

The cameras see the simulator's rendered board views (the 20-pair station
session of ``tests/calibration/test_calibrate.py``, rendered once per process):

* opencv: the views as 16-bit PNG image sequences, read by OpenCV's
  image-sequence backend; the key presses come through a stdin pipe;
* basler: pylon's camera emulation (``PYLON_CAMEMU``) streaming the views
  from TIFF folders (MSB-aligned, see ``tests/acquire/test_basler.py``) through
  pypylon; the CLI runs in a pseudo-terminal: Enter takes a pair, Ctrl-C
  ends, as a user would do it.

Each checks that N key presses take N pairs, that the images taken are the
views bit for bit, and that the calibration written recovers the
simulator's rig within its reported standard deviations. None is skipped.
"""

from __future__ import annotations

import fcntl
import os
import pty
import select
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from session_tools import sigint_default

from crossfield.calibration.coverage import (
    camera_coverage,
    coverage_cells,
    coverage_picture,
    empty_regions,
)
from crossfield.calibration.detect import BoardDetector
from crossfield.calibration.live import KeyEvents, capture_live, write_provisional_calibration
from crossfield.calibration.record import read_calibration_recording
from crossfield.calibration.report import coverage_fraction
from crossfield.camera.calibration_io import read_stereo_calibration
from crossfield.cli import main
from crossfield.errors import ConfigError
from crossfield.simulator.board_views import cached_calibration_views

N_FILES = 12  # views on disk
N_TAKEN = 10  # key presses
UPPER, LOWER = "0815-0000", "0815-0001"


@pytest.fixture(scope="module")
def views():
    return cached_calibration_views("station", 20, 1)


def truth_z(calib_path: Path, views) -> dict[str, float]:
    """(estimate - truth) / reported std for fx fy cx cy per camera; the baseline error (mm)."""
    from crossfield.calibration.file import read_calibration_uncertainty

    got = read_stereo_calibration(calib_path)
    std = read_calibration_uncertainty(calib_path).std
    truth = views.calibration
    z = {}
    for cam in ("upper", "lower"):
        K, T = np.asarray(got.camera(cam).camera_matrix), np.asarray(truth.camera(cam).camera_matrix)
        for name, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            assert std[f"{cam}.{name}"] > 0
            z[f"{cam}.{name}"] = float((K[i, j] - T[i, j]) / std[f"{cam}.{name}"])
    z["baseline_mm"] = float(np.linalg.norm(got.t_lower_upper) - np.linalg.norm(truth.t_lower_upper))
    return z


def check_truth(calib_path: Path, views) -> None:
    z = truth_z(calib_path, views)
    baseline_error = z.pop("baseline_mm")
    assert abs(baseline_error) < 0.02, baseline_error
    assert all(abs(v) < 4 for v in z.values()), z


# ---- the coverage functions ------------------------------------------------------------------------


def test_coverage_cells_count_the_points_of_each_cell():
    size = (800, 400)  # cells of 100 x 50 px
    pts = np.array([[0, 0], [99.9, 49.9], [100, 0], [799, 399], [850, -5], [450, 225]])
    counts = coverage_cells(pts, size)
    expected = np.zeros((8, 8), int)
    expected[0, 0] = 2  # (0, 0) and (99.9, 49.9)
    expected[0, 1] = 1
    expected[7, 7] = 1
    expected[0, 7] = 1  # beyond the right border, above the top: the corner cell
    expected[4, 4] = 1
    np.testing.assert_array_equal(counts, expected)
    # The report's share is this count (the set of cells hit), not a second kernel.
    assert coverage_fraction(pts, size) == pytest.approx(5 / 64)
    assert coverage_fraction(np.zeros((0, 2)), size) == 0.0


def test_empty_regions_name_the_thirds_still_uncovered():
    counts = np.zeros((8, 8), int)
    counts[:, :3] = 1  # columns 0-2: the cells whose centres lie in the left third (3-4 middle, 5-7 right)
    assert empty_regions(counts) == ("top", "top-right", "centre", "right", "bottom", "bottom-right")
    counts[:, :] = 1
    counts[5:, 5:] = 0  # the 9 cells of the bottom-right region
    assert empty_regions(counts) == ("bottom-right",)
    counts[5, 5:] = counts[6, 5:7] = 1  # 5 of its 9 cells covered: no longer empty
    assert empty_regions(counts) == ()


def test_tilts_agree_with_the_simulated_board_poses(views):
    """The provisional pose (initCameraMatrix2D + IPPE, no distortion) gives each view's tilt to a few deg."""
    detector = BoardDetector(views.board, min_points=6)
    dets = [detector.detect(v["upper"], views.bit_depth) for v in views.images[:8]]
    assert all(d is not None for d in dets)
    cov = camera_coverage("upper", dets, (1626, 1236))
    normals = np.array([p.R[:, 2] * np.sign(p.R[2, 2]) for p in views.poses[:8]])
    true_tilt = np.degrees(np.arccos(normals[:, 2]))
    assert np.max(np.abs(np.array(cov.tilts_deg) - true_tilt)) < 2.0, (cov.tilts_deg, true_tilt)
    true_spread = np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1).min()))
    assert cov.spread_deg == pytest.approx(true_spread, abs=3.0)
    assert cov.views == 8 and cov.counts.sum() == sum(len(d) for d in dets)


def test_coverage_picture_tints_covered_cells_green_and_empty_ones_red():
    counts = np.zeros((8, 8), int)
    counts[0, 0] = 3
    from crossfield.calibration.coverage import CameraCoverage

    cov = CameraCoverage("upper", (800, 400), counts, 1, (), 0.0)
    pic = coverage_picture(cov, scale=0.5)
    assert pic.shape == (200, 400, 3) and pic.dtype == np.uint8
    r, g, b = pic[10, 10].astype(int)  # inside cell (0, 0)
    assert g > r + 50
    r, g, b = pic[160, 310].astype(int)  # an empty cell (off the white cell borders)
    assert r > g + 50


# ---- opencv: image sequences, keys through a stdin pipe -------------------------------------------


@pytest.fixture(scope="module")
def sequences(views, tmp_path_factory):
    root = tmp_path_factory.mktemp("seq")
    for k, view in enumerate(views.images[:N_FILES]):
        for cam in ("upper", "lower"):
            assert cv2.imwrite(str(root / f"{cam}_{k:04d}.png"), view[cam])
    return root


def opencv_args(root: Path) -> list[str]:
    return [
        "--source", "opencv",
        "--option", f'acquire.upper="{root}/upper_%04d.png"',
        "--option", f'acquire.lower="{root}/lower_%04d.png"',
        "--option", "acquire.bit_depth=12",
    ]  # fmt: skip


def pipe_stdin(monkeypatch, text: str) -> None:
    r, w = os.pipe()
    os.write(w, text.encode())
    os.close(w)
    monkeypatch.setattr(sys, "stdin", os.fdopen(r, "r"))


def rrd_rows(path: Path) -> dict[str, list[tuple[int, dict]]]:
    import rerun.chunk as rrc

    out: dict[str, list[tuple[int, dict]]] = {}
    for chunk in rrc.RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if "pair" not in batch.schema.names:
            continue
        cols = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        for row, pair in enumerate(batch.column("pair").to_pylist()):
            out.setdefault(chunk.entity_path, []).append((pair, {n: v[row] for n, v in cols.items()}))
    return out


def test_opencv_key_presses_take_pairs_and_the_calibration_recovers_the_rig(
    views, sequences, tmp_path, monkeypatch, capsys
):
    pipe_stdin(monkeypatch, "\n" * N_TAKEN + "q\n")
    out, rrd = tmp_path / "live.yml", tmp_path / "live.rrd"
    assert main(["calibrate", *opencv_args(sequences), "-o", str(out), "--rrd", str(rrd), "--no-report"]) == 0
    text = capsys.readouterr().out
    lines = [line for line in text.splitlines() if line.startswith("pair ")]
    assert len(lines) == N_TAKEN and lines[0].startswith("pair 1 (frame 0): upper ")
    assert f"{N_TAKEN} pairs taken (ended by quit)" in text
    check_truth(out, views)
    # The live pairs are a recorded calibration session (default <CALIB>.mcap), replayable.
    recorded = read_calibration_recording(out.with_suffix(".mcap"))
    assert len(recorded.images) == N_TAKEN and recorded.bit_depth == 12
    for got, want in zip(recorded.images, views.images):
        np.testing.assert_array_equal(got["upper"], want["upper"])
        np.testing.assert_array_equal(got["lower"], want["lower"])
    assert recorded.source.startswith("crossfield calibrate --source opencv (key)")
    again = tmp_path / "again.yml"
    assert main(["calibrate", "--replay", str(out.with_suffix(".mcap")), "-o", str(again), "--no-report"]) == 0
    np.testing.assert_allclose(
        read_stereo_calibration(again).t_lower_upper, read_stereo_calibration(out).t_lower_upper, rtol=1e-8
    )
    # The live view in Rerun: per pair and camera a coverage picture and the covered share,
    # which ends at the report's coverage of all the views taken.
    rows = rrd_rows(rrd)
    assert [p for p, _ in rows["/calibration/upper/coverage"]] == list(range(N_TAKEN))
    shares = [v["Scalars:scalars"][0] for _, v in rows["/calibration/lower/covered"]]
    assert shares == sorted(shares) and len(shares) == N_TAKEN
    detector = BoardDetector(views.board, min_points=6)
    pts = np.concatenate([d.image_points for v in views.images[:N_TAKEN]
                          if (d := detector.detect(v["lower"], 12)) is not None])  # fmt: skip
    assert shares[-1] == pytest.approx(coverage_fraction(pts, (1626, 1236)))


def test_every_seconds_takes_pairs_without_keys_and_too_few_end_cleanly(sequences, tmp_path, monkeypatch, capsys):
    pipe_stdin(monkeypatch, "")  # no terminal input at all: the timer goes on
    out = tmp_path / "few.yml"
    assert main(["calibrate", *opencv_args(sequences), "--every", "0.05", "--pairs", "3", "-o", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out.count("\npair ") + captured.out.startswith("pair ") == 3
    assert "3 pairs taken (ended by pairs)" in captured.out
    assert captured.err.strip() == (
        "crossfield: 3 pairs taken, at least 6 needed (min_views): no calibration written"
    )
    assert not out.exists()


def test_live_option_errors_are_one_line(tmp_path, monkeypatch, capsys):
    pipe_stdin(monkeypatch, "")
    out = str(tmp_path / "x.yml")
    assert main(["calibrate", "--source", "opencv", "--option", "acquire.upper=0",
                 "--option", "acquire.lower=1", "--option", "acquire.speed=3", "-o", out]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert err.startswith("crossfield: error:") and "unknown option 'speed'" in err and "\n" not in err
    assert main(["calibrate", "--source", "opencv", "--option", "centroid.x=1", "-o", out]) == 2
    assert "calibrate takes source options only" in capsys.readouterr().err


# ---- basler: pylon's camera emulation, the CLI in a pseudo-terminal --------------------------------


@pytest.fixture(scope="module")
def emulated(views, tmp_path_factory):
    """TIFF folders of the views (dn << 4: the Mono12 emulated camera delivers dn) and a config."""
    root = tmp_path_factory.mktemp("camemu")
    for cam in ("upper", "lower"):
        (root / cam).mkdir()
        for k, view in enumerate(views.images[:N_FILES]):
            assert cv2.imwrite(str(root / cam / f"{k:04d}.tiff"), view[cam] << 4,
                               [cv2.IMWRITE_TIFF_COMPRESSION, 1])  # fmt: skip
    features = {
        cam: f'{{TestImageSelector = "Off", ImageFileMode = "On", ImageFilename = "{root / cam}", '
        f"Width = 1626, Height = 1236}}"
        for cam in ("upper", "lower")
    }
    config = root / "cameras.toml"
    config.write_text(
        f'[acquire]\nplugin = "basler"\nupper = "{UPPER}"\nlower = "{LOWER}"\nmax_skew_ms = 250.0\n'
        f"upper_features = {features['upper']}\nlower_features = {features['lower']}\n"
    )
    saved = os.environ.get("PYLON_CAMEMU")
    os.environ["PYLON_CAMEMU"] = "2"
    yield root, config
    if saved is None:
        os.environ.pop("PYLON_CAMEMU", None)
    else:
        os.environ["PYLON_CAMEMU"] = saved


class Terminal:
    """A child process on a pseudo-terminal that is its controlling terminal (so Ctrl-C is SIGINT)."""

    def __init__(self, argv: list[str], env: dict[str, str]):
        self.master, slave = pty.openpty()

        def controlling_tty() -> None:
            fcntl.ioctl(0, termios.TIOCSCTTY, 0)
            sigint_default()  # Ctrl-C on the terminal must reach Python as KeyboardInterrupt

        self.process = subprocess.Popen(
            argv, stdin=slave, stdout=slave, stderr=slave, env=env, start_new_session=True,
            preexec_fn=controlling_tty,
        )  # fmt: skip
        os.close(slave)
        self.text = ""

    def expect(self, needle: str, count: int = 1, timeout_s: float = 60.0) -> str:
        deadline = time.monotonic() + timeout_s
        while self.text.count(needle) < count:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"no {needle!r} (x{count}) in:\n{self.text}"
            ready, _, _ = select.select([self.master], [], [], remaining)
            if ready:
                try:
                    chunk = os.read(self.master, 65536)
                except OSError:  # EIO: the child closed the terminal
                    chunk = b""
                assert chunk or self.process.poll() is None or self.text.count(needle) >= count, self.text
                self.text += chunk.decode(errors="replace").replace("\r\n", "\n")
        return self.text

    def send(self, data: bytes) -> None:
        os.write(self.master, data)

    def finish(self, timeout_s: float = 120.0) -> int:
        deadline = time.monotonic() + timeout_s
        while self.process.poll() is None and time.monotonic() < deadline:
            ready, _, _ = select.select([self.master], [], [], 0.2)
            if ready:
                try:
                    self.text += os.read(self.master, 65536).decode(errors="replace").replace("\r\n", "\n")
                except OSError:
                    break
        code = self.process.wait(max(0.0, deadline - time.monotonic()) + 1)
        os.close(self.master)
        return code


def test_basler_enter_in_a_terminal_takes_pairs_ctrl_c_ends_and_calibrates(views, emulated, tmp_path):
    root, config = emulated
    out = tmp_path / "basler.yml"
    env = dict(os.environ, PYLON_CAMEMU="2")
    term = Terminal(
        [str(Path(sys.executable).with_name("crossfield")), "calibrate", "--source", "basler", "-c", str(config),
         "-o", str(out), "--no-report"],
        env,
    )  # fmt: skip
    try:
        term.expect("Enter takes a pair")
        for k in range(N_TAKEN):
            term.send(b"\n")
            term.expect(f"pair {k + 1} (frame {k})")
        term.send(b"\x03")  # Ctrl-C: ends the capture, the pairs taken are calibrated
        code = term.finish()
    finally:
        if term.process.poll() is None:
            term.process.kill()
    assert code == 0, term.text
    assert f"{N_TAKEN} pairs taken (ended by interrupt)" in term.text
    assert term.text.count("\npair ") == N_TAKEN
    recorded = read_calibration_recording(out.with_suffix(".mcap"))
    assert len(recorded.images) == N_TAKEN
    for got, want in zip(recorded.images, views.images):  # the emulated cameras saw the rendered views
        np.testing.assert_array_equal(got["upper"], want["upper"])
        np.testing.assert_array_equal(got["lower"], want["lower"])
    check_truth(out, views)


def hardware_triggered_source(root: Path, tmp_path: Path):
    """The basler plugin on the emulated cameras, waiting for a trigger line (trigger = hardware;
    the line is emulated by :class:`Pulses`, as in tests/acquire/test_basler.py)."""
    from crossfield.chain.registry import get_implementation, make_plugin_manager

    def features(cam: str) -> dict:
        return {"TestImageSelector": "Off", "ImageFileMode": "On", "ImageFilename": str(root / cam),
                "Width": 1626, "Height": 1236}  # fmt: skip

    options = {
        "upper": UPPER, "lower": LOWER, "frames": 0, "trigger": "hardware", "trigger_source": "Software",
        "trigger_activation": "", "max_skew_ms": 250.0,
        "calibration": str(write_provisional_calibration(tmp_path / "provisional.yml")),
        "upper_features": features("upper"), "lower_features": features("lower"),
    }  # fmt: skip
    return get_implementation(make_plugin_manager(), "acquire", "basler").create(options)


class Pulses(threading.Thread):
    """Fires both cameras' frame triggers every ``period_s`` once they grab; ``on_pulse(n)`` after each."""

    def __init__(self, source, period_s: float, on_pulse=lambda n: None):
        super().__init__(daemon=True)
        self.cams = [source.cameras[r].instant for r in ("upper", "lower")]
        self.period_s, self.on_pulse = period_s, on_pulse
        self.halt = threading.Event()
        self.start()

    def run(self) -> None:
        while not all(c.IsGrabbing() for c in self.cams) and not self.halt.is_set():
            time.sleep(0.01)
        n = 0
        while not self.halt.is_set():
            if all(c.IsGrabbing() and c.WaitForFrameTriggerReady(2000, 0) for c in self.cams):
                for cam in self.cams:  # both or neither: a pulse reaches both cameras
                    cam.ExecuteSoftwareTrigger()
            n += 1
            self.on_pulse(n)
            time.sleep(self.period_s)

    def end(self) -> None:
        self.halt.set()
        self.join(5)


def test_basler_hardware_trigger_takes_every_pulse(views, emulated, tmp_path):
    """--trigger: the cameras wait for a line; each pulse is a pair; --pairs ends the capture."""
    root, _ = emulated
    source = hardware_triggered_source(root, tmp_path)
    pulses = Pulses(source, 0.2)
    try:
        live = capture_live(
            source.frames(), views.board, KeyEvents(None), mode="trigger", pairs=4, stop=source.stop
        )
        info = source.describe()
    finally:
        pulses.end()
        source.close()
    assert live.ended_by == "pairs" and len(live.images) == 4 and live.bit_depth == 12
    assert info["incidents"] == []
    sequences = [int(n.split("frame ")[1].rstrip(")")) for n in live.names]
    for got, k in zip(live.images, sequences):  # the emulator cycles through the files, one per pulse
        np.testing.assert_array_equal(got["upper"], views.images[k % N_FILES]["upper"], err_msg=str(sequences))
        np.testing.assert_array_equal(got["lower"], views.images[k % N_FILES]["lower"], err_msg=str(sequences))
    assert live.coverage["upper"].views == 4


def test_free_running_source_key_takes_a_pair_arriving_after_the_press(views, emulated, tmp_path):
    """A camera triggered by a line keeps delivering; a key press takes the first pair after it,
    never one that was waiting before (LatestPair)."""
    root, _ = emulated
    source = hardware_triggered_source(root, tmp_path)
    events = KeyEvents(None)
    presses: list[int] = []
    arrivals: list[int] = []

    def key_every_fourth_pulse(n: int) -> None:
        if n % 4 == 2 and len(presses) < 3:
            presses.append(time.time_ns())
            events.put("take")

    pulses = Pulses(source, 0.1, key_every_fourth_pulse)
    try:
        live = capture_live(source.frames(), views.board, events, mode="key", pairs=3, free_running=True,
                            stop=source.stop, on_pair=lambda pair, _: arrivals.append(pair.frame.timestamp_ns))  # fmt: skip
    finally:
        pulses.end()
        source.close()
    assert live.ended_by == "pairs" and len(live.images) == 3
    sequences = [int(n.split("frame ")[1].rstrip(")")) for n in live.names]
    assert sequences == sorted(set(sequences))
    assert sequences[-1] > 4  # pulses went on between the presses, frames were skipped, not queued
    assert all(arrived >= pressed for arrived, pressed in zip(arrivals, presses)), (arrivals, presses)


def test_live_options_are_the_run_options_with_the_live_defaults(tmp_path):
    """--trigger makes the basler source wait for a line; frames default to 0 (until stopped);
    the config file's [acquire] options come first, --option after, as for `crossfield run`."""
    from crossfield.cli import build_parser
    from crossfield.cli.calibration import _live_options

    config = tmp_path / "cameras.toml"
    config.write_text('[acquire]\nupper = "A"\nlower = "B"\nexposure_us = 800.0\n')

    def options(*argv: str) -> dict:
        return _live_options(build_parser().parse_args(["calibrate", *argv, "-o", "c.yml"]))

    got = options("--source", "basler", "-c", str(config), "--option", "acquire.lower=C", "--trigger")
    assert got == {"upper": "A", "lower": "C", "exposure_us": 800.0, "frames": 0, "trigger": "hardware"}
    got = options("--source", "basler", "-c", str(config), "--option", "acquire.trigger=software", "--trigger")
    assert got["trigger"] == "software"  # an explicit option wins
    assert "trigger" not in options("--source", "opencv", "--option", "acquire.upper=0", "--trigger")
    assert options("--source", "opencv", "--option", "acquire.frames=5")["frames"] == 5
    config.write_text('[acquire]\nplugin = "folder"\nfolder = "x"\n')
    with pytest.raises(ConfigError, match="plugin is 'folder', but --source is 'basler'"):
        options("--source", "basler", "-c", str(config))


def test_a_board_not_found_in_a_dark_image_says_so(views, capsys):
    """12-bit data delivered as 16-bit (the opencv source's bit_depth left at 0) is too dark to detect."""
    from crossfield.calibration.live import LivePair, print_pair
    from crossfield.types import StereoFrame

    view = views.images[0]
    frame = StereoFrame(3, 0, view["upper"], view["lower"], 16)
    detector = BoardDetector(views.board, min_points=6)
    found = {cam: detector.detect(frame.image(cam), 16) for cam in ("upper", "lower")}
    assert found == {"upper": None, "lower": None}
    cov = {cam: camera_coverage(cam, [None], (1626, 1236)) for cam in ("upper", "lower")}
    print_pair(LivePair(0, frame, found), cov)
    line = capsys.readouterr().out
    peak = int(view["upper"].max())
    assert line.startswith(f"pair 1 (frame 3): upper: board not found (peak {peak} of 65535: dark, or set")
    assert "0/64 cells (0%), empty: everywhere" in line


def test_live_flags_without_a_live_source_are_refused(tmp_path, capsys):
    assert main(["calibrate", "--scenario", "station", "--every", "2", "-o", str(tmp_path / "c.yml")]) == 2
    assert capsys.readouterr().err.strip() == "crossfield: error: --every applies to live cameras (--source) only"
