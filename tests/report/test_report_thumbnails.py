"""report.html's "Cameras" section: one thumbnail per camera with the targets labelled
(pipeline/report/thumbnails.py, figures.thumbnail_chart, docs/report.md "Cameras").

Ground truth: the simulator's true target positions projected into each camera
with OpenCV (cv2.projectPoints), the recorded session replayed, block means
against cv2.resize(INTER_AREA)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from crossfield.config import parse_config
from crossfield.chain.registry import make_plugin_manager
from crossfield.replay import replay_session
from crossfield.report import thumbnails as T
from crossfield.report.figures import LABEL_OFFSET, THUMBNAIL_GID
from crossfield.chain.runner import run_session
from crossfield.session import FrameResult
from crossfield.types import CAMERAS, CentroidSet, StereoCentroids, StereoFrame

SVG = "{http://www.w3.org/2000/svg}"
N_FRAMES = 3


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A recorded table3 session, with a second ThumbnailObserver of the test's own."""
    out = tmp_path_factory.mktemp("thumbs")
    spy = T.ThumbnailObserver()
    config = parse_config({
        "session": {"output_dir": str(out), "name": "live", "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": "table3", "frames": N_FRAMES, "seed": 5},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
    }, "<test>")
    summary = run_session(config, make_plugin_manager(), observers=[spy])
    return summary, spy


@pytest.fixture(scope="module")
def replayed(live, tmp_path_factory):
    summary, _ = live
    return replay_session(summary.info.out_dir / "session.mcap", make_plugin_manager(),
                          output_dir=tmp_path_factory.mktemp("thumbs-replay"), record=False, rerun=False)


def camera_svg(page: str, camera: str) -> ET.Element:
    match = re.search(rf'<figure class="chart thumbnail" id="figure-camera-{camera}">(<svg.*?</svg>)', page, re.S)
    assert match, f"no thumbnail of the {camera} camera in report.html"
    return ET.fromstring(match.group(1))


def by_id(root: ET.Element, gid: str) -> ET.Element:
    found = [e for e in root.iter() if e.get("id") == gid]
    assert len(found) == 1, (gid, len(found))
    return found[0]


def image_mapping(root: ET.Element, camera: str, shape: tuple[int, int]):
    """thumbnail px (u, v) -> SVG units, from the embedded <image>'s size and transform."""
    image = by_id(root, THUMBNAIL_GID["image"].format(camera=camera))
    assert image.get(f"{{http://www.w3.org/1999/xlink}}href").startswith("data:image/png;base64,")
    a, b, c, d, e, f = map(float, re.fullmatch(r"matrix\(([^)]*)\)", image.get("transform")).group(1).split())
    assert b == c == 0.0 and (int(image.get("height")), int(image.get("width"))) == shape
    return lambda uv: np.column_stack([e + a * (uv[:, 0] + 0.5), f + d * (uv[:, 1] + 0.5)]), a


def true_pixels(summary, camera: str) -> dict[str, np.ndarray]:
    """id -> (2,) px of every plan point's true centre projected into ``camera`` (OpenCV)."""
    gt, cal = summary.info.ground_truth, summary.info.calibration
    ids = [*summary.info.plan.control_ids, *(t.id for t in summary.info.plan.targets)]
    X = gt.camera_points(ids)
    if camera == "upper":
        rvec, tvec = np.zeros(3), np.zeros(3)
    else:
        rvec, tvec = cv2.Rodrigues(cal.R_lower_upper)[0].ravel(), cal.t_lower_upper
    intr = cal.camera(camera)
    uv, _ = cv2.projectPoints(X, rvec, tvec, intr.camera_matrix, intr.dist_coeffs)
    return dict(zip(ids, uv.reshape(-1, 2)))


# ---- the report of a simulator session -------------------------------------------------


def test_the_report_shows_a_thumbnail_of_each_camera_with_exactly_the_target_ids(live):
    summary, _ = live
    page = (summary.info.out_dir / "report.html").read_text(encoding="utf-8")
    assert '<section id="cameras">' in page and "<h2>Cameras</h2>" in page
    plan = summary.info.plan
    expected = {*plan.control_ids, *(t.id for t in plan.targets)}
    assert [t.camera for t in summary.thumbnails] == list(CAMERAS)
    for thumb in summary.thumbnails:
        assert thumb.status == "measured" and thumb.sequence == summary.frames[0].sequence
        root = camera_svg(page, thumb.camera)
        prefix = THUMBNAIL_GID["label"].format(camera=thumb.camera, label="")
        texts = {e.get("id")[len(prefix):]: "".join(e.itertext()).strip()
                 for e in root.iter(f"{SVG}g") if e.get("id", "").startswith(prefix)}
        assert set(texts.values()) == expected and len(texts) == len(expected)  # each id once
        assert all(gid == text for gid, text in texts.items())
        assert set(thumb.labels) - {""} == expected


def test_the_markers_are_on_the_centroids_and_each_label_on_its_true_target(live):
    summary, _ = live
    page = (summary.info.out_dir / "report.html").read_text(encoding="utf-8")
    for thumb in summary.thumbnails:
        root = camera_svg(page, thumb.camera)
        to_svg, px = image_mapping(root, thumb.camera, thumb.image.shape)
        f = thumb.factor
        assert thumb.image.shape == (thumb.full_size[0] // f, thumb.full_size[1] // f)
        assert thumb.image.shape[1] <= T.MAX_WIDTH_PX < thumb.full_size[1] // (f - 1)
        kinds = np.array(thumb.kinds)
        for kind in (T.KIND_CONTROL, T.KIND_TARGET):
            group = by_id(root, THUMBNAIL_GID[kind].format(camera=thumb.camera))
            drawn = np.array([[float(u.get("x")), float(u.get("y"))] for u in group.iter(f"{SVG}use")])
            # the centroids in image px, scaled: (uv - (f - 1) / 2) / f, then onto the SVG image
            scaled = (thumb.uv[kinds == kind] - (f - 1) / 2) / f
            assert np.abs(drawn - to_svg(scaled)).max() < px  # within one thumbnail pixel
        truth = true_pixels(summary, thumb.camera)
        for label in set(thumb.labels) - {""}:
            text = by_id(root, THUMBNAIL_GID["label"].format(camera=thumb.camera, label=label)).find(f"{SVG}text")
            anchor = np.array([float(text.get("x")) - LABEL_OFFSET[0], float(text.get("y")) + LABEL_OFFSET[1]])
            where = to_svg(((truth[label] - (f - 1) / 2) / f)[None])[0]
            assert np.abs(anchor - where).max() < px, (thumb.camera, label, anchor, where)


def test_the_observer_keeps_one_small_image_per_camera_after_the_session(live):
    summary, spy = live
    assert summary.frames_processed == N_FRAMES
    kept = spy.thumbnails()
    assert len(kept) == len(CAMERAS) and spy._frame is None
    held = sum(a.nbytes for a in _arrays(vars(spy)))
    assert held == sum(t.image.nbytes + t.uv.nbytes for t in kept)
    assert all(t.image.nbytes < t.full_size[0] * t.full_size[1] / 10 for t in kept)
    for mine, runners in zip(kept, summary.thumbnails):
        assert np.array_equal(mine.image, runners.image) and mine.labels == runners.labels


def _arrays(value, seen=None):
    seen = set() if seen is None else seen
    if id(value) in seen:
        return []
    seen.add(id(value))
    if isinstance(value, np.ndarray):
        return [value]
    if isinstance(value, dict):
        items = value.values()
    elif isinstance(value, (list, tuple)):
        items = value
    elif hasattr(value, "__dataclass_fields__") or hasattr(value, "__dict__"):
        items = vars(value).values()
    else:
        return []
    return [a for item in items for a in _arrays(item, seen)]


def test_a_replay_draws_the_same_thumbnails_from_the_recorded_frames(live, replayed):
    summary, _ = live
    assert [t.camera for t in replayed.thumbnails] == list(CAMERAS)
    for a, b in zip(summary.thumbnails, replayed.thumbnails):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.uv, b.uv)
        assert (a.labels, a.kinds, a.sequence, a.factor) == (b.labels, b.kinds, b.sequence, b.factor)
    page = (replayed.info.out_dir / "report.html").read_text(encoding="utf-8")
    original = (summary.info.out_dir / "report.html").read_text(encoding="utf-8")
    for camera in CAMERAS:
        assert re.search(rf'id="figure-camera-{camera}">(<svg.*?</svg>)', page, re.S).group(1) == re.search(
            rf'id="figure-camera-{camera}">(<svg.*?</svg>)', original, re.S).group(1)


def test_the_thumbnails_keep_the_report_small(live):
    summary, _ = live
    page = (summary.info.out_dir / "report.html").read_text(encoding="utf-8")
    for camera in CAMERAS:
        figure = re.search(rf'id="figure-camera-{camera}">(<svg.*?</svg>)', page, re.S).group(1)
        assert len(figure) < 80_000, (camera, len(figure))  # PNG data URI + markers + labels


# ---- the kernels ---------------------------------------------------------------------


def test_downsample_is_the_block_mean():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 4096, size=(403, 1001), dtype=np.uint16)  # 12-bit DN
    small, f = T.downsample(image, 12, max_width=480)
    assert f == 3 and small.shape == (134, 333) and small.dtype == np.uint8
    blocks = image[: 134 * 3, : 333 * 3].reshape(134, 3, 333, 3).astype(np.float64)
    reference = blocks.mean(axis=(1, 3)) * (255.0 / 4095.0)  # the last 1001 mod 3 columns, 403 mod 3 rows dropped
    assert np.abs(small - reference).max() <= 0.5 + 1e-3
    eight, f8 = T.downsample(image[:100, :300].astype(np.uint8), 8, max_width=300)
    assert f8 == 1 and np.array_equal(eight, image[:100, :300].astype(np.uint8))


def test_a_spot_lands_where_thumbnail_uv_puts_it():
    """A Gaussian spot centred at (u, v) image px: the intensity-weighted centre of the
    thumbnail is at (u - (f - 1) / 2) / f (the OpenCV pixel-centre convention)."""
    h, w, u0, v0 = 240, 960, 401.3, 97.8
    vv, uu = np.mgrid[0:h, 0:w]
    image = np.rint(4000 * np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * 9.0**2))).astype(np.uint16)
    small, f = T.downsample(image, 12, max_width=240)
    assert f == 4
    weights = small.astype(float)
    sv, su = np.mgrid[0 : small.shape[0], 0 : small.shape[1]]
    centre = np.array([(weights * su).sum(), (weights * sv).sum()]) / weights.sum()
    thumb = T.CameraThumbnail("upper", 0, small, f, (h, w), [[u0, v0]], ("P1",), (T.KIND_TARGET,), "measured")
    assert np.abs(centre - thumb.thumbnail_uv()[0]).max() < 0.02


def _centroids(camera: str, seq: int, uv) -> CentroidSet:
    n = len(uv)
    return CentroidSet(camera, seq, uv, np.full((n, 2), 0.05), np.full(n, 30.0), np.ones(n), np.full(n, 900.0))


def test_the_observer_keeps_the_first_best_pair_and_downsamples_rarely(monkeypatch):
    """Pair 0 failed in its centroid stage, pairs 1..49 got only as far as centroids:
    pair 1 is kept (pair 0 until then), each downsampled once per camera, and no pair
    is held after its on_frame_done."""
    calls = []
    real = T.downsample
    monkeypatch.setattr(T, "downsample", lambda *a, **k: calls.append(1) or real(*a, **k))
    spy = T.ThumbnailObserver(max_width=100)
    image = np.zeros((120, 400), np.uint16)
    for seq in range(50):
        frame = StereoFrame(seq, 1000 + seq, image, image)
        spy.on_frame(frame=frame)
        cents = None if seq == 0 else StereoCentroids(
            seq, _centroids("upper", seq, [[10.0, 20.0]]), _centroids("lower", seq, [[12.0, 20.0]]))
        spy.on_frame_done(result=FrameResult(seq, 1000 + seq, centroids=cents, error="x" if seq == 0 else None))
        assert spy._frame is None
        if seq == 0:
            assert [(t.sequence, t.status, len(t.uv)) for t in spy.thumbnails()] == [(0, "image", 0)] * 2
    kept = spy.thumbnails()
    assert [(t.camera, t.sequence, t.status, t.labels) for t in kept] == [
        ("upper", 1, "centroids", ("",)), ("lower", 1, "centroids", ("",))]
    assert len(calls) == 2 * len(CAMERAS)  # pairs 0 and 1 only, for the whole session
    assert kept[0].image.shape == (30, 100) and kept[0].factor == 4
    assert np.array_equal(kept[1].uv, [[12.0, 20.0]])
    with pytest.raises(ValueError, match="max_width"):
        T.ThumbnailObserver(max_width=0)


def test_a_label_from_the_plan_is_text_not_markup():
    from crossfield.report.figures import thumbnail_chart

    label = '<script>alert(1)</script>" onload="x'
    thumb = T.CameraThumbnail("upper", 0, np.zeros((30, 40), np.uint8), 1, (30, 40), [[5.0, 5.0]],
                              (label,), (T.KIND_TARGET,), "measured")
    text = thumbnail_chart(thumb)
    assert "<script" not in text and "&lt;script&gt;" in text
    root = ET.fromstring(text)  # well-formed XML
    texts = ["".join(e.itertext()) for e in root.iter(f"{SVG}text")]
    assert texts == [label] and not list(root.iter(f"{SVG}script"))
