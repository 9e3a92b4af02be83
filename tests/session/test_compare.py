"""compare: two recorded sessions side by side (pipeline/compare.py, `crossfield compare`)."""

from __future__ import annotations

import json

import pytest
from session_tools import edit_json, record_session, rewrite_mcap

from crossfield.config import DEFAULT_PLUGINS
from crossfield.cli import main
from crossfield.compare import compare, format_table
from crossfield.recording.reader import open_recording
from crossfield.chain.registry import make_plugin_manager
from crossfield.replay import replay_session


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    record_session(out, "orig")
    original = out / "orig" / "session.mcap"
    same = replay_session(original, make_plugin_manager(), output_dir=out, rerun=False)
    replay_session(
        original, make_plugin_manager(), plugins={"centroid": "ellipse"}, output=out / "ellipse.mcap"
    )
    return original, same.info.out_dir / "session.mcap", out / "ellipse.mcap"


def test_a_replay_with_the_recorded_plugins_has_no_difference(sessions):
    original, same, _ = sessions
    result = compare(original, same)
    assert result["identical"] and result["differences"] == []
    assert len(result["characteristics"]) == 10 and all(c["delta_mm"] == 0 for c in result["characteristics"])
    assert [f["sequence"] for f in result["registration"]["per_frame"]] == [0, 1, 2]
    assert result["centroids"]["upper"]["a"]["centroids"] == 54
    assert result["centroids"]["upper"]["shift_px"]["max"] == 0.0
    assert "No differences" in format_table(result)


def test_exactly_the_edited_value_is_listed(sessions, tmp_path):
    original, _, _ = sessions
    edited = tmp_path / "edited.mcap"

    def edit(ms):
        def change(doc):
            c = next(c for c in doc["characteristics"] if c["name"] == "L03")
            c["measured_mm"] += 0.25

        return [edit_json(m, change) if m.topic == "/report" else m for m in ms]

    rewrite_mcap(original, edited, edit)
    result = compare(original, edited)
    (diff,) = result["differences"]
    assert diff["path"] == "characteristics.L03.measured_mm"
    assert diff["b"] == diff["a"] + 0.25 and diff["delta"] == diff["b"] - diff["a"]


def test_an_edited_registration_residual_is_listed(sessions, tmp_path):
    original, _, _ = sessions
    edited = tmp_path / "residual.mcap"

    def edit(ms):
        def change(doc):
            doc["residuals"][2]["residual_mm"][1] = 0.5

        return [edit_json(m, change) if m.topic == "/registration" and m.sequence == 1 else m for m in ms]

    rewrite_mcap(original, edited, edit)
    (diff,) = compare(original, edited)["differences"]
    with open_recording(original) as rec:
        doc = next(m.decoded for m in rec.messages("/registration") if m.sequence == 1)
    cid = doc["residuals"][2]["control_id"]
    assert (
        diff["path"] == f"registration[1].residual.{cid}" and diff["a"] == doc["residuals"][2]["residual_mm"]
    )
    assert diff["b"][1] == 0.5 and diff["delta"][0] == 0 and diff["delta"][2] == 0


def test_swapped_centroids_show_their_differences(sessions, capsys):
    original, _, ellipse = sessions
    result = compare(original, ellipse)
    paths = {d["path"] for d in result["differences"]}
    assert "plugins.centroid" in paths and "plugins.register" not in paths
    assert "characteristics.L01.measured_mm" in paths and "registration[0].rms_mm" in paths
    assert {"centroids.upper[0].uv", "centroids.lower[2].uv"} <= paths
    for camera in ("upper", "lower"):
        shift = result["centroids"][camera]["shift_px"]
        assert (
            0 < shift["max"] < 0.05 and shift["only_a"] == shift["only_b"] == 0
        )  # the same blobs, moved a little
    for c in result["characteristics"]:
        assert abs(c["delta_mm"]) < 0.01
    session = result["registration"]["session"]
    assert 0 < session["rotation_diff_rad"] < 1e-3 and 0 < session["translation_diff_mm"] < 0.1
    assert result["b"]["parent"]["changed"]["plugins"] == {"centroid": {"from": DEFAULT_PLUGINS["centroid"], "to": "ellipse"}}
    assert main(["compare", str(original), str(ellipse)]) == 1
    text = capsys.readouterr().out
    assert f"{DEFAULT_PLUGINS['centroid']} 0.1.0" in text and "ellipse 0.1.0" in text and "<- differs" in text
    assert "difference(s):" in text and "plugins.centroid" in text
    assert main(["compare", str(original), str(ellipse), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["differences"] == result["differences"]
