"""The board detector's corners against the rendered truth, and the views it finds (issue 28)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crossfield.calibration.boards import Board
from crossfield.calibration.detect import BoardDetector, to_uint8
from crossfield.simulator.board_views import ViewMismatch, render_calibration_views, true_image_points


def _corner_errors(views, detector):
    errors = []
    for k, view in enumerate(views.images):
        for cam, image in view.items():
            d = detector.detect(image, views.bit_depth)
            if d is not None:
                errors.append(d.image_points - true_image_points(views, k, cam)[d.ids])
    e = np.concatenate(errors)
    return np.hypot(e[:, 0], e[:, 1])


@pytest.mark.parametrize(
    ("board", "rms_px", "max_px"),
    [
        (Board(), 0.05, 0.2),  # the station board, 15 mm squares (~135 px)
        # 6 mm squares (~55 px), 0.8 mm from corner to marker: a cornerSubPix window of a third of the
        # square reaches the markers (0.34 px RMS, 1.7 px max before issue 28)
        (Board(squares_x=14, squares_y=10, square_mm=6.0, marker_mm=4.4), 0.08, 0.3),
    ],
)
def test_charuco_corners_match_the_rendered_truth(board, rms_px, max_px):
    views = render_calibration_views(n_views=2, seed=4, board=board, supersample=3)
    r = _corner_errors(views, BoardDetector(board))
    assert len(r) > 100
    assert np.sqrt(np.mean(r**2)) < rms_px
    assert r.max() < max_px


def test_chessboard_corners_match_the_truth_through_a_blurred_astigmatic_lens(monkeypatch):
    """View 1 (upper) of this layout shows the whole board; OpenCV's classic detector finds it. It is
    found, and its corners are right, by the SB detector and by the classic fallback alone."""
    board = Board(type="chessboard", squares_x=9, squares_y=6, square_mm=15.0, marker_mm=0.0, dictionary="")
    views = render_calibration_views(
        n_views=2,
        seed=2,
        board=board,
        supersample=2,
        layout_seed=7,
        mismatch=ViewMismatch(psf_sigma_px=(2.5, 2.0)),
    )
    image = views.images[1]["upper"]
    found, _ = cv2.findChessboardCorners(
        to_uint8(image, views.bit_depth),
        board.pattern_size,
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE,
    )
    assert found
    truth = true_image_points(views, 1, "upper")
    for sb_fails in (False, True):
        if sb_fails:
            monkeypatch.setattr(cv2, "findChessboardCornersSB", lambda *a, **k: (False, None))
        d = BoardDetector(board).detect(image, views.bit_depth)
        assert d is not None and len(d) == board.n_points
        err = np.hypot(*(d.image_points - truth[d.ids]).T)
        assert np.sqrt(np.mean(err**2)) < 0.08 and err.max() < 0.25, (sb_fails, err.max())
