"""The "modelfit" centroid against the synthetic renderer's truth and its Cramer-Rao bound.

Truth: the centre of mass of each rendered ellipse's coverage (what the image
holds; (u0, v0) itself is off by the renderer's sub-sample quantisation).
CRB: tests/crb_tools.py, the exact Fisher information of the renderer's model,
independent of the plugin's own (fitted-model) information.
"""

from __future__ import annotations

import numpy as np
import pytest

from crb_tools import centre_crb
from synthetic_targets import coverage, random_targets, render

from crossfield.imaging.blobs import BlobDetector, DetectorOptions
from crossfield.imaging.disc_model import edge_band, edge_profile, fit_discs, model, shape_from_moments
from crossfield.chain.registry import implementations, make_plugin_manager

SHAPE = (1236, 1626)
SUPERSAMPLE = 32


def coverage_centre(e):
    c, r0, c0 = coverage(e, SHAPE, SUPERSAMPLE)
    h, w = c.shape
    s = c.sum()
    return np.array([(c.sum(0) @ (np.arange(w) + c0)) / s, (c.sum(1) @ (np.arange(h) + r0)) / s])


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(11)
    targets = random_targets(rng, 60, shape=SHAPE, diameter_px=(12.0, 24.0))
    truth = np.array([coverage_centre(e) for e in targets])
    crb = np.array([centre_crb(e, shape=SHAPE) for e in targets])
    images = [render(targets, np.random.default_rng([11, k]), supersample=SUPERSAMPLE) for k in range(6)]
    return targets, truth, crb, images


def errors(name, options, frames):
    targets, truth, crb, images = frames
    extractor = implementations(make_plugin_manager(), "centroid")[name].create(options)
    err, sig, bound, results = [], [], [], []
    for image in images:
        result = extractor.extract(image, "upper", 0)
        d = np.linalg.norm(result.uv[:, None] - truth[None], axis=2)
        index = d.argmin(axis=1)
        assert len(result) == len(truth) and len(set(index.tolist())) == len(truth)
        err.append(result.uv - truth[index])
        sig.append(result.sigma_uv)
        bound.append(crb[index])
        results.append((result, index))
    return np.concatenate(err), np.concatenate(sig), np.concatenate(bound), results


def test_stated_sigma_is_the_independent_cramer_rao_bound(frames):
    _, sig, bound, _ = errors("modelfit", {"psf_order": "pixel"}, frames)
    ratio = np.sqrt((sig**2).sum() / np.trace(bound, axis1=1, axis2=2).sum())
    assert 0.95 < ratio < 1.05, ratio


def test_within_1_15_of_the_bound_and_closer_than_the_weighted_centroid(frames):
    """Issue 11: RMS within 1.15x the CRB. Measured on these 6 frames: modelfit 1.092x with one
    Gauss-Newton step (the default; 1.098x with two) and the ring's background plane taken off
    (1.078x with two steps and without it, the numpy float32 fit's 1.0779x: on
    these flat backgrounds the plane's own noise costs 2 %; on a sloped one it removes a bias,
    tests/centroid/test_blob_stacks.py), weighted ~1.38x (bench/bench_centroid.py --efficiency --seed 11)."""
    err_m, _, bound, _ = errors("modelfit", {"psf_order": "pixel"}, frames)
    err_w, _, _, _ = errors("weighted", {}, frames)
    crb = np.trace(bound, axis1=1, axis2=2).sum()
    ratio_m = np.sqrt((err_m**2).sum() / crb)
    ratio_w = np.sqrt((err_w**2).sum() / crb)
    assert ratio_m < 1.15 and ratio_m < ratio_w, (ratio_m, ratio_w)
    assert abs(ratio_m - 1.092) < 0.002, ratio_m  # the compiled kernel, one step, the background plane


def test_fitted_conic_is_the_rendered_ellipse(frames):
    targets, _, _, images = frames
    _, _, _, results = errors("modelfit", {"psf_order": "pixel"}, (targets, frames[1], frames[2], images[:1]))
    result, index = results[0]
    S = result.ellipse
    for k, i in enumerate(index):
        e = targets[i]
        M = np.array([[S[k, 0], S[k, 1]], [S[k, 1], S[k, 2]]])
        minor_major = 1.0 / np.sqrt(np.linalg.eigvalsh(M))  # semi-axes, ascending eigenvalues -> a first
        assert abs(minor_major[0] - e.a) < 0.2 and abs(minor_major[1] - e.b) < 0.2
        assert result.ellipse_cov[k].shape == (3, 3) and np.all(np.diag(result.ellipse_cov[k]) > 0)


def test_edge_profiles_are_distributions():
    for order in ("optical", "pixel"):
        prof = edge_profile(0.9, order)
        assert np.all(np.diff(prof.table, axis=1) >= -1e-12)
        np.testing.assert_allclose(prof.table[:, 0], 0.0, atol=1e-9)
        np.testing.assert_allclose(prof.table[:, -1], 1.0, atol=1e-9)
        # symmetric about the edge: E(d) + E(-d) = 1
        np.testing.assert_allclose(prof.table + prof.table[:, ::-1], 1.0, atol=1e-9)


def test_model_jacobian_matches_finite_differences():
    p = np.array([[0.3, -0.2, 1 / 81 * 1.1, 0.004, 1 / 50, 3000.0, 150.0]])
    v, u = np.mgrid[-12:13, -12:13].astype(float)
    du, dv = u.ravel()[None], v.ravel()[None]
    profile = edge_profile(0.9, "optical")
    _, J = model(p, du, dv, profile)
    # amplitude and background columns are exact; the centre columns neglect dE/dalpha (the
    # profile's change with the edge direction, documented), ~1 % of the slope
    for k, tol in ((0, 2e-2), (1, 2e-2), (5, 1e-6), (6, 1e-6)):
        h = 1e-6 * max(abs(p[0, k]), 1e-3)
        hi, lo = p.copy(), p.copy()
        hi[0, k] += h
        lo[0, k] -= h
        numeric = (model(hi, du, dv, profile, False)[0] - model(lo, du, dv, profile, False)[0]) / (2 * h)
        assert np.abs(numeric - J[:, k]).max() < tol * np.abs(numeric).max() + 1e-6


def reference_fit(stack, t, ref, start, band, profile, noise_sigma_dn, gain, max_iterations, tolerance_px=1e-4):
    """fit_discs's statement for one target, written plainly in numpy float64 with model():
    Gauss-Newton on the edge-band pixels, EMVA weights, the same trust region and stop,
    covariance the inverse of the last J^T W J."""
    du, dv, z = edge_band(stack, t, ref, start[2:5], band)
    p = start.astype(float).copy()
    for _ in range(max_iterations):
        mu, J = model(p[None], du[None], dv[None], profile)
        mu, J = mu[0], J[0]
        w = 1.0 / (np.maximum(mu - p[6], 0.0) / gain + noise_sigma_dn**2)
        H = (J * w) @ J.T
        step = np.linalg.solve(H, (J * w) @ (z - mu))
        centre = np.hypot(step[0], step[1])
        shape = np.abs(step[2:5]).max() / np.abs(p[2:5]).max()
        scale = min(1.0, 0.5 / centre, 0.2 / shape)
        p += scale * step
        if centre * scale < tolerance_px:
            break
    return p, np.linalg.inv(H), len(z)


@pytest.mark.parametrize("order", ["optical", "pixel"])
def test_compiled_fit_is_the_numpy_float64_fit(frames, order):
    """fit_discs (the numba kernel) against reference_fit on the synthetic targets: the
    same centres to 1e-6 px, the same shapes, amplitudes, backgrounds and covariances."""
    _, _, _, images = frames
    detector = BlobDetector(DetectorOptions())
    stacks, _, background = detector.detect_stacks(images[0])
    profile = edge_profile(0.9, order)
    sigma_e = np.sqrt(0.9**2 + 1.0 / 12.0)
    band = (3.7 * sigma_e, 3.2 * sigma_e)
    refs = np.concatenate([st.uv for st in stacks])
    moments = np.concatenate([st.moments for st in stacks])
    start = np.zeros((len(refs), 7))
    start[:, 2:5] = shape_from_moments(moments[:, 0], moments[:, 1], moments[:, 2], sigma_e)
    start[:, 5] = np.concatenate([st.peak_dn for st in stacks])
    start[:, 6] = np.concatenate([st.background_dn for st in stacks])
    for iterations in (1, 3):
        fit = fit_discs(
            stacks, refs, start, band=band, profile=profile,
            noise_sigma_dn=background.sigma_dn, gain_e_per_dn=2.86, max_iterations=iterations,
        )
        assert fit.ok.all() and len(fit.ok) == 60
        i = 0
        for st in stacks:
            for t in range(len(st)):
                p, cov, pixels = reference_fit(
                    st, t, refs[i], start[i], band, profile, background.sigma_dn, 2.86, iterations
                )
                assert fit.pixels[i] == pixels > 100
                np.testing.assert_allclose(fit.params[i, :2], p[:2], rtol=0, atol=1e-6)
                np.testing.assert_allclose(fit.params[i, 2:], p[2:], rtol=1e-6)
                np.testing.assert_allclose(fit.cov[i], cov, rtol=1e-6, atol=1e-9 * np.abs(cov).max())
                i += 1

