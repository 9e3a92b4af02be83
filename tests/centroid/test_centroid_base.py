"""BlobCentroids (crossfield.imaging.centroids): one base for the detector options and the
CentroidSet; the weighted centroid on the compiled blob stacks equals the per-blob one."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from synthetic_targets import Ellipse, distractors, random_targets, render

from crossfield.imaging.blobs import BlobDetector, DetectorOptions
from crossfield.imaging.centroids import BlobCentroids, SubPixel
from crossfield.plugins.centroid_ellipse import EllipseCentroids
from crossfield.plugins.centroid_modelfit import ModelFitCentroids
from crossfield.plugins.centroid_weighted import WeightedCentroids, weighted_centroid
from crossfield.chain.registry import implementations, make_plugin_manager

DETECTOR = list(inspect.signature(BlobCentroids).parameters)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    rng = np.random.default_rng(2024)
    targets = [t for t in random_targets(rng, 20) if t.v0 - t.a > 110]
    return render(targets + [e for group in distractors().values() for e in group], rng)


@pytest.mark.parametrize(
    "cls, own",
    [
        (WeightedCentroids, ["gain_e_per_dn"]),
        (EllipseCentroids, ["edge_level"]),
        (ModelFitCentroids, ["gain_e_per_dn", "blur_sigma_px", "psf_order", "max_iterations"]),
    ],
)
def test_each_plugin_offers_the_detector_options_and_its_own(cls, own):
    assert len(DETECTOR) == 10
    options = implementations(make_plugin_manager(), "centroid")[cls.method].options()
    assert list(options) == DETECTOR + own
    made = cls(min_area_px=7, background_stride=4)
    assert made.detector.options.min_area_px == 7 and made.detector.options.stride == 4
    with pytest.raises(ValueError, match="threshold_sigma"):
        cls(threshold_sigma=0.0)


def test_weighted_on_the_stacks_equals_the_per_blob_centroid(image):
    """Same blobs, same reasons; centres and sigmas to 1e-12 px (exact integer sums in
    slice coordinates against cv2.moments in ROI coordinates)."""
    plugin = WeightedCentroids(reject_saturated=False)
    blobs, rejected, background = BlobDetector(DetectorOptions(reject_saturated=False)).detect(image)
    per_blob = np.array([weighted_centroid(b, background, plugin.gain_e_per_dn) for b in blobs])
    per_blob = per_blob[np.lexsort((per_blob[:, 0], per_blob[:, 1]))]
    result = plugin.extract(image, "upper", 0)
    assert len(result) == len(blobs) >= 20
    np.testing.assert_allclose(result.uv, per_blob[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.sigma_uv, per_blob[:, 2:], rtol=1e-12, atol=0)
    assert sorted(r.reason for r in result.rejected) == sorted(r.reason for r in rejected)


class BoxCentres(BlobCentroids):
    """A sub-pixel step for the test: the slice's centre; the first blob 'fails'."""

    method = "box"

    def __init__(self, *, fail_first: bool = True, **detector) -> None:
        self.fail_first = fail_first
        super().__init__(**detector)

    def subpixel(self, stacks, background):
        uv = np.concatenate([np.column_stack((st.x0, st.y0)) + (st.roi.shape[2] - 1) / 2 for st in stacks])
        ok = np.ones(len(uv), bool)
        ok[0] = not self.fail_first
        return SubPixel(uv=uv, sigma_uv=np.full_like(uv, 0.5), ok=ok)


def test_the_base_assembles_the_centroid_set_and_rejects_failed_steps():
    targets = [Ellipse(300.0, 200.0, 20.0, 18.0, 0.0, 3000.0), Ellipse(100.0, 90.0, 22.0, 20.0, 0.0, 3000.0)]
    image = render(targets, np.random.default_rng(5), shape=(400, 500))
    assert list(inspect.signature(BoxCentres).parameters) == DETECTOR + ["fail_first"]
    result = BoxCentres().extract(image, "lower", 3)
    assert (result.camera, result.sequence, result.method) == ("lower", 3, "box")
    assert len(result) == 1 and [r.reason for r in result.rejected] == ["fit_failed"]
    both = BoxCentres(fail_first=False).extract(image, "upper", 0)
    assert np.all(np.diff(both.uv[:, 1]) > 0)  # raster order
    np.testing.assert_allclose(both.uv, [[100.0, 90.0], [300.0, 200.0]], atol=8.0)
    assert both.ellipse is None and both.area_px.min() > 1000
    empty = ModelFitCentroids().extract(np.full((100, 120), 150, np.uint16), "upper", 0)
    assert len(empty) == 0 and empty.ellipse.shape == (0, 3) and empty.ellipse_cov.shape == (0, 3, 3)
