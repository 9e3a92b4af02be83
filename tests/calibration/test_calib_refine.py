"""The joint refinement, the jackknife, residual maps and cross-validation against known truth (issue 28).

Detections are synthetic (``calib_synthetic``: the station's rig and poses,
exact projection, then the injected mismatch) so that 20 sessions fit in
the test budget; the rendered versions are in bench/bench_calibrate_peers.py
and tests/test_calib_crossval.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from calib_synthetic import synthetic_detections

from crossfield.calibration.crossval import calibration_of, compare, params_of
from crossfield.calibration.refine import refine
from crossfield.calibration.residuals import residual_map
from crossfield.calibration.solve import CalibrationSettings, solve_stereo
from crossfield.simulator.board_views import default_board

BOARD = default_board()
#: Camera + rig parameters compared with the truth: fx fy cx cy of both cameras, r (rad), T (mm).
COMPARED = [0, 1, 2, 3, 9, 10, 11, 12, 18, 19, 20, 21, 22, 23]


def _solve(dets, size, **kw):
    settings = CalibrationSettings(holdout_every=0, joint=False)  # step 6 run here, as a unit
    result = solve_stereo(dets, {"upper": size, "lower": size}, BOARD, settings)
    views = {k: (dets[k]["upper"], dets[k]["lower"]) for k in result.used_stereo}
    return result, refine(views, result.params, result.calibration, BOARD.object_points(), **kw)


def test_exact_corners_give_the_true_rig_and_bow():
    # without mrcal's prior (which by design moves the distortion coefficients a little towards 0)
    dets, truth, size = synthetic_detections(10, 3, noise_px=0.0, warp_mm=(0.3, -0.2))
    _, ref = _solve(dets, size, jackknife_views=False, prior=False)
    np.testing.assert_allclose(ref.params, params_of(truth), rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(ref.warp_mm, [0.3, -0.2], atol=1e-6)
    assert ref.rms_px["upper"] < 1e-6 and ref.rms_px["lower"] < 1e-6


def test_every_corner_of_each_camera_is_used():
    dets, _, size = synthetic_detections(10, 4, noise_px=0.03)
    result, ref = _solve(dets, size, jackknife_views=False)
    n_points = sum(len(dets[k][c]) for k in result.used_stereo for c in ("upper", "lower"))
    common = sum(len(np.intersect1d(dets[k]["upper"].ids, dets[k]["lower"].ids)) for k in result.used_stereo)
    assert len(ref.solution.residuals) == 2 * n_points > 2 * 2 * common  # views reach past the other camera
    # and the bow of a flat board is zero within its stated uncertainty
    assert np.all(np.abs(ref.warp_mm) < 3 * ref.warp_std_mm)


def test_stated_std_cover_the_truth_when_the_model_does_not_fit():
    """20 sessions whose corners come from a lens and board the model lacks (thin prism, per-view bow,
    a shift common to a view's corners): >= 90 % of parameter errors within 2 stated std. The Jacobian's
    std alone (independent, modelled errors) cover far fewer: the jackknife carries the test."""
    stated, jacobian = [], []
    for seed in range(20):
        dets, truth, size = synthetic_detections(
            12,
            seed,
            noise_px=0.03,
            thin_prism=(3e-4, 0.0, -2e-4, 0.0),
            warp_mm=(0.2, -0.1),
            bow_per_view_mm=0.05,
            view_shift_px=0.02,
        )
        _, ref = _solve(dets, size)
        err = np.abs(ref.params - params_of(truth))[COMPARED]
        stated.append(err / np.sqrt(np.diag(ref.covariance))[COMPARED])
        jacobian.append(err / ref.std_jacobian[COMPARED])
        # the stated std is the larger of the two, per parameter
        np.testing.assert_allclose(
            np.sqrt(np.diag(ref.covariance)), np.fmax(ref.std_jacobian, ref.std_jackknife), rtol=1e-9
        )
    assert np.mean(np.array(stated) < 2) >= 0.90
    assert np.mean(np.array(jacobian) < 2) < 0.75


def _waves(uv: np.ndarray, amplitude: float = 0.25, period_px: float = 540.0) -> np.ndarray:
    """An unmodelled distortion: (du, dv) = A (sin 2 pi v / P, cos 2 pi u / P), px."""
    return amplitude * np.column_stack(
        [np.sin(2 * np.pi * uv[:, 1] / period_px), np.cos(2 * np.pi * uv[:, 0] / period_px)]
    )


def test_residual_map_shows_an_injected_distortion():
    dets, _, size = synthetic_detections(16, 5, noise_px=0.03, field=_waves)
    _, ref = _solve(dets, size, jackknife_views=False)
    for cam, measured in ref.residual_maps.items():
        pts = np.concatenate([d[cam].image_points for d in dets if d[cam] is not None])
        expected = residual_map(cam, pts, _waves(pts), size)  # the injected field, binned the same way
        ok = (measured.count >= 10) & (expected.count >= 10)
        m, e = measured.mean_px[ok], expected.mean_px[ok]
        gain = float(np.sum(m * e) / np.sum(e * e))  # least-squares amplitude of the injected pattern
        assert 0.85 < gain < 1.1, (cam, gain)
        assert abs(measured.amplitude_px / expected.amplitude_px - 1) < 0.2
        assert measured.amplitude_px > 4 * measured.noise_amplitude_px
    # without the injected field the map is noise
    dets, _, _ = synthetic_detections(16, 5, noise_px=0.03)
    _, ref = _solve(dets, size, jackknife_views=False)
    for measured in ref.residual_maps.values():
        assert measured.amplitude_px < 2 * measured.noise_amplitude_px


def test_cross_validation_of_halves_agrees_with_the_stated_uncertainty():
    dets, _, size = synthetic_detections(
        24, 6, noise_px=0.03, thin_prism=(3e-4, 0.0, -2e-4, 0.0), bow_per_view_mm=0.05, view_shift_px=0.02
    )
    halves = [_solve(dets[h::2], size)[1] for h in (0, 1)]
    cv = compare(halves[0].calibration, halves[0].covariance, halves[1].calibration, halves[1].covariance)
    within = cv.within(2.0)
    assert min(within.values()) >= 0.9, within
    # the test can fail: a half whose upper cx is 20 of its sigma off is flagged
    shifted = params_of(halves[1].calibration)
    shifted[2] += 20 * np.sqrt(halves[1].covariance[2, 2])
    bad = compare(
        halves[0].calibration,
        halves[0].covariance,
        calibration_of(shifted, halves[1].calibration),
        halves[1].covariance,
    )
    assert bad.within(2.0)["upper"] < 0.5


def test_residual_map_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="3 points but 2 residuals"):
        residual_map("upper", np.zeros((3, 2)), np.zeros((2, 2)), (100, 100))
