"""The batched blob detector (BlobDetector.detect_stacks) and the edge band of the fit (disc_model.edge_band).

Reference: the per-blob BlobDetector.detect (the one the other centroid
plugins use), and the image itself: the stacks must hold the same blobs,
rejections, windows, backgrounds and moments, and the fit's edge-band pixels
exactly the image's window pixels.
"""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_targets import Ellipse, distractors, random_targets, render

from crossfield.imaging.blobs import BlobDetector, DetectorOptions
from crossfield.imaging.disc_model import edge_band


def frames():
    rng = np.random.default_rng(3)
    targets = [t for t in random_targets(rng, 30) if t.v0 - t.a > 110]
    yield "distractors", render(targets + [e for g in distractors().values() for e in g], rng), {}
    left = Ellipse(80.3, 90.2, 22.0, 20.0, 0.0, 3000.0)
    right = Ellipse(80.3 + 48.0, 91.7, 18.0, 18.0, 0.0, 2500.0)
    yield "neighbours", render([left, right], np.random.default_rng(21), shape=(180, 200)), {}
    cut = [Ellipse(12.0, 60.0, 15.0, 14.0, 0.0, 2800.0), Ellipse(120.0, 170.0, 12.0, 12.0, 0.0, 2800.0)]
    yield "border kept", render(cut, np.random.default_rng(5), shape=(180, 200)), {"reject_border": False}
    small = render([Ellipse(20.0, 14.0, 9.0, 8.0, 0.0, 2800.0)], np.random.default_rng(6), shape=(30, 44))
    yield "small image", small, {}


@pytest.mark.parametrize("case", list(frames()), ids=lambda c: c[0])
def test_stacks_hold_the_blobs_of_detect(case):
    _, image, options = case
    detector = BlobDetector(DetectorOptions(**options))
    blobs, rejected, background = detector.detect(image)
    stacks, rejected_s, background_s = detector.detect_stacks(image)
    assert background_s == background
    assert sorted((r.reason, r.uv) for r in rejected_s) == sorted((r.reason, r.uv) for r in rejected)
    assert sum(len(s) for s in stacks) == len(blobs) > 0
    by_uv = {b.uv: b for b in blobs}
    for st in stacks:
        for t in range(len(st)):
            blob = by_uv[tuple(st.uv[t])]  # the same weighted centroid, to the last bit
            assert st.background_dn[t] == pytest.approx(blob.background_dn, rel=1e-12)
            assert st.area_px[t] == blob.area_px and st.peak_dn[t] == pytest.approx(blob.peak_dn, rel=1e-12)
            assert st.roundness[t] == pytest.approx(blob.roundness, rel=1e-9)
            # the window, in image coordinates, is detect()'s
            rows, cols = np.nonzero(st.window[t])
            r2, c2 = np.nonzero(blob.window)
            assert sorted(zip(rows + st.y0[t], cols + st.x0[t])) == sorted(zip(r2 + blob.y0, c2 + blob.x0))
            np.testing.assert_array_equal(st.roi[t][rows, cols], image[rows + st.y0[t], cols + st.x0[t]])


def test_band_pixels_are_the_image_pixels():
    """A band wider than any window: fit_discs's pixels are the window's, with the image's values
    less the ring's background plane (its slope times the offset from the reference)."""
    _, image, _ = next(frames())
    stacks, _, _ = BlobDetector(DetectorOptions()).detect_stacks(image)
    for st in stacks:
        for t in range(len(st)):
            ref = st.uv[t]
            du, dv, values = edge_band(st, t, ref, np.array([0.01, 0.0, 0.01]), (1e9, 1e9))
            assert len(du) == st.window[t].sum()
            u, v = np.rint(du + ref[0]).astype(int), np.rint(dv + ref[1]).astype(int)
            np.testing.assert_allclose(du + ref[0], u, atol=1e-9)
            slope = st.background_gradient[t]
            np.testing.assert_allclose(values, image[v, u] - (slope[0] * du + slope[1] * dv), rtol=0, atol=1e-9)
            assert len(set(zip(u, v))) == len(u)  # every window pixel once


def test_edge_band_of_a_circle():
    """For a circle the first-order signed distance is exact: the band is the annulus."""
    image = render([Ellipse(60.3, 50.6, 11.0, 11.0, 0.0, 3000.0)], None, shape=(100, 120))
    stacks, _, _ = BlobDetector(DetectorOptions()).detect_stacks(image)
    (st,) = stacks
    radius = 10.5
    du, dv, _ = edge_band(st, 0, st.uv[0], np.array([radius**-2, 0.0, radius**-2]), (3.0, 2.0))
    got = {(round(u), round(v)) for u, v in zip(du + st.uv[0, 0], dv + st.uv[0, 1])}
    rows, cols = np.nonzero(st.window[0])
    u, v = cols + st.x0[0], rows + st.y0[0]
    r = np.hypot(u - st.uv[0, 0], v - st.uv[0, 1])
    inside = (r > radius - 3.0) & (r < radius + 2.0)
    assert got == set(zip(u[inside].tolist(), v[inside].tolist()))
    assert 0 < inside.sum() < st.window[0].sum()


def test_ring_plane_is_the_background_slope_and_the_fit_ignores_it():
    """A disc on a background sloping by (0.04, -0.03) DN/px (a vignetting edge), noise-free: the
    ring's plane recovers the slope (least squares on pixels rounded to DN), and modelfit's centre
    stays on the disc's (the slope left in, it would move it by ~1e-3 px)."""
    from crossfield.chain.registry import implementations, make_plugin_manager

    rows, cols = np.mgrid[0:100, 0:120].astype(np.float64)
    ramp = 0.04 * (cols - 60.0) - 0.03 * (rows - 50.0)
    disc = Ellipse(60.3, 50.6, 11.0, 10.0, 0.3, 3000.0)
    flat = render([disc], None, shape=(100, 120), supersample=32)  # noise-free, rounded to DN
    sloped = np.rint(flat.astype(np.float64) + ramp).astype(np.uint16)
    (st,), _, _ = BlobDetector(DetectorOptions()).detect_stacks(sloped)
    np.testing.assert_allclose(st.background_gradient[0], [0.04, -0.03], atol=0.008)  # rounding to DN
    fit = implementations(make_plugin_manager(), "centroid")["modelfit"].create({"psf_order": "pixel"})
    on_slope, on_flat = fit.extract(sloped, "upper", 0), fit.extract(flat, "upper", 0)
    assert len(on_slope) == len(on_flat) == 1
    np.testing.assert_allclose(on_slope.uv[0], on_flat.uv[0], atol=2e-4)
