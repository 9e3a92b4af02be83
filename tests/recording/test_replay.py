"""Replay: recorded raw inputs through the chosen plugins (pipeline/replay.py, `crossfield replay`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer
from session_tools import record_session, report_numbers

from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.cli import main
from crossfield.config import DEFAULT_PLUGINS
from crossfield.errors import ConfigError
from crossfield.recording.integrity import file_sha256
from crossfield.recording.reader import open_recording
from crossfield.replay import load_recorded_session, replay_session

#: Whole-chain tolerance on the simulator (mm): every characteristic's error
#: against ground truth, for every centroid and register implementation
#: (the paper claims 0.1 mm; the simulator's noise allows far less).
CHAIN_TOLERANCE_MM = 0.05
#: ... and the registration's pose at the view centre (mm) and rotation (rad).
POSE_CENTRE_MM = 0.1
POSE_ANGLE_RAD = 5e-4


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("replay")
    summary = record_session(out, "orig")
    return summary, out / "orig" / "session.mcap"


@pytest.fixture(scope="module")
def same_plugins(recorded, tmp_path_factory):
    _, path = recorded
    return replay_session(path, make_plugin_manager(), output_dir=tmp_path_factory.mktemp("same"))


def file_messages(path):
    with open_recording(path) as rec:
        return [
            (m.topic, m.log_time_ns, m.sequence, m.data)
            for m in rec.messages(decode=False, file_order=True)
            if m.topic != "/integrity"
        ]


def test_replay_reproduces_every_recorded_message(recorded, same_plugins):
    """Same topics, times, sequences and bytes, in the same order: every stage output is
    the same float. Only the messages naming the run differ (report: session id and
    folder; reference: the serial port the simulated arm had)."""
    _, path = recorded
    # /log is not a result: a live run also logs device events (port opened,
    # link down/up) that a replay of the recorded bytes cannot see.
    original = [m for m in file_messages(path) if m[0] != "/log"]
    replayed = [m for m in file_messages(same_plugins.info.out_dir / "session.mcap") if m[0] != "/log"]
    assert [m[:3] for m in original] == [m[:3] for m in replayed]
    differing = {m[0] for m, n in zip(original, replayed) if m[3] != n[3]}
    assert differing == {"/report", "/reference"}
    for a, b in zip(original, replayed):
        if a[0] == "/reference":
            da, db = json.loads(a[3]), json.loads(b[3])
            assert da.pop("source").startswith("/") and db.pop("source") == "simulator"
            assert da == db
    by_topic = {}
    for m in original:
        by_topic.setdefault(m[0], []).append(m)
    assert len(by_topic["/measurement"]) == len(by_topic["/camera/upper/image"]) == 3


def test_replayed_report_is_bit_for_bit(recorded, same_plugins):
    summary, _ = recorded
    a = json.loads((summary.info.out_dir / "report.json").read_text())
    b = json.loads((same_plugins.info.out_dir / "report.json").read_text())
    assert report_numbers(a) == report_numbers(b)
    assert a["characteristics"] and all(isinstance(c["measured_mm"], float) for c in a["characteristics"])
    # in memory too: the same floats, not just the same text
    for x, y in zip(summary.characteristics, same_plugins.characteristics):
        assert (x.measured_mm, x.uncertainty_mm, x.error_mm) == (y.measured_mm, y.uncertainty_mm, y.error_mm)
    for x, y in zip(summary.registrations, same_plugins.registrations):
        assert np.array_equal(x.fit.R, y.fit.R) and np.array_equal(x.fit.t, y.fit.t)
    # frame time stamps and the session start are the recorded ones
    assert [f.timestamp_ns for f in summary.frames] == [f.timestamp_ns for f in same_plugins.frames]
    assert b["session"]["start_time_ns"] == a["session"]["start_time_ns"]


def test_replay_names_its_parent(recorded, same_plugins):
    _, path = recorded
    parent = same_plugins.info.parent
    assert parent["path"] == str(path.resolve())
    assert parent["sha256"] == file_sha256(path)
    assert parent["session_id"] == "orig" and parent["complete"] is True
    assert parent["changed"] == {"plugins": {}, "options": {}}
    with open_recording(same_plugins.info.out_dir / "session.mcap") as rec:
        assert rec.metadata_doc("crossfield.session")["parent"] == parent
    report = json.loads((same_plugins.info.out_dir / "report.json").read_text())
    assert report["session"]["parent"]["sha256"] == parent["sha256"]


@pytest.mark.parametrize(
    "stage, name",
    [
        *[("centroid", n) for n in sorted(implementations(make_plugin_manager(), "centroid"))],
        *[("register", n) for n in sorted(implementations(make_plugin_manager(), "register"))],
    ],
)
def test_replay_with_each_implementation_stays_within_tolerance(recorded, tmp_path, stage, name):
    _, path = recorded
    summary = replay_session(
        path, make_plugin_manager(), plugins={stage: name}, output_dir=tmp_path, record=False
    )
    assert summary.info.plugins[stage]["name"] == name
    assert not any(f.error for f in summary.frames) and summary.incomplete is None
    for c in summary.characteristics:
        assert c.n == 3
        assert abs(c.error_mm) < CHAIN_TOLERANCE_MM, (c.name, c.error_mm)
        assert abs(c.error_mm) < 4 * c.uncertainty_mm
    truth = summary.info.ground_truth
    centre = np.array([0.0, 25.0, 400.0])
    for reg in summary.registrations:
        assert reg.fit.method == (name if stage == "register" else DEFAULT_PLUGINS["register"])
        dR = reg.fit.R @ truth.R_global_camera.T
        assert math.acos(min(1.0, (np.trace(dR) - 1) / 2)) < POSE_ANGLE_RAD
        moved = reg.fit.R @ centre + reg.fit.t - (truth.R_global_camera @ centre + truth.t_global_camera)
        assert np.linalg.norm(moved) < POSE_CENTRE_MM
    changed = summary.info.parent["changed"]
    recorded_name = DEFAULT_PLUGINS[stage]
    assert changed["plugins"] == (
        {} if name == recorded_name else {stage: {"from": recorded_name, "to": name}}
    )


def test_swapped_plugin_and_option_are_recorded_as_changes(recorded, tmp_path):
    _, path = recorded
    out = tmp_path / "swapped.mcap"
    summary = replay_session(
        path,
        make_plugin_manager(),
        plugins={"centroid": "ellipse"},
        options=["measure.registration_uncertainty=false"],
        output=out,
    )
    assert out.exists() and summary.info.out_dir == tmp_path / "swapped"
    with open_recording(out) as rec:
        parent = rec.metadata_doc("crossfield.session")["parent"]
        config = rec.metadata_doc("crossfield.config")
        assert rec.metadata_doc("crossfield.plugins")["centroid"]["name"] == "ellipse"
        centroids = [m.decoded for m in rec.messages("/centroids/upper")]
    assert parent["changed"] == {
        "plugins": {"centroid": {"from": DEFAULT_PLUGINS["centroid"], "to": "ellipse"}},
        # null: the key was not set, the plugin's default applied
        "options": {"measure.registration_uncertainty": {"from": None, "to": False}},
    }
    assert config["centroid"] == {"plugin": "ellipse"}
    assert config["measure"] == {"plugin": "plan", "registration_uncertainty": False}
    assert all(c["method"] == "ellipse" for c in centroids) and len(centroids) == 3
    # the replay is itself replayable: a replay of the replay reproduces it
    again = replay_session(out, make_plugin_manager(), output_dir=tmp_path, record=False)
    assert [c.measured_mm for c in again.characteristics] == [c.measured_mm for c in summary.characteristics]
    assert again.info.parent["changed"] == {"plugins": {}, "options": {}}


def test_acquire_cannot_be_swapped(recorded, tmp_path):
    _, path = recorded
    with pytest.raises(ConfigError, match="acquire stage cannot be swapped"):
        replay_session(path, make_plugin_manager(), plugins={"acquire": "folder"}, output_dir=tmp_path)
    assert not any(tmp_path.iterdir())


def test_cli_replay(recorded, tmp_path, capsys):
    _, path = recorded
    out = tmp_path / "cli.mcap"
    assert main(["replay", str(path), "--register", "horn", "-o", str(out), "-q", "--no-rerun"]) == 0
    text = capsys.readouterr().out
    assert f"replay of {path.resolve()}" in text and f"register: {DEFAULT_PLUGINS['register']} -> horn" in text
    assert "Result: PASS" in text and out.exists()


def test_cli_bad_option_is_one_line_and_leaves_no_folder(recorded, tmp_path, capsys):
    _, path = recorded
    code = main(
        ["replay", str(path), "--option", "register.reflection_ratio=0.5", "-o", str(tmp_path / "x.mcap")]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert "session.mcap (recorded config, with replay overrides): [register]" in err and "reflection_ratio" in err
    assert not any(tmp_path.iterdir())
    assert main(["replay", str(path), "--centroid", "nope", "-q"]) == 2
    assert "no centroid implementation named 'nope'; available: ellipse, modelfit, weighted" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["replay"], ["audit"], ["compare", "OTHER"]])
def test_not_mcap_and_foreign_mcap_are_clear_errors(recorded, tmp_path, capsys, command):
    _, good = recorded
    text = tmp_path / "notes.mcap"
    text.write_text("these are not the droids\n")
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="rosbag2 mcap storage")
        channel = writer.register_channel("/chatter", "json", 0)
        writer.add_message(channel, 1, b'{"a": 1}', 1)
        writer.finish()
    for path, message in ((text, "not an MCAP file"), (foreign, "not a crossfield session recording")):
        args = [command[0], str(path)] + ([str(good)] if len(command) > 1 else [])
        assert main(args) == 2
        err = capsys.readouterr().err
        assert message in err and str(path) in err and "Traceback" not in err and err.count("\n") == 1
    assert "rosbag2 mcap storage" in err


def test_load_recorded_session_reads_the_inputs_exactly(recorded):
    summary, path = recorded
    session = load_recorded_session(path)
    info = summary.info
    assert session.plan.sha256 == info.plan.sha256 and session.plan.source == info.plan.source
    for camera in ("upper", "lower"):
        a, b = session.calibration.camera(camera), info.calibration.camera(camera)
        assert np.array_equal(a.camera_matrix, b.camera_matrix) and np.array_equal(
            a.dist_coeffs, b.dist_coeffs
        )
    assert np.array_equal(session.calibration.R_lower_upper, info.calibration.R_lower_upper)
    assert session.calibration.source == info.calibration.source
    truth, got = info.ground_truth, session.ground_truth
    assert all(np.array_equal(got.points_global[k], v) for k, v in truth.points_global.items())
    assert all(
        np.array_equal(got.lines_global[k].direction, v.direction) for k, v in truth.lines_global.items()
    )
    assert session.config.to_dict() == info.config.to_dict()
    assert session.machine is not None and session.machine["cpu_count"] >= 1


# ---- recorded identifiers are data, never paths (issue 9, class 7) -----------------


def crafted(recorded_path, dst, session_id, name, output_dir):
    """A copy of the recording (rewritten with the mcap writer) whose session id,
    config [session] name and output_dir are the given strings."""
    from session_tools import rewrite_mcap

    def edit(meta):
        out = []
        for record_name, record in meta:
            record = dict(record)
            if record_name == "crossfield.session":
                doc = json.loads(record["json"])
                doc["session_id"] = session_id
                record["session_id"] = session_id
                record["json"] = json.dumps(doc)
            elif record_name == "crossfield.config":
                doc = json.loads(record["json"])
                doc["session"].update(name=name, output_dir=output_dir)
                record["json"] = json.dumps(doc)
                record.pop("toml", None)
            out.append((record_name, record))
        return out

    rewrite_mcap(recorded_path, dst, metadata=edit)
    return dst


def tree_of(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


@pytest.mark.parametrize(
    "session_id",
    ["../..", "../../escaped", "/tmp/crossfield-escaped-abs", "a/../../b", "..", ".", ""],
)
def test_a_crafted_session_id_never_becomes_a_path(recorded, tmp_path, session_id):
    _, path = recorded
    archive = tmp_path / "archive" / "deep" / "crafted"
    archive.mkdir(parents=True)
    src = crafted(path, archive / "session.mcap", session_id, "../../../name-escape", str(tmp_path / "elsewhere"))
    assert load_recorded_session(src).session_id == session_id  # the crafted id is read as it is
    before = tree_of(tmp_path)
    out = tmp_path / "chosen"
    # into the chosen output folder ...
    summary = replay_session(src, make_plugin_manager(), output_dir=out)
    assert summary.info.out_dir.parent == out and summary.info.out_dir.name == "crafted-replay"
    # ... and by default next to the recorded session's folder
    default = replay_session(src, make_plugin_manager(), rerun=False)
    assert default.info.out_dir.parent == archive.parent and default.info.out_dir.name == "crafted-replay"
    new = sorted(set(tree_of(tmp_path)) - set(before))
    assert new and all(p.startswith(("chosen", "archive/deep/crafted-replay")) for p in new), new
    assert not (tmp_path / "elsewhere").exists() and not any(p.startswith("escaped") for p in new)
    assert not Path("/tmp/crossfield-escaped-abs-replay").exists()
    # the replay names its parent by the id it read, as data
    assert summary.info.parent["session_id"] == session_id
    assert report_numbers(json.loads((summary.info.out_dir / "report.json").read_text()))["characteristics"] == (
        report_numbers(json.loads((path.parent / "report.json").read_text()))["characteristics"]
    )


def test_a_recorded_plan_path_is_never_opened(recorded, tmp_path):
    """[session] plan in a recording names a file on the recording machine: the
    replay uses the attached plan and never reads that path."""
    from session_tools import rewrite_mcap

    _, path = recorded
    decoy = tmp_path / "decoy-plan.toml"
    decoy.write_text("this is not a plan [")

    def edit(meta):
        out = []
        for name, record in meta:
            record = dict(record)
            if name == "crossfield.config":
                doc = json.loads(record["json"])
                doc["session"]["plan"] = str(decoy)
                record["json"] = json.dumps(doc)
                record.pop("toml", None)
            out.append((name, record))
        return out

    src = tmp_path / "planpath.mcap"
    rewrite_mcap(path, src, metadata=edit)
    summary = replay_session(src, make_plugin_manager(), output_dir=tmp_path / "out", rerun=False)
    assert summary.passed and summary.info.plan.sha256 == load_recorded_session(path).plan.sha256


@pytest.mark.parametrize(
    "option, reason",
    [
        ("acquire.frames=1", "reads the stereo pairs and the measurement plan from the recording"),
        ("acquire.seed=9", "reads the stereo pairs and the measurement plan from the recording"),
        ('session.plan="other.toml"', "reads the stereo pairs and the measurement plan from the recording"),
        ('session.name="x"', r"set by -o/--output \(output=\), not by session.name"),
        ('session.output_dir="/tmp"', r"set by -o/--output \(output_dir=\), not by session.output_dir"),
        ("session.record=false", r"set by --no-record \(record=\)"),
        ("session.rerun=true", r"set by --no-rerun \(rerun=\)"),
    ],
)
def test_options_a_replay_cannot_honour_are_refused_with_the_reason(recorded, tmp_path, option, reason, capsys):
    _, path = recorded
    with pytest.raises(ConfigError, match=reason):
        replay_session(path, make_plugin_manager(), options=[option], output_dir=tmp_path)
    assert not any(tmp_path.iterdir())
    assert main(["replay", str(path), "--option", option, "-o", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option.split("=")[0] in err


def test_a_recording_without_budgets_replays_with_a_computed_budget_and_says_so(recorded, same_plugins, tmp_path, capsys):
    """Issue 26 item 4 (second part): a recording made before budgets were recorded (its
    /measurement characteristics without "budget", made here by rewriting them) replays
    with the budget the measure stage computes now, and the replay says the recording had
    none; a recording with budgets gets no such note."""
    from session_tools import Msg, rewrite_mcap

    from crossfield.replay import NO_RECORDED_BUDGET

    _, path = recorded

    def strip(msgs):
        out = []
        for m in msgs:
            if m.topic == "/measurement":
                doc = json.loads(m.data)
                for c in doc["characteristics"]:
                    c.pop("budget", None)
                m = Msg(m.topic, m.log_time, m.sequence, json.dumps(doc).encode())
            out.append(m)
        return out

    old = tmp_path / "old.mcap"
    rewrite_mcap(path, old, strip)
    with open_recording(old) as rec:
        assert all("budget" not in c for m in rec.messages("/measurement") for c in m.decoded["characteristics"])
    out = tmp_path / "replayed.mcap"
    assert main(["replay", str(old), "-o", str(out), "-q", "--no-rerun"]) == 0
    assert f"  note: {NO_RECORDED_BUDGET}" in capsys.readouterr().out
    with open_recording(out) as rec:
        report = next(m.decoded for m in rec.messages("/report"))
    assert report["session"]["parent"]["notes"] == [NO_RECORDED_BUDGET]
    assert all(c["budget"] and c["uncertainty_mm"] > 0 for c in report["characteristics"])
    assert "notes" not in same_plugins.info.parent
