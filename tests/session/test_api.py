"""The Python API (`crossfield.run`, `crossfield.open_recording`), against the simulator's truth."""

from __future__ import annotations

import json
import re
from importlib import metadata

import numpy as np
import pytest
from session_tools import HtmlCells

import crossfield
from crossfield.chain.registry import make_plugin_manager
from crossfield.cli import build_parser
from crossfield.cli.session import resolve_run_config
from crossfield.errors import ConfigError, PluginError
from crossfield.simulator.scenarios import TABLE3_ACTUAL_MM


def api_run(tmp_path, **kwargs):
    kwargs.setdefault("plugin_manager", make_plugin_manager())
    return crossfield.run(output_dir=tmp_path, rerun=False, **kwargs)


@pytest.fixture(scope="module")
def table3(tmp_path_factory):
    return api_run(tmp_path_factory.mktemp("api"), scenario="table3", frames=3, seed=4, name="api")


def test_run_measures_table3_against_the_truth(table3):
    assert [c.name for c in table3.characteristics] == [f"L{k:02d}" for k in range(1, 11)]
    for c, actual in zip(table3.characteristics, TABLE3_ACTUAL_MM):
        assert c.actual_mm == pytest.approx(actual, abs=1e-9)
        assert c.n == 3
        assert abs(c.measured_mm - actual) < 0.03  # the paper claims 0.1 mm
        assert c.error_mm == pytest.approx(c.measured_mm - actual, abs=1e-12)
    assert table3.passed
    truth = table3.info.ground_truth
    R = table3.aggregate.registration.R_global_camera
    angle = np.arccos(np.clip((np.trace(R @ truth.R_global_camera.T) - 1) / 2, -1, 1))
    assert angle < 2e-4  # rad


def test_characteristics_hold_the_reported_values(table3):
    report = json.loads((table3.info.out_dir / "report.json").read_text())
    reported = {c["name"]: c for c in report["characteristics"]}
    for c in table3.characteristics:
        for key in ("measured_mm", "actual_mm", "error_mm", "deviation_mm", "uncertainty_mm", "passed"):
            assert reported[c.name][key] == getattr(c, key), (c.name, key)


def test_the_api_runs_the_cli_config(table3):
    """Same code path: the API's arguments and the CLI's flags give the same config."""
    out = str(table3.info.out_dir.parent)
    flags = ["run", "--scenario", "table3", "--frames", "3", "--seed", "4"]
    flags += ["-o", out, "--name", "api", "--no-rerun"]
    cli = resolve_run_config(build_parser().parse_args(flags))
    assert cli.stages["reference"].options == {}  # no port named ...
    recorded = table3.info.config.to_dict()
    assert recorded["reference"].pop("port") == "simulator"  # ... so the runner read the simulated arm
    expected = cli.to_dict()
    assert recorded == expected


def test_defaults_are_the_clis():
    cli = resolve_run_config(build_parser().parse_args(["run"]))
    assert crossfield.run_config().to_dict() == cli.to_dict()


def _table_rows(text: str) -> dict[str, list[str]]:
    """name -> cells of the characteristics table (columns two spaces apart, cells may hold one)."""
    rows = {}
    for line in text.splitlines():
        cells = re.split(r"\s{2,}", line.strip())
        if len(cells) > 3 and re.fullmatch(r"\d+", cells[0]):
            rows[cells[1]] = cells
    return rows


def test_summary_prints_as_a_table(table3):
    text = str(table3)
    lines = text.splitlines()
    header = next(re.split(r"\s{2,}", line.strip()) for line in lines if line.startswith("No."))
    ks = {round(c.coverage_factor, 2) for c in table3.characteristics}  # Student-t k (uncertainty.dof)
    U_head = f"U (k = {ks.pop():g})" if len(ks) == 1 else "U (k per row)"
    assert header == [
        "No.", "Characteristic", "n", "Measured", "u", U_head, "Actual", "Error", "Nominal", "Tol", "Dev",
        "Decision",
    ]
    rows = _table_rows(text)
    assert list(rows) == [c.name for c in table3.characteristics]
    for c in table3.characteristics:
        cells = dict(zip(header, rows[c.name]))
        assert int(cells["n"]) == c.n
        assert float(cells["Measured"]) == pytest.approx(c.measured_mm, abs=5e-5)
        assert float(cells["Actual"]) == pytest.approx(c.actual_mm, abs=5e-5)
        assert float(cells["Error"]) == pytest.approx(c.error_mm, abs=5e-5)
        assert float(cells["u"]) == pytest.approx(c.uncertainty_mm, abs=5e-5)
        assert float(cells[U_head].split()[0]) == pytest.approx(c.expanded_uncertainty_mm, abs=5e-5)
        assert cells["Decision"] == {"conforms": "conforms", "does_not_conform": "does not conform"}[c.decision]
    assert lines[-1] == "Result: PASS"
    assert f"RMS error vs ground truth: {table3.rms_error_mm():.4f} mm" in text
    assert str(table3.info.out_dir) in lines[0]




def test_summary_html_for_notebooks(table3):
    parser = HtmlCells()
    parser.feed(table3._repr_html_())
    header, *rows = parser.rows
    assert header[:4] == ["No.", "Characteristic", "n", "Measured"]
    assert [r[1] for r in rows] == [c.name for c in table3.characteristics]
    for row, c in zip(rows, table3.characteristics):
        assert float(row[3]) == pytest.approx(c.measured_mm, abs=5e-5)


def test_html_escapes_names():
    from crossfield.tables import html_table

    assert "<b>" not in html_table(["x"], [["<b>bold</b>"]], [False])


def test_open_recording_gives_the_recorded_frames(table3):
    with crossfield.open_recording(table3.info.out_dir / "session.mcap") as rec:
        assert rec.complete
        frames = [m.decoded for m in rec.messages(["/measurement"])]
    assert [f["sequence"] for f in frames] == [0, 1, 2]
    for c in table3.characteristics:
        per_frame = [
            next(x for x in f["characteristics"] if x["name"] == c.name)["measured_mm"] for f in frames
        ]
        assert c.measured_mm == pytest.approx(np.mean(per_frame), abs=1e-9)


def test_plugins_and_options_as_keywords(tmp_path):
    summary = api_run(
        tmp_path,
        scenario="table3",
        frames=2,
        seed=5,
        record=False,
        centroid="ellipse",
        register="horn",
        options={"centroid": {"threshold_sigma": 7.5}, "report": {"decimals": 3}},
    )
    config = summary.info.config
    assert config.stages["centroid"].plugin == "ellipse"
    assert dict(config.stages["centroid"].options) == {"threshold_sigma": 7.5}
    assert config.stages["register"].plugin == "horn"
    assert summary.info.plugins["centroid"]["name"] == "ellipse"
    assert not (summary.info.out_dir / "session.mcap").exists()
    assert summary.passed
    for c, actual in zip(summary.characteristics, TABLE3_ACTUAL_MM):
        assert abs(c.measured_mm - actual) < 0.05


def test_bad_arguments_name_the_key(tmp_path):
    pm = make_plugin_manager()
    with pytest.raises(ConfigError, match="frames applies to the simulator source, not to 'folder'"):
        crossfield.run(acquire="folder", frames=3, output_dir=tmp_path, plugin_manager=pm)
    with pytest.raises(ConfigError, match=r"\[centroid\]: unknown option 'threshold'"):
        crossfield.run(
            frames=1, options={"centroid": {"threshold": 3}}, output_dir=tmp_path, plugin_manager=pm
        )
    with pytest.raises(ConfigError, match="unknown stage 'centroids'"):
        crossfield.run(options={"centroids": {"threshold_sigma": 3}}, output_dir=tmp_path, plugin_manager=pm)
    with pytest.raises(ConfigError, match="must be a mapping"):
        crossfield.run(options={"centroid": 3}, output_dir=tmp_path, plugin_manager=pm)
    with pytest.raises(PluginError, match="no centroid implementation named 'nope'"):
        crossfield.run(centroid="nope", output_dir=tmp_path, plugin_manager=pm)
    assert not any(tmp_path.iterdir())  # nothing was written


def test_version_and_names():
    assert crossfield.__version__ == metadata.version("crossfield")
    assert set(crossfield.__all__) <= set(dir(crossfield))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        crossfield.nope  # noqa: B018
