"""The input files' JSON Schemas (crossfield.schemas): the checked-in files are the
generated ones; they are built from the parsers' own definitions (the same keys, the
same checks); every example in the repository validates and parses; a bad file
fails both the schema and the parser."""

from __future__ import annotations

import copy
import re
import tomllib
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import tomli_w

from crossfield import config as config_module
from crossfield import plan as plan_module
from crossfield import schemas
from crossfield.calibration.boards import board_from_dict
from crossfield.calibration.solve import CalibrationError, settings_from_dict
from crossfield.errors import ConfigError
from crossfield.planning import station as station_module
from crossfield.simulator.scenarios import build_scene

REPO = Path(__file__).resolve().parents[2]
STATION_EXAMPLE = REPO / "docs" / "examples" / "station-paper.toml"


def _parse(kind: str, data: dict[str, Any]) -> None:
    """The parser of ``kind`` on ``data`` (raises its one-line error)."""
    if kind == "config":
        config_module.parse_config(data, "<test>")
    elif kind == "plan":
        plan_module.parse_plan(tomli_w.dumps(data), "<test>")
    elif kind == "station":
        station_module.parse_station(tomli_w.dumps(data), "<test>")
    else:
        if not isinstance(data.get("board"), dict):
            raise ConfigError("<test>: no [board] table")
        board_from_dict(data["board"], "<test>")
        settings_from_dict(data.get("calibration", {}), "<test>")


def _errors(kind: str, data: dict[str, Any]) -> list[str]:
    return [e.message for e in jsonschema.Draft202012Validator(schemas.schema(kind)).iter_errors(data)]


def _parses(kind: str, data: dict[str, Any]) -> bool:
    try:
        _parse(kind, data)
    except (ConfigError, CalibrationError):
        return False
    return True


@pytest.mark.parametrize("name", schemas.NAMES)
def test_checked_in_files_are_the_generated_ones(name: str) -> None:
    jsonschema.Draft202012Validator.check_schema(schemas.schema(name))
    assert schemas.checked_in(name) == schemas.schema_text(name), (
        f"pipeline/schemas/{name}.schema.json is stale: run python -m crossfield.schemas"
    )


def _keywords(node: Any) -> set[str]:
    if isinstance(node, dict):
        return set(node) | {k for key, v in node.items() if key != "properties" for k in _keywords(v)} | {
            k for v in node.get("properties", {}).values() for k in _keywords(v)
        }
    if isinstance(node, list):
        return {k for v in node for k in _keywords(v)}
    return set()


@pytest.mark.parametrize("name", schemas.NAMES)
def test_only_keywords_that_draft_4_editors_read_alike(name: str) -> None:
    assert not _keywords(schemas.schema(name)) & set(schemas._DRAFT4)


def test_built_from_the_parsers_definitions() -> None:
    # config: every [session] key with its default's type; the ranges for exactly the keys the parser checks
    session = schemas.schema("config")["properties"]["session"]["properties"]
    assert list(session) == list(config_module.SESSION_DEFAULTS)
    assert set(schemas.SESSION_LIMITS) == set(config_module._SESSION_CHECKS)
    # plan: the same tables and keys, required as the parser requires them
    assert {"probing_order", *schemas.PLAN_ARRAYS} <= plan_module._TOP_KEYS
    for table, (required, optional) in plan_module._TABLE_KEYS.items():
        assert set(schemas.PLAN_VALUES[table]) == required | optional, table
    target = schemas.schema("plan")["properties"]["target"]["items"]
    assert set(target["required"]) == plan_module._TABLE_KEYS["target"][0]
    assert schemas.schema("plan")["properties"]["characteristic"]["items"]["properties"]["kind"]["enum"] == list(
        plan_module.KINDS
    )


def test_station_schema_has_every_key_the_parser_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Trace the station parser's typed accessors on the example (and on a file with explicit
    control points and the rendered bias model): each key read is in the schema with that type."""
    read: set[tuple[str, str, str]] = set()
    table = station_module._Table
    for accessor in ("number", "integer", "vector", "string", "table", "tables"):
        original = getattr(table, accessor)

        def traced(self, key, *args, _original=original, _kind=accessor, **kwargs):
            read.add((re.sub(r"\[\d+\]", "", self.path), key, _kind))
            return _original(self, key, *args, **kwargs)

        monkeypatch.setattr(table, accessor, traced)
    example = tomllib.loads(STATION_EXAMPLE.read_text(encoding="utf-8"))
    station_module.parse_station(STATION_EXAMPLE.read_text(encoding="utf-8"))
    explicit = copy.deepcopy(example)
    explicit["controls"] = {"point": [{"id": f"K{k}", "xyz_mm": [10.0 * k, 5.0, 400.0]} for k in range(3)]}
    station_module.parse_station(tomli_w.dumps(explicit))
    assert len(read) > 40
    want = {"number": ("number",), "integer": ("integer",), "vector": ("array",), "string": ("string",),
            "table": ("object",), "tables": ("array",)}
    top = schemas.schema("station")
    for path, key, kind in sorted(read):
        node = top
        for part in [p for p in path.split(".") if p]:
            node = node["properties"][part]
            node = node.get("items", node)
        assert key in node["properties"], (path, key)
        assert node["properties"][key]["type"] in want[kind], (path, key, kind)
    # perspective_bias is read without an accessor (a bool): in the schema as such
    assert top["properties"]["targets"]["properties"]["perspective_bias"]["type"] == "boolean"


def _toml_snippets() -> list[tuple[str, str, str]]:
    out = []
    for doc in sorted((REPO / "docs").glob("*.md")):
        for k, block in enumerate(re.findall(r"^```toml\n(.*?)^```", doc.read_text(encoding="utf-8"), re.S | re.M)):
            out.append((f"{doc.name}#{k + 1}", block, doc.name))
    return out


def _kind_of(data: dict[str, Any]) -> str | None:
    if "build-system" in data or "project" in data:
        return None  # a pyproject.toml
    if "board" in data:
        return "board"
    if "plan" in data or "control" in data:
        return "plan"
    if "camera" in data and "targets" in data:
        return "station"
    return "config"


def test_every_example_validates_and_parses() -> None:
    examples = [("docs/examples/station-paper.toml", "station", tomllib.loads(STATION_EXAMPLE.read_text()))]
    for scenario in ("station", "table3", "camera-limited"):  # the simulator's plans (the mismatch-* share them)
        examples.append((f"scenario {scenario}", "plan", tomllib.loads(build_scene(scenario).plan.text)))
    for where, kind, data in examples:
        assert _errors(kind, data) == [], where
        _parse(kind, data)
    # The docs' snippets: the schema and the parser agree on each (some are excerpts, e.g. a plan
    # with one control point; most are whole and valid).
    agreed = valid = 0
    for where, text, _ in _toml_snippets():
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError:
            continue  # a sketch with "..." in it
        kind = _kind_of(data)
        if kind is None:
            continue
        ok = not _errors(kind, data)
        assert ok == _parses(kind, data), (where, kind, _errors(kind, data))
        agreed += 1
        valid += ok
    assert agreed >= 10 and valid >= 8, (agreed, valid)


def _station() -> dict[str, Any]:
    return tomllib.loads(STATION_EXAMPLE.read_text(encoding="utf-8"))


def _plan() -> dict[str, Any]:
    return tomllib.loads(build_scene("station").plan.text)


BOARD = {"board": {"type": "chessboard", "squares_x": 9, "squares_y": 6, "square_mm": 20.0}}


def _with(base: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """``base`` with ``path`` (dotted; ``name#k`` the k-th table of an array) set to ``value``."""
    data = copy.deepcopy(base)
    node = data
    parts = path.split(".")
    for part in parts[:-1]:
        name, _, index = part.partition("#")
        node = node.setdefault(name, {})
        if index:
            node = node[int(index)]
    name, _, index = parts[-1].partition("#")
    node[name] = value
    return data


BAD: list[tuple[str, str, Any]] = [
    # (kind, what, the bad document)
    ("config", "unknown table", {"sesion": {}}),
    ("config", "unknown [session] key", {"session": {"frames": 3}}),
    ("config", "record not a bool", {"session": {"record": "yes"}}),
    ("config", "match_tolerance_mm <= 0", {"session": {"match_tolerance_mm": 0.0}}),
    ("config", "rerun_image_every < 0", {"session": {"rerun_image_every": -2}}),
    ("config", "output_dir blank", {"session": {"output_dir": "  "}}),
    ("config", "monte_carlo = 1", {"session": {"monte_carlo": 1}}),
    ("config", "compression unknown", {"session": {"compression": "gzip"}}),
    ("config", "empty plugin name", {"centroid": {"plugin": ""}}),
    ("config", "unknown [catalog] key", {"catalog": {"uri": "x.sqlite"}}),
    ("plan", "unknown key in a target", lambda: _with(_plan(), "target#0.radius", 3.0)),
    ("plan", "search_radius <= 0", lambda: _with(_plan(), "target#0.search_radius", 0.0)),
    ("plan", "kind unknown", lambda: _with(_plan(), "characteristic#0.kind", "angle")),
    ("plan", "decision rule unknown", lambda: _with(_plan(), "uncertainty", {"decision_rule": "lenient"})),
    ("plan", "consistency_alpha = 1", lambda: _with(_plan(), "uncertainty", {"consistency_alpha": 1.0})),
    ("plan", "an id with a dot", lambda: _with(_plan(), "control#0.id", "C.1")),
    ("plan", "two controls", lambda: _with(_plan(), "control", _plan()["control"][:2])),
    ("station", "unknown [camera] key", lambda: _with(_station(), "camera.f_mm", 16.0)),
    ("station", "focal length 0", lambda: _with(_station(), "camera.focal_length_mm", 0.0)),
    ("station", "distortion of 4", lambda: _with(_station(), "camera.distortion", [0.0] * 4)),
    ("station", "bias model unknown", lambda: _with(_station(), "targets.bias_model", "magic")),
    ("station", "kind unknown", lambda: _with(_station(), "characteristic#0.kind", "angle")),
    ("station", "2 controls", lambda: _with(_station(), "controls.count", 2)),
    ("board", "no [board]", {"calibration": {}}),
    ("board", "squares_x = 1", lambda: _with(BOARD, "board.squares_x", 1)),
    ("board", "unknown type", lambda: _with(BOARD, "board.type", "dots")),
    ("board", "a charuco key on a chessboard", lambda: _with(BOARD, "board.marker_mm", 11.0)),
    ("board", "distortion unknown", lambda: _with(BOARD, "calibration", {"distortion": "fisheye"})),
    ("board", "min_views 2", lambda: _with(BOARD, "calibration", {"min_views": 2})),
]


@pytest.mark.parametrize("kind, what, bad", BAD, ids=[f"{k}: {w}" for k, w, _ in BAD])
def test_a_bad_file_fails_the_schema_and_the_parser(kind: str, what: str, bad: Any) -> None:
    data = bad() if callable(bad) else bad
    assert _errors(kind, data), what
    with pytest.raises((ConfigError, CalibrationError)):
        _parse(kind, data)
