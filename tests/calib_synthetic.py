"""Synthetic calibration detections with known truth (no rendering): for fast solver tests.

The station's rig and board poses (``crossfield.simulator.board_views``),
the board points projected exactly (``cv2.projectPoints``, the points
outside the image dropped), then what a real session adds:

* ``noise_px``: independent Gaussian corner noise (px, per coordinate);
* ``field``: an unmodelled distortion, a function (N, 2) px -> (N, 2) px
  displacement added to every observed pixel;
* ``thin_prism``: (s1, s2, s3, s4) lens terms no fitted model has;
* ``warp_mm``: a fixed board bow (wx, wy) and ``bow_per_view_mm`` the std
  of a random bow per view (errors correlated within a view);
* ``view_shift_px``: std of a random shift common to a view's corners in
  each image (correlated errors, e.g. a PSF that changes with the view);
* ``dist_coeffs``: (k1, k2, p1, p2, k3) for both cameras in place of the
  station's (the returned truth has them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np

from crossfield.calibration.detect import BoardDetection
from crossfield.simulator.board_views import board_height_mm, default_board, station_board_poses
from crossfield.simulator.scenarios import station_calibration
from crossfield.types import CAMERAS


def synthetic_detections(
    n_views: int,
    seed: int,
    *,
    noise_px: float = 0.03,
    field: Callable[[np.ndarray], np.ndarray] | None = None,
    thin_prism: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    warp_mm: tuple[float, float] = (0.0, 0.0),
    bow_per_view_mm: float = 0.0,
    view_shift_px: float = 0.0,
    layout_seed: int | None = None,
    dist_coeffs: tuple[float, float, float, float, float] | None = None,
):
    """(detections per view {camera: BoardDetection}, truth StereoCalibration, image size)."""
    board = default_board()
    truth = station_calibration()
    if dist_coeffs is not None:
        D = np.array(dist_coeffs, float)
        truth = replace(
            truth, upper=replace(truth.upper, dist_coeffs=D), lower=replace(truth.lower, dist_coeffs=D)
        )
    rng = np.random.default_rng([seed, 28])
    poses = station_board_poses(
        n_views, board, layout_seed=1000 + seed if layout_seed is None else layout_seed
    )
    obj = board.object_points()
    ids = np.arange(len(obj))
    w, h = truth.upper.image_size
    R_lu, t_lu = np.asarray(truth.R_lower_upper), np.asarray(truth.t_lower_upper)
    dets = []
    for pose in poses:
        bow = np.asarray(warp_mm) + bow_per_view_mm * rng.standard_normal(2)
        X = obj.copy()
        X[:, 2] = board_height_mm(X[:, 0], X[:, 1], board, tuple(bow))
        X_u = X @ pose.R.T + pose.t
        view = {}
        for cam in CAMERAS:
            Xc = X_u if cam == "upper" else X_u @ R_lu.T + t_lu
            intr = truth.camera(cam)
            D = np.zeros(12)
            D[:5] = np.asarray(intr.dist_coeffs)[:5]
            D[8:12] = thin_prism
            uv, _ = cv2.projectPoints(
                Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.asarray(intr.camera_matrix), D
            )
            uv = uv.reshape(-1, 2)
            if field is not None:
                uv = uv + field(uv)
            uv = uv + noise_px * rng.standard_normal(uv.shape) + view_shift_px * rng.standard_normal(2)
            inside = (uv[:, 0] > 5) & (uv[:, 0] < w - 6) & (uv[:, 1] > 5) & (uv[:, 1] < h - 6)
            view[cam] = BoardDetection(ids[inside], uv[inside], obj[inside]) if inside.sum() >= 8 else None
        dets.append(view)
    return dets, truth, (w, h)
