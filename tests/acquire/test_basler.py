"""acquire "basler" through the real pylon SDK, with pylon's camera emulation.

pylon's camera-emulation transport layer offers ``PYLON_CAMEMU`` emulated
cameras (serial numbers 0815-0000, 0815-0001, ...); it reads the variable
each time devices are enumerated. With ``TestImageSelector = Off``,
``ImageFileMode = On`` and ``ImageFilename`` = a folder, an emulated camera
streams the folder's images in file-name order (cycling).

Emulator behaviour the tests rely on (measured with pypylon 26.9, pylon
12.4; ``test_emulator_reads_files_as_16_bit_full_scale`` pins it): a
16-bit image file is taken as full-scale 16-bit and reduced to the pixel
format by dropping low bits - Mono12 delivers ``file >> 4``, Mono16 the
file unchanged. So the tests write the simulator's 12-bit images
MSB-aligned (``dn << 4``, lossless for dn < 4096) and the Mono12 camera
delivers the simulator's DN bit for bit. The emulator reports camera
timestamps of 0 (the skew check then uses host arrival times) and ignores
exposure, gain and trigger delay for file images.

None of these tests is skipped: without pypylon or the emulation they fail.
"""

from __future__ import annotations

import ctypes
import faulthandler
import os
import signal
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from pypylon import pylon

from crossfield.camera.calibration_io import write_stereo_calibration
from crossfield.errors import ConfigError, PluginError
from crossfield.hookspecs import hookimpl
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.plugins import acquire_basler
from crossfield.plugins.acquire_basler import BaslerStereoSource, select_device
from crossfield.plugins.acquire_simulator import SimulatorSource

N_FRAMES = 3
SEED = 5
UPPER, LOWER = "0815-0000", "0815-0001"

# pylon's StartGrabbing installs its own SIGALRM handler (its waitable timers,
# Pylon::CWaitableTimer, use timer_create + SIGALRM and take the signal's value as a
# pointer; test_pylon_takes_over_sigalrm_when_grabbing pins it). pytest-timeout's
# default method is a SIGALRM: a test of this module running into the timeout would
# then segfault in Pylon::WaitObjectEx::Signal() and end the whole run. So no SIGALRM
# timer here: each test is bounded by the watchdog below (it stops every Basler
# source still running, so the test fails on its own assertions), and pytest-timeout
# keeps its signal-free thread method only as the last resort for a hang in C++.
WATCHDOG_S = 120.0
pytestmark = pytest.mark.timeout(WATCHDOG_S + 60, method="thread")


@pytest.fixture(autouse=True)
def watchdog(monkeypatch):
    """Stop every BaslerStereoSource still grabbing after WATCHDOG_S s and fail the test."""
    running: list[BaslerStereoSource] = []
    frames = BaslerStereoSource.frames

    def tracked(self):
        running.append(self)
        return frames(self)

    monkeypatch.setattr(BaslerStereoSource, "frames", tracked)
    fired = threading.Event()

    def expire() -> None:
        fired.set()
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        for source in running:
            source.stop()

    timer = threading.Timer(WATCHDOG_S, expire)
    timer.daemon = True
    timer.start()
    yield
    timer.cancel()
    assert not fired.is_set(), f"the test ran longer than {WATCHDOG_S:g} s; its sources were stopped (stacks above)"


class FrameCollector:
    """Observer keeping every full FrameResult (with centroids and points)."""

    def __init__(self) -> None:
        self.results = []

    @hookimpl
    def on_frame_done(self, result) -> None:
        self.results.append(result)


@pytest.fixture(scope="module")
def emulation():
    """Two emulated cameras; fails (never skips) when pylon offers none."""
    saved = os.environ.get("PYLON_CAMEMU")
    os.environ["PYLON_CAMEMU"] = "2"
    try:
        serials = [d.GetSerialNumber() for d in pylon.TlFactory.GetInstance().EnumerateDevices()
                   if d.GetDeviceClass() == "BaslerCamEmu"]
        assert {UPPER, LOWER} <= set(serials), f"pylon camera emulation is not available (found {serials})"
        yield
    finally:
        if saved is None:
            os.environ.pop("PYLON_CAMEMU", None)
        else:
            os.environ["PYLON_CAMEMU"] = saved


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    """The simulator's station frames as MSB-aligned 16-bit TIFF folders + its calibration YAML."""
    root = tmp_path_factory.mktemp("station")
    simulator = SimulatorSource(scenario="station", frames=N_FRAMES, seed=SEED)
    frames = list(simulator.frames())
    for camera in ("upper", "lower"):
        (root / camera).mkdir()
        for f in frames:
            # uncompressed TIFF: the emulator decodes the file for every frame (PNG is ~3x slower)
            assert cv2.imwrite(str(root / camera / f"{f.sequence:04d}.tiff"), f.image(camera) << 4,
                               [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    write_stereo_calibration(root / "calibration.yml", simulator.calibration)
    (root / "plan.toml").write_text(simulator.default_plan.text)
    return root, frames, simulator


def emulated_features(root: Path, camera: str) -> dict:
    return {
        "TestImageSelector": "Off",
        "ImageFileMode": "On",
        "ImageFilename": str(root / camera),
        "Width": 1626,
        "Height": 1236,
    }


def make_source(root: Path, **options) -> BaslerStereoSource:
    options = {
        "upper": UPPER,
        "lower": LOWER,
        "calibration": str(root / "calibration.yml"),
        "frames": N_FRAMES,
        "max_skew_ms": 250.0,  # host-arrival skew on a loaded test machine; the checks are tested below
        "upper_features": emulated_features(root, "upper"),
        "lower_features": emulated_features(root, "lower"),
    } | options
    return BaslerStereoSource(**options)


def incident_keys(info: dict) -> list[tuple[str, str, int]]:
    return [(i["kind"], i["camera"], i["sequence"]) for i in info["incidents"]]


def test_emulated_cameras_deliver_the_simulator_frames_bit_exact(emulation, station):
    root, frames, simulator = station
    source = make_source(root, exposure_us=5000.0, gain_db=6.0)
    try:
        got = list(source.frames())
        again = list(source.frames())  # a second grab: block ids restart, so must the frame counters
        info = source.describe()
    finally:
        source.close()
    assert [f.sequence for f in got] == [f.sequence for f in again] == list(range(N_FRAMES))
    for first, second in zip(got, again):
        np.testing.assert_array_equal(first.upper, second.upper)
    for pair, truth in zip(got, frames):
        assert pair.bit_depth == 12
        assert pair.upper.dtype == np.uint16 and pair.lower.dtype == np.uint16
        np.testing.assert_array_equal(pair.upper, truth.upper)
        np.testing.assert_array_equal(pair.lower, truth.lower)
    assert not np.array_equal(got[0].upper, got[1].upper)  # fresh noise per frame: the files really cycle
    assert info["incidents"] == [] and info["pairs_delivered"] == 2 * N_FRAMES == info["triggers_sent"]
    np.testing.assert_array_equal(source.calibration.R_lower_upper, simulator.calibration.R_lower_upper)
    for role, serial in (("upper", UPPER), ("lower", LOWER)):
        cam = info["cameras"][role]
        assert cam["serial"] == serial and cam["model"] == "CamEmu" and cam["vendor"] == "Basler"
        assert cam["firmware"] == "1.1"
        assert (cam["width"], cam["height"]) == (1626, 1236)
        assert cam["pixel_format"] == "Mono12"
        assert cam["exposure_us"] == pytest.approx(5000.0)
        assert cam["gain_db"] == pytest.approx(6.0, abs=1e-3)
        trigger = (cam["trigger_mode"], cam["trigger_source"], cam["trigger_selector"])
        assert trigger == ("On", "Software", "FrameStart")
        assert cam["camera_timestamps"].startswith("no")
        assert cam["features_set"]["ImageFilename"] == str(root / role)


def test_emulator_reads_files_as_16_bit_full_scale(emulation, tmp_path):
    """What the emulator makes of a 16-bit file in Mono12 and Mono16 (why the tests write dn << 4)."""
    rng = np.random.default_rng(0)
    dn = rng.integers(0, 4096, size=(1236, 1626), dtype=np.uint16)
    (tmp_path / "upper").mkdir()
    (tmp_path / "lower").mkdir()
    cv2.imwrite(str(tmp_path / "upper" / "0.png"), dn)  # LSB-aligned 12-bit values
    cv2.imwrite(str(tmp_path / "lower" / "0.png"), dn << 4)  # MSB-aligned
    write_stereo_calibration(tmp_path / "calibration.yml", SimulatorSource(frames=1).calibration)
    for pixel_format, upper_expected, lower_expected in (
        ("Mono12", dn >> 4, dn),
        ("Mono16", dn, dn << 4),
    ):
        source = make_source(tmp_path, frames=1, pixel_format=pixel_format)
        try:
            (pair,) = list(source.frames())
        finally:
            source.close()
        np.testing.assert_array_equal(pair.upper, upper_expected)
        np.testing.assert_array_equal(pair.lower, lower_expected)
        assert pair.bit_depth == int(pixel_format[4:])


def test_failed_buffer_drops_the_pair_and_is_reported(emulation, station):
    root, frames, _ = station
    source = make_source(root, frames=4)
    logged = []
    source.log = lambda **kw: logged.append(kw)
    got = []
    try:
        for pair in source.frames():
            got.append(pair)
            if pair.sequence == 1:  # the lower camera's next buffer fails (emulator feature)
                lower = source.cameras["lower"]
                lower.write("ForceFailedBufferCount", 1, "test")
                lower.write("ForceFailedBuffer", True, "test")
        info = source.describe()
    finally:
        source.close()
    assert [p.sequence for p in got] == [0, 1, 3, 4]
    for pair in got:  # each camera's k-th frame shows file k mod N (the failed buffer used up file 2)
        np.testing.assert_array_equal(pair.upper, frames[pair.sequence % N_FRAMES].upper)
        np.testing.assert_array_equal(pair.lower, frames[pair.sequence % N_FRAMES].lower)
    assert incident_keys(info) == [("grab_failed", "lower", 2)]
    assert "incompletely grabbed" in info["incidents"][0]["message"]
    assert info["triggers_sent"] == 5 and info["pairs_delivered"] == 4
    assert len(logged) == 1 and logged[0]["level"] == "warning" and "grab_failed" in logged[0]["message"]


def test_frames_arriving_after_the_timeout_are_never_paired(emulation, station):
    """The emulator answers a trigger after ~10 ms; with a 1 ms timeout every frame is late."""
    root, _, _ = station
    source = make_source(root, frames=2, timeout_ms=1.0, max_consecutive_drops=6)
    try:
        got = list(source.frames())
        info = source.describe()
    finally:
        source.close()
    kinds = [i["kind"] for i in info["incidents"]]
    assert got == []
    assert kinds[-1] == "stopped" and info["incident_counts"]["stopped"] == 1
    assert "timeout" in kinds
    assert "late_frame" in kinds  # the late frames were seen and discarded, not paired
    assert set(kinds) <= {"timeout", "late_frame", "not_ready", "stopped"}


def test_hardware_trigger_pairs_by_time_and_drops_a_missed_pulse(emulation, station):
    """External triggering, emulated: a pulse thread fires both cameras' (software)
    frame triggers every PULSE_S and skips the lower camera on pulse 2, as a broken
    trigger wire would. The source only listens and pairs by arrival time.

    The emulator stamps no camera time, so the pairs are made by host arrival, which
    a loaded machine delays by up to a few 100 ms (measured at load 9: 70-350 ms):
    max_skew_ms is half the pulse period, so a frame is paired with its own pulse's
    partner and never with the next one while the delay stays below it. A source
    that still lacks pairs after the last pulse is stopped, and the test fails on
    the pairs it got instead of waiting for pulses that never come."""
    pulse_s = 0.5
    root, frames, _ = station
    source = make_source(
        root, frames=3, trigger="hardware", trigger_source="Software", trigger_activation="",
        max_skew_ms=pulse_s / 2 * 1000, timeout_ms=1000.0,
    )
    errors = []

    def pulses():
        try:
            cams = [source.cameras[r].instant for r in ("upper", "lower")]
            deadline = time.monotonic() + 10
            while not all(c.IsGrabbing() for c in cams) and time.monotonic() < deadline:
                time.sleep(0.01)
            for pulse in range(4):
                for role, cam in zip(("upper", "lower"), cams):
                    if role == "lower" and pulse == 2:
                        continue
                    assert cam.WaitForFrameTriggerReady(1000, pylon.TimeoutHandling_Return)
                    cam.ExecuteSoftwareTrigger()
                time.sleep(pulse_s)
            deadline = time.monotonic() + 5  # the last frames' way through the emulator and the readers
            while source.pairs_delivered < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
        except Exception as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)
        finally:
            source.stop()  # no more pulses: frames() must end, whatever it got

    thread = threading.Thread(target=pulses)
    thread.start()
    try:
        got = list(source.frames())
        info = source.describe()
    finally:
        thread.join()
        source.close()
    assert errors == []
    assert [p.sequence for p in got] == [0, 1, 3], incident_keys(info)  # upper frame 2 had no partner
    lower_index = [0, 1, 2]  # the lower camera's own frame count (it never saw pulse 2)
    for pair, k in zip(got, lower_index):
        np.testing.assert_array_equal(pair.upper, frames[pair.sequence % N_FRAMES].upper)
        np.testing.assert_array_equal(pair.lower, frames[k % N_FRAMES].lower)
    assert incident_keys(info) == [("no_partner", "upper", 2)]


def test_frames_returns_only_after_the_readers_have_stopped(emulation, station, monkeypatch):
    """A reader thread busy when the pairs are done (here: 1.5 s inside the inbox, longer
    than one reader poll and than the 1.25 s the source used to wait) is waited for, never
    left running while its camera is stopped, closed and destroyed: a grab result
    released after that is a use-after-free in pylon."""
    root, _, _ = station
    put = acquire_basler._Inbox.put

    def slow_put(self, frame):
        put(self, frame)
        if frame.camera == "lower":
            time.sleep(1.5)  # the frame is handed over; the reader still holds its grab result

    monkeypatch.setattr(acquire_basler._Inbox, "put", slow_put)
    source = make_source(root, frames=1)
    try:
        (pair,) = list(source.frames())
        alive = [t.name for t in threading.enumerate() if t.name.startswith("basler-reader")]
    finally:
        source.close()
    assert pair.sequence == 0
    assert alive == []


def test_pylon_takes_over_sigalrm_when_grabbing(emulation, station):
    """Why this module has no SIGALRM timeout (see WATCHDOG_S): after StartGrabbing the
    process's SIGALRM handler is pylon's, not Python's. If a pylon release stops doing
    that, this test fails and pytest-timeout's signal method can come back."""

    class SigAction(ctypes.Structure):
        _fields_ = [("handler", ctypes.c_void_p), ("mask", ctypes.c_ulong * 16), ("flags", ctypes.c_int),
                    ("restorer", ctypes.c_void_p)]

    class DlInfo(ctypes.Structure):
        _fields_ = [("fname", ctypes.c_char_p), ("fbase", ctypes.c_void_p), ("sname", ctypes.c_char_p),
                    ("saddr", ctypes.c_void_p)]

    libc = ctypes.CDLL(None)

    def sigalrm_library() -> str:
        action, info = SigAction(), DlInfo()
        assert libc.sigaction(signal.SIGALRM, None, ctypes.byref(action)) == 0
        assert action.handler and libc.dladdr(ctypes.c_void_p(action.handler), ctypes.byref(info))
        return Path(info.fname.decode()).name

    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)  # no SIGALRM timer armed in this module
    saved = signal.signal(signal.SIGALRM, lambda *_: None)
    try:
        assert sigalrm_library().startswith("libpython")
        source = make_source(station[0], frames=1)
        try:
            list(source.frames())
            taken = sigalrm_library()
        finally:
            source.close()
    finally:
        signal.signal(signal.SIGALRM, saved)
    assert taken.startswith("libpylonbase"), taken


def test_skew_beyond_max_skew_ms_refuses_the_pair(emulation, station):
    """With a max_skew_ms far below the emulator's trigger-to-trigger host timing no pair passes."""
    root, _, _ = station
    source = make_source(root, frames=1, max_skew_ms=1e-6, max_consecutive_drops=2)
    try:
        got = list(source.frames())
        info = source.describe()
    finally:
        source.close()
    assert got == []
    assert [i["kind"] for i in info["incidents"]] == ["skew", "skew", "stopped"]
    assert "host arrival" in info["incidents"][0]["message"]


def test_camera_selection_errors_list_the_cameras(emulation, station):
    root, _, _ = station
    with pytest.raises(ConfigError, match=r"option 'lower': no camera has the serial .* 'nope'.*0815-0000"):
        make_source(root, lower="nope")
    with pytest.raises(ConfigError, match=r"upper camera \(CamEmu, serial 0815-0000\) delivers 1024x1040"):
        make_source(root, upper_features={})
    with pytest.raises(ConfigError, match=r"option 'lower_features': the lower camera .* 'NoSuchFeature'"):
        make_source(root, lower_features={"NoSuchFeature": 1})
    with pytest.raises(ConfigError, match=r"option 'features': cannot set ExposureTime = -5 on the upper"):
        make_source(root, features={"ExposureTime": -5})


def test_select_device_by_serial_or_user_id():
    def info(serial, user, model="acA1600-20gm"):
        d = pylon.DeviceInfo()
        d.SetSerialNumber(serial)
        d.SetUserDefinedName(user)
        d.SetModelName(model)
        return d

    devices = [info("21000001", "UPPER"), info("21000002", "LOWER"), info("21000003", "21000001")]
    assert select_device(devices, "LOWER", "lower").GetSerialNumber() == "21000002"
    assert select_device(devices, "21000002", "lower").GetSerialNumber() == "21000002"
    with pytest.raises(ConfigError, match="matches 2 cameras"):
        select_device(devices, "21000001", "upper")
    with pytest.raises(ConfigError, match=r"'X'; cameras found: acA1600-20gm serial '21000001' user id 'UPP"):
        select_device(devices, "X", "upper")


def test_basler_is_registered_and_says_how_to_install_pypylon(monkeypatch, tmp_path):
    pm = make_plugin_manager()
    impl = get_implementation(pm, "acquire", "basler")
    assert impl.plugin == "crossfield.plugins.acquire_basler"
    monkeypatch.setitem(sys.modules, "pypylon", None)  # as if pypylon were not installed
    with pytest.raises(PluginError, match=r"install crossfield\[basler\]"):
        impl.create({"upper": "a", "lower": "b", "calibration": str(tmp_path / "c.yml")})


def test_options_are_checked_before_touching_a_camera():
    with pytest.raises(ValueError, match="option 'trigger' must be one of software, hardware"):
        BaslerStereoSource(upper="a", lower="b", calibration="c.yml", trigger="line")
    with pytest.raises(ValueError, match="option 'pixel_format'"):
        BaslerStereoSource(upper="a", lower="b", calibration="c.yml", pixel_format="Mono12p")
    with pytest.raises(ValueError, match="name the same camera"):
        BaslerStereoSource(upper="a", lower="a", calibration="c.yml")


# ---- the whole pipeline over the emulated cameras ------------------------------------------------

GROUND_TRUTH_KEYS = {"actual_mm", "error_mm", "ground_truth"}  # only the simulator knows the truth


def _without(value, drop):
    """``value`` with the keys in ``drop`` removed at every level."""
    if isinstance(value, dict):
        return {k: _without(v, drop) for k, v in value.items() if k not in drop}
    if isinstance(value, list):
        return [_without(v, drop) for v in value]
    return value


def test_session_over_emulated_cameras_reports_what_the_simulator_source_reports(
    emulation, station, tmp_path
):
    """Same frames -> same numbers: run_session with acquire = basler (emulated
    cameras streaming the simulator's station frames, calibration from a YAML
    file, plan from a TOML file, the simulated arm on a pseudo-terminal) and with
    acquire = simulator; the reports agree in every measured number."""
    import json

    from crossfield.config import parse_config
    from crossfield.chain.runner import run_session

    root, frames, simulator = station
    common = {"record": False, "rerun": False, "output_dir": str(tmp_path)}
    report = {"plugin": "json"}  # report.json is what is compared; report.html's figures would only add time
    full = {"simulator": FrameCollector(), "basler": FrameCollector()}
    simulated = run_session(
        parse_config({
            "session": common | {"name": "simulator"},
            "acquire": {"plugin": "simulator", "scenario": "station", "frames": N_FRAMES, "seed": SEED},
            "reference": {"plugin": "romer-serial", "port": "simulator"},
            "report": report,
        }, "<simulator>"),
        make_plugin_manager(),
        observers=[full["simulator"]],
    )
    with simulator.serve_arm() as port:  # the same arm points (same seed) on a fresh pty
        basler = run_session(
            parse_config({
                "session": common | {"name": "basler", "plan": str(root / "plan.toml")},
                "acquire": {
                    "plugin": "basler", "upper": UPPER, "lower": LOWER, "frames": N_FRAMES,
                    "calibration": str(root / "calibration.yml"), "max_skew_ms": 250.0,
                    "upper_features": emulated_features(root, "upper"),
                    "lower_features": emulated_features(root, "lower"),
                },
                "reference": {"plugin": "romer-serial", "port": port},
                "report": report,
            }, "<basler>"),
            make_plugin_manager(),
            observers=[full["basler"]],
        )
    assert basler.info.acquisition["source"] == "basler"
    assert basler.info.acquisition["cameras"]["upper"]["serial"] == UPPER
    assert basler.info.ground_truth is None and simulated.info.ground_truth is not None
    assert [f.sequence for f in basler.frames] == list(range(N_FRAMES))
    assert [f.sequence for f in simulated.frames] == list(range(N_FRAMES))
    assert not any(f.error for f in basler.frames + simulated.frames)
    # The session keeps slim per-frame results; the centroids and points are
    # compared as the observers saw them.
    assert len(full["basler"].results) == len(full["simulator"].results) == N_FRAMES
    for b, s in zip(full["basler"].results, full["simulator"].results):
        np.testing.assert_array_equal(b.centroids.upper.uv, s.centroids.upper.uv)
        np.testing.assert_array_equal(b.points.xyz, s.points.xyz)
        np.testing.assert_array_equal(b.registration.fit.R, s.registration.fit.R)
        assert [c.measured_mm for c in b.measurement.characteristics] == [
            c.measured_mm for c in s.measurement.characteristics
        ]

    reports = {
        name: json.loads(next(p for p in summary.report_files if p.name == "report.json").read_text())
        for name, summary in (("basler", basler), ("simulator", simulated))
    }
    for key in ("frames", "registration", "characteristics", "frames_processed", "frames_failed", "passed"):
        drop = GROUND_TRUTH_KEYS | {"timestamp_ns"}
        ours, theirs = (_without(reports[n][key], drop) for n in ("basler", "simulator"))
        assert ours == theirs, key
    assert reports["simulator"]["ground_truth_known"] and not reports["basler"]["ground_truth_known"]
    assert reports["basler"]["characteristics"][0]["measured_mm"] == simulated.characteristics[0].measured_mm
