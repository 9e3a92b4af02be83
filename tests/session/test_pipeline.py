"""The whole chain on the simulator, against its ground truth."""

import json
import re

import numpy as np
import pytest

from crossfield.cli import main
from crossfield.config import parse_config
from crossfield.hookspecs import hookimpl
from crossfield.chain.registry import make_plugin_manager
from crossfield.chain.runner import run_session
from crossfield.simulator.scenarios import TABLE3_ACTUAL_MM


def run(tmp_path, **stages):
    data = {
        "session": {"output_dir": str(tmp_path), "name": "s", "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": "table3", "frames": 3, "seed": 4},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
    }
    for stage, value in stages.items():
        data.setdefault(stage, {}).update(value)
    return run_session(parse_config(data, "<test>"), make_plugin_manager())


@pytest.fixture(scope="module")
def table3(tmp_path_factory):
    return run(tmp_path_factory.mktemp("table3"))


def test_table3_lengths_within_the_papers_claim(table3):
    chars = {c.name: c for c in table3.characteristics}
    assert len(chars) == 10
    for k, actual in enumerate(TABLE3_ACTUAL_MM):
        c = chars[f"L{k + 1:02d}"]
        assert c.actual_mm == pytest.approx(actual, abs=1e-9)
        assert c.n == 3
        assert abs(c.error_mm) < 0.1
        # Far better than the claim on the simulator; also consistent with the stated uncertainty.
        assert abs(c.error_mm) < 0.03
        assert abs(c.error_mm) < 4 * c.uncertainty_mm
    assert table3.passed
    assert table3.rms_error_mm() < 0.02


def test_registration_recovers_the_true_pose(table3):
    truth = table3.info.ground_truth
    for reg in table3.registrations:
        R, t = reg.fit.R, reg.fit.t
        dR = R @ truth.R_global_camera.T
        angle = np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))
        assert angle < 2e-4  # rad
        # Compare where the pose puts the view centre rather than t itself (lever arm).
        centre = np.array([0.0, 25.0, 400.0])
        assert np.linalg.norm((R @ centre + t) - (truth.R_global_camera @ centre + truth.t_global_camera)) < 0.05
        assert len(reg.correspondence.control_ids) == 8
        assert reg.fit.rms_mm < 0.05


def test_every_target_found_and_triangulated_near_truth(table3):
    truth = table3.info.ground_truth
    for frame in table3.frames:
        assert frame.error is None
        assert frame.n_camera_points == 18
        assert set(frame.measurement.target_points) == {f"P{k}" for k in range(1, 11)}
        for pid, xyz in frame.measurement.target_points.items():
            assert np.linalg.norm(np.asarray(xyz) - truth.points_global[pid]) < 0.1


def test_session_folder_and_report_json(table3):
    out = table3.info.out_dir
    for name in ("session.mcap", "report.json", "report.html"):
        assert (out / name).stat().st_size > 0
    report = json.loads((out / "report.json").read_text())
    by_name = {c["name"]: c for c in report["characteristics"]}
    for c in table3.characteristics:
        assert by_name[c.name]["measured_mm"] == c.measured_mm
        assert by_name[c.name]["actual_mm"] == c.actual_mm
        assert by_name[c.name]["error_mm"] == c.error_mm


@pytest.mark.parametrize("centroid", ["ellipse"])
@pytest.mark.parametrize("register", ["umeyama", "horn"])
def test_alternative_plugins_agree_with_truth(tmp_path, centroid, register):
    summary = run(tmp_path, centroid={"plugin": centroid}, register={"plugin": register})
    assert summary.passed
    assert max(abs(c.error_mm) for c in summary.characteristics) < 0.05


def test_cli_bad_config_is_one_line_naming_the_key(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text("[acquire]\nplugin = 'simulator'\nscenaro = 'table3'\n")
    assert main(["run", "-c", str(config), "-o", str(tmp_path), "-q"]) == 2
    err = capsys.readouterr().err
    assert re.search(r"bad.toml.*\[acquire\]: unknown option 'scenaro'", err)
    assert "Traceback" not in err


def test_cli_unknown_plugin_lists_choices(tmp_path, capsys):
    assert main(["run", "--centroid", "nope", "-o", str(tmp_path), "-q"]) == 2
    assert "no centroid implementation named 'nope'; available: ellipse, modelfit, weighted" in capsys.readouterr().err


def test_cli_plugins_lists_every_stage(capsys):
    assert main(["plugins", "--json"]) == 0
    table = json.loads(capsys.readouterr().out)
    assert {e["name"] for e in table["register"]} >= {"svd", "umeyama", "horn"}
    assert all(table[stage] for stage in table)


# ---- every option the user sets is honoured or refused (issue 9, class 5) -----------


def recorded_run(folder):
    """(config, CMM bytes, reference source) recorded by a session in ``folder``."""
    from crossfield.recording.reader import open_recording

    with open_recording(folder / "session.mcap") as rec:
        config = rec.metadata_doc("crossfield.config")
        raw = b"".join(m.data for m in rec.messages("/cmm/raw", decode=False))
    report = json.loads((folder / "report.json").read_text(encoding="utf-8"))
    return config, raw, report["reference"]["source"]


def test_option_reference_port_is_read_never_replaced_by_the_simulated_arm(tmp_path, capsys):
    """The documented romer-sim set-up: an arm on a real pty named with --option
    reference.port=...; the session reads that arm, not the simulator's own."""
    from crossfield.plugins.acquire_simulator import SimulatorSource
    from crossfield.simulator.arm import SimulatedArm
    from crossfield.simulator.scenarios import build_scene

    # Another arm than the built-in one: the same scene probed with other noise.
    outside = SimulatedArm(build_scene("table3").arm_probes(np.random.default_rng(99)))
    builtin = SimulatedArm(SimulatorSource(scenario="table3", seed=4).arm_probes())
    assert outside.expected_bytes() != builtin.expected_bytes()
    with outside.serve_pty() as port:
        code = main(
            ["run", "--scenario", "table3", "--frames", "1", "--seed", "4", "-o", str(tmp_path), "--name", "ext",
             "--no-rerun", "-q", "--option", f"reference.port={json.dumps(port)}"]
        )
        assert outside.wait_done(5.0)
    assert code == 0, capsys.readouterr().err
    config, raw, source = recorded_run(tmp_path / "ext")
    assert config["reference"]["port"] == port and source == port
    assert raw == outside.expected_bytes()

    # Without a port the simulator's own arm is read, and the config says so.
    assert main(["run", "--scenario", "table3", "--frames", "1", "--seed", "4", "-o", str(tmp_path),
                 "--name", "own", "--no-rerun", "-q"]) == 0
    config, raw, source = recorded_run(tmp_path / "own")
    assert config["reference"]["port"] == "simulator" and source.startswith("/")
    assert raw == builtin.expected_bytes()


def test_the_python_api_gets_the_simulated_arm_by_default(tmp_path):
    config = parse_config(
        {"session": {"output_dir": str(tmp_path), "name": "api", "rerun": False, "record": False},
         "acquire": {"frames": 1, "scenario": "table3", "seed": 4}},
        "<api>",
    )
    summary = run_session(config, make_plugin_manager())
    assert summary.passed and summary.info.config.stages["reference"].options["port"] == "simulator"
    assert len(summary.reference.points) == len(summary.info.plan.probing_order())


class NoArm:
    """A stereo source (the simulator's frames) that serves no simulated arm."""

    def __init__(self, inner):
        self.inner = inner
        self.calibration, self.ground_truth, self.default_plan = inner.calibration, inner.ground_truth, inner.default_plan

    def frames(self):
        return self.inner.frames()

    def describe(self):
        return self.inner.describe()

    def close(self):
        pass


def test_port_simulator_without_a_simulated_arm_is_refused_with_the_reason(tmp_path):
    from crossfield.errors import ConfigError
    from crossfield.plugins.acquire_simulator import SimulatorSource

    source = NoArm(SimulatorSource(scenario="table3", frames=1))
    config = parse_config(
        {"session": {"output_dir": str(tmp_path), "name": "x"}, "reference": {"port": "simulator"}}, "cfg.toml"
    )
    with pytest.raises(ConfigError, match=r"cfg.toml: \[reference\]: port = 'simulator' needs an acquire source"):
        run_session(config, make_plugin_manager(), source=source)
    # and with no port at all the reference says it needs one
    with pytest.raises(ConfigError, match=r"romer-serial' needs option 'port'"):
        run_session(parse_config({"session": {"output_dir": str(tmp_path)}}, "c2.toml"), make_plugin_manager(),
                    source=source)
    assert not any(tmp_path.iterdir())


class LogCollector:
    def __init__(self):
        self.lines = []

    @hookimpl
    def on_log(self, level, message, timestamp_ns):
        self.lines.append((level, message))


class ArmSource(NoArm):
    """The simulator's frames and arm; reports one incident per pair through ``self.log``."""

    log = None

    def serve_arm(self):
        return self.inner.serve_arm()

    def frames(self):
        for frame in self.inner.frames():
            if self.log is not None:
                self.log(level="warning", message=f"incident at pair {frame.sequence}", timestamp_ns=frame.timestamp_ns)
            yield frame


class ConnectedSource(ArmSource):
    def connect_log(self, log):
        self.log = log


@pytest.mark.parametrize("klass, connected", [(ConnectedSource, True), (ArmSource, False)])
def test_a_device_log_is_connected_by_its_declared_protocol_not_by_an_attribute(tmp_path, klass, connected):
    from crossfield.plugins.acquire_simulator import SimulatorSource
    from crossfield.stages import ReportsIncidents, ServesSimulatedArm

    source = klass(SimulatorSource(scenario="table3", frames=2, seed=4))
    assert isinstance(source, ServesSimulatedArm) and isinstance(source, ReportsIncidents) is connected
    logs = LogCollector()
    config = parse_config({"session": {"output_dir": str(tmp_path), "name": "log", "rerun": False}}, "<t>")
    summary = run_session(config, make_plugin_manager(), source=source, observers=[logs])
    assert summary.passed
    incidents = [m for level, m in logs.lines if m.startswith("incident")]
    assert incidents == (["incident at pair 0", "incident at pair 1"] if connected else [])
    # the serial plugin's own incidents arrive through its connect_log in both cases
    assert any(m.startswith("romer-serial ") and "points imported" in m for _, m in logs.lines)
