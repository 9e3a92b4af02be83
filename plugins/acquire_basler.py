"""acquire "basler": a stereo pair of Basler cameras through pylon (pypylon).

Needs the optional extra ``crossfield[basler]`` (pypylon); the plugin is
registered without it and says so when a session selects it.

* The two cameras are chosen by serial number or device user id (options
  ``upper`` and ``lower``), as pylon reports them when it enumerates the
  devices (``DeviceSerialNumber`` / ``DeviceUserID``).
* Each camera is opened, set to ``pixel_format`` (Mono8/10/12/16, delivered
  as uint16), ``exposure_us`` and ``gain_db`` if given, frame-start trigger
  on, trigger source ``Software`` (``trigger = "software"``) or the
  ``trigger_source`` line (``trigger = "hardware"``), then the ``features``
  (both cameras) and ``upper_features`` / ``lower_features`` (one camera)
  are written in order: any GenICam feature by name (this is how a test
  points pylon's camera emulation at image files).
* Grab strategy OneByOne: every frame the camera delivers is seen, in order,
  so none can be skipped unnoticed (LatestImageOnly would silently discard
  the frames the pairing check counts). A reader thread per camera takes
  the results from pylon and stamps each with the host time on arrival.
* Software trigger: per pair, wait until both cameras are ready for a frame
  trigger, execute the trigger on both, take the frame answering it from
  each. Hardware trigger: the cameras are triggered by a line; frames are
  paired by time (:class:`crossfield.camera.pairing.ArrivalPairer`).
* A pair is refused, never mismatched, when a frame times out, arrives
  failed, belongs to an earlier trigger (frame counter), follows lost
  frames, or when the two frames are more than ``max_skew_ms`` apart. Each
  refusal is an :class:`crossfield.camera.pairing.Incident`, listed by
  :meth:`describe` and passed to :attr:`BaslerStereoSource.log`.

See ``docs/cameras.md`` for wiring, settings and the emulation test.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from crossfield.plugin_api import (
    CAMERAS,
    Acquisition,
    ArrivalPairer,
    BlockCounter,
    ConfigError,
    GrabbedFrame,
    IncidentLog,
    LogCallable,
    PluginError,
    Register,
    StereoCalibration,
    StereoFrame,
    hookimpl,
    pair_skew_ns,
    read_stereo_calibration,
)

#: Pixel formats the source accepts -> significant bits. pylon delivers them
#: unpacked, one pixel per uint8/uint16 word, LSB-aligned.
PIXEL_FORMAT_BITS: dict[str, int] = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}
TRIGGERS: tuple[str, ...] = ("software", "hardware")
#: GigE Vision 1.x block ids are 16 bit and skip 0 on wrapping.
GIGE_BLOCK_MODULUS = 65535
#: How long a reader thread waits in one RetrieveResult call (ms); bounds the
#: time needed to stop the readers.
READER_POLL_MS = 50
#: How long stopping waits for a reader thread (s) before it reports the thread stuck.
READER_STOP_S = 30.0

INSTALL_HINT = "install crossfield[basler] (pip install 'crossfield[basler]', which brings pypylon)"


def import_pylon():
    """``(pylon, genicam)`` from pypylon, or a :class:`PluginError` saying how to install it."""
    try:
        from pypylon import genicam, pylon
    except ImportError as exc:  # pragma: no cover - pypylon is installed in the dev venv
        raise PluginError(
            f"acquire plugin 'basler' needs pypylon, which is not installed: {INSTALL_HINT} ({exc})"
        ) from None
    return pylon, genicam


# --------------------------------------------------------------------------
# Device selection and GenICam feature access
# --------------------------------------------------------------------------


def device_label(info: Any) -> str:
    """``"<model> serial <sn> user id <id>"`` for messages."""
    user = info.GetUserDefinedName()
    return f"{info.GetModelName()} serial {info.GetSerialNumber()!r}" + (f" user id {user!r}" if user else "")


def select_device(devices: list[Any], wanted: str, role: str) -> Any:
    """The pylon DeviceInfo whose serial number or user id is ``wanted``.

    No match, or more than one, is a :class:`ConfigError` listing the cameras found.
    """
    matches = [d for d in devices if wanted in (d.GetSerialNumber(), d.GetUserDefinedName())]
    found = "; ".join(device_label(d) for d in devices) or "none (check cabling, power, network settings)"
    if not matches:
        raise ConfigError(
            f"option {role!r}: no camera has the serial number or user id {wanted!r}; cameras found: {found}"
        )
    if len(matches) > 1:
        raise ConfigError(
            f"option {role!r}: {wanted!r} matches {len(matches)} cameras "
            f"({'; '.join(map(device_label, matches))}); use a serial number"
        )
    return matches[0]


class _Camera:
    """One opened pylon camera in its role (``upper``/``lower``)."""

    def __init__(self, role: str, info: Any, pylon: Any, genicam: Any):
        self.role = role
        self.pylon = pylon
        self.genicam = genicam
        self.serial = info.GetSerialNumber()
        self.device_class = info.GetDeviceClass()
        self.instant = pylon.InstantCamera(pylon.TlFactory.GetInstance().CreateDevice(info))
        self.instant.Open()
        self.user_id = self.read("DeviceUserID", info.GetUserDefinedName())
        self.model = self.read("DeviceModelName", info.GetModelName())
        self.features_set: dict[str, Any] = {}
        self.counter = BlockCounter(GIGE_BLOCK_MODULUS if self.device_class == "BaslerGigE" else None)
        self.tick_ns = 1.0  # camera timestamp unit in ns; set by configure()
        self.last_timestamp: int | None = None  # raw timestamp of the latest result (0 = camera gives none)

    @property
    def name(self) -> str:
        return f"{self.role} camera ({self.model}, serial {self.serial})"

    def node(self, name: str) -> Any | None:
        node = self.instant.GetNodeMap().GetNode(name)
        return node if self.genicam.IsAvailable(node) else None

    def read(self, name: str, default: Any = None) -> Any:
        """The feature's value (str for enumerations and strings), or ``default``."""
        node = self.node(name)
        if node is None or not self.genicam.IsReadable(node):
            return default
        try:
            return node.Value
        except self.genicam.GenericException:
            return node.ToString()

    def write(self, name: str, value: Any, option: str) -> None:
        """Set feature ``name``; errors are :class:`ConfigError` naming the option, camera and feature."""
        node = self.node(name)
        if node is None:
            raise ConfigError(f"option {option!r}: the {self.name} has no feature {name!r}")
        try:
            if isinstance(node, self.pylon.CommandParameter):
                if value is not True:
                    raise ConfigError(f"option {option!r}: {name!r} is a command; give true to execute it")
                node.Execute()
            elif isinstance(value, str):
                node.FromString(value)
            else:
                node.Value = value
        except self.genicam.GenericException as exc:
            detail = str(exc).split(" : ")[0]
            raise ConfigError(
                f"option {option!r}: cannot set {name} = {value!r} on the {self.name}: {detail}"
            ) from None
        self.features_set[name] = value

    def write_first(self, names: tuple[str, ...], value: Any, option: str) -> str:
        """Write the first of ``names`` the camera has (SFNC name, then the older GigE one)."""
        for name in names:
            if self.node(name) is not None:
                self.write(name, value, option)
                return name
        raise ConfigError(
            f"option {option!r}: the {self.name} has none of the features {', '.join(names)}; "
            f"set the camera's own feature with 'features'"
        )

    def configure(
        self,
        *,
        pixel_format: str,
        exposure_us: float | None,
        gain_db: float | None,
        trigger: str,
        trigger_source: str,
        trigger_activation: str,
        features: Mapping[str, Any],
        own_features: Mapping[str, Any],
        own_option: str,
    ) -> None:
        self.write("PixelFormat", pixel_format, "pixel_format")
        if exposure_us is not None:
            if self.node("ExposureAuto") is not None:
                self.write("ExposureAuto", "Off", "exposure_us")
            self.write_first(("ExposureTime", "ExposureTimeAbs"), float(exposure_us), "exposure_us")
        if gain_db is not None:
            if self.node("GainAuto") is not None:
                self.write("GainAuto", "Off", "gain_db")
            self.write_first(("Gain", "GainAbs"), float(gain_db), "gain_db")
        if self.node("AcquisitionMode") is not None:
            self.write("AcquisitionMode", "Continuous", "trigger")
        self.write("TriggerSelector", "FrameStart", "trigger")
        self.write("TriggerMode", "On", "trigger")
        if trigger == "software":
            self.write("TriggerSource", "Software", "trigger")
        else:
            self.write("TriggerSource", trigger_source, "trigger_source")
            if trigger_activation:
                self.write("TriggerActivation", trigger_activation, "trigger_activation")
        for option, table in (("features", features), (own_option, own_features)):
            for name, value in table.items():
                self.write(str(name), value, option)
        frequency = self.read("GevTimestampTickFrequency")  # GigE: ticks per second; USB3: timestamps in ns
        self.tick_ns = 1e9 / float(frequency) if frequency else 1.0

    def image_size(self) -> tuple[int, int]:
        return (int(self.read("Width")), int(self.read("Height")))

    def describe(self) -> dict[str, Any]:
        """The camera's identity and settings as read back from it (JSON-able)."""

        def first(*names: str) -> Any:
            for name in names:
                value = self.read(name)
                if value is not None:
                    return value
            return None

        return {
            "model": self.model,
            "vendor": self.read("DeviceVendorName"),
            "serial": self.serial,
            "user_id": self.user_id,
            "device_class": self.device_class,
            "firmware": first("DeviceFirmwareVersion", "DeviceVersion"),
            "device_version": self.read("DeviceVersion"),
            "pixel_format": self.read("PixelFormat"),
            "width": self.read("Width"),
            "height": self.read("Height"),
            "offset_x": self.read("OffsetX"),
            "offset_y": self.read("OffsetY"),
            "exposure_us": first("ExposureTime", "ExposureTimeAbs"),
            "gain_db": first("Gain", "GainAbs"),
            "gain_raw": self.read("GainRaw"),
            "trigger_selector": self.read("TriggerSelector"),
            "trigger_mode": self.read("TriggerMode"),
            "trigger_source": self.read("TriggerSource"),
            "trigger_activation": self.read("TriggerActivation"),
            "timestamp_tick_ns": self.tick_ns,
            "camera_timestamps": (
                "unknown (no frame yet)" if self.last_timestamp is None
                else "yes" if self.last_timestamp
                else "no (the camera reports 0; skew from host arrival times)"
            ),
            "features_set": {k: v for k, v in self.features_set.items()},
        }

    def close(self) -> None:
        try:
            if self.instant.IsGrabbing():
                self.instant.StopGrabbing()
            if self.instant.IsOpen():
                self.instant.Close()
        finally:
            self.instant.DestroyDevice()


# --------------------------------------------------------------------------
# Reader threads
# --------------------------------------------------------------------------


class _Inbox:
    """Frames delivered by the reader threads, per camera, in arrival order."""

    def __init__(self) -> None:
        self._queues: dict[str, deque[GrabbedFrame]] = {c: deque() for c in CAMERAS}
        self._any: deque[GrabbedFrame] = deque()
        self._cond = threading.Condition()
        self.errors: list[str] = []

    def put(self, frame: GrabbedFrame) -> None:
        with self._cond:
            self._queues[frame.camera].append(frame)
            self._any.append(frame)
            self._cond.notify_all()

    def fail(self, message: str) -> None:
        with self._cond:
            self.errors.append(message)
            self._cond.notify_all()

    def get(self, camera: str, deadline: float) -> GrabbedFrame | None:
        """The oldest frame of ``camera``, waiting until ``deadline`` (time.monotonic)."""
        with self._cond:
            while not self._queues[camera] and not self.errors:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            if not self._queues[camera]:
                return None
            frame = self._queues[camera].popleft()
            self._any.remove(frame)
            return frame

    def get_any(self, deadline: float) -> GrabbedFrame | None:
        """The oldest frame of either camera, waiting until ``deadline``."""
        with self._cond:
            while not self._any and not self.errors:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            if not self._any:
                return None
            frame = self._any.popleft()
            self._queues[frame.camera].remove(frame)
            return frame

    def drain(self) -> list[GrabbedFrame]:
        """Everything waiting, oldest first."""
        with self._cond:
            frames = list(self._any)
            self._any.clear()
            for q in self._queues.values():
                q.clear()
            return frames


class _Reader(threading.Thread):
    """Retrieves one camera's results, stamps their host arrival time, posts them to the inbox."""

    def __init__(self, camera: _Camera, inbox: _Inbox):
        super().__init__(name=f"basler-reader-{camera.role}", daemon=True)
        self.camera = camera
        self.inbox = inbox
        self.stop = threading.Event()
        self.count = 0

    def run(self) -> None:
        pylon = self.camera.pylon
        instant = self.camera.instant
        try:
            while not self.stop.is_set():
                result = instant.RetrieveResult(READER_POLL_MS, pylon.TimeoutHandling_Return)
                if not result.IsValid():
                    continue
                host_ns = time.time_ns()
                try:
                    self.inbox.put(self.convert(result, host_ns))
                finally:
                    result.Release()
                self.count += 1
        except Exception as exc:  # noqa: BLE001 - reported through the inbox; never die silently
            if not self.stop.is_set():
                self.inbox.fail(f"{self.camera.name}: reading results failed: {type(exc).__name__}: {exc}")

    def convert(self, result: Any, host_ns: int) -> GrabbedFrame:
        ok = bool(result.GrabSucceeded())
        image = None
        error = ""
        if ok:
            image = result.GetArray()  # a copy: the buffer returns to pylon on Release()
            if image.dtype != np.uint16:
                image = image.astype(np.uint16)
        else:
            error = f"{result.GetErrorDescription()} (error 0x{result.GetErrorCode() & 0xFFFFFFFF:08X})"
        timestamp = int(result.GetTimeStamp())
        self.camera.last_timestamp = timestamp
        return GrabbedFrame(
            camera=self.camera.role,
            ok=ok,
            index=self.count,
            block_id=int(result.GetBlockID()),
            camera_ns=round(timestamp * self.camera.tick_ns),
            host_ns=host_ns,
            image=image,
            error=error,
        )


# --------------------------------------------------------------------------
# The source
# --------------------------------------------------------------------------


def _positive_number(value: Any, option: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise ValueError(f"option {option!r} must be a positive number, got {value!r}")
    return float(value)


def _features(value: Any, option: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise ValueError(f"option {option!r} must be a table of GenICam feature = value, got {value!r}")
    for name, v in value.items():
        if not isinstance(v, (bool, int, float, str)):
            raise ValueError(
                f"option {option!r}: feature {name!r} must be a bool, number or string, got {v!r}"
            )
    return dict(value)


class BaslerStereoSource:
    """Stereo pairs from two Basler cameras (pylon), paired by trigger and checked in time.

    upper, lower: serial number or device user id of each camera.
    calibration: stereo calibration file or list of files (OpenCV FileStorage
    YAML, :mod:`crossfield.camera.calibration_io`: M1 D1 M2 D2 R T, camera 1 = upper,
    T in mm); image sizes not stored there are taken from the cameras.
    frames: pairs to deliver (0 = until :meth:`stop` or :meth:`close`).
    trigger: ``software`` (the source triggers both cameras per pair) or
    ``hardware`` (the cameras are triggered by ``trigger_source``, e.g.
    ``Line1``, on ``trigger_activation``; the source pairs by time).
    exposure_us, gain_db: written to the cameras when given (else left as set).
    pixel_format: Mono8, Mono10, Mono12 or Mono16; bit_depth: significant bits
    (0 = those of the pixel format).
    timeout_ms: how long to wait for a frame after a trigger (software) or
    for the partner of a frame (hardware). ready_timeout_ms: how long to
    wait for both cameras to be ready for a software trigger (a camera is
    busy while it exposes and reads out the previous frame).
    max_skew_ms: largest time offset between the two frames of a pair
    (camera clocks when the cameras have them, else host arrival times).
    max_consecutive_drops: give up after this many refused pairs in a row
    (0 = never).
    features, upper_features, lower_features: further GenICam features to
    write (name = value), to both cameras / one camera, after the above.

    ``log`` (attribute, not an option; set by :meth:`connect_log`): a callable receiving ``level``,
    ``message``, ``timestamp_ns`` keyword arguments for each incident.
    """

    ground_truth = None
    default_plan = None

    def __init__(
        self,
        *,
        upper: str,
        lower: str,
        calibration: str | list[str],
        frames: int = 10,
        trigger: str = "software",
        trigger_source: str = "Line1",
        trigger_activation: str = "RisingEdge",
        exposure_us: float | None = None,
        gain_db: float | None = None,
        pixel_format: str = "Mono12",
        bit_depth: int = 0,
        timeout_ms: float = 1000.0,
        ready_timeout_ms: float = 1000.0,
        max_skew_ms: float = 20.0,
        max_consecutive_drops: int = 10,
        features: Mapping[str, Any] | None = None,
        upper_features: Mapping[str, Any] | None = None,
        lower_features: Mapping[str, Any] | None = None,
    ):
        for option, value in (("upper", upper), ("lower", lower)):
            if not isinstance(value, str) or not value:
                raise ValueError(
                    f"option {option!r} must be a camera serial number or user id, got {value!r}"
                )
        if upper == lower:
            raise ValueError(f"options 'upper' and 'lower' name the same camera {upper!r}")
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
            raise ValueError(f"option 'frames' must be an integer >= 0 (0 = until stopped), got {frames!r}")
        if trigger not in TRIGGERS:
            raise ValueError(f"option 'trigger' must be one of {', '.join(TRIGGERS)}, got {trigger!r}")
        if pixel_format not in PIXEL_FORMAT_BITS:
            raise ValueError(
                f"option 'pixel_format' must be one of {', '.join(PIXEL_FORMAT_BITS)}, got {pixel_format!r}"
            )
        bits = PIXEL_FORMAT_BITS[pixel_format]
        if isinstance(bit_depth, bool) or not isinstance(bit_depth, int) or not 0 <= bit_depth <= bits:
            raise ValueError(
                f"option 'bit_depth' must be 0 (from the pixel format) or 1..{bits} for {pixel_format}, "
                f"got {bit_depth!r}"
            )
        drops = max_consecutive_drops
        if isinstance(drops, bool) or not isinstance(drops, int) or drops < 0:
            raise ValueError(f"option 'max_consecutive_drops' must be an integer >= 0, got {drops!r}")
        if isinstance(calibration, str):
            calibration_files = [calibration] if calibration else []
        elif isinstance(calibration, (list, tuple)) and all(isinstance(c, str) and c for c in calibration):
            calibration_files = list(calibration)
        else:
            calibration_files = []
        if not calibration_files:
            raise ValueError(
                f"option 'calibration' must be a calibration file or a list of files, got {calibration!r}"
            )
        self.n_frames = frames
        self.trigger = trigger
        self.trigger_source = trigger_source
        self.pixel_format = pixel_format
        self.bit_depth = bit_depth or PIXEL_FORMAT_BITS[pixel_format]
        self.timeout_ms = _positive_number(timeout_ms, "timeout_ms")
        self.ready_timeout_ms = _positive_number(ready_timeout_ms, "ready_timeout_ms")
        self.max_skew_ms = _positive_number(max_skew_ms, "max_skew_ms")
        self.max_consecutive_drops = max_consecutive_drops
        self.calibration_files = [str(Path(p).expanduser()) for p in calibration_files]
        self.settings = {
            "exposure_us": None if exposure_us is None else _positive_number(exposure_us, "exposure_us"),
            "gain_db": None if gain_db is None else float(gain_db),
            "features": _features(features or {}, "features"),
            "upper_features": _features(upper_features or {}, "upper_features"),
            "lower_features": _features(lower_features or {}, "lower_features"),
        }
        self.log: LogCallable | None = None
        self.incidents = IncidentLog("basler")
        self.pairs_delivered = 0
        self.triggers_sent = 0
        self._stop = threading.Event()
        self._readers: dict[str, _Reader] = {}
        self.pylon, self.genicam = import_pylon()
        self.cameras: dict[str, _Camera] = {}
        try:
            self._open(upper, lower, trigger_source, trigger_activation)
            sizes = [self.cameras[c].image_size() for c in CAMERAS]
            self.calibration: StereoCalibration = read_stereo_calibration(
                self.calibration_files, image_sizes=sizes
            )
            for camera, size in zip(CAMERAS, sizes):
                want = self.calibration.camera(camera).image_size
                if tuple(want) != tuple(size):
                    raise ConfigError(
                        f"the {self.cameras[camera].name} delivers {size[0]}x{size[1]} px, the {camera} "
                        f"camera's calibration ({self.calibration.source}) is for {want[0]}x{want[1]} px; "
                        f"set Width/Height (option '{camera}_features') or use the matching calibration"
                    )
        except BaseException:
            self.close()
            raise

    # ---- set-up ------------------------------------------------------------------------------

    def connect_log(self, log: LogCallable) -> None:
        """Report incidents through ``log`` from now on
        (:class:`crossfield.stages.ReportsIncidents`; the runner passes ``on_log``)."""
        self.log = log

    def _open(self, upper: str, lower: str, trigger_source: str, trigger_activation: str) -> None:
        pylon = self.pylon
        devices = list(pylon.TlFactory.GetInstance().EnumerateDevices())
        wanted = {"upper": upper, "lower": lower}
        infos = {role: select_device(devices, wanted[role], role) for role in CAMERAS}
        if infos["upper"].GetFullName() == infos["lower"].GetFullName():
            raise ConfigError(f"options 'upper' ({upper!r}) and 'lower' ({lower!r}) select the same camera")
        for role in CAMERAS:
            try:
                self.cameras[role] = _Camera(role, infos[role], pylon, self.genicam)
            except self.genicam.GenericException as exc:
                raise PluginError(
                    f"cannot open the {role} camera ({device_label(infos[role])}): {exc}"
                ) from None
            self.cameras[role].configure(
                pixel_format=self.pixel_format,
                exposure_us=self.settings["exposure_us"],
                gain_db=self.settings["gain_db"],
                trigger=self.trigger,
                trigger_source=trigger_source,
                trigger_activation=trigger_activation,
                features=self.settings["features"],
                own_features=self.settings[f"{role}_features"],
                own_option=f"{role}_features",
            )

    # ---- acquisition -------------------------------------------------------------------------

    def frames(self) -> Iterator[StereoFrame]:
        """Yield checked stereo pairs (uint16, ``bit_depth``-bit) until ``frames`` are delivered.

        Software trigger: ``sequence`` = trigger index (a refused pair leaves
        a gap), ``timestamp_ns`` = host time when the trigger was sent.
        Hardware trigger: ``sequence`` = upper camera's frame index,
        ``timestamp_ns`` = host arrival of the earlier frame of the pair.
        """
        if self._readers:
            raise PluginError("basler source: frames() is already running")
        self._stop.clear()
        inbox = _Inbox()
        for role in CAMERAS:
            camera = self.cameras[role]
            # Block ids restart with every grab (stream) start, so the counter does too.
            camera.counter = BlockCounter(camera.counter.modulus)
            camera.instant.StartGrabbing(self.pylon.GrabStrategy_OneByOne)
            self._readers[role] = _Reader(camera, inbox)
        for reader in self._readers.values():
            reader.start()
        try:
            pairs = self._software_pairs(inbox) if self.trigger == "software" else self._hardware_pairs(inbox)
            delivered = 0
            for frame in pairs:
                delivered += 1
                self.pairs_delivered += 1
                yield frame
                if self.n_frames and delivered >= self.n_frames:
                    return
        finally:
            self._stop_readers()

    def _stop_readers(self) -> None:
        """Stop the reader threads, then the grabbing.

        A reader is never abandoned: while it may still be inside RetrieveResult or
        hold a grab result, its camera must not be stopped, closed or destroyed (pylon
        gives no safety there). Each poll returns within READER_POLL_MS, so the join
        is short unless the machine starves the thread; a reader still alive after
        READER_STOP_S is an error and its camera is left open rather than destroyed
        under it (:meth:`close` reports it again).
        """
        for reader in self._readers.values():
            reader.stop.set()
        for reader in self._readers.values():
            reader.join(timeout=READER_STOP_S)
        stuck = [role for role, reader in self._readers.items() if reader.is_alive()]
        if stuck:
            raise PluginError(
                f"basler source: the {' and '.join(stuck)} camera's reader thread did not stop within "
                f"{READER_STOP_S:g} s; the camera is left open"
            )
        for camera in self.cameras.values():
            if camera.instant.IsGrabbing():
                camera.instant.StopGrabbing()
        self._readers = {}

    def _check_readers(self, inbox: _Inbox, sequence: int) -> bool:
        if inbox.errors:
            message = "; ".join(inbox.errors) + "; acquisition stopped"
            self.incidents.add("stopped", "both", sequence, message, "error")
            return False
        return True

    def _give_up(self, drops: int, sequence: int, what: str = "pairs in a row were refused") -> bool:
        if self.max_consecutive_drops and drops >= self.max_consecutive_drops:
            self.incidents.add(
                "stopped", "both", sequence,
                f"{drops} {what} (max_consecutive_drops {self.max_consecutive_drops}); acquisition stopped",
                "error",
            )
            return True
        return False

    def _software_pairs(self, inbox: _Inbox) -> Iterator[StereoFrame]:
        self.incidents.log = self.log
        timeout_s = self.timeout_ms / 1000
        previous: tuple[GrabbedFrame, GrabbedFrame] | None = None
        drops = 0
        k = 0
        while not self._stop.is_set() and self._check_readers(inbox, k):
            if not self._ready_for_trigger(k):
                drops += 1
                k += 1
                if self._give_up(drops, k - 1):
                    return
                continue
            for frame in inbox.drain():  # whatever came before this trigger does not answer it
                self._discard_early(frame, k)
            trigger_ns = time.time_ns()
            for role in CAMERAS:
                self.cameras[role].instant.ExecuteSoftwareTrigger()
                self.cameras[role].counter.trigger_sent()
            self.triggers_sent += 1
            deadline = time.monotonic() + timeout_s
            got = {role: self._frame_for_trigger(inbox, role, k, trigger_ns, deadline) for role in CAMERAS}
            pair = self._accept(k, got, previous)
            if pair is None:
                drops += 1
                if self._give_up(drops, k):
                    return
            else:
                drops = 0
                previous = (got["upper"], got["lower"])
                yield StereoFrame(k, trigger_ns, got["upper"].image, got["lower"].image, self.bit_depth)
            k += 1

    def _discard_early(self, frame: GrabbedFrame, k: int) -> None:
        """A frame that arrived before trigger ``k`` was sent cannot answer it: it is a
        late frame of an earlier trigger, or one no trigger of ours asked for."""
        counter = self.cameras[frame.camera].counter
        if counter.unsolicited(frame.block_id):
            self.incidents.add(
                "unexpected_frame", frame.camera, k,
                f"{frame.camera} frame (block {frame.block_id}) arrived before trigger {k} without a trigger "
                f"asking for it; discarded (is the camera free-running or triggered by another source?)",
            )
        else:
            self.incidents.add(
                "late_frame", frame.camera, k,
                f"{frame.camera} frame (block {frame.block_id}) of an earlier trigger arrived after its "
                f"pair was given up, before trigger {k}; discarded",
            )

    def _ready_for_trigger(self, k: int) -> bool:
        pylon = self.pylon
        not_ready = []
        for role in CAMERAS:
            instant = self.cameras[role].instant
            if instant.CanWaitForFrameTriggerReady() and not instant.WaitForFrameTriggerReady(
                max(1, round(self.ready_timeout_ms)), pylon.TimeoutHandling_Return
            ):
                not_ready.append(role)
        if not_ready:
            self.incidents.add(
                "not_ready", "both" if len(not_ready) == 2 else not_ready[0], k,
                f"{' and '.join(not_ready)} camera not ready for a frame trigger within ready_timeout_ms "
                f"{self.ready_timeout_ms:g}; trigger {k} not sent",
            )
            return False
        return True

    def _frame_for_trigger(
        self, inbox: _Inbox, role: str, k: int, trigger_ns: int, deadline: float
    ) -> GrabbedFrame | None:
        """The frame answering trigger ``k`` (sent at host time ``trigger_ns``) from
        camera ``role``, or None (incident recorded)."""
        counter = self.cameras[role].counter
        while True:
            frame = inbox.get(role, deadline)
            if frame is None:
                self.incidents.add(
                    "timeout", role, k,
                    f"{role}: no frame within timeout_ms {self.timeout_ms:g} of trigger {k}; "
                    f"pair {k} dropped",
                )
                return None
            if frame.host_ns < trigger_ns:  # arrived before the trigger was sent (causality)
                self._discard_early(frame, k)
                continue
            verdict = counter.classify(frame.block_id)
            if verdict == BlockCounter.STALE:
                self.incidents.add(
                    "late_frame", role, k,
                    f"{role}: frame with block {frame.block_id} belongs to an earlier trigger "
                    f"(trigger {k} expects block {counter.expected}); discarded",
                )
                continue
            if not frame.ok:
                self.incidents.add(
                    "grab_failed", role, k, f"{role}: frame of trigger {k} (block {frame.block_id}) failed: "
                    f"{frame.error}; pair {k} dropped",
                )
                return None
            if verdict == BlockCounter.AHEAD:
                self.incidents.add(
                    "counter_mismatch", role, k,
                    f"{role}: frame of trigger {k} carries block {frame.block_id}, frames were lost "
                    f"before it (counter resynchronised); pair {k} dropped",
                )
                return None
            return frame

    def _accept(
        self, k: int, got: dict[str, GrabbedFrame | None], previous: tuple[GrabbedFrame, GrabbedFrame] | None
    ) -> tuple[GrabbedFrame, GrabbedFrame] | None:
        upper, lower = got["upper"], got["lower"]
        if upper is None or lower is None:
            return None
        skew_ns, basis = pair_skew_ns(upper, lower, previous)
        if abs(skew_ns) > self.max_skew_ms * 1e6:
            self.incidents.add(
                "skew", "both", k,
                f"the frames of trigger {k} are {skew_ns / 1e6:+.3f} ms apart (upper - lower, {basis}), "
                f"more than max_skew_ms {self.max_skew_ms:g}; pair {k} dropped",
            )
            return None
        return upper, lower

    def _hardware_pairs(self, inbox: _Inbox) -> Iterator[StereoFrame]:
        self.incidents.log = self.log
        pairer = ArrivalPairer(round(self.max_skew_ms * 1e6), round(self.timeout_ms * 1e6), self.incidents)

        def dropped() -> int:
            return sum(1 for i in self.incidents if i.kind in ("no_partner", "timeout", "grab_failed"))

        dropped_before = dropped()
        while not self._stop.is_set() and self._check_readers(inbox, -1):
            frame = inbox.get_any(time.monotonic() + READER_POLL_MS / 1000)
            now = time.time_ns()
            pairs = pairer.push(frame, now) if frame is not None else pairer.poll(now)
            if pairs:
                dropped_before = dropped()
            elif self._give_up(dropped() - dropped_before, -1, "frames in a row were dropped unpaired"):
                return
            for u, l in pairs:
                yield StereoFrame(u.index, min(u.host_ns, l.host_ns), u.image, l.image, self.bit_depth)

    # ---- control and record ------------------------------------------------------------------

    def stop(self) -> None:
        """End :meth:`frames` after the pair in progress (callable from another thread)."""
        self._stop.set()

    def describe(self) -> dict[str, Any]:
        """Source, cameras and incidents so far, for the session record (JSON-able)."""
        return {
            "source": "basler",
            "pypylon": _pypylon_version(),
            "trigger": self.trigger,
            "trigger_source": "Software" if self.trigger == "software" else self.trigger_source,
            "grab_strategy": "OneByOne",
            "pixel_format": self.pixel_format,
            "bit_depth": self.bit_depth,
            "frames": self.n_frames,
            "timeout_ms": self.timeout_ms,
            "ready_timeout_ms": self.ready_timeout_ms,
            "max_skew_ms": self.max_skew_ms,
            "max_consecutive_drops": self.max_consecutive_drops,
            "skew_basis": "camera clock intervals when both cameras give timestamps, else host arrival times",
            "calibration_files": list(self.calibration_files),
            "cameras": self._camera_info(),
            "pairs_delivered": self.pairs_delivered,
            "triggers_sent": self.triggers_sent,
            "incident_counts": self.incidents.counts(),
            "incidents": self.incidents.as_dicts(),
        }

    def _camera_info(self) -> dict[str, Any]:
        if self.cameras:
            self._last_camera_info = {role: cam.describe() for role, cam in self.cameras.items()}
        return getattr(self, "_last_camera_info", {})

    def close(self) -> None:
        """Stop grabbing and release both cameras (safe to call twice; :meth:`describe`
        still reports the cameras as they were)."""
        self._stop.set()
        if self._readers:
            self._stop_readers()
        if self.cameras:
            try:
                self._camera_info()
            except Exception:  # noqa: BLE001 - a camera that cannot be read must still be closed
                pass
        cameras, self.cameras = self.cameras, {}
        errors = []
        for camera in cameras.values():
            try:
                camera.close()
            except Exception as exc:  # noqa: BLE001 - close both, then report
                errors.append(f"{camera.name}: {exc}")
        if errors:
            raise PluginError("closing the Basler cameras failed: " + "; ".join(errors))


def _pypylon_version() -> str:
    try:
        from importlib import metadata

        return metadata.version("pypylon")
    except Exception:  # noqa: BLE001
        return "unknown"


@hookimpl
def register_acquires(register: Register[Acquisition]) -> None:
    register("basler", BaslerStereoSource, "Two Basler cameras via pylon (pypylon; crossfield[basler])")
