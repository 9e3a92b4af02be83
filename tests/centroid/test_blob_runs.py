"""Blobs as pixel runs (crossfield.imaging.runs) against OpenCV.

Reference: ``cv2.findContours(RETR_EXTERNAL)`` on the thresholded image, each
outer contour filled with ``cv2.drawContours`` and boxed with
``cv2.boundingRect``: the same blobs, boxes and filled pixels, on random
images dense enough to have holes, blobs inside holes, diagonal contacts and
runs across the scan's 64-pixel blocks; and ``cv2.dilate`` by the detector's
disc for the painted dilation.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crossfield.imaging.runs import BLOCK, blob_runs, paint_runs


def opencv_blobs(image: np.ndarray, threshold: int) -> dict[tuple[int, int, int, int], np.ndarray]:
    """{bounding box (x, y, w, h): filled 0/1 mask over the box} from OpenCV."""
    mask = (image > threshold).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = {}
    for contour in contours:
        x, y, w, h = cv2.boundingRect(contour)
        filled = np.zeros((h, w), np.uint8)
        cv2.drawContours(filled, (contour,), -1, 1, thickness=-1, offset=(-x, -y))
        out[(x, y, w, h)] = filled
    return out


def run_blobs(image: np.ndarray, threshold: int) -> dict[tuple[int, int, int, int], np.ndarray]:
    """The same from blob_runs, each blob painted over its box by paint_runs."""
    found = blob_runs(image, threshold)
    out = {}
    for b, (x, y, w, h) in enumerate(found.boxes.tolist()):
        filled = np.zeros((1, h, w), np.uint8)
        paint_runs(found.runs, found.offsets, np.array([b]), np.array([x]), np.array([y]), filled, 0)
        assert filled.sum() == found.area[b]
        out[(x, y, w, h)] = filled[0]
    rows = found.runs[:, 0]
    for b in range(len(found)):  # each blob's runs in raster order, inside its box
        mine = found.runs[found.offsets[b] : found.offsets[b + 1]]
        assert np.all(np.diff(mine[:, 0] * (image.shape[1] + 1) + mine[:, 1]) > 0)
    assert np.all((rows >= 0) & (rows < image.shape[0]))
    return out


def assert_same_blobs(image: np.ndarray, threshold: int) -> None:
    expected, got = opencv_blobs(image, threshold), run_blobs(image, threshold)
    assert sorted(got) == sorted(expected)
    for box, filled in expected.items():
        np.testing.assert_array_equal(got[box], filled, err_msg=f"blob with box {box}")


@settings(max_examples=300, deadline=None)
@given(
    height=st.integers(1, 40),
    width=st.integers(1, 2 * BLOCK + 9),
    density=st.floats(0.05, 0.75),
    seed=st.integers(0, 2**32 - 1),
)
def test_random_binary_images_give_opencv_blobs(height, width, density, seed):
    """Dense random pixels: holes, blobs in holes, diagonal contacts, runs over block edges."""
    image = (np.random.default_rng(seed).random((height, width)) < density).astype(np.uint16) * 900 + 100
    assert_same_blobs(image, 500)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), blur=st.floats(0.7, 3.0))
def test_blurred_noise_at_its_median_gives_opencv_blobs(seed, blur):
    """Smooth blobs with ragged edges, as near a threshold in a real frame."""
    noise = np.random.default_rng(seed).random((70, 3 * BLOCK + 5)).astype(np.float32) * 4000
    image = cv2.GaussianBlur(noise, (0, 0), blur).astype(np.uint16)
    assert_same_blobs(image, int(np.median(image)))


def test_a_ring_with_a_dot_inside_is_one_filled_blob():
    image = np.zeros((30, 30), np.uint16)
    cv2.circle(image, (15, 15), 9, 1000, thickness=2)
    image[14:17, 14:17] = 1000  # inside the hole: no outer contour of its own
    found = blob_runs(image, 500)
    assert len(found) == 1  # the dot is inside the ring's hole
    painted = np.zeros((1, 30, 30), np.uint8)
    paint_runs(found.runs, found.offsets, np.array([0]), np.array([0]), np.array([0]), painted, 0)
    assert painted[0, 15, 15] == 1 and painted[0, 15, 9] == 1  # the dot, and the hole around it
    assert_same_blobs(image, 500)


def test_runs_reaching_row_ends_and_block_edges():
    width = 2 * BLOCK + 3
    image = np.zeros((6, width), np.uint16)
    image[1, BLOCK - 2 : BLOCK + 2] = 9  # across a block edge
    image[2, width - 5 :] = 9  # to the row's end, in the partial last block
    image[3, :] = 9  # the whole row
    image[5, BLOCK - 1] = 9  # the last pixel of a block, alone
    found = blob_runs(image, 0)
    runs = {tuple(r) for r in found.runs.tolist()}
    assert {(1, BLOCK - 2, BLOCK + 2), (2, width - 5, width), (3, 0, width), (5, BLOCK - 1, BLOCK)} == runs
    assert_same_blobs(image, 0)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.int32])
def test_integer_types_and_thresholds_at_their_limits(dtype):
    info = np.iinfo(dtype)
    image = np.full((5, 70), info.max, dtype)
    image[2, 10:20] = info.min
    assert len(blob_runs(image, info.max)) == 0  # nothing is above the highest value
    everything = blob_runs(image, info.min - 1)  # everything is above: one blob, the frame
    assert len(everything) == 1 and everything.area[0] == image.size
    holed = blob_runs(image, info.min)  # the frame less a dent: its hole filled
    assert holed.boxes.tolist() == [[0, 0, 70, 5]] and holed.area[0] == image.size


@pytest.mark.parametrize("grow", [0, 1, 2, 3])
def test_painted_dilation_is_cv2_dilate_by_the_disc(grow):
    rng = np.random.default_rng(grow)
    image = (rng.random((25, 40)) < 0.08).astype(np.uint8)
    found = blob_runs(image, 0)
    y, x = np.mgrid[-grow : grow + 1, -grow : grow + 1]
    kernel = (x * x + y * y <= (grow + 0.5) ** 2).astype(np.uint8)
    # a window that cuts the frame: the whole blob's dilation, clipped to the window
    x0, y0 = 5, 3
    painted = np.zeros((len(found), 18, 30), np.uint8)
    blobs = np.arange(len(found))
    paint_runs(found.runs, found.offsets, blobs, np.full_like(blobs, x0), np.full_like(blobs, y0), painted, grow)
    for b in blobs:
        alone = np.zeros_like(image)
        for r, s, e in found.runs[found.offsets[b] : found.offsets[b + 1]].tolist():
            alone[r, s:e] = 1
        dilated = cv2.dilate(alone, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        np.testing.assert_array_equal(painted[b], dilated[y0 : y0 + 18, x0 : x0 + 30])
