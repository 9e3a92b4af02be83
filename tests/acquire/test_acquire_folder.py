"""acquire "folder" and crossfield.camera.calibration_io: files written as OpenCV's stereo_calib.cpp does."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest

from crossfield.camera.calibration_io import (
    read_stereo_calibration,
    stereo_calibration_from_yaml,
    stereo_calibration_to_yaml,
    write_stereo_calibration,
)
from crossfield.errors import ConfigError
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.stages import Acquisition
from crossfield.types import CameraIntrinsics, StereoCalibration
from crossfield.plugins import acquire_folder

W, H = 64, 48  # small images keep the tests fast; the format does not care

M1 = np.array([[3636.2, 0.0, 812.7], [0.0, 3635.8, 617.1], [0.0, 0.0, 1.0]])
M2 = np.array([[3630.9, 0.0, 815.3], [0.0, 3631.4, 620.2], [0.0, 0.0, 1.0]])
D1 = np.array([[-0.0512, 0.0213, 1.1e-4, -2.3e-4, 0.0031, 0.0, 0.0, 0.0]])  # 1x8: CALIB_RATIONAL_MODEL
D2 = np.array([[-0.0487, 0.0178, -0.9e-4, 1.2e-4, 0.0027, 0.0, 0.0, 0.0]])
R = cv2.Rodrigues(np.array([2.1e-3, -3.2e-3, 0.8e-3]))[0]
T = np.array([[0.31], [-50.12], [0.22]])


def write_stereo_calib_files(folder, *, skip: str = "", R_value=R):
    """intrinsics.yml + extrinsics.yml exactly as samples/cpp/stereo_calib.cpp writes them."""
    fs = cv2.FileStorage(str(folder / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", M1), ("D1", D1), ("M2", M2), ("D2", D2)):
        if key != skip:
            fs.write(key, value)
    fs.release()
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(M1, D1, M2, D2, (1626, 1236), R, T)
    fs = cv2.FileStorage(str(folder / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("R", R_value), ("T", T), ("R1", R1), ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)):
        if key != skip:
            fs.write(key, value)
    fs.release()


def image(rng, bits=12, size=(W, H)) -> np.ndarray:
    return rng.integers(0, 1 << bits, size=(size[1], size[0]), dtype=np.uint16)


def write_pairs(folder, rng, sequences=(1, 2), name="{camera}_{seq:04d}.png"):
    written = {}
    for seq in sequences:
        for camera in ("upper", "lower"):
            img = image(rng)
            path = folder / name.format(camera=camera, seq=seq)
            assert cv2.imwrite(str(path), img)
            written[(camera, seq)] = img
    return written


def source(**options):
    pm = make_plugin_manager(builtins=False, extra=[acquire_folder])
    return get_implementation(pm, "acquire", "folder").create(options, where="test.toml: [acquire]")


def test_reads_stereo_calib_files_and_16_bit_png_pairs(tmp_path):
    rng = np.random.default_rng(1)
    write_stereo_calib_files(tmp_path)
    written = write_pairs(tmp_path, rng, sequences=(1, 2, 10))
    os.utime(tmp_path / "upper_0002.png", ns=(1_700_000_000_123_456_789, 1_700_000_000_123_456_789))
    (tmp_path / "notes.txt").write_text("ignored: does not match the pattern")

    src = source(path=str(tmp_path))
    assert isinstance(src, Acquisition)
    assert src.ground_truth is None and src.default_plan is None
    cal = src.calibration
    np.testing.assert_array_equal(cal.upper.camera_matrix, M1)
    np.testing.assert_array_equal(cal.lower.camera_matrix, M2)
    np.testing.assert_array_equal(cal.upper.dist_coeffs, D1.ravel())
    np.testing.assert_array_equal(cal.lower.dist_coeffs, D2.ravel())
    np.testing.assert_array_equal(cal.R_lower_upper, R)
    np.testing.assert_array_equal(cal.t_lower_upper, T.ravel())
    assert cal.upper.image_size == (W, H) == cal.lower.image_size  # from the images: stereo_calib stores none
    assert "intrinsics.yml" in cal.source and "extrinsics.yml" in cal.source

    frames = list(src.frames())
    assert [f.sequence for f in frames] == [1, 2, 10]
    for frame in frames:
        assert frame.bit_depth == 12
        for camera in ("upper", "lower"):
            got = frame.image(camera)
            assert got.dtype == np.uint16 and got.shape == (H, W)
            np.testing.assert_array_equal(got, written[(camera, frame.sequence)])
        assert frame.timestamp_ns == os.stat(tmp_path / f"upper_{frame.sequence:04d}.png").st_mtime_ns
    assert frames[1].timestamp_ns == 1_700_000_000_123_456_789
    described = json.loads(json.dumps(src.describe()))
    assert described["pairs"] == 3 and described["first_sequence"] == 1 and described["last_sequence"] == 10
    src.close()


def test_single_calibration_file_round_trip(tmp_path):
    calibration = StereoCalibration(
        CameraIntrinsics(M1, D1.ravel(), (1626, 1236)),
        CameraIntrinsics(M2, D2.ravel()[:5], (1626, 1236)),
        R,
        T.ravel(),
    )
    path = write_stereo_calibration(tmp_path / "calibration.yml", calibration)
    back = read_stereo_calibration(path)
    for camera in ("upper", "lower"):
        got, want = back.camera(camera), calibration.camera(camera)
        np.testing.assert_array_equal(got.camera_matrix, want.camera_matrix)
        np.testing.assert_array_equal(got.dist_coeffs, want.dist_coeffs)
        assert got.image_size == (1626, 1236)
    np.testing.assert_array_equal(back.R_lower_upper, R)
    np.testing.assert_array_equal(back.t_lower_upper, T.ravel())
    # The stereo_calib.cpp extras are written for other tools and match cv2.stereoRectify.
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    expected_P2 = cv2.stereoRectify(M1, D1, M2, D2[:, :5], (1626, 1236), R, T, flags=cv2.CALIB_ZERO_DISPARITY,
                                    alpha=-1)[3]
    np.testing.assert_allclose(fs.getNode("P2").mat(), expected_P2)
    fs.release()
    # In-memory text (for recording attachments) reads back the same.
    text = stereo_calibration_to_yaml(calibration)
    again = stereo_calibration_from_yaml(text, "attachment calibration.yml")
    np.testing.assert_array_equal(again.upper.camera_matrix, M1)
    np.testing.assert_array_equal(again.t_lower_upper, T.ravel())


def test_cameras_of_different_sizes_round_trip(tmp_path):
    calibration = StereoCalibration(
        CameraIntrinsics(M1, D1.ravel(), (1626, 1236)),
        CameraIntrinsics(M2, D2.ravel(), (1600, 1200)),
        R,
        T.ravel(),
    )
    path = write_stereo_calibration(tmp_path / "c.yml", calibration, rectification=False)
    back = read_stereo_calibration(path)
    assert back.upper.image_size == (1626, 1236) and back.lower.image_size == (1600, 1200)


def test_opencv4_yaml_header_is_read(tmp_path):
    """Files from OpenCV 4.x start with '%YAML:1.0'."""
    text = stereo_calibration_to_yaml(
        StereoCalibration(CameraIntrinsics(M1, D1.ravel(), (W, H)), CameraIntrinsics(M2, D2.ravel(), (W, H)),
                          R, T.ravel()),
        rectification=False,
    )
    lines = text.splitlines()
    assert lines[0].startswith("%YAML")
    path = tmp_path / "calibration.yml"
    path.write_text("\n".join(["%YAML:1.0"] + lines[1:]) + "\n")
    np.testing.assert_array_equal(read_stereo_calibration(path).R_lower_upper, R)


def test_tiff_files_with_a_custom_pattern_and_calibration_list(tmp_path):
    rng = np.random.default_rng(2)
    calib = tmp_path / "calib"
    calib.mkdir()
    write_stereo_calib_files(calib)
    written = write_pairs(tmp_path, rng, sequences=(7,), name="run3-{camera}-{seq}.tif")
    src = source(path=str(tmp_path), pattern="run*-{camera}-{seq}.tif",
                 calibration=["calib/intrinsics.yml", str(calib / "extrinsics.yml")])
    (frame,) = list(src.frames())
    assert frame.sequence == 7
    np.testing.assert_array_equal(frame.lower, written[("lower", 7)])


def test_8_bit_images_are_accepted_for_bit_depth_8(tmp_path):
    write_stereo_calib_files(tmp_path)
    img = np.random.default_rng(3).integers(0, 256, (H, W), dtype=np.uint8)
    for camera in ("upper", "lower"):
        cv2.imwrite(str(tmp_path / f"{camera}_1.png"), img)
    (frame,) = list(source(path=str(tmp_path), bit_depth=8).frames())
    assert frame.upper.dtype == np.uint16 and frame.bit_depth == 8
    np.testing.assert_array_equal(frame.upper, img)


# ---------------------------------------------------------------------------------------------------
# Errors name the file (and key)
# ---------------------------------------------------------------------------------------------------


def test_missing_pair_partner_names_the_file(tmp_path):
    rng = np.random.default_rng(4)
    write_stereo_calib_files(tmp_path)
    write_pairs(tmp_path, rng, sequences=(1,))
    cv2.imwrite(str(tmp_path / "upper_0003.png"), image(rng))
    with pytest.raises(ConfigError, match=r"upper_0003\.png: no lower image .*lower_0003\.png"):
        source(path=str(tmp_path))


def test_unreadable_image_names_the_file(tmp_path):
    rng = np.random.default_rng(5)
    write_stereo_calib_files(tmp_path)
    write_pairs(tmp_path, rng)
    (tmp_path / "lower_0002.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a PNG")
    frames = source(path=str(tmp_path)).frames()
    assert next(frames).sequence == 1
    with pytest.raises(ConfigError, match=r"lower_0002\.png: unreadable image"):
        next(frames)


def test_wrong_image_size_names_the_file(tmp_path):
    rng = np.random.default_rng(6)
    write_stereo_calib_files(tmp_path)
    write_pairs(tmp_path, rng)
    cv2.imwrite(str(tmp_path / "upper_0002.png"), image(rng, size=(W + 2, H)))
    with pytest.raises(ConfigError, match=rf"upper_0002\.png: image is {W + 2}x{H} px.*{W}x{H} px"):
        list(source(path=str(tmp_path)).frames())


def test_image_size_must_match_a_calibration_that_states_it(tmp_path):
    rng = np.random.default_rng(7)
    write_pairs(tmp_path, rng, sequences=(1,))
    calibration = StereoCalibration(
        CameraIntrinsics(M1, D1.ravel(), (1626, 1236)),
        CameraIntrinsics(M2, D2.ravel(), (1626, 1236)),
        R,
        T.ravel(),
    )
    write_stereo_calibration(tmp_path / "calibration.yml", calibration)
    with pytest.raises(ConfigError, match=rf"upper_0001\.png: image is {W}x{H} px.*1626x1236 px"):
        list(source(path=str(tmp_path)).frames())


@pytest.mark.parametrize(
    "img, bit_depth, message",
    [
        (np.zeros((H, W), np.uint8), 12, r"lower_0001\.png: expected 16-bit unsigned pixels .* got uint8"),
        (np.zeros((H, W, 3), np.uint16), 12, r"lower_0001\.png: expected a single-channel"),
        (np.full((H, W), 5000, np.uint16), 12, r"lower_0001\.png: pixel value 5000 exceeds the 12-bit range"),
    ],
)
def test_wrong_pixel_format_names_the_file(tmp_path, img, bit_depth, message):
    write_stereo_calib_files(tmp_path)
    cv2.imwrite(str(tmp_path / "upper_0001.png"), image(np.random.default_rng(8)))
    cv2.imwrite(str(tmp_path / "lower_0001.png"), img)
    with pytest.raises(ConfigError, match=message):
        list(source(path=str(tmp_path), bit_depth=bit_depth).frames())


@pytest.mark.parametrize("key", ["M1", "D2", "R", "T"])
def test_missing_calibration_key_names_key_and_file(tmp_path, key):
    write_stereo_calib_files(tmp_path, skip=key)
    write_pairs(tmp_path, np.random.default_rng(9), sequences=(1,))
    message = rf"intrinsics\.yml, .*extrinsics\.yml: calibration key '{key}' is missing"
    with pytest.raises(ConfigError, match=message):
        source(path=str(tmp_path))


def test_bad_calibration_values_name_key_and_file(tmp_path):
    write_pairs(tmp_path, np.random.default_rng(10), sequences=(1,))
    write_stereo_calib_files(tmp_path, R_value=np.diag([1.0, 1.0, -1.0]))  # a reflection
    with pytest.raises(ConfigError, match=r"extrinsics\.yml: calibration key .R. is not a rotation .*-1"):
        source(path=str(tmp_path))
    write_stereo_calib_files(tmp_path)  # good R again; now a 6-element D1
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", M1), fs.write("D1", np.zeros((1, 6))), fs.write("M2", M2), fs.write("D2", D2)
    fs.release()
    with pytest.raises(ConfigError, match=r"intrinsics\.yml: calibration key 'D1' must be .* shape \(1, 6\)"):
        source(path=str(tmp_path))
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", 3.0), fs.write("D1", D1), fs.write("M2", M2), fs.write("D2", D2)
    fs.release()
    with pytest.raises(ConfigError, match=r"intrinsics\.yml: calibration key 'M1' is not an OpenCV matrix"):
        source(path=str(tmp_path))


def test_calibration_file_problems_name_the_file(tmp_path):
    write_pairs(tmp_path, np.random.default_rng(11), sequences=(1,))
    with pytest.raises(ConfigError, match=r"no calibration given and none found .*intrinsics\.yml \+ extr"):
        source(path=str(tmp_path))
    with pytest.raises(ConfigError, match=r"nope\.yml: calibration file not found"):
        source(path=str(tmp_path), calibration="nope.yml")
    (tmp_path / "broken.yml").write_text("%YAML:1.0\nM1: [1, 2\n")
    with pytest.raises(ConfigError, match=r"broken\.yml: not a readable OpenCV FileStorage"):
        source(path=str(tmp_path), calibration="broken.yml")


def test_folder_and_option_problems(tmp_path):
    with pytest.raises(ConfigError, match="image folder not found"):
        source(path=str(tmp_path / "missing"))
    with pytest.raises(ConfigError, match=r"no image files match the pattern '\{camera\}_\{seq\}\.png'"):
        source(path=str(tmp_path))
    with pytest.raises(ConfigError, match=r"test\.toml: \[acquire\]: .*'pattern' must contain \{seq\}"):
        source(path=str(tmp_path), pattern="{camera}.png")
    with pytest.raises(ConfigError, match="option 'bit_depth'"):
        source(path=str(tmp_path), bit_depth=20)
    rng = np.random.default_rng(12)
    write_pairs(tmp_path, rng, sequences=(1,))
    cv2.imwrite(str(tmp_path / "upper_1.png"), image(rng))
    message = r"upper_1\.png: same camera and sequence number \(upper, 1\) as .*upper_0001"
    with pytest.raises(ConfigError, match=message):
        source(path=str(tmp_path))
