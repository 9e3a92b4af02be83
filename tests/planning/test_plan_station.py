"""crossfield plan: station files, the two prediction routes, sweeps, recommendation, report, CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from crossfield.cli import main
from crossfield.errors import ConfigError
from crossfield.planning.report import write_report
from crossfield.planning.routes import analytic, predict, true_value
from crossfield.planning.station import (
    load_station, parse_station, station_from_scenario, with_controls, with_focal_length, with_working_distance,
)
from crossfield.planning.sweeps import recommend, run_sweeps

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "station-paper.toml"


@pytest.fixture(scope="module")
def scenario():
    return station_from_scenario("station")


@pytest.fixture(scope="module")
def paper():
    return load_station(EXAMPLE)


def _u(doc, route="analytic"):
    return np.array([c[route]["u_mm"] for c in doc["characteristics"]])


# ---- the station ---------------------------------------------------------------------------------


def test_scenario_station_is_the_simulator_geometry(scenario):
    from crossfield.simulator.scenarios import build_scene

    scene = build_scene("station")
    truth = scene.ground_truth
    assert scenario.in_view()
    for c in scenario.characteristics:
        spec = next(s for s in scene.plan.characteristics if s.name == c.name)
        if c.kind == "point_line":
            expected = truth.lines_global[spec.b].distance(truth.points_global[spec.a])
        elif c.kind == "point_point":
            expected = float(np.linalg.norm(truth.points_global[spec.a] - truth.points_global[spec.b]))
        else:
            expected = float(truth.points_global[spec.a][2])
        assert true_value(scenario, c) == pytest.approx(expected, abs=1e-9)


def test_example_station_is_the_papers(paper, scenario):
    assert paper.in_view()
    assert len(paper.control_ids) == 8 and paper.frames == 10
    assert paper.focal_length_mm == 16.0 and paper.baseline_mm == pytest.approx(50.0)
    # Same targets and reference elements as the scenario: the same true lengths (to the rounding of the file).
    for c in paper.characteristics:
        twin = next(s for s in scenario.characteristics if s.name == c.name)
        assert true_value(paper, c) == pytest.approx(true_value(scenario, twin), abs=0.02)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("focal_length_mm = 16.0", "focal_length_mm = -16.0"), "camera.focal_length_mm"),
        (lambda t: t.replace("sigma_mm = 0.01", "sigma_mm = 'x'"), "cmm.sigma_mm"),
        (lambda t: t.replace('kind = "depth"', 'kind = "angle"'), "characteristic[4].kind"),
        (lambda t: t.replace('b = "L3"', 'b = "L9"', 1), "unknown reference line 'L9'"),
        (lambda t: t.replace("blur_sigma_px", "blur_px"), "unknown key(s) in [camera]: blur_px"),
        (lambda t: t.replace("count = 8", "count = 2"), "controls.count"),
        (lambda t: t.replace("[cmm]", "[cmm"), "invalid TOML"),
        (lambda t: t.replace("radius_mm = 2.5", 'radius_mm = 2.5\nbias_model = "drawn"'), "targets.bias_model"),
        (lambda t: t.replace("radius_mm = 2.5", 'radius_mm = 2.5\nbias_model = "rendered"')
         .replace("[targets]", 'centroid = "magic"\n\n[targets]'), "camera.centroid': no centroid implementation"),
    ],
)
def test_bad_station_files_give_one_clear_error(edit, message):
    text = edit(EXAMPLE.read_text())
    with pytest.raises(ConfigError, match="station.toml") as info:
        parse_station(text, "station.toml")
    assert message in str(info.value)


def test_cli_reports_a_bad_station_file_without_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE.read_text().replace("pixel_pitch_mm = 0.0044\n", ""))
    assert main(["plan", str(bad), "--route", "analytic"]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: key 'camera.pixel_pitch_mm' is missing" in err and "Traceback" not in err


# ---- the routes ----------------------------------------------------------------------------------


def test_routes_agree_where_fitzpatrick_is_exact(scenario):
    """CMM noise only (isotropic, equal weights): the analytic route (Fitzpatrick + line-fit covariance)
    and the Monte Carlo route through the kernels agree within the Monte Carlo sampling error."""
    cmm_only = dataclasses.replace(scenario, centroid_efficiency=1e-4)
    doc = predict(cmm_only, sessions=3000, seed=1)
    for c in doc["characteristics"]:
        if c["analytic"]["u_mm"] > 1e-6:
            assert c["monte_carlo"]["u_mm"] == pytest.approx(c["analytic"]["u_mm"], rel=0.06), c["name"]


def test_routes_agree_on_the_camera_part_with_the_anisotropic_linear_model(scenario):
    """Camera noise only: the Monte Carlo (triangulation + weighted Kabsch) equals the linear propagation
    with the exact anisotropic registration covariance; Fitzpatrick's isotropic FLE is exact only for
    the short camera-only length P1-P2 (the registration cancels) and overstates the long ones."""
    cam_only = dataclasses.replace(scenario, cmm_sigma_mm=0.0)
    doc = predict(cam_only, sessions=3000, seed=2)
    for c in doc["characteristics"]:
        assert c["monte_carlo"]["u_mm"] == pytest.approx(c["analytic"]["u_linear_mm"], rel=0.06), c["name"]
    p1p2 = next(c for c in doc["characteristics"] if c["name"] == "P1-P2")
    assert p1p2["monte_carlo"]["u_mm"] == pytest.approx(p1p2["analytic"]["u_mm"], rel=0.06)
    p1l3 = next(c for c in doc["characteristics"] if c["name"] == "P1-L3")
    assert p1l3["analytic"]["u_random_mm"] > 1.3 * p1l3["monte_carlo"]["std_mm"]


def test_session_uncertainty_averages_only_the_camera_part(scenario):
    one = analytic(dataclasses.replace(scenario, frames=1))
    ten = analytic(dataclasses.replace(scenario, frames=10))
    for a, b in zip(one["characteristics"], ten["characteristics"]):
        assert b["u_random_mm"] ** 2 == pytest.approx(a["u_cmm_mm"] ** 2 + a["u_camera_frame_mm"] ** 2 / 10, rel=1e-9)
        # The perspective bias is fixed: the same for any number of frames, and part of u.
        assert b["bias_mm"] == pytest.approx(a["bias_mm"], rel=1e-9)
        assert b["u_mm"] ** 2 == pytest.approx(b["u_random_mm"] ** 2 + b["bias_mm"] ** 2, rel=1e-9)


def test_perspective_bias_propagates_alike_in_both_routes(scenario):
    """The blob centres' perspective eccentricity, propagated linearly (analytic) and through the
    kernels (Monte Carlo): the same session bias; it dominates the camera-only length P1-P2."""
    doc = predict(scenario, sessions=2000, seed=3)
    for c in doc["characteristics"]:
        sampling = c["monte_carlo"]["std_mm"] / np.sqrt(2000)
        assert c["monte_carlo"]["bias_mm"] == pytest.approx(c["analytic"]["bias_mm"], abs=4 * sampling + 5e-5)
    p1p2 = next(c for c in doc["characteristics"] if c["name"] == "P1-P2")
    assert abs(p1p2["analytic"]["bias_mm"]) > 5 * p1p2["analytic"]["u_random_mm"]
    off = predict(dataclasses.replace(scenario, perspective_bias=False), route="analytic")
    assert all(c["analytic"]["bias_mm"] == 0.0 for c in off["characteristics"])


# ---- sweeps --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sweeps(paper):
    # The random part: the perspective bias of the blob centres is a fixed offset that does not
    # follow these monotony laws (it changes sign with the view angle).
    return run_sweeps(dataclasses.replace(paper, perspective_bias=False), route="analytic")


def _series(sweeps, name):
    pts = sweeps["sweeps"][name]["points"]
    return [p["value"] for p in pts], np.array([[c["analytic_u_mm"] for c in p["characteristics"]] for p in pts])


def test_sweeps_are_monotone_where_physics_says_so(sweeps):
    rel = 1 + 1e-9
    for name, direction in (("n_controls", -1), ("focal_length_mm", -1), ("baseline_mm", -1),
                            ("control_spread", -1), ("working_distance_mm", +1), ("cmm_sigma_mm", +1)):
        values, u = _series(sweeps, name)
        assert values == sorted(values)
        steps = u[1:] / u[:-1]
        if direction < 0:
            assert np.all(steps <= rel), (name, steps)  # never worse
        else:
            assert np.all(steps >= 1 / rel), (name, steps)
    # The camera-only length P1-P2 follows the stereo geometry: sigma ~ z^2 / (f b).
    values, u = _series(sweeps, "baseline_mm")
    assert u[0, 2] > 1.8 * u[1, 2]  # 25 mm vs 50 mm baseline
    values, u = _series(sweeps, "cmm_sigma_mm")
    assert u[-1, 0] / u[0, 0] > 30  # the CMM dominates P1-L3


def test_sweep_on_dask_equals_the_local_one(paper):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp", host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        remote = run_sweeps(paper, sessions=50, names=["n_controls"], values={"n_controls": [4, 8]}, client=client)
    local = run_sweeps(paper, sessions=50, names=["n_controls"], values={"n_controls": [4, 8]})
    assert remote == local


def test_recommendation_is_the_smallest_layout(paper):
    target = 0.03
    rec = recommend(paper, target, sessions=300)
    assert rec["reached"]
    n, f = rec["n_controls"], rec["focal_length_mm"]
    k = paper.coverage_factor

    def worst_U(station):
        return k * max(_u(predict(station, route="analytic")))

    chosen = with_focal_length(with_controls(paper, n), f)
    assert chosen.in_view() and worst_U(chosen) <= target
    for t in rec["tried"]:
        if (t["n_controls"], t["focal_length_mm"]) == (n, f):
            break
        variant = with_focal_length(with_controls(paper, t["n_controls"]), t["focal_length_mm"])
        assert not variant.in_view() or worst_U(variant) > target
    assert f"{n} control points" in rec["reason"]
    # An unreachable target says so and names what limits it.
    rec = recommend(paper, 0.001, n_controls=(4, 8), focal_lengths_mm=(16.0,), sessions=50)
    assert not rec["reached"] and "CMM part" in rec["reason"]


def test_working_distance_keeps_the_object_fixed(paper):
    far = with_working_distance(paper, 600.0)
    np.testing.assert_allclose(far.to_global(far.camera_xyz), paper.to_global(paper.camera_xyz), atol=1e-9)
    assert far.working_distance_mm == pytest.approx(600.0)


# ---- report and CLI ------------------------------------------------------------------------------


def test_report_has_inline_svg_plots_and_json(tmp_path, paper, sweeps):
    prediction = predict(paper, sessions=100)
    html_path, json_path = write_report(tmp_path, prediction, sweeps, None)
    text = html_path.read_text()
    assert text.count("<svg") == len(sweeps["sweeps"]) + 1  # one per sweep + the TRE field
    for name in sweeps["sweeps"]:
        assert f'id="sweep-{name}"' in text
    # issue 27 item 7: the shared record header, the station as a table (no Python reprs)
    assert 'id="record-header"' in text and 'id="station-parameters"' in text
    assert "{&#39;" not in text and "[&#39;" not in text and "{'" not in text
    doc = json.loads(json_path.read_text())
    assert doc["sweeps"]["sweeps"].keys() == sweeps["sweeps"].keys()
    assert [c["name"] for c in doc["characteristics"]] == [c.name for c in paper.characteristics]


def test_plan_json_cli(capsys, scenario):
    # The station scenario (its rendered bias is cached by the `scenario` fixture's predictions).
    assert main(["plan", "--scenario", "station", "--json", "--sessions", "200"]) == 0
    doc = json.loads(capsys.readouterr().out)
    names = [c["name"] for c in doc["characteristics"]]
    assert names == [c.name for c in scenario.characteristics] == [
        "P1-L3", "P2-L3", "P1-P2", "P1-R1", "P1-depth", "P2-depth"]
    assert doc["bias_model"] == "rendered" and 0.01 < doc["centroid_bias_rms_px"] < 0.04
    for c in doc["characteristics"]:
        assert c["predicted_u_mm"] == c["monte_carlo"]["u_mm"] > 0
        assert c["analytic"]["u_mm"] == pytest.approx(c["predicted_u_mm"], rel=0.2)
        assert c["predicted_U_mm"] == pytest.approx(2 * c["predicted_u_mm"])
    assert len(doc["tre_field"]["tre_mm"]) == len(doc["tre_field"]["y_mm"])


def test_crb_cli(capsys):
    assert main(["crb", "--scenario", "station", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [p["id"] for p in doc["points"]][:2] == ["P1", "P2"]
    for p in doc["points"]:
        sx, sy, sz = p["camera_sigma_mm"]
        assert sz > 4 * max(sx, sy)  # depth is the weak axis of the 50 mm baseline
    assert main(["crb"]) == 2
    assert "station file or --scenario" in capsys.readouterr().err
