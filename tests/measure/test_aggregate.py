"""Session aggregates computed frame by frame (pipeline/chain/aggregate.py) against batch numpy
computations on the same per-frame values; bounded memory for long sessions; the report
of a session whose per-frame rows were cut.

Synthetic frame results only: no images, no simulator, no other stage.
"""

from __future__ import annotations

import gc
import json
import math
import weakref
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.chain.aggregate import (
    FRAME_ERRORS_KEPT,
    FRAME_ROWS_KEPT,
    RunningStats,
    SessionAccumulator,
    aggregate_frames,
    summarise,
    summary_of_frames,
)
from crossfield.config import parse_config
from crossfield.plan import parse_plan
from crossfield.chain.runner import finish_session
from crossfield.session import FrameResult, SessionInfo, SessionSummary
from crossfield.types import (
    CameraIntrinsics,
    CharacteristicResult,
    Correspondence,
    Measurement,
    ReferenceData,
    Registration,
    RigidFit,
    StereoCalibration,
)
from crossfield.plugins import report_html
from crossfield.report import document as report_document

PLAN = parse_plan(
    """
[plan]
name = "aggregate test"

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
[[target]]
id = "P3"
nominal = [0.0, 22.0, 31.0]
search_radius = 3.0

[[characteristic]]
name = "P1-P2"
kind = "point_point"
a = "P1"
b = "P2"
nominal = 5.5
tolerance = 0.05

[[characteristic]]
name = "P2-P3"
kind = "point_point"
a = "P2"
b = "P3"
nominal = 1234.5678
tolerance = 0.05

[[characteristic]]
name = "never"
kind = "point_point"
a = "P1"
b = "P3"
nominal = 10.0
tolerance = 0.05
""",
    "plans/aggregate.toml",
)
CONTROLS = ("C1", "C2", "C3", "C4")
R_TRUE = Rotation.from_euler("zyx", [0.7, -0.3, 0.2]).as_matrix()
T_TRUE = np.array([-93.4623, 44.8897, -312.5442])
T0 = 1_767_268_800_000_000_000


def synthetic_frames(n: int, seed: int = 1, *, fail_every: int = 0, fail_at: tuple[int, ...] = ()):
    """n frame results: noisy registrations (a control dropped every 7th frame), two
    characteristics (P2-P3 NaN with P3 not found every 5th frame, no uncertainty every
    4th), 'never' not measured; frame k fails when (k + 1) % fail_every == 0 or k in fail_at."""
    rng = np.random.default_rng(seed)
    for k in range(n):
        ts = T0 + k * 71_428_571
        if (fail_every and (k + 1) % fail_every == 0) or k in fail_at:
            yield FrameResult(k, ts, error=f"frame {k}: register: only 2 controls matched", n_camera_points=9)
            continue
        controls = CONTROLS if k % 7 else CONTROLS[1:]
        residuals = rng.normal(scale=0.01, size=(len(controls), 3))
        fit = RigidFit(
            R=R_TRUE @ Rotation.from_rotvec(rng.normal(scale=2e-4, size=3)).as_matrix(),
            t=T_TRUE + rng.normal(scale=0.02, size=3),
            residuals=residuals,
            rms_mm=float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))),
            method="svd",
            scale=1.0 + float(rng.normal(scale=1e-6)),
        )
        registration = Registration(
            k,
            fit,
            Correspondence(
                np.arange(len(controls)),
                controls,
                unmatched_control=tuple(c for c in CONTROLS if c not in controls),
            ),
        )
        missing = ("P3",) if k % 5 == 0 else ()
        values = {
            "P1-P2": 5.5 + 0.003 + float(rng.normal(scale=0.004)),
            "P2-P3": math.nan if missing else 1234.5678 + float(rng.normal(scale=0.006)),
        }
        results = []
        for spec in PLAN.characteristics:
            if spec.name not in values:
                continue
            value = values[spec.name]
            results.append(
                CharacteristicResult(
                    name=spec.name,
                    kind=spec.kind,
                    measured_mm=value,
                    nominal_mm=spec.nominal_mm,
                    tolerance_mm=spec.tolerance_mm,
                    deviation_mm=value - spec.nominal_mm,
                    passed=abs(value - spec.nominal_mm) <= spec.tolerance_mm,
                    uncertainty_mm=None if k % 4 == 0 else 0.002 + 0.001 * float(rng.random()),
                    actual_mm=spec.nominal_mm + 0.001,
                    error_mm=value - spec.nominal_mm - 0.001,
                    elements=(spec.a, spec.b),
                )
            )
        measurement = Measurement(
            k, tuple(results), {"P1": (10.0, 20.0, 30.0 + k * 1e-6)}, missing_targets=missing
        )
        yield FrameResult(k, ts, registration=registration, measurement=measurement, n_camera_points=12)


def session_info(tmp_path: Path, record: bool = True) -> SessionInfo:
    intrinsics = CameraIntrinsics(
        np.array([[4000.0, 0, 812.5], [0, 4000.0, 617.5], [0, 0, 1]]), np.zeros(5), (1626, 1236)
    )
    return SessionInfo(
        session_id="long",
        out_dir=tmp_path,
        config=parse_config({"session": {"record": record}}, "long.toml"),
        calibration=StereoCalibration(intrinsics, intrinsics, np.eye(3), np.array([0.0, -60.0, 0.0])),
        plan=PLAN,
        plugins={},
        packages={},
        acquisition={"source": "synthetic"},
    )


def project(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Hartley et al. 2013): batch reference, written out here."""
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


# --------------------------------------------------------------------------
# Aggregates against a batch computation
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frames():
    return list(synthetic_frames(1500, fail_every=97))


@pytest.fixture(scope="module")
def aggregate(frames):
    accumulator = SessionAccumulator(PLAN)  # default bounds: rows and errors are cut
    for frame in frames:
        accumulator.add(frame)
    return accumulator, accumulator.result()


def test_running_stats_match_numpy_and_survive_a_large_offset():
    rng = np.random.default_rng(3)
    values = -312.5442 + rng.normal(scale=0.02, size=20_000)  # mean / std ~ 1.6e4
    stats = RunningStats()
    for v in values:
        stats.add(v)
    assert stats.n == values.size
    assert stats.mean == pytest.approx(values.mean(), rel=1e-15, abs=0)
    assert stats.variance() == pytest.approx(values.var(ddof=1), rel=1e-12, abs=0)
    vectors = RunningStats((3,))
    for v in values.reshape(-1, 4)[:, :3]:
        vectors.add(v)
    columns = values.reshape(-1, 4)[:, :3]
    exact_mean = [math.fsum(column) / len(column) for column in columns.T]  # correctly rounded sums
    np.testing.assert_allclose(vectors.mean, exact_mean, rtol=1e-15, atol=0)
    np.testing.assert_allclose(vectors.variance(), columns.var(axis=0, ddof=1), rtol=1e-12)
    one = RunningStats()
    one.add(2.5)
    assert (one.mean, one.variance()) == (2.5, 0.0)


def test_characteristics_equal_the_batch_computation(frames, aggregate):
    _, agg = aggregate
    assert [c.name for c in agg.characteristics] == [s.name for s in PLAN.characteristics]
    for c in agg.characteristics[:2]:
        results = [
            r
            for f in frames
            if f.measurement
            for r in f.measurement.characteristics
            if r.name == c.name and math.isfinite(r.measured_mm)
        ]
        values = np.array([r.measured_mm for r in results])
        u = np.array([r.uncertainty_mm for r in results if r.uncertainty_mm is not None])
        assert c.n == len(values) and c.n > 1000
        assert c.measured_mm == pytest.approx(values.mean(), rel=1e-14)
        assert c.std_mm == pytest.approx(values.std(ddof=1), rel=1e-12)
        assert c.uncertainty_mm == pytest.approx(
            max(values.std(ddof=1) / math.sqrt(len(values)), u.mean()), rel=1e-12
        )
        assert c.deviation_mm == pytest.approx(values.mean() - c.nominal_mm, abs=1e-12)
        assert c.error_mm == pytest.approx(values.mean() - c.actual_mm, abs=1e-12)
        assert c.elements == results[0].elements and c.passed
    never = agg.characteristics[2]
    assert never.n == 0 and math.isnan(never.measured_mm) and not never.passed
    # summarise (the public function) gives the same floats, bit for bit
    assert summarise(frames, PLAN) == agg.characteristics


def test_registration_equals_the_batch_computation(frames, aggregate):
    accumulator, agg = aggregate
    regs = [f.registration for f in frames if f.registration is not None]
    reg = agg.registration
    assert reg.n_frames == len(regs) == 1500 - 15
    Rs = np.array([r.fit.R for r in regs])
    R_mean = project(Rs.mean(axis=0))
    np.testing.assert_allclose(reg.R_global_camera, R_mean, rtol=0, atol=1e-13)
    # the chordal L2 mean equals Markley's quaternion average (scipy)
    np.testing.assert_allclose(reg.R_global_camera, Rotation.from_matrix(Rs).mean().as_matrix(), atol=1e-10)
    ts = np.array([r.fit.t for r in regs])
    np.testing.assert_allclose(reg.t_global_camera_mm, ts.mean(axis=0), rtol=1e-14, atol=0)
    np.testing.assert_allclose(reg.t_std_mm, ts.std(axis=0, ddof=1), rtol=1e-12, atol=0)
    rms = np.array([r.fit.rms_mm for r in regs])
    assert reg.rms_mm == pytest.approx(math.sqrt(np.mean(rms**2)), rel=1e-13)
    assert reg.rms_mean_mm == pytest.approx(rms.mean(), rel=1e-13) and reg.rms_max_mm == rms.max()
    assert reg.scale == pytest.approx(np.mean([r.fit.scale for r in regs]), rel=1e-15)
    chord = np.sqrt(np.mean(np.sum((Rs - R_mean) ** 2, axis=(1, 2))))
    assert reg.rotation_rms_rad == pytest.approx(2 * math.asin(chord / (2 * math.sqrt(2))), rel=1e-9)
    angles = Rotation.from_matrix(np.einsum("ji,fjk->fik", R_mean, Rs)).magnitude()
    # the RMS angle (chordal) is the spread's RMS, 2e-4 rad per axis -> about 3.5e-4 rad
    assert reg.rotation_rms_rad == pytest.approx(math.sqrt(np.mean(angles**2)), rel=1e-6)
    kept = [f.registration.fit.R for f in accumulator.rows if f.registration is not None]
    listed = Rotation.from_matrix(np.einsum("ji,fjk->fik", R_mean, np.array(kept))).magnitude()
    assert reg.rotation_spread_rad == pytest.approx(listed.max(), rel=1e-6)


def test_control_residuals_equal_the_batch_computation(frames, aggregate):
    _, agg = aggregate
    by_control: dict[str, list[np.ndarray]] = {}
    for f in frames:
        if f.registration is not None:
            for cid, r in zip(f.registration.correspondence.control_ids, f.registration.fit.residuals):
                by_control.setdefault(cid, []).append(r)
    controls = agg.registration.controls
    assert [c.id for c in controls] == list(by_control)  # order of first match
    for c in controls:
        stack = np.array(by_control[c.id])
        assert c.n_frames == len(stack)
        np.testing.assert_allclose(c.residual_mm, stack.mean(axis=0), rtol=0, atol=1e-15)
        assert c.rms_norm_mm == pytest.approx(np.sqrt(np.mean(np.sum(stack**2, axis=1))), rel=1e-13)
        assert c.max_norm_mm == pytest.approx(np.max(np.linalg.norm(stack, axis=1)), rel=1e-15)
    assert (
        next(c for c in controls if c.id == "C1").n_frames
        < next(c for c in controls if c.id == "C2").n_frames
    )


def test_counts_errors_and_missing_targets(frames, aggregate):
    accumulator, agg = aggregate
    failed = [f for f in frames if f.error]
    assert agg.frames_processed == 1500 and agg.frames_failed == len(failed) == 15
    assert [(e.sequence, e.timestamp_ns, e.error) for e in agg.frame_errors] == [
        (f.sequence, f.timestamp_ns, f.error) for f in failed
    ]
    assert agg.frame_errors_omitted == 0
    missing = sum(1 for f in frames if f.measurement and "P3" in f.measurement.missing_targets)
    assert agg.missing_targets == (("P3", missing),)
    assert [f.sequence for f in accumulator.rows] == list(range(FRAME_ROWS_KEPT))
    assert all(f.points is None and f.centroids is None for f in accumulator.rows)


def test_feeding_the_same_frames_again_reproduces_every_float(frames, aggregate, tmp_path):
    accumulator, first = aggregate
    again = SessionAccumulator(PLAN)
    for frame in frames:
        again.add(frame)
    second = again.result()
    info = session_info(tmp_path)
    a = SessionSummary(info, ReferenceData(()), accumulator.rows, first.characteristics, aggregate=first)
    b = SessionSummary(info, ReferenceData(()), again.rows, second.characteristics, aggregate=second)
    assert report_document.dumps(report_document.build_report(a)) == report_document.dumps(
        report_document.build_report(b)
    )


def test_a_summary_of_frames_is_aggregated_from_every_frame(frames, tmp_path):
    few = frames[:120]
    summary = summary_of_frames(session_info(tmp_path), ReferenceData(()), few)
    direct = aggregate_frames(few, PLAN)
    assert summary.frames_processed == 120 and summary.frames_omitted == 0 and summary.frames_failed == 1
    assert summary.aggregate.characteristics == direct.characteristics
    assert np.array_equal(summary.aggregate.registration.R_global_camera, direct.registration.R_global_camera)
    assert not summary.passed  # frame 96 failed


# --------------------------------------------------------------------------
# A long session: bounded memory, the report says what it left out
# --------------------------------------------------------------------------


class EndHook:
    def on_session_end(self, summary):
        self.summary = summary


@pytest.fixture(scope="module")
def long_session(tmp_path_factory):
    """5000 frames (every 10th failed) through the runner's aggregation and report path."""
    out = tmp_path_factory.mktemp("long")
    accumulator = SessionAccumulator(PLAN)
    results, registrations = [], []
    for frame in synthetic_frames(5000, seed=2, fail_every=10):
        results.append(weakref.ref(frame))
        if frame.registration is not None:
            registrations.append(weakref.ref(frame.registration))
        accumulator.add(frame)
        del frame
    gc.collect()
    hook = EndHook()
    summary = finish_session(
        hook,
        SimpleNamespace(report=report_html.HtmlReport()),
        session_info(out),
        ReferenceData(()),
        accumulator,
    )
    assert hook.summary is summary
    return summary, results, registrations, out


def test_a_long_session_keeps_a_bounded_number_of_rows(long_session):
    summary, results, registrations, _ = long_session
    assert len(summary.frames) == FRAME_ROWS_KEPT < 5000
    assert summary.frames_processed == 5000 and summary.frames_omitted == 5000 - FRAME_ROWS_KEPT
    assert summary.frames_failed == 500 and len(summary.aggregate.frame_errors) == FRAME_ERRORS_KEPT
    assert len(summary.registrations) == FRAME_ROWS_KEPT - FRAME_ROWS_KEPT // 10
    # nothing else is held: the fed results are gone (the rows are slim copies), and of
    # the registrations only those of the kept rows are alive
    assert sum(r() is not None for r in results) == 0
    alive = {r().sequence for r in registrations if r() is not None}
    assert alive == {f.sequence for f in summary.frames if f.registration is not None}
    assert summary.aggregate.registration.n_frames == 4500
    assert summary.characteristics[0].n == 4500


def test_the_report_of_a_long_session_says_what_it_left_out(long_session):
    _, _, _, out = long_session
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    report_document.validate(report)
    assert report["frames_processed"] == 5000 and report["frames_failed"] == 500
    assert len(report["frames"]) == FRAME_ROWS_KEPT and report["frames_omitted"] == 4800
    assert "first 200 of 5000 frames" in report["frames_note"] and "/measurement" in report["frames_note"]
    assert len(report["frame_errors"]) == FRAME_ERRORS_KEPT and report["frame_errors_omitted"] == 400
    assert report["missing_targets"] == {"P3": 1000}
    assert len(report["registration"]["per_frame"]) == 180 and report["registration"]["n_frames"] == 4500
    assert report["registration"]["control_points"][0]["n_frames"] > 3000
    problems = report["problems"]
    assert len(problems) < FRAME_ROWS_KEPT + FRAME_ERRORS_KEPT + 10
    assert "frame 999: register: only 2 controls matched" in problems  # a kept error beyond the rows
    assert any(p.startswith("400 more failed frame(s) not listed") for p in problems)
    assert "targets not found over all 5000 frames: P3 in 1000 frame(s)" in problems
    assert report["passed"] is False
    page = (out / "report.html").read_text(encoding="utf-8")
    assert 'id="frames-note"' in page and "4800 left out" in page
    assert page.count("<tr>") < 2 * FRAME_ROWS_KEPT  # the frames table is bounded too


def test_an_unrecorded_long_session_says_so(tmp_path):
    accumulator = SessionAccumulator(PLAN, rows_kept=3)
    for frame in synthetic_frames(10):
        accumulator.add(frame)
    aggregate = accumulator.result()
    summary = SessionSummary(
        session_info(tmp_path, record=False),
        ReferenceData(()),
        accumulator.rows,
        aggregate.characteristics,
        aggregate=aggregate,
    )
    note = report_document.build_report(summary)["frames_note"]
    assert note.startswith("the first 3 of 10 frames") and "not recorded" in note


def test_a_failure_after_the_kept_rows_fails_the_session(tmp_path):
    accumulator = SessionAccumulator(PLAN, rows_kept=50)
    for frame in synthetic_frames(300, fail_at=(250,)):
        accumulator.add(frame)
    aggregate = accumulator.result()
    chars = aggregate.characteristics[:2]  # drop the unmeasured one: every characteristic passes
    summary = SessionSummary(
        session_info(tmp_path), ReferenceData(()), accumulator.rows, chars, aggregate=aggregate
    )
    assert not any(f.error for f in summary.frames) and summary.frames_failed == 1
    assert not summary.passed
    assert "frame 250: register: only 2 controls matched" in report_document.problems(summary)
    ok = SessionAccumulator(PLAN, rows_kept=50)
    for frame in synthetic_frames(300):
        ok.add(frame)
    assert SessionSummary(
        summary.info, summary.reference, ok.rows, ok.result().characteristics[:2], aggregate=ok.result()
    ).passed


def test_bounds_are_checked():
    with pytest.raises(ValueError, match="rows_kept"):
        SessionAccumulator(PLAN, rows_kept=-1)


def test_vector_stats_are_running_stats_bit_for_bit():
    """RunningStats((3,)) (Python floats per component, issue 25) against the same Welford
    update on NumPy float64 arrays, the formulation it replaced."""

    class NumpyWelford:
        def __init__(self):
            self.n, self.shift, self.mean_, self.m2 = 0, np.zeros(3), np.zeros(3), np.zeros(3)

        def add(self, x):
            x = np.asarray(x, dtype=np.float64)
            if self.n == 0:
                self.shift = x
            self.n += 1
            y = x - self.shift
            delta = y - self.mean_
            self.mean_ = self.mean_ + delta / self.n
            self.m2 = self.m2 + delta * (y - self.mean_)

        @property
        def mean(self):
            return self.shift + self.mean_

        def variance(self):
            return self.m2 / (self.n - 1) if self.n > 1 else np.zeros(3)

    rng = np.random.default_rng(11)
    for scale, offset in ((0.01, 0.0), (0.02, -312.5), (1e-6, 1e3)):
        fast, reference = RunningStats((3,)), NumpyWelford()
        assert np.array_equal(fast.mean, reference.mean) and np.array_equal(fast.variance(), reference.variance())
        for k in range(60):
            x = offset + rng.normal(scale=scale, size=3)
            fast.add(x if k % 2 else tuple(x))
            reference.add(x)
            assert fast.n == reference.n
            for a, b in ((fast.mean, reference.mean), (fast.m2, reference.m2),
                         (fast.variance(), reference.variance())):
                assert np.array_equal(a.view(np.uint64), np.asarray(b, dtype=np.float64).view(np.uint64))
