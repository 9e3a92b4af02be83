"""Centroid stage: every registered "centroid" implementation against synthetic truth.

Images come from tests/synthetic_targets.py: super-sampled ellipses with known
sub-pixel centres, Gaussian blur, Poisson + read noise from a seeded rng. The
truth for a centroid is the centre of the image ellipse (the centre of a
projected circle's ellipse is not the projection of the circle's centre;
see test_perspective_ellipse_centre_is_the_truth).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_targets import Ellipse, coverage, distractors, random_targets, render

from crossfield.errors import ConfigError
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.types import CentroidSet, StereoFrame
from crossfield.imaging.blobs import BlobDetector, DetectorOptions, estimate_background
from crossfield.plugins.centroid_weighted import weighted_centroid

IMPLEMENTATIONS = implementations(make_plugin_manager(), "centroid")
NAMES = sorted(IMPLEMENTATIONS)

#: RMS radial error bounds (pixels) over a frame of 30-60 px targets.
NOISE_FREE_RMS_PX = 0.01
NOISY_RMS_PX = 0.02
#: the implementations agree to this (pixels) on the same noisy frame
AGREEMENT_PX = 0.03


def make(name: str, **options) -> object:
    return IMPLEMENTATIONS[name].create(options)


def match(result: CentroidSet, truth: np.ndarray, radius: float = 2.0) -> np.ndarray:
    """For each true centre (M, 2), the index of the centroid within ``radius``
    px; asserts there is exactly one and no centroid is left over."""
    d = np.linalg.norm(result.uv[:, None, :] - truth[None, :, :], axis=2)
    index = d.argmin(axis=0)
    assert np.all(d[index, np.arange(len(truth))] < radius), "a target was not found"
    assert len(set(index.tolist())) == len(truth) == len(result), (
        f"{len(result)} centroids for {len(truth)} targets"
    )
    return index


def frame(seed: int, count: int = 20, noise: bool = True, **render_options):
    rng = np.random.default_rng(seed)
    targets = random_targets(rng, count)
    image = render(targets, rng if noise else None, **render_options)
    return image, np.array([[t.u0, t.v0] for t in targets])


@pytest.fixture(scope="module")
def noisy_frame():
    return frame(11)


def test_both_implementations_are_registered():
    assert {"weighted", "ellipse"} <= set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_empty_image_gives_empty_set(name):
    extractor = make(name)
    for image in (np.zeros((1236, 1626), np.uint16), np.full((1236, 1626), 150, np.uint16)):
        result = extractor.extract(image, "upper", 7)
        assert isinstance(result, CentroidSet)
        assert len(result) == 0 and result.uv.shape == (0, 2) and result.sigma_uv.shape == (0, 2)
        assert result.rejected == () and result.camera == "upper" and result.sequence == 7
        assert result.method == name


@pytest.mark.parametrize("name", NAMES)
def test_pure_noise_gives_no_blobs(name):
    image = render([], np.random.default_rng(3))
    result = make(name).extract(image, "lower", 0)
    assert len(result) == 0 and result.rejected == ()


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("blur", [0.7, 1.2])
def test_noise_free_accuracy(name, blur):
    image, truth = frame(5, noise=False, blur_sigma_px=blur)
    result = make(name).extract(image, "upper", 0)
    err = result.uv[match(result, truth)] - truth
    rms = math.sqrt(np.mean(np.sum(err**2, axis=1)))
    assert rms < NOISE_FREE_RMS_PX, rms
    assert np.abs(err).max() < 2 * NOISE_FREE_RMS_PX


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [1, 2])
def test_noisy_accuracy_and_error_within_uncertainty(name, seed):
    image, truth = frame(seed, count=25, blur_sigma_px=0.7 + 0.5 * (seed - 1))
    result = make(name).extract(image, "upper", 0)
    index = match(result, truth)
    err = result.uv[index] - truth
    rms = math.sqrt(np.mean(np.sum(err**2, axis=1)))
    assert rms < NOISY_RMS_PX, rms
    z = err / result.sigma_uv[index]
    assert np.abs(z).max() < 5.0, z
    assert np.all(result.sigma_uv > 0)
    # the other per-centroid fields are filled in sensibly
    assert np.all(result.area_px > 500) and np.all(result.roundness > 0.6)
    assert np.all((result.peak > 2000) & (result.peak < 3700))


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(
    "target, gain",
    [
        (Ellipse(100.3, 90.7, 20.0, 16.0, 0.4, 3000.0), 2.86),  # typical bright target
        (Ellipse(99.6, 91.2, 12.0, 9.0, 1.1, 300.0), 2.86),  # small, faint: read noise matters
        (Ellipse(100.8, 90.1, 25.0, 24.0, 0.0, 3000.0), 0.5),  # low gain: photon noise dominates
    ],
    ids=["bright", "faint", "low-gain"],
)
def test_uncertainty_matches_scatter_over_noise_draws(name, target, gain):
    options = {"min_area_px": 20}
    if "gain_e_per_dn" in IMPLEMENTATIONS[name].options():
        options["gain_e_per_dn"] = gain
    extractor = make(name, **options)
    uv, sigma = [], []
    for k in range(60):
        image = render([target], np.random.default_rng(100 + k), shape=(180, 200), gain_e_per_dn=gain)
        result = extractor.extract(image, "upper", k)
        assert len(result) == 1
        uv.append(result.uv[0])
        sigma.append(result.sigma_uv[0])
    uv, sigma = np.array(uv), np.array(sigma)
    ratio = uv.std(axis=0, ddof=1) / sigma.mean(axis=0)
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio
    # and the scatter is around the truth (bias well below the scatter)
    bias = uv.mean(axis=0) - (target.u0, target.v0)
    assert np.all(np.abs(bias) < 3 * sigma.mean(axis=0) + 0.01), bias


def test_weighted_uncertainty_formula_matches_explicit_sum():
    """The moment-based sigma of "weighted" equals the per-pixel sum it stands for:
    sigma_u^2 = sum((u_i-u_c)^2 var_i)/S^2 + (sum(u_i-u_c)/S)^2 var_b."""
    image = render([Ellipse(70.2, 64.9, 18.0, 14.0, 0.7, 2500.0)], np.random.default_rng(9), shape=(140, 150))
    blobs, _, background = BlobDetector(DetectorOptions()).detect(image)
    (blob,) = blobs
    gain = 2.86
    u, v, su, sv = weighted_centroid(blob, background, gain)
    rows, cols = np.nonzero(blob.window)
    w = blob.roi[rows, cols].astype(np.float64) - blob.background_dn
    ui, vi = blob.x0 + cols, blob.y0 + rows
    total = w.sum()
    assert u == pytest.approx((ui * w).sum() / total, abs=1e-7)
    assert v == pytest.approx((vi * w).sum() / total, abs=1e-7)
    var_i = background.sigma_dn**2 + np.maximum(w, 0) / gain
    var_b = background.sigma_dn**2 / blob.ring_count
    # the photon term uses sum((u_i-u_c)^2 w_i) unclipped (a central moment);
    # the clipping of negative margins changes it by far less than 1e-3
    for coord, centre, sigma in ((ui, u, su), (vi, v, sv)):
        d = coord - centre
        explicit = (d**2 * var_i).sum() / total**2 + (d.sum() / total) ** 2 * var_b
        assert sigma == pytest.approx(math.sqrt(explicit), rel=1e-3)


@pytest.mark.parametrize("name", NAMES)
def test_rejects_non_target_blobs_with_reasons(name):
    groups = distractors()
    targets = [
        Ellipse(700.0, 500.0, 22.0, 19.0, 0.3, 3000.0),
        Ellipse(1000.4, 800.6, 26.0, 25.0, 0.0, 2600.0),
    ]
    image = render(targets + [e for group in groups.values() for e in group], np.random.default_rng(4))
    result = make(name).extract(image, "upper", 0)
    match(result, np.array([[t.u0, t.v0] for t in targets]))
    for reason, blobs in groups.items():
        for blob in blobs:
            near = [r for r in result.rejected if math.dist(r.uv, (blob.u0, blob.v0)) < blob.a + 2]
            assert [r.reason for r in near] == [reason], (reason, blob, result.rejected)
    assert len(result.rejected) == sum(len(g) for g in groups.values())


@pytest.mark.parametrize("name", NAMES)
def test_area_limits(name):
    target = Ellipse(100.0, 90.0, 20.0, 20.0, 0.0, 3000.0)  # about 1300 px
    image = render([target], np.random.default_rng(2), shape=(180, 200))
    assert [r.reason for r in make(name, max_area_px=800).extract(image, "upper", 0).rejected] == [
        "too_large"
    ]
    assert [r.reason for r in make(name, min_area_px=2000).extract(image, "upper", 0).rejected] == [
        "too_small"
    ]
    assert len(make(name).extract(image, "upper", 0)) == 1


@pytest.mark.parametrize("name", NAMES)
def test_saturated_target_measured_when_allowed(name):
    target = Ellipse(100.25, 90.6, 20.0, 17.0, 0.5, 6000.0)
    image = render([target], np.random.default_rng(8), shape=(180, 200))
    assert image.max() == 4095
    assert [r.reason for r in make(name).extract(image, "upper", 0).rejected] == ["saturated"]
    result = make(name, reject_saturated=False).extract(image, "upper", 0)
    assert len(result) == 1
    assert np.abs(result.uv[0] - (target.u0, target.v0)).max() < 0.02


@pytest.mark.parametrize("name", NAMES)
def test_order_independent_and_raster_ordered(name, noisy_frame):
    """Flipping or transposing the image maps the centroids exactly, whatever
    order the blobs are found in; the output is in raster order (v, then u)."""
    image, _ = noisy_frame
    extractor = make(name)
    result = extractor.extract(image, "upper", 0)
    assert np.all(np.diff(result.uv[:, 1]) >= 0)
    w = image.shape[1]

    flipped = extractor.extract(np.ascontiguousarray(image[:, ::-1]), "upper", 0)
    mirrored = np.column_stack((w - 1 - flipped.uv[:, 0], flipped.uv[:, 1]))
    order = np.lexsort((mirrored[:, 0], mirrored[:, 1]))
    np.testing.assert_allclose(mirrored[order], result.uv, atol=1e-6)
    # sigma differs slightly: the strided background subsample sees other pixels
    np.testing.assert_allclose(flipped.sigma_uv[order], result.sigma_uv, rtol=1e-2)

    transposed = extractor.extract(np.ascontiguousarray(image.T), "upper", 0)
    swapped = transposed.uv[:, ::-1]
    order = np.lexsort((swapped[:, 0], swapped[:, 1]))
    np.testing.assert_allclose(swapped[order], result.uv, atol=1e-6)
    np.testing.assert_allclose(transposed.sigma_uv[order][:, ::-1], result.sigma_uv, rtol=1e-4)
    np.testing.assert_array_equal(transposed.area_px[order], result.area_px)


@pytest.mark.skipif(len(NAMES) < 2, reason="needs two implementations")
def test_implementations_agree(noisy_frame):
    image, truth = noisy_frame
    results = {name: make(name).extract(image, "upper", 0) for name in NAMES}
    reference = results[NAMES[0]]
    for name in NAMES[1:]:
        other = results[name]
        assert len(other) == len(reference) == len(truth)
        assert np.abs(other.uv - reference.uv).max() < AGREEMENT_PX
        np.testing.assert_array_equal(other.area_px, reference.area_px)


@pytest.mark.parametrize("name", NAMES)
def test_perspective_ellipse_centre_is_the_truth(name):
    """A tilted circle projects to an ellipse whose centre is not the projection
    of the circle's centre; the centroid is the ellipse centre."""
    K = np.array([[2400.0, 0, 813.0], [0, 2400.0, 618.0], [0, 0, 1]])
    centre = np.array([-18.0, 10.0, 160.0])  # mm, camera frame
    tilt = math.radians(55.0)
    e1 = np.array([math.cos(tilt), 0.0, math.sin(tilt)])  # circle plane axes
    e2 = np.array([0.0, 1.0, 0.0])
    radius = 1.5  # mm
    # plane (x, y, 1) -> image homography and the circle's image conic
    H = K @ np.column_stack((e1, e2, centre))
    Hinv = np.linalg.inv(H)
    conic = Hinv.T @ np.diag([1.0, 1.0, -(radius**2)]) @ Hinv
    A, b, c = conic[:2, :2], conic[:2, 2], conic[2, 2]
    ellipse_centre = -np.linalg.solve(A, b)
    k = ellipse_centre @ A @ ellipse_centre - c
    lam, vec = np.linalg.eigh(A / k)
    semi = 1.0 / np.sqrt(lam)  # ascending lam: semi[0] is the major semi-axis
    theta = math.atan2(vec[1, 0], vec[0, 0])
    target = Ellipse(*ellipse_centre, semi[0], semi[1], theta, 3000.0)
    projected_centre = (K @ centre)[:2] / centre[2]
    assert np.linalg.norm(projected_centre - ellipse_centre) > 0.1  # the bias is real here

    image = render([target], np.random.default_rng(6))
    result = make(name).extract(image, "upper", 0)
    assert len(result) == 1
    assert np.linalg.norm(result.uv[0] - ellipse_centre) < 0.02
    assert result.roundness[0] == pytest.approx(semi[1] / semi[0], abs=0.05)


def test_renderer_is_centred():
    """Test helper check: the rendered coverage's first moments are the ellipse centre."""
    e = Ellipse(30.37, 25.81, 9.0, 6.0, 0.6)
    cov, r0, c0 = coverage(e, (60, 60), supersample=16)
    rows, cols = np.indices(cov.shape)
    total = cov.sum()
    assert (cols * cov).sum() / total + c0 == pytest.approx(e.u0, abs=2e-3)
    assert (rows * cov).sum() / total + r0 == pytest.approx(e.v0, abs=2e-3)
    assert total == pytest.approx(math.pi * e.a * e.b, rel=2e-3)


def test_background_estimate():
    level, read, gain = 150.0, 4.0, 2.0
    image = render([], np.random.default_rng(12), background_dn=level, read_noise_dn=read, gain_e_per_dn=gain)
    bg = estimate_background(image, threshold_sigma=8.0)
    expected_sigma = math.sqrt(read**2 + level / gain)
    assert bg.level_dn == pytest.approx(level, abs=0.3)
    assert bg.sigma_dn == pytest.approx(expected_sigma, rel=0.05)
    assert bg.threshold_dn == math.floor(bg.level_dn + 8.0 * bg.sigma_dn)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(
    "options", [{"min_roundness": 1.5}, {"threshold_sigma": 0}, {"min_area_px": 0}, {"bogus": 1}]
)
def test_bad_options_are_config_errors(name, options):
    with pytest.raises(ConfigError):
        IMPLEMENTATIONS[name].create(options)


@pytest.mark.parametrize("name", NAMES)
def test_rejects_non_2d_input(name):
    with pytest.raises(ValueError):
        make(name).extract(np.zeros((10, 10, 3), np.uint16), "upper", 0)


@pytest.mark.parametrize("name", NAMES)
def test_reads_frozen_stereo_frame_images(name, noisy_frame):
    """StereoFrame makes its images read-only; extraction must not write to them."""
    image, truth = noisy_frame
    stereo = StereoFrame(sequence=3, timestamp_ns=0, upper=image.copy(), lower=image[:, ::-1])
    assert not stereo.upper.flags.writeable
    upper = make(name).extract(stereo.upper, "upper", stereo.sequence)
    match(upper, truth)
    np.testing.assert_array_equal(stereo.upper, image)
    assert len(make(name).extract(stereo.lower, "lower", stereo.sequence)) == len(truth)


@pytest.mark.parametrize("name", NAMES)
def test_close_neighbours_are_kept_apart(name):
    """Two targets whose ROIs overlap (edges 8 px apart): each window excludes
    the other blob's pixels and the ring excludes both."""
    left = Ellipse(80.3, 90.2, 22.0, 20.0, 0.0, 3000.0)
    right = Ellipse(80.3 + 22.0 + 8.0 + 18.0, 91.7, 18.0, 18.0, 0.0, 2500.0)
    image = render([left, right], np.random.default_rng(21), shape=(180, 200))
    blobs, _, background = BlobDetector(DetectorOptions()).detect(image)
    assert len(blobs) == 2
    for blob in blobs:  # the other blob reaches into each ROI
        other = (blob.roi > background.threshold_dn) & (blob.component == 0)
        assert other.sum() > 0 and not (other & (blob.window > 0)).any()
    result = make(name).extract(image, "upper", 0)
    truth = np.array([[left.u0, left.v0], [right.u0, right.v0]])
    err = result.uv[match(result, truth)] - truth
    assert np.abs(err).max() < 0.03, err
    assert result.rejected == ()
