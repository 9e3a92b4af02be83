"""acquire "opencv": a stereo pair from two ``cv2.VideoCapture`` sources.

Each of ``upper`` and ``lower`` is what ``cv2.VideoCapture`` opens: an
integer is a device index (``/dev/video<N>`` on Linux), a string a video
file, a stream URL or an image-sequence pattern such as
``"upper/img_%04d.png"`` (``docs/cameras.md``).

Bit depth: string sources are opened with ``CAP_PROP_CONVERT_RGB = 0`` so
that single-channel 16-bit material (16-bit PNG/TIFF sequences, FFV1
``gray16le`` video) arrives unchanged as uint16; device indices keep
OpenCV's default conversion (a webcam's YUYV/MJPEG becomes 8-bit BGR). A
3-channel frame becomes grey: channel 0 when the three channels are equal
(grey material decoded as BGR, exact), else ``cv2.cvtColor(BGR2GRAY)``.
Frames are delivered as uint16; ``bit_depth`` = 0 takes 8 for 8-bit frames
and 16 for 16-bit ones; a smaller value (e.g. 12) is checked against every
frame (a value >= 2**bit_depth is an error).

Pairing: by read order - ``grab()`` on both sources, then ``retrieve()``
(OpenCV's recipe for keeping several cameras close in time). When both
sources give frame timestamps (``CAP_PROP_POS_MSEC``: the presentation time
of the frame just read for files, the driver's buffer time for V4L2
devices), a pair whose timestamps differ by more than ``max_skew_ms`` is
refused and the earlier frame dropped, so that the later one is paired with
the other source's next frame (the streams resynchronise). Image sequences
give no timestamps (-1): no skew check is possible, which
:meth:`OpenCVStereoSource.describe` says. A pattern (a string with ``%``)
is read with OpenCV's image-sequence backend (``CAP_IMAGES``) unless
``backend`` says otherwise: left to ``CAP_ANY``, FFmpeg's image2 demuxer
would take it and reduce 16-bit PNGs to 8 bits. Every refusal is an incident
(:mod:`crossfield.camera.pairing`).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from crossfield.plugin_api import (
    CAMERAS,
    Acquisition,
    ConfigError,
    IncidentLog,
    LogCallable,
    Register,
    StereoCalibration,
    StereoFrame,
    hookimpl,
    read_stereo_calibration,
)

#: Names accepted by the ``backend`` option -> OpenCV's VideoCapture API preference.
BACKENDS: dict[str, int] = {
    "any": cv2.CAP_ANY,
    "ffmpeg": cv2.CAP_FFMPEG,
    "images": cv2.CAP_IMAGES,
    "v4l2": cv2.CAP_V4L2,
    "gstreamer": cv2.CAP_GSTREAMER,
}


@dataclass(frozen=True)
class _Read:
    """One frame read from one source: read index, timestamp (ms, -1 = none), host time (ns)."""

    index: int
    pos_ms: float
    host_ns: int
    image: np.ndarray


def _fourcc(value: float) -> str:
    code = int(value)
    text = "".join(chr((code >> (8 * k)) & 0xFF) for k in range(4))
    return text if code and text.isprintable() else ""


class OpenCVStereoSource:
    """Stereo pairs from two OpenCV VideoCapture sources, paired by read order.

    upper, lower: device index (int) or file / URL / image-sequence pattern (str).
    calibration: stereo calibration file or list of files (OpenCV FileStorage
    YAML, :mod:`crossfield.camera.calibration_io`; camera 1 = upper, T in mm).
    frames: pairs to deliver (0 = until a stream ends or :meth:`stop`).
    bit_depth: significant bits of the pixel values (0 = 8 or 16 from the frames).
    max_skew_ms: largest timestamp difference within a pair (when the
    sources give timestamps). backend: ``any``, ``ffmpeg``, ``images``,
    ``v4l2`` or ``gstreamer``.

    ``log`` (attribute, set by :meth:`connect_log`): as for the basler source, a callable receiving
    ``level``, ``message``, ``timestamp_ns`` for each incident.
    """

    ground_truth = None
    default_plan = None

    def __init__(
        self,
        *,
        upper: int | str,
        lower: int | str,
        calibration: str | list[str],
        frames: int = 0,
        bit_depth: int = 0,
        max_skew_ms: float = 20.0,
        backend: str = "any",
    ):
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
            raise ValueError(
                f"option 'frames' must be an integer >= 0 (0 = until a stream ends), got {frames!r}"
            )
        if isinstance(bit_depth, bool) or not isinstance(bit_depth, int) or not 0 <= bit_depth <= 16:
            raise ValueError(f"option 'bit_depth' must be 0 (from the frames) or 1..16, got {bit_depth!r}")
        if isinstance(max_skew_ms, bool) or not isinstance(max_skew_ms, (int, float)) or not max_skew_ms > 0:
            raise ValueError(f"option 'max_skew_ms' must be a positive number of ms, got {max_skew_ms!r}")
        if backend not in BACKENDS:
            raise ValueError(f"option 'backend' must be one of {', '.join(BACKENDS)}, got {backend!r}")
        if isinstance(calibration, str) and calibration:
            files = [calibration]
        elif isinstance(calibration, (list, tuple)) and calibration and all(
            isinstance(c, str) and c for c in calibration
        ):
            files = list(calibration)
        else:
            raise ValueError(
                f"option 'calibration' must be a calibration file or a list of files, got {calibration!r}"
            )
        self.specs = {"upper": upper, "lower": lower}
        self.n_frames = frames
        self.bit_depth_option = bit_depth
        self.bit_depth = bit_depth
        self.max_skew_ms = float(max_skew_ms)
        self.backend = backend
        self.calibration_files = [str(Path(f).expanduser()) for f in files]
        self.log: LogCallable | None = None
        self.incidents = IncidentLog("opencv")
        self.pairs_delivered = 0
        self.frames_read = {c: 0 for c in CAMERAS}
        self.timestamps_available: bool | None = None
        self._stop = threading.Event()
        self.captures: dict[str, cv2.VideoCapture] = {}
        try:
            for camera in CAMERAS:
                self.captures[camera] = self._open(camera, self.specs[camera])
            sizes = [self._reported_size(c) for c in CAMERAS]
            self.calibration: StereoCalibration = read_stereo_calibration(
                self.calibration_files, image_sizes=None if None in sizes else sizes
            )
            for camera, size in zip(CAMERAS, sizes):
                want = self.calibration.camera(camera).image_size
                if size is not None and tuple(size) != tuple(want):
                    raise ConfigError(
                        f"option {camera!r}: {self.specs[camera]!r} delivers {size[0]}x{size[1]} px, "
                        f"the {camera} camera's calibration ({self.calibration.source}) is for "
                        f"{want[0]}x{want[1]} px"
                    )
            self._description = {c: self._describe_capture(c) for c in CAMERAS}
        except BaseException:
            self.close()
            raise

    # ---- set-up ------------------------------------------------------------------------------

    def connect_log(self, log: LogCallable) -> None:
        """Report incidents through ``log`` from now on
        (:class:`crossfield.stages.ReportsIncidents`; the runner passes ``on_log``)."""
        self.log = log

    def _open(self, camera: str, spec: int | str) -> cv2.VideoCapture:
        if isinstance(spec, bool) or not isinstance(spec, (int, str)) or spec == "":
            raise ValueError(
                f"option {camera!r} must be a device index (integer) or a file/URL (string), got {spec!r}"
            )
        api = BACKENDS[self.backend]
        if self.backend == "any" and isinstance(spec, str) and "%" in spec:
            # An image-sequence pattern: OpenCV's own reader (IMREAD_UNCHANGED). Left to
            # CAP_ANY, FFmpeg's image2 demuxer takes it and reduces 16-bit PNGs to 8 bits.
            api = cv2.CAP_IMAGES
        if isinstance(spec, int):
            capture = cv2.VideoCapture(spec, api)
        else:
            # Keep single-channel 16-bit material as it is (no BGR conversion). A backend
            # that does not know the property refuses to open with it (CAP_IMAGES, which
            # reads with IMREAD_UNCHANGED anyway): then open without it.
            capture = cv2.VideoCapture(spec, api, [cv2.CAP_PROP_CONVERT_RGB, 0])
            if not capture.isOpened():
                capture = cv2.VideoCapture(spec, api)
        if not capture.isOpened():
            hint = ""
            if isinstance(spec, str) and "://" not in spec and "%" not in spec and not Path(spec).exists():
                hint = ": file not found"
            raise ConfigError(
                f"option {camera!r}: OpenCV cannot open {spec!r} (backend {self.backend}){hint}"
            )
        return capture

    def _reported_size(self, camera: str) -> tuple[int, int] | None:
        capture = self.captures[camera]
        w, h = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        return (w, h) if w > 0 and h > 0 else None

    def _describe_capture(self, camera: str) -> dict[str, Any]:
        capture = self.captures[camera]
        count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
        return {
            "source": self.specs[camera],
            "backend": capture.getBackendName(),
            "width": int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": float(capture.get(cv2.CAP_PROP_FPS)),
            "fourcc": _fourcc(capture.get(cv2.CAP_PROP_FOURCC)),
            "frame_count": int(count) if count > 0 else None,
        }

    # ---- reading -----------------------------------------------------------------------------

    def _grey16(self, camera: str, image: np.ndarray, index: int) -> np.ndarray:
        """The frame as (H, W) uint16, checked against the bit depth and the calibration."""
        where = f"{camera} source {self.specs[camera]!r}, frame {index}"
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        elif image.ndim == 3 and image.shape[2] in (3, 4):
            bgr = image[:, :, :3]
            if np.array_equal(bgr[:, :, 0], bgr[:, :, 1]) and np.array_equal(bgr[:, :, 0], bgr[:, :, 2]):
                image = bgr[:, :, 0]
            else:
                image = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2GRAY)
        if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
            raise ConfigError(
                f"{where}: unsupported frame (shape {image.shape}, {image.dtype}); "
                f"expected 8- or 16-bit grey or BGR"
            )
        natural = 8 if image.dtype == np.uint8 else 16
        if not self.bit_depth:
            self.bit_depth = natural
        elif self.bit_depth_option == 0 and natural != self.bit_depth:
            raise ConfigError(
                f"{where}: {natural}-bit frame, earlier frames were {self.bit_depth}-bit; "
                f"the two sources must deliver the same depth (or set the option 'bit_depth')"
            )
        if self.bit_depth < natural:
            peak = int(image.max())
            if peak >= 1 << self.bit_depth:
                raise ConfigError(
                    f"{where}: pixel value {peak} exceeds the {self.bit_depth}-bit range (option 'bit_depth')"
                )
        want = self.calibration.camera(camera).image_size
        if (image.shape[1], image.shape[0]) != tuple(want):
            raise ConfigError(
                f"{where}: frame is {image.shape[1]}x{image.shape[0]} px, the {camera} camera's calibration "
                f"({self.calibration.source}) is for {want[0]}x{want[1]} px"
            )
        return np.ascontiguousarray(image, dtype=np.uint16)

    def _read(self, camera: str, index: int, host_ns: int) -> _Read | None:
        ok, image = self.captures[camera].retrieve()
        if not ok or image is None:
            return None
        pos = float(self.captures[camera].get(cv2.CAP_PROP_POS_MSEC))
        return _Read(index, pos if pos >= 0 else -1.0, host_ns, self._grey16(camera, image, index))

    def frames(self) -> Iterator[StereoFrame]:
        """Yield pairs in read order: ``sequence`` = the upper source's frame index
        (a refused pair leaves a gap); ``timestamp_ns`` = host time of the first
        pair shifted by the upper frame's timestamp (or the host time of the
        grab when the sources give no timestamps)."""
        self.incidents.log = self.log
        heads: dict[str, _Read] = {}
        anchor_ns: int | None = None
        while not self._stop.is_set() and (not self.n_frames or self.pairs_delivered < self.n_frames):
            need = [c for c in CAMERAS if c not in heads]
            grabbed = {c: self.captures[c].grab() for c in need}  # grab both first, then decode
            host_ns = time.time_ns()
            for camera in need:
                read = self._read(camera, self.frames_read[camera], host_ns) if grabbed[camera] else None
                if read is None:
                    self._stream_ended(camera, heads, grabbed)
                    return
                self.frames_read[camera] += 1
                heads[camera] = read
            u, l = heads["upper"], heads["lower"]
            if self.timestamps_available is None:
                self.timestamps_available = u.pos_ms >= 0 and l.pos_ms >= 0
            if u.pos_ms >= 0 and l.pos_ms >= 0:
                skew_ms = u.pos_ms - l.pos_ms
                if abs(skew_ms) > self.max_skew_ms:
                    earlier = "upper" if skew_ms < 0 else "lower"
                    dropped = heads.pop(earlier)
                    self.incidents.add(
                        "skew", earlier, u.index,
                        f"upper frame {u.index} ({u.pos_ms:.3f} ms) and lower frame {l.index} "
                        f"({l.pos_ms:.3f} ms) are {skew_ms:+.3f} ms apart, more than max_skew_ms "
                        f"{self.max_skew_ms:g}; the earlier {earlier} frame {dropped.index} is dropped",
                    )
                    continue
            heads.clear()
            if u.pos_ms >= 0:
                if anchor_ns is None:
                    anchor_ns = u.host_ns - round(u.pos_ms * 1e6)
                timestamp_ns = anchor_ns + round(u.pos_ms * 1e6)
            else:
                timestamp_ns = u.host_ns
            self.pairs_delivered += 1
            yield StereoFrame(u.index, timestamp_ns, u.image, l.image, self.bit_depth)

    def _stream_ended(self, camera: str, heads: dict[str, _Read], grabbed: dict[str, bool]) -> None:
        other = "lower" if camera == "upper" else "upper"
        other_has_more = other in heads or bool(grabbed.get(other))
        if other_has_more:
            sequence = heads["upper"].index if "upper" in heads else self.frames_read["upper"]
            self.incidents.add(
                "stream_ended", camera, sequence,
                f"the {camera} source {self.specs[camera]!r} ended after {self.frames_read[camera]} frames "
                f"while the {other} source still delivers (read {self.frames_read[other]}); "
                f"acquisition stopped",
            )

    # ---- control and record ------------------------------------------------------------------

    def stop(self) -> None:
        """End :meth:`frames` before the next pair (callable from another thread)."""
        self._stop.set()

    def describe(self) -> dict[str, Any]:
        """Sources, depth, pairing and incidents so far (JSON-able)."""
        if self.timestamps_available is None:
            skew_check = "not known before the first pair"
        elif self.timestamps_available:
            skew_check = f"CAP_PROP_POS_MSEC, max_skew_ms {self.max_skew_ms:g}"
        else:
            skew_check = (
                "unavailable: a source gives no timestamps (CAP_PROP_POS_MSEC = -1); pairs by read order only"
            )
        return {
            "source": "opencv",
            "opencv": cv2.__version__,
            "backend_option": self.backend,
            "cameras": self._description,
            "bit_depth": self.bit_depth or None,
            "frames": self.n_frames,
            "max_skew_ms": self.max_skew_ms,
            "skew_check": skew_check,
            "calibration_files": list(self.calibration_files),
            "frames_read": dict(self.frames_read),
            "pairs_delivered": self.pairs_delivered,
            "incident_counts": self.incidents.counts(),
            "incidents": self.incidents.as_dicts(),
        }

    def close(self) -> None:
        """Release both sources (safe to call twice)."""
        self._stop.set()
        for capture in self.captures.values():
            capture.release()
        self.captures = {}


@hookimpl
def register_acquires(register: Register[Acquisition]) -> None:
    register(
        "opencv", OpenCVStereoSource,
        "Two OpenCV VideoCapture sources (devices, video files, image sequences)",
    )
