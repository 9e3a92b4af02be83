"""Config, plan and plugin-registry validation: errors name the file and key."""

import textwrap

import pytest

from crossfield.config import load_config, parse_config, with_overrides
from crossfield.errors import ConfigError, PluginError
from crossfield.hookspecs import hookimpl
from crossfield.plan import load_plan, parse_plan
from crossfield.chain.registry import STAGES, get_implementation, implementations, make_plugin_manager

GOOD_PLAN = """
[plan]
name = "t"
[[control]]
id = "C1"
[[control]]
id = "C2"
[[control]]
id = "C3"
[[target]]
id = "P1"
nominal = [1.0, 2.0, 3.0]
search_radius = 2.0
[[reference_line]]
id = "L3"
probes = 6
fit = "cylinder"
[[characteristic]]
name = "P1-L3"
kind = "point_line"
a = "P1"
b = "L3"
nominal = 300.0
tolerance = 0.1
"""


def test_defaults_name_every_stage():
    config = load_config()
    assert set(config.stages) == set(STAGES)
    assert config.stages["acquire"].plugin == "simulator"


def test_unknown_table_and_session_key_are_named(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[centroids]\nplugin = 'weighted'\n")
    with pytest.raises(ConfigError, match=r"bad.toml: unknown table \[centroids\]"):
        load_config(path)
    path.write_text("[session]\noutptu_dir = 'x'\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[session\] unknown key 'outptu_dir'"):
        load_config(path)
    path.write_text("[session]\nrecord = 'yes'\n")
    with pytest.raises(ConfigError, match=r"\[session\] key 'record' must be a bool"):
        load_config(path)


def test_invalid_toml_names_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text("[session\n")
    with pytest.raises(ConfigError, match="broken.toml: not valid TOML"):
        load_config(path)


def test_unknown_plugin_option_names_key_and_lists_options():
    pm = make_plugin_manager()
    impl = get_implementation(pm, "acquire", "simulator")
    with pytest.raises(ConfigError, match=r"cfg.toml: \[acquire\]: unknown option 'scenaro'.*known options: .*scenario"):
        impl.create({"scenaro": "table3"}, "cfg.toml: [acquire]")
    with pytest.raises(ConfigError, match=r"unknown scenario 'nope'"):
        impl.create({"scenario": "nope"}, "cfg.toml: [acquire]")


def test_unknown_implementation_lists_available_names():
    pm = make_plugin_manager()
    with pytest.raises(PluginError, match=r"no centroid implementation named 'magic'; available: .*weighted.*may not be installed"):
        get_implementation(pm, "centroid", "magic")


def test_duplicate_implementation_name_is_an_error():
    class Copycat:
        @hookimpl
        def register_acquires(self, register):
            register("simulator", dict)

    pm = make_plugin_manager(extra=[Copycat()])
    with pytest.raises(PluginError, match="duplicate acquire implementation 'simulator'"):
        implementations(pm, "acquire")


def test_overrides_replace_plugin_and_set_options():
    config = parse_config({"centroid": {"plugin": "weighted", "threshold_sigma": 5}}, "c.toml")
    changed = with_overrides(config, {"centroid": "other"}, ["acquire.frames=3", "session.name=\"x\""])
    assert changed.stages["centroid"].plugin == "other"
    assert dict(changed.stages["centroid"].options) == {}
    assert changed.stages["acquire"].options["frames"] == 3
    assert changed.session["name"] == "x"
    with pytest.raises(ConfigError, match="unknown stage 'acquisition'"):
        with_overrides(config, {}, ["acquisition.frames=3"])


def test_plan_parses_and_orders_probes():
    plan = parse_plan(GOOD_PLAN, "p.toml")
    assert plan.probing_order() == ["C1", "C2", "C3", "L3.1", "L3.2", "L3.3", "L3.4", "L3.5", "L3.6"]
    assert plan.characteristics[0].kind == "point_line"


@pytest.mark.parametrize(
    "old, new, message",
    [
        ('tolerance = 0.1', 'tolerence = 0.1', r"\[\[characteristic\]\] #1: unknown key 'tolerence'"),
        ('kind = "point_line"', 'kind = "angle"', r"\[\[characteristic\]\] #1: key 'kind' must be one of"),
        ('b = "L3"', 'b = "L4"', r"key 'b' names 'L4', which is no reference line"),
        ('search_radius = 2.0', 'search_radius = -1', r"\[\[target\]\] #1: key 'search_radius' must be > 0"),
        ('nominal = [1.0, 2.0, 3.0]', 'nominal = [1.0, 2.0]', r"key 'nominal' must be \[x, y, z\]"),
        ('id = "C2"', 'id = "C1"', r"\[\[control\]\] #2: duplicate id 'C1'"),
        ('probes = 6', 'probes = 3', r"key 'probes' must be an integer >= 5"),
    ],
)
def test_malformed_plan_names_the_key(old, new, message):
    assert old in GOOD_PLAN
    with pytest.raises(ConfigError, match=r"p.toml: .*" + message):
        parse_plan(GOOD_PLAN.replace(old, new, 1), "p.toml")


def test_plan_file_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match="missing.toml: cannot read plan"):
        load_plan(tmp_path / "missing.toml")
    path = tmp_path / "plan.toml"
    path.write_text(textwrap.dedent(GOOD_PLAN).replace("[[control]]\nid = \"C3\"\n", ""))
    with pytest.raises(ConfigError, match="plan.toml: .*at least 3 control points"):
        load_plan(path)
