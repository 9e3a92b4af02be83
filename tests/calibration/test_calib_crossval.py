"""`crossfield calibrate --cross-validate` on the station scenario (rendered views), and what it writes."""

from __future__ import annotations

import json

import cv2
import numpy as np

from crossfield.cli import main


def test_station_cross_validation_agrees_with_the_stated_uncertainty(tmp_path, capsys):
    calib = tmp_path / "calib.yml"
    assert main(["calibrate", "--scenario", "station", "--cross-validate", "-o", str(calib)]) == 0
    assert "cross-validation (9 + 9 views)" in capsys.readouterr().out
    report = json.loads((tmp_path / "calib-report.json").read_text())
    cv = report["quality"]["cross_validation"]
    # the two halves differ by at most 2.5 of the difference's predicted sigma anywhere (Mahalanobis norm
    # on the normal scale; seed 1: 1.96 upper, 1.44 lower), >= 90 % of each image within 2 sigma, the
    # 3-D points at the working distance within 2 sigma (1.32)
    assert cv["projection"]["upper"]["max_ratio"] < 2.5 and cv["projection"]["lower"]["max_ratio"] < 2.5
    assert cv["within_2_sigma"]["upper"] >= 0.9 and cv["within_2_sigma"]["lower"] >= 0.9
    assert cv["within_2_sigma"]["points"] == 1.0
    assert cv["points"]["max_diff_mm"] > 0
    # the stated std are the larger of the Jacobian's and the jackknife's, in the YAML and the report
    fs = cv2.FileStorage(str(calib), cv2.FILE_STORAGE_READ)
    jac, jk = fs.getNode("std_jacobian").mat().ravel(), fs.getNode("std_jackknife").mat().ravel()
    stated = np.concatenate(
        [fs.getNode(k).mat().ravel() for k in ("std_M1", "std_D1", "std_M2", "std_D2", "std_R", "std_T")]
    )
    np.testing.assert_allclose(stated, np.maximum(jac, jk), rtol=1e-6)
    assert np.all(jk > 0)
    warp = fs.getNode("calobject_warp_mm").mat().ravel()
    warp_std = fs.getNode("calobject_warp_std_mm").mat().ravel()
    assert np.all(np.abs(warp) < 3 * warp_std + 1e-3)  # the simulated board is flat
    fs.release()
    maps = report["quality"]["residual_maps"]
    for cam in ("upper", "lower"):
        assert maps[cam]["amplitude_px"] < 2.5 * maps[cam]["noise_amplitude_px"]  # the model fits: noise
    html = (tmp_path / "calib-report.html").read_text()
    assert "Cross-validation" in html and "Residual maps" in html and 'alt="cross-validation"' in html
