"""The Rerun visualisation: logger content, MCAP -> logger, and the real viewer.

One simulated session (the station scenario, 3 pairs, MCAP and .rrd) is
shared by every test. The .rrd is read back with rerun's chunk reader and
checked against the session's own results (every drawn segment has the
length the characteristic reports, arrows are the registration residuals
magnified, centroids carry their plan ids...). The viewer tests start the
real Rerun viewer headless (Mesa lavapipe; ``make test`` installs it),
take a screenshot first and then read every view's error reports through
``rerun.experimental.ViewerClient``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from crossfield.cli import main
from crossfield.config import parse_config
from crossfield.errors import ConfigError, RecordingError
from crossfield.geometry import fit_cylinder_axis
from crossfield.hookspecs import hookimpl
from crossfield.recording.reader import open_recording
from crossfield.chain.registry import make_plugin_manager
from crossfield.viz.blueprint import (
    VIEW_3D,
    VIEW_CAMERA,
    VIEW_DEVIATION,
    VIEW_REPORT,
    VIEW_RESIDUALS,
    station_eye,
)
from crossfield.viz.rerun_log import COLOURS, RESIDUAL_SCALE, RerunLogger, characteristic_segment
from crossfield.viz.rerun_mcap import log_recording
from crossfield.chain.runner import run_session
from crossfield.types import Line3D
from crossfield.viz.view import HeadlessViewer, png_is_blank, rerun_executable

FRAMES = 3


def session_config(out: Path, name: str, **session) -> object:
    return parse_config(
        {
            "session": {"output_dir": str(out), "name": name, **session},
            "acquire": {"plugin": "simulator", "scenario": "station", "frames": FRAMES, "seed": 7},
            "reference": {"plugin": "romer-serial", "port": "simulator"},
        },
        "<test>",
    )


class FrameResults:
    """Observer keeping every pair's complete result (the summary may keep less)."""

    def __init__(self):
        self.results = []

    @hookimpl
    def on_frame_done(self, result):
        self.results.append(result)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A recorded simulator session: (summary with every pair's full result, session folder)."""
    out = tmp_path_factory.mktemp("rerun")
    collected = FrameResults()
    summary = run_session(session_config(out, "station"), make_plugin_manager(), observers=[collected])
    assert not any(f.error for f in summary.frames)
    return dataclasses.replace(summary, frames=tuple(collected.results)), summary.info.out_dir


def rrd_rows(path: Path) -> dict[str, list[tuple[int | None, dict]]]:
    """entity path -> [(frame or None for static, {component column: value})] in file order."""
    import rerun.chunk as rrc

    out: dict[str, list[tuple[int | None, dict]]] = defaultdict(list)
    for chunk in rrc.RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        frames = (
            batch.column("frame").to_pylist() if "frame" in batch.schema.names else [None] * batch.num_rows
        )
        for row in range(batch.num_rows):
            out[chunk.entity_path].append(
                (
                    frames[row],
                    {name: values[row] for name, values in columns.items() if values[row] is not None},
                )
            )
    return out


def latest(rows: dict, entity: str, column: str, frame: int | None = None):
    """The value of ``column`` at ``frame`` (latest at; static if frame is None)."""
    found = None
    for f, values in rows.get(entity, ()):
        at = f is None or (frame is not None and f <= frame)
        later = found is None or f is None or found[0] is None or f >= found[0]
        if column in values and at and later:
            found = (f, values[column])
    assert found is not None, f"{entity}: no {column} at frame {frame}"
    return found[1]


def by_frame(rows: dict, entity: str) -> dict:
    """frame (None: static) -> the component values logged there (images left out)."""
    out: dict = {}
    for f, values in rows.get(entity, ()):
        out.setdefault(f, {}).update({k: v for k, v in values.items() if not k.startswith("Image:")})
    return out


def rerun_verify(path: Path) -> None:
    proc = subprocess.run(
        [rerun_executable(), "rrd", "verify", str(path)],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "RERUN_ANALYTICS": "0"},
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


# --------------------------------------------------------------------------
# What the logger writes
# --------------------------------------------------------------------------


def test_session_rrd_verifies_and_holds_the_session(sim):
    summary, folder = sim
    rrd = folder / "session.rrd"
    rerun_verify(rrd)
    rows = rrd_rows(rrd)
    last = summary.frames[-1]
    seq = last.sequence
    info = summary.info

    # Cameras: pinholes (+0.5 px), the lower camera's pose, T_global_camera per pair.
    for camera in ("upper", "lower"):
        K = (
            np.array(latest(rows, f"/world/camera/{camera}/image", "Pinhole:image_from_camera")[0])
            .reshape(3, 3)
            .T
        )
        expected = info.calibration.camera(camera).camera_matrix + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]
        assert np.allclose(K, expected, rtol=1e-6)
    fit = last.registration.fit
    t = latest(rows, "/world/camera", "Transform3D:translation", seq)
    assert np.allclose(np.array(t) * 1000.0, fit.t, atol=1e-3)

    # Centroids: Rerun pixel convention (+0.5), labelled with the control id they were matched to.
    labels = latest(rows, "/world/camera/upper/image/centroids", "Points2D:labels", seq)
    uv = np.array(latest(rows, "/world/camera/upper/image/centroids", "Points2D:positions", seq))
    assert np.allclose(uv - 0.5, last.centroids.upper.uv, atol=1e-3)
    points, corr = last.points, last.registration.correspondence
    for cid, k in zip(corr.control_ids, corr.camera_index):
        assert labels[int(points.upper_index[k])] == cid
    for tid in last.measurement.target_points:
        assert tid in labels

    # CMM elements (static): controls, reference points, line probes, by their plan labels.
    assert set(latest(rows, "/world/cmm/controls", "Points3D:labels")) == set(info.plan.control_ids)
    assert latest(rows, "/world/cmm/reference_points", "Points3D:labels") == list(
        info.plan.reference_point_ids
    )
    probes = latest(rows, "/world/cmm/line_probes", "Points3D:labels")
    assert probes == [label for label in info.plan.probing_order() if label.startswith("L3.")]

    # Residual vectors: from each CMM control point, camera minus CMM, magnified.
    by_label = summary.reference.by_label()
    origins = np.array(latest(rows, "/world/registration/residuals", "Arrows3D:origins", seq)) * 1000.0
    vectors = np.array(latest(rows, "/world/registration/residuals", "Arrows3D:vectors", seq)) * 1000.0
    q = np.array([by_label[c].xyz for c in corr.control_ids])
    assert np.allclose(origins, q, atol=1e-3)
    assert np.allclose(vectors / RESIDUAL_SCALE, fit.residuals, atol=1e-6)
    measured = np.array(latest(rows, "/world/registration/controls", "Points3D:positions", seq)) * 1000.0
    assert np.allclose(measured - q, fit.residuals, atol=2e-3)  # float32 metres: ~0.06 um resolution

    # The fitted axis lies on the simulator's true L3 axis (within the CMM noise).
    truth = info.ground_truth.lines_global["L3"]
    ends = np.array(latest(rows, "/world/cmm/axes/L3", "LineStrips3D:strips")[0]) * 1000.0
    assert max(truth.distance(p) for p in ends) < 0.1
    assert np.linalg.norm(ends[1] - ends[0]) > 50.0

    # Every characteristic is a segment as long as its measured value, coloured by pass/fail.
    for c in last.measurement.characteristics:
        entity = f"/world/characteristics/{c.name}"
        segment = np.array(latest(rows, entity, "LineStrips3D:strips", seq)[0]) * 1000.0
        assert np.linalg.norm(segment[1] - segment[0]) == pytest.approx(c.measured_mm, abs=2e-3), c.name
        label = latest(rows, entity, "LineStrips3D:labels", seq)[0]
        assert label.startswith(f"{c.name} {c.measured_mm:.4f} mm")
        colour = latest(rows, entity, "LineStrips3D:colors", seq)[0]
        assert colour >> 8 == int.from_bytes(bytes(COLOURS["pass" if c.passed else "fail"]), "big")

    # Series over the pairs, the report and the session documents.
    rms = [values["Scalars:scalars"][0] for f, values in rows["/registration/rms_mm"] if f is not None]
    assert rms == [f.registration.fit.rms_mm for f in summary.frames]
    for cid in corr.control_ids:
        assert (
            len([1 for f, v in rows[f"/registration/residual_mm/{cid}"] if "Scalars:scalars" in v]) == FRAMES
        )
    report = latest(rows, "/report", "TextDocument:text")[0]
    assert report.startswith("# PASS" if summary.passed else "# FAIL")
    for k, c in enumerate(summary.characteristics, start=1):
        assert f"| {k} | {c.name} | {c.n} | {c.measured_mm:.4f} | {c.uncertainty_mm:.4f} | " in report
        assert f" | {c.expanded_uncertainty_mm:.4f} | " in report
    assert "x1000" in latest(rows, "/session", "TextDocument:text")[0]


def test_images_are_every_fifth_pair_by_default_and_scaled_to_16_bits(sim):
    summary, folder = sim
    rows = rrd_rows(folder / "session.rrd")
    frames = [f for f, v in rows["/world/camera/lower/image"] if "Image:buffer" in v]
    assert frames == [f.sequence for f in summary.frames if f.sequence % 5 == 0] == [0]
    with open_recording(folder / "session.mcap") as rec:
        m = next(iter(rec.messages("/camera/lower/image")))
        raw = np.frombuffer(m.decoded.data, "<u2").reshape(m.decoded.height, m.decoded.width)
    shown = latest(rows, "/world/camera/lower/image", "Image:buffer", frames[0])
    assert np.array_equal(np.array(shown, dtype=np.uint8).view("<u2").reshape(raw.shape), raw << 4)


def test_image_every_n_from_the_session_config(tmp_path):
    config = session_config(tmp_path, "sparse", record=False, rerun_image_every=2)
    summary = run_session(config, make_plugin_manager())
    rows = rrd_rows(summary.info.out_dir / "session.rrd")
    assert [f for f, v in rows["/world/camera/upper/image"] if "Image:buffer" in v] == [0, 2]
    # centroids and points of every pair regardless
    assert [f for f, v in rows["/world/camera/upper/image/centroids"] if "Points2D:positions" in v] == [
        0,
        1,
        2,
    ]
    with pytest.raises(ConfigError, match="rerun_image_every"):
        run_session(
            session_config(tmp_path, "bad", record=False, rerun_image_every=-1), make_plugin_manager()
        )


def test_a_failed_stage_clears_the_older_result(sim, tmp_path):
    """A pair whose registration failed must not show the previous pair's residuals or targets."""
    summary, _ = sim
    logger = RerunLogger(tmp_path / "failed.rrd")
    first, second = summary.frames[:2]
    failed = dataclasses.replace(second, registration=None, measurement=None, error="frame 1: register: boom")
    logger.on_session_start(session=summary.info)
    logger.on_reference(reference=summary.reference)
    logger.on_frame_done(result=first)
    logger.on_frame_done(result=failed)
    # a summary with other frames than its session's: its report document is rebuilt from them
    # (report=None), as the runner builds it once at the session end from what the session holds
    logger.on_session_end(summary=dataclasses.replace(summary, frames=(first, failed), report=None))
    rerun_verify(tmp_path / "failed.rrd")
    rows = rrd_rows(tmp_path / "failed.rrd")
    for entity in ("/world/registration", "/world/targets", "/world/characteristics"):
        cleared = [f for f, v in rows[entity] if v.get("Clear:is_recursive") == [True]]
        assert cleared == [failed.sequence], entity
    # the centroids of the failed pair are still shown, without plan ids
    labels = latest(rows, "/world/camera/upper/image/centroids", "Points2D:labels", failed.sequence)
    assert labels == [str(i) for i in range(len(failed.centroids.upper))]
    assert "FAIL" in latest(rows, "/report", "TextDocument:text")[0]


def test_the_mcap_recording_gives_the_same_view_as_the_live_logger(sim, tmp_path):
    summary, folder = sim
    rrd = tmp_path / "from_mcap.rrd"
    logger = RerunLogger(rrd)
    replayed = log_recording(folder / "session.mcap", logger)
    assert logger.closed
    rerun_verify(rrd)
    assert [c.measured_mm for c in replayed.characteristics] == [
        c.measured_mm for c in summary.characteristics
    ]
    live, shown = rrd_rows(folder / "session.rrd"), rrd_rows(rrd)
    entities = {e for e in live if e.startswith(("/world", "/registration", "/measurement"))}
    assert entities == {e for e in shown if e.startswith(("/world", "/registration", "/measurement"))}
    for entity in sorted(entities):
        assert by_frame(live, entity) == by_frame(shown, entity), entity
    assert latest(live, "/report", "TextDocument:text") == latest(shown, "/report", "TextDocument:text")


def test_a_foreign_or_missing_file_is_a_clear_error(tmp_path, capsys):
    from mcap.writer import Writer

    foreign = tmp_path / "other.mcap"
    with open(foreign, "wb") as f:
        writer = Writer(f)
        writer.start(library="someone-else")
        writer.finish()
    with pytest.raises(RecordingError, match="not a crossfield session recording"):
        log_recording(foreign, RerunLogger(tmp_path / "x.rrd"))
    assert main(["view", str(tmp_path / "nothing.rrd")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["view", str(tmp_path)]) == 2
    assert "a folder without session.mcap or report.json; view wants a session folder" in capsys.readouterr().err


# --------------------------------------------------------------------------
# Geometry of what is drawn
# --------------------------------------------------------------------------


def test_characteristic_segments_measure_what_their_kind_says():
    a = np.array([10.0, 20.0, 30.0])
    line = Line3D(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    seg = characteristic_segment("point_line", a, line=line)
    assert np.allclose(seg[1], [0.0, 0.0, 30.0])  # the foot: orthogonal to the line
    assert np.linalg.norm(seg[1] - seg[0]) == pytest.approx(line.distance(a))
    assert np.allclose(characteristic_segment("depth", a)[1], [10.0, 20.0, 0.0])
    assert np.allclose(characteristic_segment("point_point", a, np.zeros(3)), [a, np.zeros(3)])
    assert characteristic_segment("point_point", a) is None


def test_station_eye_looks_across_the_scene_plane_from_slightly_above():
    """Points in the vertical plane y = -0.5 m: the eye looks at their bounding-box
    centre along the plane's normal, 10 degrees from the horizontal, from 0.85 diagonals."""
    points = np.array([[0.8, -0.5, 0.3], [1.2, -0.5, 0.6], [0.9, -0.5, 0.7], [1.1, -0.5, 0.35]])
    eye = station_eye(points)
    position = np.array(eye.position.as_arrow_array().to_pylist()[0])
    target = np.array(eye.look_target.as_arrow_array().to_pylist()[0])
    lo, hi = points.min(axis=0), points.max(axis=0)
    assert np.allclose(target, (lo + hi) / 2)
    sight = target - position
    assert np.linalg.norm(sight) == pytest.approx(0.85 * np.linalg.norm(hi - lo))
    assert abs(sight[0]) < 1e-9  # no component along the plane: perpendicular to it
    assert math.degrees(math.atan2(-sight[2], abs(sight[1]))) == pytest.approx(10.0)


def test_fitted_axis_is_the_measurement_plugins_fit(sim):
    summary, _ = sim
    from crossfield.viz.rerun_log import fit_reference_axes

    probes = np.array([p.xyz for p in summary.reference.labelled("L3") if p.label != "L3"])
    sigma = max(p.sigma_mm for p in summary.reference.labelled("L3"))
    reference_fit = fit_cylinder_axis(probes, sigma_mm=sigma)
    shown = fit_reference_axes(summary.info.plan, summary.reference)["L3"]
    assert np.allclose(shown.line.point, reference_fit.line.point)
    assert np.allclose(shown.line.direction, reference_fit.line.direction)


# --------------------------------------------------------------------------
# The real viewer, headless
# --------------------------------------------------------------------------


def colour_pixels(
    png: bytes, colour: tuple[int, int, int], box: tuple[float, float, float, float], tol: int = 40
) -> int:
    """Pixels within ``tol`` of an RGB colour inside a box given as fractions (x0, y0, x1, y1)."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1].astype(int)
    h, w = image.shape[:2]
    x0, y0, x1, y1 = box
    part = image[int(y0 * h) : int(y1 * h), int(x0 * w) : int(x1 * w)]
    return int((np.abs(part - np.array(colour)).max(axis=2) <= tol).sum())


def test_default_blueprint_renders_in_the_viewer_without_errors(sim, tmp_path):
    _, folder = sim
    with HeadlessViewer(window_size=(1600, 1000)) as viewer:
        viewer.open(folder / "session.rrd")
        viewer.show("frame")
        png = viewer.screenshot(tmp_path / "shot.png")  # the screenshot first, then the reports
        reports, shown = viewer.reports_of_every_view()  # each tab shown in turn
        names = viewer.view_names()
    assert (tmp_path / "shot.png").read_bytes() == png and not png_is_blank(png)
    assert [r for r in reports if r.severity == "error"] == []
    assert shown == set(names) and len(names) == 9  # every view of the blueprint was drawn
    assert any(n.startswith(VIEW_3D) for n in names)
    assert set(VIEW_CAMERA.values()) <= set(names)
    assert {VIEW_RESIDUALS, VIEW_DEVIATION, VIEW_REPORT} <= set(names)
    # The camera views (right column) show the orange rings of the matched control targets,
    # the 3-D view (left) the yellow fitted axis.
    assert colour_pixels(png, COLOURS["control"], (0.6, 0.03, 1.0, 0.6)) > 200
    assert colour_pixels(png, COLOURS["axis"], (0.0, 0.03, 0.6, 0.6), tol=30) > 20


def test_crossfield_view_screenshot_of_an_mcap_recording(sim, tmp_path, capsys):
    _, folder = sim
    png, rrd = tmp_path / "mcap.png", tmp_path / "kept.rrd"
    status = main(
        [
            "view",
            str(folder / "session.mcap"),
            "--screenshot",
            str(png),
            "--save",
            str(rrd),
            "--window-size",
            "1200x800",
            "--image-every",
            "1",
        ]
    )
    out = capsys.readouterr().out
    assert status == 0, out
    assert "screenshot written" in out and "error" not in out
    assert cv2.imread(str(png)).shape[:2] == (800, 1200)
    assert not png_is_blank(png.read_bytes())
    rerun_verify(rrd)
    # --image-every 1: every recorded image is in the .rrd, whatever the session logged live.
    images = [f for f, v in rrd_rows(rrd)["/world/camera/upper/image"] if "Image:buffer" in v]
    assert images == list(range(FRAMES))


def test_the_mcap_file_is_viewable_without_our_code(sim, tmp_path):
    """``rerun session.mcap``: Rerun's own MCAP import shows images, calibrations,
    point clouds and transforms, with no view reporting an error once the camera is registered."""
    summary, folder = sim
    with HeadlessViewer(window_size=(1200, 800)) as viewer:
        viewer.open(folder / "session.mcap")
        end = viewer.timeline_end("message_log_time")
        viewer.client.set_time("message_log_time", timestamp=np.datetime64(end, "ns"), play_state="paused")
        png = viewer.settled_png()
        reports = viewer.reports()
        schema = viewer.client.get_recording_schema(max_entities=1000)
    assert not png_is_blank(png)
    assert [r for r in reports if r.severity == "error"] == []
    components = {e.entity_path: {c.component for c in e.components} for e in schema.entities}
    assert "Image:buffer" in components["/camera/upper/image"]
    assert "Pinhole:image_from_camera" in components["/camera/lower/calibration"]
    assert "Points3D:positions" in components["/points/global"]
    assert "Transform3D:translation" in components["/tf"]
    assert end >= summary.frames[-1].timestamp_ns  # the cursor was after the last pair


def test_run_view_streams_live_to_a_viewer(tmp_path, capsys):
    with HeadlessViewer(window_size=(1200, 800)) as viewer:
        status = main(
            [
                "run",
                "--frames",
                "2",
                "--seed",
                "3",
                "-o",
                str(tmp_path),
                "--name",
                "live",
                "--no-record",
                "--no-rerun",
                "-q",
                "--view",
                viewer.url,
            ]
        )
        assert status in (0, 1), capsys.readouterr().err
        viewer.wait_for(lambda: viewer.timeline_end("frame") == 1, what="frame 1")
        paths = set(viewer.entity_paths())
        viewer.show("frame", 1)
        png = viewer.settled_png()
        reports = viewer.reports()
        names = viewer.view_names()
    assert not (tmp_path / "live" / "session.rrd").exists()  # --no-rerun: streamed only
    for entity in (
        "/world/camera",
        "/world/camera/upper/image",
        "/world/camera/upper/image/centroids",
        "/world/cmm/controls",
        "/world/cmm/axes/L3",
        "/world/registration/residuals",
        "/world/targets",
        "/world/characteristics/P1-L3",
        "/registration/rms_mm",
        "/report",
    ):
        assert entity in paths, entity
    assert any(n.startswith(VIEW_3D) for n in names)
    assert not png_is_blank(png)
    assert [r for r in reports if r.severity == "error"] == []


def test_view_web_serves_the_web_viewer_on_localhost(sim):
    import sys
    import time
    import urllib.request

    from crossfield.viz.view import free_port

    _, folder = sim
    port = free_port()
    crossfield = str(Path(sys.executable).parent / "crossfield")
    process = subprocess.Popen(
        [crossfield, "view", str(folder / "session.rrd"), "--web", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline, page = time.monotonic() + 30, ""
        while time.monotonic() < deadline and not page:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as response:
                    page = response.read().decode()
            except OSError:
                time.sleep(0.2)
        assert "Rerun" in page
    finally:
        process.terminate()  # SIGTERM: crossfield stops the web viewer it started
        out, _ = process.communicate(timeout=20)
    assert process.returncode == 0, out
    assert f"http://127.0.0.1:{port}/" in out


def test_run_view_without_a_display_is_a_clear_error(monkeypatch, capsys, tmp_path):
    from crossfield.viz.view import free_port

    for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr("crossfield.viz.view.LIVE_VIEWER_PORT", free_port())
    status = main(["run", "--frames", "1", "-o", str(tmp_path), "--no-record", "--no-rerun", "-q", "--view"])
    err = capsys.readouterr().err
    assert status == 2
    assert "could not start the Rerun viewer" in err and "--view URL" in err
    assert list(tmp_path.iterdir()) == []  # no session was started


def test_an_error_in_a_hidden_tab_is_reported(tmp_path):
    """The view check is not blind: a 3-D view forced to draw a 2-D image without a
    pinhole, in a tab that is not shown at first, is reported as an error."""
    import uuid

    import rerun as rr
    import rerun.blueprint as rrb

    rec = rr.RecordingStream("crossfield-test", recording_id=uuid.uuid4())
    rec.save(str(tmp_path / "bad.rrd"))
    bad = rrb.Spatial3DView(origin="/", name="Bad 3-D", overrides={"img": [rrb.Visualizer("Image")]})
    rec.send_blueprint(rrb.Blueprint(rrb.Tabs(rrb.TextDocumentView(origin="doc", name="Doc"), bad)))
    rec.log("doc", rr.TextDocument("shown first"), static=True)
    rec.set_time("frame", sequence=0)
    rec.log("img", rr.Image(np.zeros((4, 4), np.uint8)))
    rec.flush()
    rec.disconnect()
    with HeadlessViewer(window_size=(800, 600)) as viewer:
        viewer.open(tmp_path / "bad.rrd")
        viewer.show("frame")
        viewer.settled_png()
        assert viewer.reports() == []  # the bad view is in the hidden tab
        reports, shown = viewer.reports_of_every_view()
    assert shown == {"Doc", "Bad 3-D"}
    assert [(r.view, r.severity) for r in reports] == [("Bad 3-D", "error")]
