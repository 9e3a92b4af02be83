"""Robust calibration (issue 28, calib2): mrcal's corner outlier rule, per-view weights, view rejection.

Synthetic detections with known truth (``calib_synthetic``): exact projection
of the station's rig, then noise chosen per view here.
"""

from __future__ import annotations

import numpy as np
from calib_synthetic import synthetic_detections

from crossfield.calibration.crossval import params_of
from crossfield.calibration.detect import BoardDetection
from crossfield.calibration.joint import K_DROP, K_TRIGGER, ViewPoints, outlier_corners
from crossfield.calibration.refine import refine, view_weights
from crossfield.calibration.solve import CalibrationSettings, solve_stereo
from crossfield.simulator.board_views import default_board

BOARD = default_board()
T_SLICE = slice(21, 24)  # T (mm) in the camera + rig block (plumb_bob)


def _noisy(dets, sigmas, seed):
    """dets with Gaussian corner noise of sigmas[k] px (per coordinate) added to view k."""
    rng = np.random.default_rng(seed)
    out = []
    for view, s in zip(dets, sigmas):
        out.append(
            {
                cam: None
                if d is None
                else BoardDetection(
                    d.ids, d.image_points + s * rng.standard_normal(d.image_points.shape), d.object_points
                )
                for cam, d in view.items()
            }
        )
    return out


def _solve(dets, size, **kw):
    settings = CalibrationSettings(holdout_every=0, joint=False)
    result = solve_stereo(dets, {"upper": size, "lower": size}, BOARD, settings)
    views = {k: (dets[k]["upper"], dets[k]["lower"]) for k in result.used_stereo}
    return result, refine(
        views, result.params, result.calibration, BOARD.object_points(), jackknife_views=False, **kw
    )


def test_outlier_rule_is_mrcals():
    """Gaussian residuals: none marked; one coordinate past 5 sigma: every corner past 4 sigma marked."""
    rng = np.random.default_rng(1)
    r = 0.05 * rng.standard_normal(4000)
    assert not outlier_corners(r).any()
    r[2 * 17 + 1] = 0.4  # corner 17's v: 8 sigma
    r[2 * 40] = 0.22  # corner 40's u: ~4.4 sigma, dropped only because a round was started
    sigma = np.sqrt(np.mean(r**2))
    assert np.abs(r).max() > K_TRIGGER * sigma
    expected = np.flatnonzero(np.any(np.abs(r.reshape(-1, 2)) > K_DROP * sigma, axis=1))
    assert {17, 40} <= set(expected)
    np.testing.assert_array_equal(np.flatnonzero(outlier_corners(r)), expected)


def test_gross_corner_errors_are_rejected_and_do_not_bias_the_rig():
    """Eight corners of the lower camera 1.5 px off (a misdetection): the rejection drops them and the
    rig equals the one from the clean corners; without it T is off by several times as much."""
    dets, truth, size = synthetic_detections(12, 5, noise_px=0.03)
    clean = _solve(dets, size)[1]
    bad = [dict(v) for v in dets]
    for k in range(8):
        d = bad[k]["lower"]
        uv = d.image_points.copy()
        uv[3] += (1.5, -1.0)
        bad[k]["lower"] = BoardDetection(d.ids, uv, d.object_points)
    _, robust = _solve(bad, size)
    _, plain = _solve(bad, size, reject_corners=False)
    assert robust.outlier_corners >= 8
    err = lambda ref: np.linalg.norm(ref.params[T_SLICE] - params_of(truth)[T_SLICE])
    np.testing.assert_allclose(robust.params[T_SLICE], clean.params[T_SLICE], atol=2e-3)
    assert err(plain) > 3 * abs(err(robust) - err(clean)) + 2e-3


def test_view_weights_follow_each_views_corner_noise():
    """Views of 0.02 px and 0.08 px corners: the clean views weigh more, by less than the true 4x
    (each view's noise is shrunk towards the pooled one, ``prior_dof`` = 20: here to ~2.5x), and
    without the shrinkage by 4x to the estimate's spread."""
    dets, _, size = synthetic_detections(12, 6, noise_px=0.0)
    sigmas = [0.02 if k % 2 else 0.08 for k in range(12)]
    noisy = _noisy(dets, sigmas, 6)
    result, ref = _solve(noisy, size, weight_views=False, reject_corners=False)
    keys = result.used_stereo
    assert len(keys) == 12
    views = [
        ViewPoints(u.object_points, u.image_points, lo.object_points, lo.image_points)
        for u, lo in ((noisy[k]["upper"], noisy[k]["lower"]) for k in keys)
    ]
    for prior_dof, lo, hi in ((20.0, 2.0, 3.2), (0.0, 3.5, 4.5)):
        w = np.array([[v.weight_upper, v.weight_lower] for v in view_weights(views, ref.solution, prior_dof)])
        ratio = w[1::2].mean() / w[0::2].mean()
        assert lo < ratio < hi, (prior_dof, ratio)


def test_noisy_good_views_are_kept_and_a_moved_board_dropped():
    """Two views with corners 4x noisier than the rest (steep, blurred views) are kept: the old rule
    (3 x median, 0.15 px floor) dropped them. A view whose lower image saw the board turned by 0.3 deg
    in the image (the board moved between the exposures) is dropped at the stereo stage, with its reason."""
    dets, _, size = synthetic_detections(14, 7, noise_px=0.0)
    sigmas = [0.06] * 14
    sigmas[2] = sigmas[9] = 0.24
    noisy = _noisy(dets, sigmas, 7)
    d = noisy[5]["lower"]
    c, a = d.image_points.mean(axis=0), np.radians(0.3)
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    noisy[5]["lower"] = BoardDetection(d.ids, (d.image_points - c) @ turn.T + c, d.object_points)
    settings = CalibrationSettings(holdout_every=0, joint=False)
    result = solve_stereo(noisy, {"upper": size, "lower": size}, BOARD, settings)
    assert [(v.view, v.stage) for v in result.dropped] == [(5, "stereo")]
    assert "stereo RMS reprojection error" in result.dropped[0].reason
    assert {2, 9} <= set(result.used_stereo)
