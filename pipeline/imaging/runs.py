"""Threshold and connected blobs of a frame as pixel runs, in one compiled pass.

One job: from an (H, W) integer image and a threshold, the blobs of
:mod:`crossfield.imaging.blobs` step 3: the 8-connected components of the
pixels strictly above the threshold, each with its holes filled (what
``cv2.findContours(RETR_EXTERNAL)`` and a filled ``cv2.drawContours`` of each
outer contour give; ``tests/centroid/test_blob_runs.py`` holds them to it). A blob
lying inside another's hole is part of that blob, as it is no outer contour.

A blob is a list of runs: (row, first column, end column) with the end
exclusive, in raster order. The method (Rosenfeld & Pfaltz 1966; the
run-based form of He, Chao & Suzuki 2008):

1. Scan each row in blocks of ``BLOCK`` pixels: a block with no pixel above
   the threshold (nearly all of a target frame) is skipped after one
   vectorised 0/1 OR; the others become a 64-bit mask whose rising and
   falling edges are the runs. The frame is read once and nothing
   full-frame is written.
2. Union-find over the runs: a run joins every run of the row above that
   overlaps it, or touches it diagonally (8-connectivity: columns
   [s1, e1) and [s2, e2) connect if s1 <= e2 and s2 <= e1).
3. Labels in raster order of each blob's first run; bounding box and run
   count per label.
4. Holes: only a blob with two runs in one row can have one. For those, the
   pixels of the bounding box (plus a 1-pixel frame) not reached from the
   frame by a 4-connected flood fill of non-blob pixels are the filled blob
   (holes are 4-connected where blobs are 8-connected: Suzuki & Abe 1985);
   its runs replace the blob's, and a blob with a pixel there is absorbed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

__all__ = ["BLOCK", "BlobRuns", "blob_runs", "paint_runs"]

#: pixels per block of the threshold scan: one vectorised 0/1 OR per block, a 64-bit mask of the hits
BLOCK = 64


@dataclass(frozen=True)
class BlobRuns:
    """The filled blobs of one frame, as runs.

    runs: (R, 3) int64 (row, first column, end column exclusive), grouped by
    blob, each blob's runs in raster order; offsets: (N + 1,) blob b's runs
    are ``runs[offsets[b]:offsets[b + 1]]``; boxes: (N, 4) int64 the
    bounding boxes (x, y, w, h) as ``cv2.boundingRect``'s (px); area: (N,)
    pixels of each filled blob. Blobs in raster order of their first pixel.
    """

    runs: np.ndarray
    offsets: np.ndarray
    boxes: np.ndarray
    area: np.ndarray

    def __len__(self) -> int:
        return len(self.boxes)


def blob_runs(image: np.ndarray, threshold_dn: int) -> BlobRuns:
    """The filled 8-connected blobs of the pixels of the (H, W) integer
    ``image`` strictly above ``threshold_dn`` (module docstring)."""
    image = np.ascontiguousarray(image)
    threshold = int(threshold_dn)
    if image.dtype.kind in "ui":
        limits = np.iinfo(image.dtype)
        if threshold >= limits.max:  # nothing can be above
            threshold, image = limits.max, image[:0]
        elif threshold < limits.min:  # everything is: compare in a wider type
            image = image.astype(np.int64)
    runs = _scan_runs(image, image.dtype.type(threshold))
    runs, offsets, boxes, area = _label_runs(runs)
    return BlobRuns(runs, offsets, boxes, area)


@numba.njit(cache=True, nogil=True)
def _block_flags(image, threshold):
    """(H, ceil(W / BLOCK)) uint8: 1 where a block of a row has a pixel > threshold.

    A 0/1 OR over each block, in a loop of its own so that the compiler
    vectorises it (it does not inside :func:`_scan_runs`' bit work, nor a max
    reduction). A partial last block is tested as the last ``BLOCK`` pixels
    of the row (1 if the row is shorter)."""
    height, width = image.shape
    blocks = -(-width // BLOCK)
    flags = np.ones((height, blocks), np.uint8)
    if width < BLOCK:
        return flags
    whole = width // BLOCK
    tail = width - BLOCK  # the first column of the last BLOCK pixels
    for r in range(height):
        row = image[r]
        for b in range(whole):
            c0 = b * BLOCK
            above = np.uint8(0)
            for k in range(BLOCK):
                above |= np.uint8(row[c0 + k] > threshold)
            flags[r, b] = above
        if whole < blocks:
            above = np.uint8(0)
            for k in range(BLOCK):
                above |= np.uint8(row[tail + k] > threshold)
            flags[r, whole] = above
    return flags


@numba.njit(cache=True, nogil=True, inline="always")
def _block_bits(row, c0, count, threshold):
    """uint64 with bit k set where row[c0 + k] > threshold, k < count <= 64."""
    bits = np.uint64(0)
    for k in range(count):
        bits |= np.uint64(row[c0 + k] > threshold) << np.uint64(k)
    return bits


@numba.njit(cache=True, nogil=True)
def _scan_runs(image, threshold):
    """Step 1: (R, 3) int64 runs of pixels > ``threshold`` (of the image's dtype), raster order.

    Each flagged block's pixels become a 64-bit mask; the runs' starts are its
    rising edges (bit set, the one before clear: ``bits & ~(bits << 1 | carry)``)
    and their ends the falling ones, taken lowest first."""
    height, width = image.shape
    flags = _block_flags(image, threshold)
    blocks = flags.shape[1]
    runs = np.empty((1024, 3), np.int64)
    n = 0
    one = np.uint64(1)
    for r in range(height):
        row = image[r]
        carry = np.uint64(0)  # 1: the previous block's last pixel is above
        start = 0
        for b in range(blocks):
            c0 = b * BLOCK
            count = min(BLOCK, width - c0)
            if not flags[r, b]:
                bits = np.uint64(0)
            elif count == BLOCK or width < BLOCK:
                bits = _block_bits(row, c0, count, threshold)
            else:  # the partial last block, as its flag was taken: the row's last BLOCK pixels
                bits = _block_bits(row, width - BLOCK, BLOCK, threshold) >> np.uint64(BLOCK - count)
            if not (bits | carry):
                continue
            before = (bits << one) | carry  # bit k: pixel c0 + k - 1 is above
            rise = bits & ~before
            fall = ~bits & before
            if count < BLOCK:
                fall &= (one << np.uint64(count)) - one
            while rise | fall:  # the edges in column order
                at_rise = trailing_zeros(rise) if rise else BLOCK
                at_fall = trailing_zeros(fall) if fall else BLOCK
                if at_rise < at_fall:
                    start = c0 + at_rise
                    rise &= rise - one
                else:
                    if n == len(runs):
                        runs = _grown(runs)
                    runs[n, 0], runs[n, 1], runs[n, 2] = r, start, c0 + at_fall
                    n += 1
                    fall &= fall - one
            carry = (bits >> np.uint64(count - 1)) & one
        if carry:  # a run reaching the row's end
            if n == len(runs):
                runs = _grown(runs)
            runs[n, 0], runs[n, 1], runs[n, 2] = r, start, width
            n += 1
    return runs[:n]


@numba.njit(cache=True, nogil=True)
def _grown(runs):
    grown = np.empty((2 * len(runs), 3), np.int64)
    grown[: len(runs)] = runs
    return grown


@numba.njit(cache=True, nogil=True)
def _find(parent, i):
    while parent[i] != i:  # path halving
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(cache=True, nogil=True)
def _label_runs(runs):
    """Steps 2-4: (runs grouped by blob, offsets (N + 1,), boxes (N, 4), area (N,))."""
    count = len(runs)
    parent = np.arange(count)
    # step 2: the previous row's runs are runs[above:here] when they lie on row r - 1
    above = here = 0
    while here < count:
        r = runs[here, 0]
        end = here
        while end < count and runs[end, 0] == r:
            end += 1
        if above < here and runs[above, 0] == r - 1:
            p = above
            for q in range(here, end):
                s, e = runs[q, 1], runs[q, 2]
                while p < here and runs[p, 2] < s:  # ends left of this and every later run
                    p += 1
                k = p
                while k < here and runs[k, 1] <= e:
                    a, b = _find(parent, q), _find(parent, k)
                    if a != b:  # the root is the earlier run: labels in raster order
                        if a < b:
                            parent[b] = a
                        else:
                            parent[a] = b
                    k += 1
        above, here = here, end
    # step 3: labels, boxes (x0, y0, x1, y1 inclusive), runs per label, rows with two runs
    label = np.empty(count, np.int64)
    of_root = np.full(count, -1)
    n = 0
    for i in range(count):
        root = _find(parent, i)
        if of_root[root] < 0:
            of_root[root] = n
            n += 1
        label[i] = of_root[root]
    box = np.empty((n, 4), np.int64)
    box[:, 0] = np.iinfo(np.int64).max
    box[:, 1] = np.iinfo(np.int64).max
    box[:, 2] = -1
    box[:, 3] = -1
    per_label = np.zeros(n, np.int64)
    last_row = np.full(n, -1)
    gaps = np.zeros(n, np.bool_)
    for i in range(count):
        b = label[i]
        r = runs[i, 0]
        box[b, 0] = min(box[b, 0], runs[i, 1])
        box[b, 1] = min(box[b, 1], r)
        box[b, 2] = max(box[b, 2], runs[i, 2] - 1)
        box[b, 3] = max(box[b, 3], r)
        per_label[b] += 1
        if last_row[b] == r:
            gaps[b] = True
        last_row[b] = r
    offsets = np.zeros(n + 1, np.int64)
    for b in range(n):
        offsets[b + 1] = offsets[b] + per_label[b]
    grouped = np.empty((count, 3), np.int64)
    fill = offsets[:-1].copy()
    for i in range(count):  # stable: each label's runs stay in raster order
        b = label[i]
        grouped[fill[b]] = runs[i]
        fill[b] += 1
    # step 4: holes, and blobs inside them
    absorbed = np.zeros(n, np.bool_)
    extra = np.empty((256, 3), np.int64)  # the filled blobs' runs, blob after blob
    extra_n = 0
    extra_from = np.full(n, -1)
    extra_to = np.full(n, -1)
    for b in range(n):
        if not gaps[b] or absorbed[b]:
            continue
        x0, y0, x1, y1 = box[b, 0] - 1, box[b, 1] - 1, box[b, 2] + 1, box[b, 3] + 1
        h, w = y1 - y0 + 1, x1 - x0 + 1
        grid = np.zeros((h, w), np.uint8)  # 1: blob, 2: outside (reached), 0: hole
        for i in range(offsets[b], offsets[b + 1]):
            grid[grouped[i, 0] - y0, grouped[i, 1] - x0 : grouped[i, 2] - x0] = 1
        stack = np.empty((h * w, 2), np.int64)
        grid[0, 0] = 2
        stack[0, 0], stack[0, 1] = 0, 0
        top = 1
        while top:
            top -= 1
            y, x = stack[top, 0], stack[top, 1]
            for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w and grid[yy, xx] == 0:
                    grid[yy, xx] = 2
                    stack[top, 0], stack[top, 1] = yy, xx
                    top += 1
        holes = 0
        for y in range(h):
            for x in range(w):
                holes += grid[y, x] == 0
        if holes == 0:
            continue
        # blobs with a pixel in a hole are inside it (their first pixel suffices: they
        # cannot cross this blob's boundary without joining it)
        for c in range(n):
            if c != b and not absorbed[c]:
                r0, c0 = grouped[offsets[c], 0], grouped[offsets[c], 1]
                if y0 < r0 < y1 and x0 < c0 < x1 and grid[r0 - y0, c0 - x0] == 0:
                    absorbed[c] = True
        extra_from[b] = extra_n
        for y in range(1, h - 1):
            x = 1
            while x < w - 1:
                if grid[y, x] != 2:
                    start = x
                    while x < w - 1 and grid[y, x] != 2:
                        x += 1
                    if extra_n == len(extra):
                        grown = np.empty((2 * extra_n, 3), np.int64)
                        grown[:extra_n] = extra
                        extra = grown
                    extra[extra_n, 0], extra[extra_n, 1], extra[extra_n, 2] = y + y0, start + x0, x + x0
                    extra_n += 1
                x += 1
        extra_to[b] = extra_n
    # the output: kept blobs, filled runs where there were holes
    keep = 0
    total = 0
    for b in range(n):
        if not absorbed[b]:
            keep += 1
            total += extra_to[b] - extra_from[b] if extra_from[b] >= 0 else per_label[b]
    out_runs = np.empty((total, 3), np.int64)
    out_offsets = np.zeros(keep + 1, np.int64)
    out_boxes = np.empty((keep, 4), np.int64)
    out_area = np.zeros(keep, np.int64)
    j = 0
    k = 0
    for b in range(n):
        if absorbed[b]:
            continue
        if extra_from[b] >= 0:
            src = extra[extra_from[b] : extra_to[b]]
        else:
            src = grouped[offsets[b] : offsets[b + 1]]
        for i in range(len(src)):
            out_runs[k] = src[i]
            out_area[j] += src[i, 2] - src[i, 1]
            k += 1
        out_offsets[j + 1] = k
        out_boxes[j, 0] = box[b, 0]
        out_boxes[j, 1] = box[b, 1]
        out_boxes[j, 2] = box[b, 2] - box[b, 0] + 1
        out_boxes[j, 3] = box[b, 3] - box[b, 1] + 1
        j += 1
    return out_runs, out_offsets, out_boxes, out_area


@numba.njit(cache=True, nogil=True)
def paint_runs(runs, offsets, blobs, xs, ys, out, grow):
    """Sets out[t] to 1 on blob ``blobs[t]``'s pixels, grown by ``grow`` px.

    runs, offsets: :class:`BlobRuns`'; blobs: (T,) blob indices; xs, ys: (T,)
    the image column and row of out[t]'s pixel (0, 0); out: (T, H, W) uint8,
    painted where blob and slice overlap (the rest is left as it is). grow:
    the radius d of the dilation by the digital disc x^2 + y^2 <= (d + 0.5)^2
    (``cv2.dilate`` by that kernel, on a zero border), each run widened by
    floor(sqrt((d + 0.5)^2 - dy^2)) on row offset dy; 0: the blob itself.
    """
    height, width = out.shape[1], out.shape[2]
    reach = np.empty(2 * grow + 1, np.int64)
    for dy in range(-grow, grow + 1):
        reach[dy + grow] = int(math.floor(math.sqrt((grow + 0.5) ** 2 - dy * dy)))
    for t in range(len(blobs)):
        b = blobs[t]
        for i in range(offsets[b], offsets[b + 1]):
            r = runs[i, 0] - ys[t]
            for dy in range(-grow, grow + 1):
                row = r + dy
                if row < 0 or row >= height:
                    continue
                lo = max(runs[i, 1] - xs[t] - reach[dy + grow], 0)
                hi = min(runs[i, 2] - xs[t] + reach[dy + grow], width)
                for c in range(lo, hi):
                    out[t, row, c] = 1
