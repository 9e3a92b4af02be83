"""Stereo calibration against the simulator's truth (docs/calibration.md).

The default session (20 simulated ChArUco pairs of the station rig) is
rendered once per test process (``cached_calibration_views``) and shared by
the solver tests, the YAML tests and the end-to-end CLI test.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.calibration.boards import Board, board_from_dict, board_toml, load_board
from crossfield.calibration.detect import BoardDetection, BoardDetector
from crossfield.calibration.file import read_calibration_uncertainty, write_calibration_result
from crossfield.calibration.report import report_dict, write_report
from crossfield.calibration.solve import (
    CalibrationError,
    CalibrationSettings,
    calibrate_images,
    check_mirrored,
    detect_views,
    solve_stereo,
)
from crossfield.camera.calibration_io import read_stereo_calibration
from crossfield.cli import main
from crossfield.errors import ConfigError
from crossfield.simulator.board_views import (
    board_texture,
    cached_calibration_views,
    render_board,
    render_calibration_views,
)
from crossfield.simulator.optics import project
from crossfield.simulator.render import SensorModel
from crossfield.simulator.scenarios import station_calibration


def truth_vector(calibration) -> np.ndarray:
    """The true parameters in the solver's order (fx fy cx cy k1..k3 per camera, rvec, T)."""
    out = []
    for cam in (calibration.upper, calibration.lower):
        K = np.asarray(cam.camera_matrix)
        out += [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(cam.dist_coeffs)[:5]]
    out += [*cv2.Rodrigues(np.asarray(calibration.R_lower_upper))[0].ravel(), *calibration.t_lower_upper]
    return np.array(out)


@pytest.fixture(scope="module")
def station_views():
    return cached_calibration_views("station", 20, 1)


@pytest.fixture(scope="module")
def station_result(station_views):
    v = station_views
    return calibrate_images(v.images, v.board, v.bit_depth)


# ---- board definition --------------------------------------------------------------------------------


def test_board_toml_round_trip_and_errors(tmp_path):
    board = Board(type="chessboard", squares_x=9, squares_y=6, square_mm=12.5, marker_mm=0, dictionary="")
    path = tmp_path / "board.toml"
    path.write_text(board_toml(board))
    loaded = load_board(path)
    assert (loaded.type, loaded.squares_x, loaded.squares_y, loaded.square_mm) == ("chessboard", 9, 6, 12.5)
    assert loaded.object_points().shape == (8 * 5, 3)
    (tmp_path / "bad.toml").write_text(
        '[board]\ntype = "charuco"\nsquares_x = 11\nsquares_y = 8\nsquare_mm = 15.0\nmarker_mm = 16.0\n'
    )
    with pytest.raises(ConfigError, match=r"bad.toml: \[board\] marker_mm .* must be < square_mm"):
        load_board(tmp_path / "bad.toml")
    with pytest.raises(ConfigError, match=r"\[board\] square_mm is missing"):
        board_from_dict({"type": "chessboard", "squares_x": 9, "squares_y": 6}, "b.toml")
    with pytest.raises(ConfigError, match="looks the same after a half turn"):
        board_from_dict({"type": "chessboard", "squares_x": 8, "squares_y": 6, "square_mm": 10.0}, "b.toml")
    with pytest.raises(ConfigError, match="unknown key 'squares'"):
        board_from_dict({"type": "chessboard", "squares": 9}, "b.toml")
    with pytest.raises(ConfigError, match="not an OpenCV predefined dictionary"):
        board_from_dict(
            {"squares_x": 5, "squares_y": 5, "square_mm": 10, "marker_mm": 7, "dictionary": "DICT_9X9"}
        )


def test_charuco_object_points_match_opencv():
    board = Board()
    np.testing.assert_allclose(board.object_points(), board.charuco_board().getChessboardCorners(), atol=1e-5)


# ---- detection -------------------------------------------------------------------------------------


def _truth_pixels(views, k, camera, detection):
    pose, cal = views.poses[k], views.calibration
    X = detection.object_points @ pose.R.T + pose.t
    if camera == "lower":
        X = X @ np.asarray(cal.R_lower_upper).T + cal.t_lower_upper
    return project(X, cal.camera(camera))


def test_partial_charuco_views_are_detected_accurately(station_views):
    """Views with the board partly outside the image still give their visible corners, at the true place."""
    v = station_views
    detector = BoardDetector(v.board)
    partial = 0
    for k in range(6):
        for cam in ("upper", "lower"):
            d = detector.detect(v.images[k][cam], v.bit_depth)
            assert d is not None
            err = np.linalg.norm(d.image_points - _truth_pixels(v, k, cam, d), axis=1)
            assert np.median(err) < 0.05 and err.max() < 0.2, (k, cam, err.max())
            partial += len(d) < v.board.n_points
    assert partial >= 6  # most of these views show part of the board only


@pytest.mark.parametrize("kind", ["chessboard", "circles"])
def test_chessboard_and_circle_grid_detection(kind):
    """Small chessboard / asymmetric circle grid, whole in view: every point found at the truth."""
    if kind == "chessboard":
        board = board_from_dict({"type": "chessboard", "squares_x": 9, "squares_y": 6, "square_mm": 12.0})
    else:
        board = board_from_dict(
            {"type": "circles", "circles_x": 4, "circles_y": 7, "spacing_mm": 10.0, "diameter_mm": 8.0}
        )
    cal = station_calibration()
    R = Rotation.from_rotvec([0.25, -0.2, 0.1]).as_matrix()
    w, h = board.extent_mm
    t = np.array([0.0, 20.0, 400.0]) - R @ np.array([w / 2, h / 2, 0.0])
    image = render_board(
        board_texture(board), R, t, cal.upper, SensorModel(), np.random.default_rng(3), supersample=3
    )
    d = BoardDetector(board).detect(image, 12)
    assert d is not None and len(d) == board.n_points
    err = np.linalg.norm(d.image_points - project(d.object_points @ R.T + t, cal.upper), axis=1)
    # Circle centres carry the perspective bias of an ellipse's centre (hence the looser bound).
    assert err.max() < (0.1 if kind == "chessboard" else 0.3)
    assert d.orientation() == 1.0


# ---- solving -------------------------------------------------------------------------------------------


def test_default_scenario_recovers_the_rig(station_views, station_result):
    r, truth = station_result, station_views.calibration
    assert r.rms_stereo_px < 0.06
    assert abs(r.baseline_mm - np.linalg.norm(truth.t_lower_upper)) < 0.01
    z = (r.params - truth_vector(truth)) / r.std
    assert np.all(np.abs(z) < 4), dict(zip(r.param_names, z.round(2)))
    assert not [d for d in r.dropped if d.stage not in ("detect",)]
    # Held-out pairs: the lower points lie on their epipolar lines to the corner noise.
    assert r.held_out and all(rms < 0.05 for rms, _ in r.holdout_epipolar_px.values())
    assert np.all(r.uncertainty_sigma_mm > 0) and np.all(r.uncertainty_sigma_mm < 0.5)


def test_standard_deviations_cover_the_truth():
    """Over independent sessions the errors / reported std are ~N(0, 1): coverage, not a single case."""
    z = []
    for seed in (2, 3, 4):
        v = render_calibration_views(n_views=10, seed=seed, layout_seed=100 + seed)
        r = calibrate_images(v.images, v.board, v.bit_depth)
        z.append((r.params - truth_vector(v.calibration)) / r.std)
    z = np.abs(np.concatenate(z))
    assert len(z) == 72
    # 68 % and 95 % expected; the bounds allow for the strong correlations within a session (k1 k2 k3).
    assert np.mean(z < 1) > 0.5
    assert np.mean(z < 2) > 0.85
    assert z.max() < 4.5


def test_outlier_view_is_dropped_with_its_reason(station_views, station_result):
    """The board moves 0.5 mm between the two exposures of view 5: that view is dropped, the rest stands."""
    v = station_views
    pose = v.poses[5]
    dR = Rotation.from_rotvec([0.0007, -0.0005, 0.0004]).as_matrix()
    R_u, t_u = dR @ pose.R, dR @ pose.t + np.array([0.45, -0.3, 0.25])
    cal = v.calibration
    R_lu, t_lu = np.asarray(cal.R_lower_upper), np.asarray(cal.t_lower_upper)
    moved = render_board(
        board_texture(v.board),
        R_lu @ R_u,
        R_lu @ t_u + t_lu,
        cal.lower,
        SensorModel(),
        np.random.default_rng(9),
        illumination_seed=12,
    )
    images = list(v.images)
    images[5] = {"upper": images[5]["upper"], "lower": moved}
    r = calibrate_images(images, v.board, v.bit_depth)
    dropped = [d for d in r.dropped if d.view == 5]
    assert [d.stage for d in dropped] == ["stereo"]
    assert "stereo RMS reprojection error" in dropped[0].reason
    assert 5 not in r.used_stereo
    assert abs(r.baseline_mm - np.linalg.norm(cal.t_lower_upper)) < 0.01
    data = report_dict(r)
    assert data["dropped"][0]["view"] == 5 and data["views"][5]["status"] == "dropped"


def test_too_few_views_are_refused(station_views):
    v = station_views
    with pytest.raises(CalibrationError, match=r"too few views for the upper camera: 4 usable, at least 6"):
        calibrate_images(v.images[:4], v.board, v.bit_depth, CalibrationSettings(holdout_every=0))


def test_mirrored_images_are_refused(station_views):
    v = station_views
    images = [
        {"upper": view["upper"], "lower": np.ascontiguousarray(view["lower"][:, ::-1])}
        for view in v.images[:8]
    ]
    with pytest.raises(
        CalibrationError, match=r"the lower camera's images are mirrored.*flipping them left-right"
    ):
        calibrate_images(images, v.board, v.bit_depth)


def test_reflected_detections_are_refused(station_views):
    """Points whose board-to-image map reverses orientation (a reflected read-out) refuse that camera."""
    v = station_views
    detections = detect_views(v.images[:6], v.board, v.bit_depth)
    width = v.calibration.upper.image_size[0]
    reflected = []
    for view in detections:
        d = view["upper"]
        flipped = BoardDetection(
            d.ids, np.column_stack([width - 1 - d.image_points[:, 0], d.image_points[:, 1]]), d.object_points
        )
        assert d.orientation() == 1.0 and flipped.orientation() == -1.0
        reflected.append({"upper": flipped, "lower": view["lower"]})
    with pytest.raises(
        CalibrationError,
        match=r"the upper camera's images are mirrored: the board appears reflected "
        r"in 6 of 6 views",
    ):
        check_mirrored(reflected, None, v.board, v.bit_depth, 6)
    check_mirrored(detections, None, v.board, v.bit_depth, 6)  # the real views pass


def test_rational_model_is_offered(station_views):
    v = station_views
    detections = detect_views(v.images, v.board, v.bit_depth)
    r = solve_stereo(
        detections,
        {c: v.calibration.camera(c).image_size for c in ("upper", "lower")},
        v.board,
        CalibrationSettings(distortion="rational"),
    )
    assert len(r.calibration.upper.dist_coeffs) == 8 and len(r.param_names) == 2 * 12 + 6
    assert abs(r.baseline_mm - np.linalg.norm(v.calibration.t_lower_upper)) < 0.02


# ---- files -----------------------------------------------------------------------------------------


def test_yaml_has_stereo_calib_keys_and_std(tmp_path, station_result):
    path = write_calibration_result(tmp_path / "calib.yml", station_result)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    c = station_result.calibration
    for key, want in (
        ("M1", c.upper.camera_matrix),
        ("D1", c.upper.dist_coeffs),
        ("M2", c.lower.camera_matrix),
        ("D2", c.lower.dist_coeffs),
        ("R", c.R_lower_upper),
        ("T", c.t_lower_upper),
    ):
        np.testing.assert_allclose(fs.getNode(key).mat().reshape(np.shape(want)), want, rtol=1e-15)
    for key in ("R1", "R2", "P1", "P2", "Q"):
        assert fs.getNode(key).mat().shape in ((3, 3), (3, 4), (4, 4))
    assert int(fs.getNode("image_width").real()) == 1626
    np.testing.assert_allclose(fs.getNode("std_T").mat().ravel(), station_result.std[-3:])
    fs.release()
    unc = read_calibration_uncertainty(path)
    assert unc.names == station_result.param_names
    np.testing.assert_allclose(unc.covariance, station_result.covariance)
    back = read_stereo_calibration(path)
    np.testing.assert_allclose(back.t_lower_upper, c.t_lower_upper)


def test_yaml_written_like_stereo_calib_sample_loads(tmp_path, station_result):
    """samples/cpp/stereo_calib.cpp writes intrinsics.yml (M1 D1 M2 D2) and extrinsics.yml (R T R1 R2 P1 P2 Q)."""
    c = station_result.calibration
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (
        ("M1", c.upper.camera_matrix),
        ("D1", c.upper.dist_coeffs.reshape(1, -1)),
        ("M2", c.lower.camera_matrix),
        ("D2", c.lower.dist_coeffs.reshape(1, -1)),
    ):
        fs.write(key, np.asarray(value))
    fs.release()
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
        c.upper.camera_matrix,
        c.upper.dist_coeffs,
        c.lower.camera_matrix,
        c.lower.dist_coeffs,
        (1626, 1236),
        c.R_lower_upper,
        c.t_lower_upper.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=-1,
    )
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (
        ("R", c.R_lower_upper),
        ("T", c.t_lower_upper.reshape(3, 1)),
        ("R1", R1),
        ("R2", R2),
        ("P1", P1),
        ("P2", P2),
        ("Q", Q),
    ):
        fs.write(key, np.asarray(value))
    fs.release()
    back = read_stereo_calibration(
        [tmp_path / "intrinsics.yml", tmp_path / "extrinsics.yml"], image_sizes=((1626, 1236), (1626, 1236))
    )
    np.testing.assert_allclose(back.lower.camera_matrix, c.lower.camera_matrix)
    np.testing.assert_allclose(back.R_lower_upper, c.R_lower_upper)
    assert read_calibration_uncertainty(tmp_path / "extrinsics.yml") is None


def test_report_json_and_html(tmp_path, station_result):
    json_path, html_path = write_report(station_result, tmp_path / "calib-report")
    data = json.loads(json_path.read_text())
    assert set(data["rms_px"]) == {"upper", "lower", "stereo"}
    assert len(data["views"]) == 20 and {v["status"] for v in data["views"]} <= {
        "used",
        "held out",
        "dropped",
    }
    assert data["coverage"]["upper"] > 0.7
    assert data["uncertainty_3d"]["length"]["pairs"] > 0
    text = html_path.read_text()
    # coverage and residual map per camera (no cross-validation plot: not asked for)
    assert text.count("data:image/png;base64,") == 4 and "Held-out views" in text
    # issue 27 item 7: the shared record header, the board as a table (no JSON)
    assert 'id="record-header"' in text and 'id="record-date"' in text and 'id="seal-chain-head"' in text
    assert 'id="board"' in text and "{&#34;" not in text and '{"' not in text
    assert f"<th>squares x</th><td>{station_result.board.squares_x}</td>" in text


# ---- end to end ------------------------------------------------------------------------------------


def test_calibrate_then_run_table3_then_verify(tmp_path, capsys):
    """Issue 10, "What it must show": calibrate --scenario station -> YAML -> run table3 with it:
    every |error| < 0.1 mm and within its U, U carrying the calibration's own parameter
    uncertainty (the YAML's std keys, not the stated default); then verify passes with it.
    The 20 views are the ones the solver tests render (cached), one stereo pair per session."""
    calib = tmp_path / "calib.yml"
    assert main(["calibrate", "--scenario", "station", "-o", str(calib)]) == 0
    assert "baseline |T|" in capsys.readouterr().out
    assert (tmp_path / "calib-report.html").is_file()
    code = main(
        [
            "run",
            "--scenario",
            "table3",
            "--frames",
            "1",
            "--option",
            f"acquire.calibration={json.dumps(str(calib))}",
            "-o",
            str(tmp_path / "runs"),
            "--name",
            "t3",
            "--no-record",
            "--no-rerun",
            "-q",
        ]
    )
    capsys.readouterr()
    report = json.loads((tmp_path / "runs" / "t3" / "report.json").read_text())
    assert report["acquisition"]["calibration_file"] == str(calib)
    characteristics = report["characteristics"]
    assert len(characteristics) == 10
    for c in characteristics:
        assert abs(c["error_mm"]) < 0.1 and abs(c["error_mm"]) <= c["expanded_uncertainty_mm"], c["name"]
    assert code == 0
    # U includes the calibration's parameter uncertainty, read from the std keys calibrate wrote:
    # u(s)^2 = (u(|T|)/|T|)^2 + sum over the cameras (u(fx)/fx)^2 / 2 (pipeline/uncertainty/calibration.py),
    # here recomputed from the calibration report's parameters and their standard deviations.
    unc = report["uncertainty"]
    # the file states every std_* key: its parameters are propagated into each characteristic
    # (crossfield.uncertainty.calibration.calibration_contributions); the scale is still reported
    assert unc["calibration_scale_u_source"].startswith("propagated parameters") and "cov_params" in unc[
        "calibration_scale_u_source"]
    params = {p["name"]: p for p in json.loads((tmp_path / "calib-report.json").read_text())["parameters"]}
    T = np.array([params[f"rig.T{c}"]["value"] for c in "xyz"])
    u_T = np.array([params[f"rig.T{c}"]["std"] for c in "xyz"])
    n = np.linalg.norm(T)
    terms = [np.sqrt(np.sum((T / n * u_T) ** 2)) / n]
    terms += [params[f"{cam}.fx"]["std"] / params[f"{cam}.fx"]["value"] / np.sqrt(2) for cam in ("upper", "lower")]
    assert unc["calibration_scale_u"] == pytest.approx(np.sqrt(np.sum(np.square(terms))), rel=1e-6)
    for c in characteristics:
        budget = {t["source"]: t for t in c["budget"]}
        assert budget["calibration"]["unit"] == "mm" and budget["calibration"]["u_mm"] > 0
        u_c = np.sqrt(sum(t["u_mm"] ** 2 for t in c["budget"]))
        assert c["expanded_uncertainty_mm"] == pytest.approx(c["coverage_factor"] * u_c, rel=1e-9)
    out = tmp_path / "verification"
    assert (
        main(
            ["verify", "--scenario", "station", "--calibration", str(calib), "-o", str(out), "--frames", "1"]
        )
        == 0
    )
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["passed"] and len(data["positions"]) >= 7 and data["max_abs_error_mm"] < 0.1


def test_calibrate_cli_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "upper_0000.png").write_bytes(b"not a png")
    (tmp_path / "lower_0000.png").write_bytes(b"not a png")
    assert main(["calibrate", "--images", str(tmp_path), "-o", str(tmp_path / "c.yml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("crossfield: error:") and "upper_0000.png: unreadable image" in err


def test_calibration_session_records_and_replays(tmp_path, station_views, capsys):
    """--record writes the raw pairs; --replay re-detects and re-solves them (same settings: same result).

    The pairs go through the folder source's file format on the way (16-bit PNG), so
    ``--images`` is exercised too."""
    from crossfield.calibration.images import write_image_pairs
    from crossfield.calibration.record import TOPIC_IMAGE, read_calibration_recording

    folder = tmp_path / "views"
    write_image_pairs(folder, station_views.images[:10])
    first, mcap = tmp_path / "first.yml", tmp_path / "cal.mcap"
    assert (
        main(["calibrate", "--images", str(folder), "-o", str(first), "--record", str(mcap), "--no-report"])
        == 0
    )
    recorded = read_calibration_recording(mcap)
    assert len(recorded.images) == 10 and recorded.bit_depth == 12 and TOPIC_IMAGE.format(camera="upper")
    np.testing.assert_array_equal(recorded.images[3]["lower"], station_views.images[3]["lower"])
    again = tmp_path / "again.yml"
    assert main(["calibrate", "--replay", str(mcap), "-o", str(again), "--no-report"]) == 0
    a, b = read_stereo_calibration(first), read_stereo_calibration(again)
    # Same images, same detections; OpenCV's multi-threaded solver agrees to ~1e-10, not bit for bit.
    np.testing.assert_allclose(a.t_lower_upper, b.t_lower_upper, rtol=1e-8)
    np.testing.assert_allclose(a.upper.camera_matrix, b.upper.camera_matrix, rtol=1e-8)
    rational = tmp_path / "rational.yml"
    assert (
        main(
            [
                "calibrate",
                "--replay",
                str(mcap),
                "-o",
                str(rational),
                "--distortion",
                "rational",
                "--no-report",
            ]
        )
        == 0
    )
    assert len(read_stereo_calibration(rational).upper.dist_coeffs) == 8
    capsys.readouterr()
