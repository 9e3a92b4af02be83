"""JSON Schemas (draft 2020-12) of crossfield's input files, for editors
(docs/user-guide.md, "Editing the input files"): the session config
(docs/config.md), the measurement plan (docs/plan.md), the station file
(docs/planning.md) and the board file (docs/calibration.md).

Each schema is built here from the parser's own definitions, so that the two
cannot drift apart:

* config (:mod:`crossfield.config`): the tables ``STAGES``, the ``[session]``
  keys, types and defaults ``SESSION_DEFAULTS``, the ``[catalog]`` keys
  ``CATALOG_KEYS``, the default plugins ``DEFAULT_PLUGINS``;
* plan (:mod:`crossfield.plan`): every table's required and optional keys
  (``_TABLE_KEYS``), the characteristic kinds ``KINDS``, the line fits
  ``LINE_FITS``, the decision rules ``RULES``;
* board (:mod:`crossfield.calibration.boards`): the keys and types of each
  board type (``_KEYS``, ``BOARD_TYPES``, ``_DEFAULTS``), and the
  ``[calibration]`` table from the fields of ``CalibrationSettings``;
* station (:mod:`crossfield.planning.station`): its parser reads keys through
  typed accessors, not from a table; :data:`STATION` lists them as those
  accessors read them (tests/structure/test_schemas.py traces the parser's
  accessors and checks each key it reads is here, with that type).

What a value must be beyond its type (a range, a choice) is stated here where the
parser checks it by code (:data:`SESSION_LIMITS`, :data:`PLAN_VALUES`); the
tests check that every such key is one the parser checks and that a value the
schema refuses is refused by the parser too. Cross-key rules (an id named by a
characteristic exists, the probing order lists each point once) are the
parser's alone: a file that passes the schema can still fail ``crossfield``
with a one-line error naming the key.

The schemas declare draft 2020-12 (the tests validate with it) but use only keywords
that mean the same in draft 4, the one editors' TOML servers implement (taplo,
Even Better TOML): no ``const``, no numeric ``exclusiveMinimum`` (``> 0`` is
``"not": {"maximum": 0}``) (:data:`_DRAFT4` checks it).

The files ``<name>.schema.json`` beside this module are the checked-in output
(an editor's ``#:schema`` directive can name them); ``python -m crossfield.schemas``
rewrites them, and the tests check they equal :func:`schema_text`.
"""

from __future__ import annotations

import json
from dataclasses import fields
from importlib import resources
from pathlib import Path
from typing import Any, Callable

__all__ = ["NAMES", "PLAN_VALUES", "SESSION_LIMITS", "STATION", "checked_in", "schema", "schema_text", "write"]

DRAFT = "https://json-schema.org/draft/2020-12/schema"
ID_BASE = "https://crossfield.invalid/schemas/"  # a name, not a place: the files ship with crossfield

NUMBER: dict[str, Any] = {"type": "number"}
INTEGER: dict[str, Any] = {"type": "integer"}
STRING: dict[str, Any] = {"type": "string"}
BOOLEAN: dict[str, Any] = {"type": "boolean"}
NON_NEGATIVE: dict[str, Any] = {"type": "number", "minimum": 0}
POSITIVE: dict[str, Any] = {"type": "number", "not": {"maximum": 0}}  # > 0 (see _DRAFT4)
NON_EMPTY: dict[str, Any] = {"type": "string", "minLength": 1}
ID: dict[str, Any] = {"type": "string", "pattern": r"^[^.]*[^.\s][^.]*$"}  # plan ids: not blank, no '.'


def _vector(n: int, item: dict[str, Any] = NUMBER) -> dict[str, Any]:
    return {"type": "array", "items": item, "minItems": n, "maxItems": n}


def _table(properties: dict[str, Any], required: list[str] | tuple[str, ...] = (), **extra: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "object", "properties": properties, "additionalProperties": False}
    if required:
        out["required"] = sorted(required)
    out.update(extra)
    return out


def _of_python(value: Any) -> dict[str, Any]:
    """The JSON type of a parser's default value (bool before int: a bool is an int in Python)."""
    if isinstance(value, bool):
        return dict(BOOLEAN)
    if isinstance(value, int):
        return dict(INTEGER)
    if isinstance(value, float):
        return dict(NUMBER)  # the parser takes an integer where a float is wanted
    return dict(STRING)


# ---- config -------------------------------------------------------------------------------------

#: [session] key -> what its value must be beyond its type: the schema form of
#: ``crossfield.config._SESSION_CHECKS`` (the same keys; tests check both refuse the same values).
SESSION_LIMITS: dict[str, dict[str, Any]] = {
    "match_tolerance_mm": {"not": {"maximum": 0}},
    "rerun_image_every": {"minimum": 0},
    "output_dir": {"pattern": r"\S"},
    "monte_carlo": {"anyOf": [{"enum": [0]}, {"minimum": 2}]},
    "compression": {"enum": ["zstd", "lz4", "none"]},
}


def config_schema() -> dict[str, Any]:
    from crossfield.config import CATALOG_KEYS, DEFAULT_PLUGINS, SESSION_DEFAULTS
    from crossfield.types import STAGES

    session = {
        key: {**_of_python(default), **SESSION_LIMITS.get(key, {}), "default": default}
        for key, default in SESSION_DEFAULTS.items()
    }
    stages = {
        stage: {
            "type": "object",
            "description": f"the {stage} stage: plugin = the implementation's name (crossfield plugins), "
            "the other keys its options",
            "properties": {"plugin": {**NON_EMPTY, "default": DEFAULT_PLUGINS[stage]}},
            "additionalProperties": True,
        }
        for stage in STAGES
    }
    return {
        "title": "crossfield session config (docs/config.md)",
        "type": "object",
        "properties": {
            "session": _table(session),
            "catalog": _table({key: STRING for key in CATALOG_KEYS}),
            **stages,
        },
        "additionalProperties": False,
    }


# ---- plan ---------------------------------------------------------------------------------------

#: The plan's arrays of tables ([[name]]); its other top-level keys are tables or probing_order.
PLAN_ARRAYS = ("control", "target", "reference_point", "reference_line", "characteristic")

#: plan table -> key -> its value as ``crossfield.plan.parse_plan`` checks it (the same keys as the
#: parser's ``_TABLE_KEYS``: tests check it). Choices are filled in from the parser's tuples.
PLAN_VALUES: dict[str, dict[str, Callable[[], dict[str, Any]] | dict[str, Any]]] = {
    "plan": {"name": STRING},
    "control": {"id": ID, "description": STRING},
    "target": {"id": ID, "nominal": _vector(3), "search_radius": POSITIVE, "description": STRING},
    "reference_point": {"id": ID, "description": STRING},
    "reference_line": {
        "id": ID,
        "probes": {"type": "integer", "minimum": 2},  # >= 5 for fit = "cylinder"
        "fit": lambda: {"enum": list(_plan().LINE_FITS), "default": "line"},
        "description": STRING,
    },
    "characteristic": {
        "name": STRING, "kind": lambda: {"enum": list(_plan().KINDS)}, "a": STRING, "b": STRING,
        "nominal": NUMBER, "description": STRING, "tolerance": POSITIVE, "upper_tol": NUMBER,
        "lower_tol": NUMBER,
    },
    "uncertainty": {
        "coverage_factor": {**POSITIVE, "default": 2.0},
        "decision_rule": lambda: {"enum": list(_plan().RULES), "default": "simple"},
        "calibration_scale_u": NON_NEGATIVE,
        "target_radius": NON_NEGATIVE,
        "max_tilt_deg": NON_NEGATIVE,
        "eccentricity_corrected": BOOLEAN,
        "eccentricity_residual": NON_NEGATIVE,
        "consistency_alpha": {"type": "number", "allOf": [{"not": {"maximum": 0}}, {"not": {"minimum": 1}}]},
    },
    "temperature": {
        "part": NUMBER, "u_part": NON_NEGATIVE, "part_alpha": NON_NEGATIVE, "u_part_alpha": NON_NEGATIVE,
        "reference": NUMBER, "u_reference": NON_NEGATIVE, "reference_alpha": NON_NEGATIVE,
        "u_reference_alpha": NON_NEGATIVE,
    },
    "job": {"part": STRING, "serial": STRING, "operator": STRING, "order": STRING, "instrument": {}},
    "instrument": {"id": STRING, "kind": STRING, "calibrated": STRING, "due": STRING},
}


def _plan():
    import crossfield.plan as plan

    return plan


def _plan_table(name: str) -> dict[str, Any]:
    required, optional = _plan()._TABLE_KEYS[name]
    values = PLAN_VALUES[name]
    props = {key: dict(v() if callable(v) else v) for key, v in values.items() if key in required | optional}
    if name == "job":
        props["instrument"] = {"type": "array", "items": _plan_table("instrument")}
    if name == "characteristic":
        # 'tolerance' (symmetric), or both 'upper_tol' and 'lower_tol'
        return _table(props, tuple(required), anyOf=[{"required": ["tolerance"]},
                                                     {"required": ["upper_tol", "lower_tol"]}])
    return _table(props, tuple(required))


def plan_schema() -> dict[str, Any]:
    top = _plan()._TOP_KEYS
    props: dict[str, Any] = {}
    for name in sorted(top - {"probing_order"}):
        table = _plan_table(name)
        props[name] = {"type": "array", "items": table} if name in PLAN_ARRAYS else table
    props["control"]["minItems"] = 3  # parse_plan: at least 3 control points
    props["probing_order"] = {"type": "array", "items": STRING, "uniqueItems": True}
    return {
        "title": "crossfield measurement plan (docs/plan.md)",
        "type": "object",
        "properties": props,
        "required": ["control"],
        "additionalProperties": False,
    }


# ---- station ------------------------------------------------------------------------------------

_FINITE = {"type": "number"}


def _number(minimum: float | None = None, strict: bool = False, default: float | None = None) -> dict[str, Any]:
    """``_Table.number``: a finite number, ``>= minimum`` (``> minimum`` if strict)."""
    out = dict(_FINITE)
    if minimum is not None:
        out.update({"not": {"maximum": minimum}} if strict else {"minimum": minimum})
    if default is not None:
        out["default"] = default
    return out


def _integer(minimum: int = 1, default: int | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "integer", "minimum": minimum}
    if default is not None:
        out["default"] = default
    return out


def _string(choices: tuple[str, ...] | None = None, default: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = dict(NON_EMPTY)
    if choices:
        out["enum"] = list(choices)
    if default is not None:
        out["default"] = default
    return out


def _station_tables() -> dict[str, Any]:
    from crossfield.planning.station import BIAS_MODELS, KINDS

    point = _table({"id": _string(), "xyz_mm": _vector(3), "normal": _vector(3)}, ["id", "xyz_mm"])
    return {
        "station": _table({"name": _string(), "frames": _integer(1, 10),
                           "coverage_factor": _number(0.0, True, 2.0)}),
        "camera": _table({
            "image_size": _vector(2, {"type": "number", "minimum": 16, "multipleOf": 1}),
            "pixel_pitch_mm": _number(0.0, True), "focal_length_mm": _number(0.0, True),
            "baseline_mm": _number(0.0, True), "baseline_direction": _vector(3),
            "toe_in_deg": _number(default=0.0), "distortion": _vector(5),
            "gain_dn_per_e": _number(0.0, default=0.35), "read_noise_dn": _number(0.0, default=2.5),
            "blur_sigma_px": _number(0.0, True, 0.9), "background_dn": _number(0.0, default=150.0),
            "centroid_efficiency": _number(1.0), "centroid": _string(default="weighted"),
        }, ["image_size", "pixel_pitch_mm", "focal_length_mm", "baseline_mm"]),
        "targets": _table({
            "radius_mm": _number(0.0, True), "signal_dn": _number(0.0, True),
            "working_distance_mm": _number(0.0, True), "view_centre_mm": _vector(2),
            "perspective_bias": {**BOOLEAN, "default": True},
            "bias_model": _string(BIAS_MODELS, "eccentricity"),
            "point": {"type": "array", "items": point, "minItems": 1},
        }, ["radius_mm", "signal_dn", "working_distance_mm", "point"]),
        "controls": _table({
            "half_size_mm": _vector(3, NON_NEGATIVE), "count": _integer(3),
            "point": {"type": "array", "items": _table({"id": _string(), "xyz_mm": _vector(3)}, ["id", "xyz_mm"])},
        }),
        "cmm": _table({"sigma_mm": _number(0.0), "R_global_camera_rotvec": _vector(3),
                       "t_global_camera_mm": _vector(3)}, ["sigma_mm"]),
        "reference_point": {"type": "array", "items": _table({"id": _string(), "xyz_mm": _vector(3)},
                                                             ["id", "xyz_mm"])},
        "reference_line": {"type": "array", "items": _table({
            "id": _string(), "point_mm": _vector(3), "direction": _vector(3),
            "radius_mm": _number(0.0, default=15.0), "probe_heights_mm": _vector(3),
            "probe_angles_deg": _vector(4), "probe_ball_mm": _number(0.0, default=3.0),
            "fit": _string(("cylinder", "line"), "cylinder"),
        }, ["id", "point_mm", "direction"])},
        "characteristic": {"type": "array", "minItems": 1, "items": _table(
            {"name": _string(), "kind": _string(KINDS), "a": _string(), "b": _string()},
            ["name", "kind", "a"],
            # b names the point or line of point_point / point_line (not read for depth)
            anyOf=[{"properties": {"kind": {"enum": ["depth"]}}}, {"required": ["b"]}],
        )},
    }


#: The station file's tables (see the module docstring): built on first use.
STATION: dict[str, Any] = {}


def station_schema() -> dict[str, Any]:
    if not STATION:
        STATION.update(_station_tables())
    return {
        "title": "crossfield station file (docs/planning.md)",
        "type": "object",
        "properties": dict(STATION),
        "required": ["camera", "targets", "cmm", "characteristic"],
        "additionalProperties": False,
    }


# ---- board --------------------------------------------------------------------------------------


def _board_value(kind: type) -> dict[str, Any]:
    """``boards._check_value``: int >= 2, a length in mm > 0, a bool, a string."""
    if kind is int:
        return {"type": "integer", "minimum": 2}
    if kind is float:
        return dict(POSITIVE)
    if kind is bool:
        return dict(BOOLEAN)
    return dict(STRING)


def board_schema() -> dict[str, Any]:
    from crossfield.calibration import boards
    from crossfield.calibration.solve import DISTORTION_MODELS, CalibrationSettings

    variants = []
    for kind in boards.BOARD_TYPES:
        keys = boards._KEYS[kind]
        props: dict[str, Any] = {"type": {"enum": [kind]}}
        for key, t in keys.items():
            props[key] = _board_value(t)
            if key in boards._DEFAULTS:
                props[key]["default"] = boards._DEFAULTS[key]
        required = [k for k in keys if k not in boards._DEFAULTS]
        if kind != "charuco":  # charuco is the default type
            required.append("type")
        variants.append(_table(props, required))
    settings: dict[str, Any] = {}
    for f in fields(CalibrationSettings):
        settings[f.name] = {**_of_python(f.default), "default": f.default}
    settings["distortion"]["enum"] = list(DISTORTION_MODELS)
    settings["min_views"]["minimum"] = 3
    return {
        "title": "crossfield board file (docs/calibration.md)",
        "type": "object",
        "properties": {
            "board": {"oneOf": variants},
            "calibration": _table(settings),
        },
        "required": ["board"],
        "additionalProperties": True,  # other tables are their readers' (read_board_file)
    }


#: Keywords whose meaning differs between draft 4 and 2020-12 (or that draft 4 lacks): never used.
_DRAFT4 = ("const", "exclusiveMinimum", "exclusiveMaximum", "if", "then", "else", "prefixItems",
           "dependentRequired", "unevaluatedProperties")


# ---- the files ----------------------------------------------------------------------------------

_BUILDERS: dict[str, Callable[[], dict[str, Any]]] = {
    "config": config_schema,
    "plan": plan_schema,
    "station": station_schema,
    "board": board_schema,
}
#: The schema names, as ``python -m crossfield.schemas`` writes them (``<name>.schema.json``).
NAMES = tuple(_BUILDERS)


def schema(name: str) -> dict[str, Any]:
    """The JSON Schema of the input file ``name`` (one of :data:`NAMES`)."""
    if name not in _BUILDERS:
        raise KeyError(f"no schema {name!r}; schemas: {', '.join(NAMES)}")
    return {"$schema": DRAFT, "$id": f"{ID_BASE}{name}.schema.json", **_BUILDERS[name]()}


def schema_text(name: str) -> str:
    """:func:`schema` as the checked-in file holds it (indented JSON, a final newline)."""
    return json.dumps(schema(name), indent=2, ensure_ascii=False) + "\n"


def checked_in(name: str) -> str:
    """The text of the checked-in ``<name>.schema.json`` (installed with crossfield)."""
    return resources.files("crossfield.schemas").joinpath(f"{name}.schema.json").read_text(encoding="utf-8")


def write(folder: str | Path | None = None) -> list[Path]:
    """Write every schema to ``folder`` (default: beside this module); the paths written."""
    out = Path(folder) if folder is not None else Path(__file__).parent
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in NAMES:
        path = out / f"{name}.schema.json"
        path.write_text(schema_text(name), encoding="utf-8")
        paths.append(path)
    return paths
