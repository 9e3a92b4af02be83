"""acquire "opencv": two VideoCapture sources over files written with cv2.VideoWriter / cv2.imwrite."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from crossfield.camera.calibration_io import write_stereo_calibration
from crossfield.errors import ConfigError
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.types import CameraIntrinsics, StereoCalibration
from crossfield.plugins.acquire_opencv import OpenCVStereoSource
from crossfield.plugins.acquire_simulator import SimulatorSource

SMALL = (160, 120)  # width, height of the synthetic videos


def small_calibration(path: Path) -> Path:
    K = np.array([[400.0, 0, 79.5], [0, 400.0, 59.5], [0, 0, 1]])
    intr = CameraIntrinsics(K, np.zeros(5), SMALL)
    calibration = StereoCalibration(intr, intr, np.eye(3), np.array([0.0, -50.0, 0.0]))
    return write_stereo_calibration(path, calibration)


def write_ffv1(path: Path, images: list[np.ndarray], fps: float, color: bool = False) -> Path:
    """Lossless FFV1 in Matroska; 16-bit grey (gray16le) for uint16 input."""
    h, w = images[0].shape[:2]
    params = [cv2.VIDEOWRITER_PROP_IS_COLOR, int(color)]
    if images[0].dtype == np.uint16:
        params += [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U]
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h), params)
    assert writer.isOpened(), "OpenCV's FFmpeg backend cannot write FFV1"
    for image in images:
        writer.write(image)
    writer.release()
    return path


def numbered(n: int, seed: int, bits: int = 12) -> list[np.ndarray]:
    """n random images; pixel (0, 0) holds the frame number."""
    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 1 << bits, size=SMALL[::-1], dtype=np.uint16) for _ in range(n)]
    for k, image in enumerate(images):
        image[0, 0] = k
    return images


@pytest.fixture(scope="module")
def station_videos(tmp_path_factory):
    """The simulator's station frames as 16-bit FFV1 videos at the camera's 14 Hz."""
    root = tmp_path_factory.mktemp("videos")
    simulator = SimulatorSource(scenario="station", frames=3, seed=3)
    frames = list(simulator.frames())
    for camera in ("upper", "lower"):
        write_ffv1(root / f"{camera}.mkv", [f.image(camera) for f in frames], fps=14.0)
    write_stereo_calibration(root / "calibration.yml", simulator.calibration)
    return root, frames


def test_ffv1_videos_deliver_the_simulator_frames_bit_exact(station_videos):
    root, frames = station_videos
    source = OpenCVStereoSource(
        upper=str(root / "upper.mkv"), lower=str(root / "lower.mkv"),
        calibration=str(root / "calibration.yml"), bit_depth=12,
    )
    try:
        got = list(source.frames())
        info = source.describe()
    finally:
        source.close()
    assert [f.sequence for f in got] == [0, 1, 2]
    for pair, truth in zip(got, frames):
        assert pair.bit_depth == 12 and pair.upper.dtype == np.uint16
        np.testing.assert_array_equal(pair.upper, truth.upper)
        np.testing.assert_array_equal(pair.lower, truth.lower)
    # timestamps follow the stream's presentation times (Matroska stores ms)
    assert np.diff([p.timestamp_ns for p in got]) / 1e6 == pytest.approx([71.0, 72.0], abs=1.0)
    upper = info["cameras"]["upper"]
    assert upper["backend"] == "FFMPEG" and upper["fourcc"].upper() == "FFV1"
    assert info["skew_check"].startswith("CAP_PROP_POS_MSEC")
    assert info["incidents"] == [] and info["pairs_delivered"] == 3


def test_image_sequence_pattern_is_read_unchanged_without_a_skew_check(tmp_path):
    upper, lower = numbered(4, 1), numbered(4, 2)
    for camera, images in (("upper", upper), ("lower", lower)):
        (tmp_path / camera).mkdir()
        for k, image in enumerate(images):
            cv2.imwrite(str(tmp_path / camera / f"img_{k:04d}.png"), image)
    source = OpenCVStereoSource(
        upper=str(tmp_path / "upper" / "img_%04d.png"), lower=str(tmp_path / "lower" / "img_%04d.png"),
        calibration=str(small_calibration(tmp_path / "cal.yml")), frames=3,  # backend "any" picks CAP_IMAGES
    )
    try:
        got = list(source.frames())
        info = source.describe()
    finally:
        source.close()
    assert [p.sequence for p in got] == [0, 1, 2]  # frames = 3 of the 4
    for p in got:
        np.testing.assert_array_equal(p.upper, upper[p.sequence])
        np.testing.assert_array_equal(p.lower, lower[p.sequence])
        assert p.bit_depth == 16  # bit_depth 0: taken from the 16-bit frames
    assert info["skew_check"].startswith("unavailable")
    assert info["cameras"]["upper"]["backend"] == "CV_IMAGES"


def test_skewed_streams_resynchronise_on_timestamps(tmp_path):
    """Upper at 14 Hz, lower at 7 Hz: every other upper frame has a partner at the same time."""
    upper, lower = numbered(8, 3), numbered(4, 4)
    source = OpenCVStereoSource(
        upper=str(write_ffv1(tmp_path / "u.mkv", upper, 14.0)),
        lower=str(write_ffv1(tmp_path / "l.mkv", lower, 7.0)),
        calibration=str(small_calibration(tmp_path / "cal.yml")), max_skew_ms=20.0,
    )
    try:
        got = list(source.frames())
        info = source.describe()
    finally:
        source.close()
    assert [p.sequence for p in got] == [0, 2, 4, 6]
    for k, p in enumerate(got):
        assert (int(p.upper[0, 0]), int(p.lower[0, 0])) == (p.sequence, k)
        np.testing.assert_array_equal(p.lower, lower[k])
    kinds = [(i["kind"], i["camera"], i["sequence"]) for i in info["incidents"]]
    assert kinds == [
        ("skew", "upper", 1), ("skew", "upper", 3), ("skew", "upper", 5), ("stream_ended", "lower", 7),
    ]
    message = info["incidents"][0]["message"]
    assert "(71.000 ms) and lower frame 1 (143.000 ms) are -72.000 ms apart" in message


def test_a_shorter_stream_ends_the_session_with_an_incident(tmp_path):
    calibration = str(small_calibration(tmp_path / "cal.yml"))
    source = OpenCVStereoSource(
        upper=str(write_ffv1(tmp_path / "u.mkv", numbered(5, 5), 14.0)),
        lower=str(write_ffv1(tmp_path / "l.mkv", numbered(3, 6), 14.0)),
        calibration=calibration,
    )
    logged = []
    source.log = lambda **kw: logged.append(kw)
    try:
        got = list(source.frames())
    finally:
        source.close()
    assert [p.sequence for p in got] == [0, 1, 2]
    assert [i.kind for i in source.incidents] == ["stream_ended"]
    assert "ended after 3 frames" in logged[0]["message"]


def test_grey_material_decoded_as_bgr_is_taken_exactly(tmp_path):
    grey = [(image >> 4).astype(np.uint8) for image in numbered(2, 7)]
    bgr = [cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) for g in grey]
    path = str(write_ffv1(tmp_path / "c.mkv", bgr, 14.0, color=True))
    calibration = str(small_calibration(tmp_path / "cal.yml"))
    source = OpenCVStereoSource(upper=path, lower=path, calibration=calibration)
    try:
        got = list(source.frames())
    finally:
        source.close()
    assert len(got) == 2 and got[0].bit_depth == 8
    np.testing.assert_array_equal(got[1].upper, grey[1])


def test_errors_name_the_source_and_frame(tmp_path, station_videos):
    root, _ = station_videos
    with pytest.raises(ConfigError, match=r"option 'lower': OpenCV cannot open .*nope.mkv.*file not found"):
        OpenCVStereoSource(upper=str(root / "upper.mkv"), lower=str(tmp_path / "nope.mkv"),
                           calibration=str(root / "calibration.yml"))
    with pytest.raises(ConfigError, match=r"'upper'.* delivers 1626x1236 px, the upper camera's .* 160x120"):
        OpenCVStereoSource(upper=str(root / "upper.mkv"), lower=str(root / "lower.mkv"),
                           calibration=str(small_calibration(tmp_path / "cal.yml")))
    source = OpenCVStereoSource(upper=str(root / "upper.mkv"), lower=str(root / "lower.mkv"),
                                calibration=str(root / "calibration.yml"), bit_depth=8)
    try:
        with pytest.raises(ConfigError, match=r"upper source .*upper.mkv', frame 0: pixel value \d+ exceeds"):
            next(source.frames())
    finally:
        source.close()
    with pytest.raises(ValueError, match="option 'backend'"):
        OpenCVStereoSource(upper=0, lower=1, calibration="c.yml", backend="dshow")


def test_opencv_source_is_registered():
    impl = get_implementation(make_plugin_manager(), "acquire", "opencv")
    assert impl.factory is OpenCVStereoSource
    assert set(impl.options()) >= {"upper", "lower", "calibration", "frames", "max_skew_ms"}
