"""The report stage: report.json (values, schema), report.html (Tables 1-3, escaping), summary text.

Everything is built from synthetic data classes; no simulator, no other stage.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import re
import math
from html.parser import HTMLParser
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.config import parse_config
from crossfield.errors import ConfigError
from crossfield.plan import parse_plan
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.chain.aggregate import summarise, summary_of_frames
from crossfield.session import FrameResult, SessionInfo, SessionSummary
from crossfield.types import (
    CameraIntrinsics,
    CameraPoints,
    CharacteristicResult,
    Correspondence,
    GroundTruth,
    Measurement,
    ReferenceData,
    Registration,
    RigidFit,
    StereoCalibration,
)
from crossfield.plugins import report_html
from crossfield.report import document as report_document
from crossfield.report.document import calibration_sha256

PLAN_NAME = 'Bracket <script>alert("x")</script> & co'
EVIL_PROBLEM = "line 7: bad checksum <img src=x onerror=alert(1)>"

PLAN_TOML = f"""
[plan]
name = '{PLAN_NAME}'

[[control]]
id = "C1"
[[control]]
id = "C2"
[[control]]
id = "C3"
[[control]]
id = "C4"

[[target]]
id = "P1"
nominal = [10.0, 20.0, 30.0]
search_radius = 3.0
[[target]]
id = "P2"
nominal = [15.0, 22.0, 31.0]
search_radius = 3.0

[[reference_line]]
id = "L3"
probes = 6
fit = "cylinder"

[[characteristic]]
name = "P1-L3"
kind = "point_line"
a = "P1"
b = "L3"
nominal = 308.35
tolerance = 0.1

[[characteristic]]
name = "P2-L3"
kind = "point_line"
a = "P2"
b = "L3"
nominal = 311.3778
tolerance = 0.1

[[characteristic]]
name = "P1-P2 <b>gap</b>"
kind = "point_point"
a = "P1"
b = "P2"
nominal = 5.5
tolerance = 0.01
"""

# Truth: the first two characteristics have known actual values, the third not.
ACTUAL = {"P1-L3": 308.35, "P2-L3": 311.3778}
# Per-frame measured values (awkward doubles on purpose).
MEASURED = {
    "P1-L3": [308.41340000000002, 308.3893333333333, 308.40071234567891],
    "P2-L3": [311.38090000000005, 311.37123456789, 311.3855555555555],
    "P1-P2 <b>gap</b>": [5.523456789012345, 5.51987654321, 5.52011111111111],
}
CONTROLS = ("C1", "C2", "C3", "C4")
FAILED_NS = 1_767_268_800_210_000_000
FAILED_ERROR = "correspondence: only 2 <controls>"

R_TRUE = Rotation.from_euler("zyx", [0.7, -0.3, 0.2]).as_matrix()
T_TRUE = np.array([-93.4623, 44.8897, -312.5442])


def make_registration(sequence: int, rng: np.random.Generator, controls=CONTROLS) -> Registration:
    """A per-frame fit: the true pose perturbed by a small random rotation and shift."""
    dR = Rotation.from_rotvec(rng.normal(scale=2e-4, size=3)).as_matrix()
    residuals = rng.normal(scale=0.01, size=(len(controls), 3))
    fit = RigidFit(
        R=R_TRUE @ dR,
        t=T_TRUE + rng.normal(scale=0.02, size=3),
        residuals=residuals,
        rms_mm=float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))),
        method="svd",
    )
    return Registration(sequence, fit, Correspondence(np.arange(len(controls)), tuple(controls)))


def make_measurement(sequence: int, k: int, plan, with_truth: bool) -> Measurement:
    results = []
    for spec in plan.characteristics:
        measured = MEASURED[spec.name][k]
        actual = ACTUAL.get(spec.name) if with_truth else None
        deviation = measured - spec.nominal_mm
        results.append(
            CharacteristicResult(
                name=spec.name,
                kind=spec.kind,
                measured_mm=measured,
                nominal_mm=spec.nominal_mm,
                tolerance_mm=spec.tolerance_mm,
                deviation_mm=deviation,
                passed=abs(deviation) <= spec.tolerance_mm,
                uncertainty_mm=0.012 + 0.001 * k,
                actual_mm=actual,
                error_mm=None if actual is None else measured - actual,
                elements=(spec.a,) + ((spec.b,) if spec.b else ()),
            )
        )
    return Measurement(
        sequence,
        tuple(results),
        {"P1": (10.01, 20.02, 30.03), "P2": (15.0, 22.0, 31.0 + k / 3)},
        missing_targets=(),
    )


def make_summary(
    *, with_truth: bool = True, failed_frame: bool = True, incomplete: str | None = None
) -> SessionSummary:
    rng = np.random.default_rng(7)
    plan = parse_plan(PLAN_TOML, "plans/bracket.toml")
    intrinsics = CameraIntrinsics(
        np.array([[4000.0, 0, 812.5], [0, 4000.0, 617.5], [0, 0, 1]]), np.zeros(5), (1626, 1236)
    )
    calibration = StereoCalibration(
        intrinsics, intrinsics, np.eye(3), np.array([0.0, -60.0, 0.0]), source="calib/<rig>.yaml"
    )
    truth = GroundTruth({}, {}, R_TRUE, T_TRUE) if with_truth else None
    info = SessionInfo(
        session_id="20260101-120000-demo",
        out_dir=Path("recordings/demo"),
        config=parse_config({"acquire": {"scenario": "table3", "seed": 3}}, "demo.toml"),
        calibration=calibration,
        plan=plan,
        plugins={
            stage: {"name": name, "plugin": f"plugins.{module}", "package": "crossfield", "version": "0.1"}
            for stage, name, module in (
                ("report", "html", "report_html"), ("register", "svd", "register_svd")
            )
        },
        packages={"numpy": np.__version__, "crossfield": "0.1.0"},
        acquisition={"scenario": "table3", "exposure_us": 1500.0},
        ground_truth=truth,
        start_time_ns=1_767_268_800_123_456_789,
    )
    frames = []
    for k in range(3):
        points = CameraPoints(
            k, np.zeros((6, 3)), np.full((6, 3), 0.01), np.arange(6), np.arange(6), np.zeros(6)
        )
        frames.append(
            FrameResult(
                sequence=k,
                timestamp_ns=1_767_268_800_000_000_000 + k * 70_000_000,
                points=points,
                registration=make_registration(k, rng),
                measurement=make_measurement(k, k, plan, with_truth),
            )
        )
    if failed_frame:
        frames.append(
            FrameResult(sequence=3, timestamp_ns=FAILED_NS, error=FAILED_ERROR)
        )
    reference = ReferenceData(points=(), problems=(EVIL_PROBLEM,), source="/dev/pts/7")
    return summary_of_frames(info, reference, frames, incomplete=incomplete)


# --------------------------------------------------------------------------
# A small parser: table id -> rows of cell texts
# --------------------------------------------------------------------------


class TableParser(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tables: dict[str, list[list[str]]] = {}
        self.tags: list[str] = []
        self.attributes: set[str] = set()
        self._table: str | None = None
        self._row: list[str] | None = None
        self._cell: list[str] | None = None
        self._in_caption = False

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        attrs = dict(attrs)
        self.attributes.update(attrs)
        if tag == "table" and attrs.get("id"):
            self._table = attrs["id"]
            self.tables[self._table] = []
        elif tag == "tr" and self._table:
            self._row = []
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []

    def handle_endtag(self, tag):
        if tag == "table":
            self._table = None
        elif tag == "tr" and self._table and self._row is not None:
            self.tables[self._table].append(self._row)
            self._row = None
        elif tag in ("td", "th") and self._cell is not None:
            self._row.append(" ".join("".join(self._cell).split()))
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def parse_tables(text: str) -> TableParser:
    parser = TableParser()
    parser.feed(text)
    return parser


def body_rows(rows: list[list[str]], header: list[str]) -> list[dict[str, str]]:
    """Rows (after the header row) as dicts keyed by the header; drops the footer note row."""
    return [dict(zip(header, r)) for r in rows[1:] if len(r) == len(header)]


# --------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def summary() -> SessionSummary:
    return make_summary()


@pytest.fixture(scope="module")
def written(summary, tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("report") / "nested" / "session"
    reporter = get_implementation(make_plugin_manager(), "report", "html").create({})
    paths = reporter.write(summary, out_dir)
    return reporter, out_dir, paths


@pytest.fixture(scope="module")
def report(written):
    _, out_dir, _ = written
    return json.loads((out_dir / "report.json").read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def page(written):
    _, out_dir, _ = written
    return (out_dir / "report.html").read_text(encoding="utf-8")


# --------------------------------------------------------------------------
# report.json
# --------------------------------------------------------------------------


def test_write_creates_both_files(written):
    _, out_dir, paths = written
    assert [p.name for p in paths] == ["report.json", "report.html"]
    assert all(p.parent == out_dir and p.is_file() for p in paths)
    assert sorted(p.name for p in out_dir.iterdir()) == ["report.html", "report.json"]  # no temp files left


def test_report_json_follows_schema(report):
    report_document.validate(report)


def test_schema_rejects_bad_reports(report):
    bad = copy.deepcopy(report)
    del bad["characteristics"][0]["passed"]
    with pytest.raises(jsonschema.ValidationError):
        report_document.validate(bad)
    bad = copy.deepcopy(report)
    bad["characteristics"][2]["actual_mm"] = 5.5  # actual without error
    with pytest.raises(jsonschema.ValidationError):
        report_document.validate(bad)
    bad = copy.deepcopy(report)
    bad["registration"]["R_global_camera"] = [[1.0, 0.0], [0.0, 1.0]]
    with pytest.raises(jsonschema.ValidationError):
        report_document.validate(bad)


def test_characteristics_round_trip_exactly(summary, report):
    assert len(report["characteristics"]) == 3
    fields = ("measured_mm", "std_mm", "uncertainty_mm", "nominal_mm", "tolerance_mm", "deviation_mm")
    for no, (c, entry) in enumerate(zip(summary.characteristics, report["characteristics"]), start=1):
        assert entry["no"] == no
        assert entry["name"] == c.name and entry["kind"] == c.kind
        assert entry["elements"] == list(c.elements)
        assert entry["n_frames"] == c.n == 3
        for key in fields:
            assert entry[key] == getattr(c, key), key  # exact: floats are written with repr
        assert entry["passed"] is c.passed
        # independent check of the aggregation (crossfield.chain.aggregate.summarise)
        values = MEASURED[c.name]
        assert entry["measured_mm"] == pytest.approx(np.mean(values), abs=1e-12)
        assert entry["std_mm"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
        assert entry["deviation_mm"] == pytest.approx(np.mean(values) - c.nominal_mm, abs=1e-12)


def test_ground_truth_columns_present_only_where_known(summary, report):
    first, second, third = report["characteristics"]
    for entry in (first, second):
        assert entry["actual_mm"] == ACTUAL[entry["name"]]
        assert entry["error_mm"] == entry["measured_mm"] - entry["actual_mm"]
    assert "actual_mm" not in third and "error_mm" not in third
    errors = [first["error_mm"], second["error_mm"]]
    assert report["rms_error_mm"] == summary.rms_error_mm()
    expected = math.sqrt((errors[0] ** 2 + errors[1] ** 2) / 2)
    assert report["rms_error_mm"] == pytest.approx(expected, rel=1e-15)
    assert report["ground_truth_known"] is True


def test_pass_fail(report):
    assert [c["passed"] for c in report["characteristics"]] == [True, True, False]
    assert report["passed"] is False
    assert report["incomplete"] is False and report["incomplete_reason"] is None


def test_provenance(summary, report):
    info = summary.info
    assert report["format"] == "crossfield-report/2"
    assert report["session"]["id"] == info.session_id
    assert report["session"]["start_time_ns"] == info.start_time_ns
    assert report["session"]["start_time_utc"] == "2026-01-01T12:00:00.123456+00:00"
    assert report["config"] == info.config.to_dict()
    assert report["config"]["acquire"] == {"plugin": "simulator", "scenario": "table3", "seed": 3}
    assert report["config_source"] == "demo.toml"
    assert report["plugins"] == {k: dict(v) for k, v in info.plugins.items()}
    assert report["packages"] == dict(info.packages)
    assert report["calibration"]["source"] == "calib/<rig>.yaml"
    assert report["calibration"]["sha256"] == calibration_sha256(info.calibration)
    assert re.fullmatch(r"[0-9a-f]{64}", report["calibration"]["sha256"])
    assert report["plan"] == {"name": PLAN_NAME, "source": "plans/bracket.toml", "sha256": info.plan.sha256}
    assert report["reference"] == {"source": "/dev/pts/7", "n_points": 0, "problems": [EVIL_PROBLEM]}


def test_frames_and_problems(report):
    assert report["frames_processed"] == 4
    assert report["frames_failed"] == 1
    assert report["frame_errors"] == [
        {"sequence": 3, "timestamp_ns": FAILED_NS, "error": FAILED_ERROR}
    ]
    assert report["frame_errors_omitted"] == 0 and report["missing_targets"] == {}
    assert [f["sequence"] for f in report["frames"]] == [0, 1, 2, 3]
    assert report["frames_omitted"] == 0 and report["frames_note"] is None  # every frame listed
    assert report["frames"][1]["characteristics"][0] == {
        "name": "P1-L3",
        "measured_mm": MEASURED["P1-L3"][1],
        "uncertainty_mm": 0.012 + 0.001 * 1,
        "passed": True,
    }
    assert report["frames"][2]["target_points_mm"]["P2"] == [15.0, 22.0, 31.0 + 2 / 3]
    assert report["frames"][3]["registration_rms_mm"] is None
    assert f"reference import: {EVIL_PROBLEM}" in report["problems"]
    assert "frame 3: correspondence: only 2 <controls>" in report["problems"]


def test_registration_is_the_session_mean(summary, report):
    regs = summary.registrations
    reg = report["registration"]
    assert reg["aggregate"] == "session_mean" and reg["n_frames"] == 3
    R = np.array(reg["R_global_camera"])
    # The chordal L2 mean equals Markley's quaternion average (scipy's Rotation.mean).
    R_scipy = Rotation.from_matrix(np.array([r.fit.R for r in regs])).mean().as_matrix()
    np.testing.assert_allclose(R, R_scipy, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert reg["det_R"] == pytest.approx(1.0, abs=1e-12)
    # aggregated frame by frame (crossfield.chain.aggregate): equal to the batch computation to rounding
    translations = np.array([r.fit.t for r in regs])
    np.testing.assert_allclose(reg["t_global_camera_mm"], translations.mean(axis=0), rtol=1e-14, atol=0)
    np.testing.assert_allclose(reg["t_std_mm"], translations.std(axis=0, ddof=1), rtol=1e-12, atol=0)
    assert [f["rms_mm"] for f in reg["per_frame"]] == [r.fit.rms_mm for r in regs]
    assert [f["R_global_camera"] for f in reg["per_frame"]] == [r.fit.R.tolist() for r in regs]
    assert reg["rms_mm"] == pytest.approx(math.sqrt(np.mean([r.fit.rms_mm**2 for r in regs])), rel=1e-15)
    spread = max(Rotation.from_matrix(R.T @ r.fit.R).magnitude() for r in regs)
    assert reg["rotation_spread_rad"] == pytest.approx(spread, rel=1e-6)


def test_registration_residuals_per_control(summary, report):
    regs = summary.registrations
    controls = report["registration"]["control_points"]
    assert [c["id"] for c in controls] == list(CONTROLS)
    for i, entry in enumerate(controls):
        stack = np.array([r.fit.residuals[i] for r in regs])
        assert entry["n_frames"] == 3
        np.testing.assert_allclose(entry["residual_mm"], stack.mean(axis=0), rtol=0, atol=1e-15)
        assert entry["residual_norm_mm"] == pytest.approx(np.linalg.norm(stack.mean(axis=0)), rel=1e-14)
        assert entry["rms_norm_mm"] == pytest.approx(np.sqrt(np.mean(np.sum(stack**2, axis=1))), rel=1e-14)
        assert entry["max_norm_mm"] == pytest.approx(np.max(np.linalg.norm(stack, axis=1)), rel=1e-14)


def test_pose_error_against_ground_truth(report):
    reg = report["registration"]
    gt = reg["ground_truth"]
    R = np.array(reg["R_global_camera"])
    assert gt["R_global_camera"] == R_TRUE.tolist()
    assert gt["rotation_error_rad"] == pytest.approx(Rotation.from_matrix(R_TRUE.T @ R).magnitude(), rel=1e-6)
    assert gt["translation_error_mm"] == (np.array(reg["t_global_camera_mm"]) - T_TRUE).tolist()
    assert 0 < gt["rotation_error_rad"] < 1e-3


def test_report_json_is_strict_json_when_nothing_was_measured(tmp_path):
    base = make_summary(failed_frame=False)
    frames = tuple(FrameResult(f.sequence, f.timestamp_ns, error="triangulation failed") for f in base.frames)
    empty = summary_of_frames(base.info, base.reference, frames, incomplete="stopped by user")
    reporter = report_html.HtmlReport()
    reporter.write(empty, tmp_path)
    text = (tmp_path / "report.json").read_text(encoding="utf-8")
    assert "NaN" not in text
    report = json.loads(text)
    report_document.validate(report)
    assert report["registration"] is None
    for c in report["characteristics"]:
        assert c["measured_mm"] is None and c["n_frames"] == 0 and not c["passed"]
    assert report["rms_error_mm"] is None and report["passed"] is False
    assert report["incomplete"] is True and report["incomplete_reason"] == "stopped by user"
    page = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert "No frame was registered" in page and "INCOMPLETE: stopped by user" in page


def test_incomplete_session_does_not_pass():
    passing = make_summary(failed_frame=False)
    # make every characteristic pass
    chars = tuple(dataclasses.replace(c, passed=True) for c in passing.characteristics)
    ok = dataclasses.replace(passing, characteristics=chars)
    assert ok.passed
    assert not dataclasses.replace(ok, incomplete="crash").passed


def test_nan_frames_are_not_averaged():
    base = make_summary(failed_frame=False)
    plan = base.info.plan
    nan_result = CharacteristicResult("P1-L3", "point_line", math.nan, 308.35, 0.1, math.nan, False)
    extra = FrameResult(9, 0, measurement=Measurement(9, (nan_result,), {}, missing_targets=("P1",)))
    chars = summarise(base.frames + (extra,), plan)
    assert chars[0].n == 3 and chars[0].measured_mm == pytest.approx(np.mean(MEASURED["P1-L3"]), abs=1e-12)


# --------------------------------------------------------------------------
# report.html
# --------------------------------------------------------------------------


def test_html_is_self_contained(page):
    parsed = parse_tables(page)
    assert {"script", "link", "img", "iframe", "object", "embed"}.isdisjoint(parsed.tags)
    assert {"src", "href"}.isdisjoint(parsed.attributes)
    assert not any(a.startswith("on") for a in parsed.attributes)  # no event handlers
    # inline SVG refers to its own parts only (url(#id), xlink:href="#id")
    assert not re.search(r"url\((?!#)", page) and "@import" not in page
    assert all(ref.startswith("#") for ref in re.findall(r'href="([^"]*)"', page))
    assert page.startswith("<!DOCTYPE html>") and "<style>" in page
    assert page.count("<svg") >= 2  # the deviation chart, the residual vectors (and trends)


def test_html_escapes_every_string(page):
    assert "<script" not in page.lower()
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; co" in page
    assert "<img" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page
    assert "<b>gap</b>" not in page and "&lt;b&gt;gap&lt;/b&gt;" in page
    assert "calib/&lt;rig&gt;.yaml" in page


def test_html_table1_rotation(report, page):
    rows = parse_tables(page).tables["table1-rotation"]
    R = report["registration"]["R_global_camera"]
    assert rows[:3] == [[f"{v:.4f}" for v in row] for row in R]
    assert f"det R = {report['registration']['det_R']:.6f}" in rows[3][0]


def test_html_table2_translation(report, page):
    rows = parse_tables(page).tables["table2-translation"]
    t = report["registration"]["t_global_camera_mm"]
    s = report["registration"]["t_std_mm"]
    cov = report["registration"]["covariance"]
    u = cov["t_u_mm"] if cov else [None] * 3
    fmt = lambda v: "\u2014" if v is None else f"{v:.4f}"  # noqa: E731
    assert rows[1:4] == [[axis, f"{v:.4f}", fmt(w), f"{e:.4f}"] for axis, v, w, e in zip("xyz", t, u, s)]


def test_html_table3_lengths(report, page):
    rows = parse_tables(page).tables["table3-lengths"]
    header = rows[0]
    assert header == [
        "No.", "Characteristic", "Elements", "Frames", "Measured", "Std", "u", "Actual", "Error",
        "Nominal", "Tolerance", "Deviation", "U (k = 2)", "Decision",
    ]
    table = body_rows(rows, header)
    assert len(table) == 3
    for row, c in zip(table, report["characteristics"]):
        assert row["No."] == str(c["no"])
        assert row["Characteristic"].startswith(c["name"])
        assert float(row["Measured"]) == round(c["measured_mm"], 4)
        assert float(row["u"]) == round(c["uncertainty_mm"], 4)
        assert float(row["U (k = 2)"]) == round(c["expanded_uncertainty_mm"], 4)
        assert float(row["Nominal"]) == round(c["nominal_mm"], 4)
        assert row["Tolerance"] == f"\u00b1{c['tolerance_mm']:.4f}"
        assert float(row["Deviation"]) == round(c["deviation_mm"], 4)
        text = {"conforms": "\u2713 conforms", "does_not_conform": "\u2717 does not conform"}
        assert row["Decision"] == text.get(c["decision"], "? not proven")
        assert c["decision"] == ("conforms" if c["passed"] else "does_not_conform")  # simple rule
        if "actual_mm" in c:
            assert float(row["Actual"]) == round(c["actual_mm"], 4)
            assert float(row["Error"]) == round(c["error_mm"], 4)
        else:
            assert row["Actual"] == row["Error"] == "—"
    assert f"{report['rms_error_mm']:.4f} mm" in page


def test_html_residual_table(report, page):
    rows = parse_tables(page).tables["residuals"]
    table = body_rows(rows, rows[0])
    for row, cp in zip(table, report["registration"]["control_points"], strict=True):
        assert row["Control"] == cp["id"]
        assert [float(row[k]) for k in ("dx", "dy", "dz")] == [round(v, 4) for v in cp["residual_mm"]]
        assert float(row["|mean|"]) == round(cp["residual_norm_mm"], 4)


def test_html_without_ground_truth_has_no_truth_columns(tmp_path):
    summary = make_summary(with_truth=False)
    report_html.HtmlReport(decimals=3).write(summary, tmp_path)
    report = json.loads((tmp_path / "report.json").read_text(encoding="utf-8"))
    report_document.validate(report)
    assert all("actual_mm" not in c and "error_mm" not in c for c in report["characteristics"])
    assert report["rms_error_mm"] is None and report["ground_truth_known"] is False
    assert report["registration"]["ground_truth"] is None
    rows = parse_tables((tmp_path / "report.html").read_text(encoding="utf-8")).tables["table3-lengths"]
    assert "Actual" not in rows[0] and "Error" not in rows[0]
    assert body_rows(rows, rows[0])[0]["Measured"] == f"{report['characteristics'][0]['measured_mm']:.3f}"


# --------------------------------------------------------------------------
# Terminal summary, registry
# --------------------------------------------------------------------------


def test_summary_text(summary, written, report):
    reporter, _, _ = written
    text = reporter.summary_text(summary)
    for c in report["characteristics"]:
        line = next(line for line in text.splitlines() if c["name"] in line)
        assert f"{c['measured_mm']:.4f}" in line
        if "actual_mm" in c:
            assert f"{c['actual_mm']:.4f}" in line and f"{c['error_mm']:+.4f}" in line
        assert line.rstrip().endswith("conforms" if c["passed"] else "does not conform")
        assert f"{c['expanded_uncertainty_mm']:.4f}" in line and f"\u00b1{c['tolerance_mm']:.4f}" in line
    assert "Characteristics (mm;" in text and "U (k = 2)" in text
    assert f"RMS error vs ground truth: {report['rms_error_mm']:.4f} mm" in text
    assert text.splitlines()[-1] == "Result: FAIL"
    assert "4 processed, 1 failed" in text


def test_summary_text_neutralises_control_characters():
    summary = make_summary()
    info = summary.info
    plan = parse_plan(PLAN_TOML.replace(f"'{PLAN_NAME}'", '"evil\\u001b[2J"'), "x.toml")
    info = dataclasses.replace(info, plan=plan)
    text = report_html.summary_text(dataclasses.replace(summary, info=info))
    assert "\x1b" not in text and "evil\\x1b[2J" in text


def test_json_reporter_writes_only_json(summary, tmp_path):
    reporter = get_implementation(make_plugin_manager(), "report", "json").create({})
    assert reporter.write(summary, tmp_path) == [tmp_path / "report.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]
    assert json.loads((tmp_path / "report.json").read_text())["characteristics"][0]["measured_mm"] == (
        summary.characteristics[0].measured_mm
    )


def test_reporter_options_are_checked():
    impl = get_implementation(make_plugin_manager(), "report", "html")
    assert impl.create({"decimals": 6}).decimals == 6
    with pytest.raises(ConfigError, match="decimals"):
        impl.create({"decimals": -1})
    with pytest.raises(ConfigError, match="unknown option 'colour'"):
        impl.create({"colour": "blue"})
