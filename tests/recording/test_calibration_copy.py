"""Issue 26 item 2: the calibration file is recorded whole, and replay and audit build the
budget's calibration term from the recorded copy (pipeline/recording/calibration_files.py),
naming a file on disk that changed or is gone."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from session_tools import record_session

from crossfield.audit import audit, format_report
from crossfield.camera.calibration_io import write_stereo_calibration
from crossfield.chain.registry import make_plugin_manager
from crossfield.recording.reader import open_recording
from crossfield.replay import replay_session
from crossfield.simulator.scenarios import station_calibration

STD_T_MM, STD_F_PX = 0.01, 0.5


def write_calibration(path, std_t_mm):
    cal = station_calibration()
    std_m = np.array([[STD_F_PX, STD_F_PX, 0.3, 0.3]])
    extra = {"std_T": np.full((3, 1), std_t_mm), "std_M1": std_m, "std_M2": std_m}
    write_stereo_calibration(path, cal, extra=extra)
    return cal


def expected_scale_u(cal, std_t_mm):
    """u(s)^2 = (u(|T|)/|T|)^2 + 2 (u(f)/f/sqrt(2))^2 (uncertainty/calibration.py): with
    equal per-component std, u(|T|) = std_T."""
    T = float(np.linalg.norm(cal.t_lower_upper))
    fx = [float(c.camera_matrix[0, 0]) for c in (cal.upper, cal.lower)]
    return math.sqrt((std_t_mm / T) ** 2 + sum((STD_F_PX / f / math.sqrt(2.0)) ** 2 for f in fx))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("calcopy")
    calib = out / "calib.yml"
    cal = write_calibration(calib, STD_T_MM)
    summary = record_session(out, "s", frames=1, acquire={"calibration": str(calib)}, reference={"sigma_mm": 0.0005})
    return calib, cal, summary, out / "s" / "session.mcap"


def test_the_calibration_file_is_recorded_whole_and_the_budget_reads_it(session):
    calib, cal, summary, path = session
    assert summary.aggregate.calibration_uncertainty_source == "calibration file std_* keys"
    assert summary.aggregate.calibration_scale_u == pytest.approx(expected_scale_u(cal, STD_T_MM), rel=1e-12)
    with open_recording(path) as rec:
        copy = rec.attachment("calibration/stereo.yml")
        listed = rec.metadata_doc("crossfield.session")["calibration_files"]
    assert copy.data == calib.read_bytes() and copy.media_type == "text/yaml"
    assert listed == [
        {"attachment": "calibration/stereo.yml", "path": str(calib),
         "sha256": hashlib.sha256(calib.read_bytes()).hexdigest(), "bytes": len(copy.data)}
    ]  # fmt: skip


def test_a_changed_or_deleted_file_replays_and_audits_from_the_recorded_copy(session, tmp_path):
    calib, cal, summary, path = session
    recorded_sha = hashlib.sha256(calib.read_bytes()).hexdigest()
    live_u = summary.aggregate.calibration_scale_u
    pm = make_plugin_manager()
    try:
        write_calibration(calib, 50 * STD_T_MM)  # a new calibration written over the old one
        disk_sha = hashlib.sha256(calib.read_bytes()).hexdigest()
        note = (
            f"the calibration file on disk at {calib} differs from the recorded copy "
            f"(sha256 {disk_sha[:12]}… on disk vs {recorded_sha[:12]}… recorded); the budget uses the recorded copy"
        )
        report = audit(path, pm)  # the reproduction replays every frame, budgets included
        assert report.passed, format_report(report)
        assert note in report.provenance["notes"] and f"  note: {note}" in format_report(report)
        assert report.provenance["calibration"]["files"][0]["sha256"] == recorded_sha
        calib.unlink()
        replayed = replay_session(path, pm, output_dir=tmp_path, record=False, rerun=False)
        assert replayed.aggregate.calibration_scale_u == live_u  # the same float as live
        gone = f"the calibration file on disk at {calib} is gone; the budget uses the recorded copy"
        assert any(n.startswith(gone) for n in replayed.info.parent["notes"])
        report = audit(path, pm, reproduce=False)
        assert report.passed and any(n.startswith(gone) for n in report.provenance["notes"])
    finally:
        write_calibration(calib, STD_T_MM)


def test_a_recording_without_the_copy_reads_the_path_as_before_and_says_so(session, tmp_path):
    """A recording made before the copies were kept (here: this one with the copy and its
    listing removed) falls back to the recorded path and says so."""
    import json

    from session_tools import rewrite_mcap

    from crossfield.recording.calibration_files import session_calibration_files
    from crossfield.replay import RecordingSource, calibration_notes, load_recorded_session

    calib, cal, summary, path = session

    def drop_listing(meta):
        out = []
        for name, record in meta:
            if name == "crossfield.session":
                doc = json.loads(record["json"])
                doc.pop("calibration_files")
                record = {**record, "json": json.dumps(doc)}
            out.append((name, record))
        return out

    older = tmp_path / "older.mcap"
    rewrite_mcap(path, older, metadata=drop_listing,
                 attachments=lambda atts: [a for a in atts if not a.name.startswith("calibration/")])  # fmt: skip
    recorded = load_recorded_session(older)
    assert recorded.calibration_files is None
    assert calibration_notes(recorded) == [
        f"the recording holds no copy of the calibration file {calib} (recorded before the copies were kept): "
        f"the budget's calibration term is read from that path on disk, as it is now"
    ]
    (read,) = session_calibration_files(RecordingSource(recorded))
    assert read.path == str(calib) and read.data == calib.read_bytes()


class _Viewer:
    """The observer hooks :func:`crossfield.viz.rerun_mcap.log_recording` calls, without Rerun."""

    def wants_images(self, sequence):
        return False

    def __getattr__(self, name):
        if name.startswith("on_"):
            return lambda **kw: None
        raise AttributeError(name)


def test_the_viewer_summarises_a_recording_as_the_live_run_did(session):
    """The viewer of a recording (viz/rerun_mcap.py) builds its summary the live way
    (chain/aggregate.py session_accumulator): the budget from the recorded calibration
    copy, the consistency warning naming the reference source, the motion test's line."""
    from crossfield.report.document import build_report
    from crossfield.viz.rerun_mcap import log_recording

    calib, cal, summary, path = session
    shown = log_recording(path, _Viewer())
    live, again = build_report(summary), build_report(shown)
    assert summary.aggregate.consistency.warning  # the stated sigma_mm is too small: the warning fires
    assert "the reference source 'romer-serial'" in summary.aggregate.consistency.warning
    assert again["uncertainty"]["consistency"] == live["uncertainty"]["consistency"]
    assert again["station_moved"] == live["station_moved"]
    assert shown.aggregate.calibration_scale_u == summary.aggregate.calibration_scale_u


def test_report_states_the_split_of_the_registration_excess(session):
    """report.json carries the camera/CMM split of the registration residuals' excess as the
    session computed it (crossfield.uncertainty.consistency): on this session the stated arm sigma
    is too small, so the CMM term is inflated, and the CMM's share lies in [0, 1]."""
    from crossfield.report.document import build_report

    _, _, summary, _ = session
    check = summary.aggregate.consistency
    section = build_report(summary)["uncertainty"]["consistency"]
    assert section["cmm_share"] == pytest.approx(check.cmm_share) and 0.0 <= section["cmm_share"] <= 1.0
    assert section["cmm_evidence_dof"] == check.cmm_evidence_dof
    assert section["camera_registration_excess"] == pytest.approx(check.camera_registration_excess)
    assert section["cmm_inflation"] == pytest.approx(check.cmm_inflation) and section["cmm_inflation"] > 1.0
    assert "split between camera and CMM" in section["rule"]
