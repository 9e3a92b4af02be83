"""The session config: which implementation runs each stage, with its options.

A TOML file (``docs/config.md``)::

    [session]
    output_dir = "recordings"   # sessions are written to <output_dir>/<name>/
    plan = ""                   # measurement plan; "" = the source's default plan
    record = true               # write session.mcap
    rerun = true                # write session.rrd

    [acquire]
    plugin = "simulator"        # the implementation; every other key is an option
    scenario = "table3"

    [centroid]
    plugin = "modelfit"
    ...

Stage options are checked against the implementation's factory signature
when the session starts; every error names the file and the key.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from crossfield.errors import ConfigError
from crossfield.types import STAGES

DEFAULT_PLUGINS: dict[str, str] = {
    "acquire": "simulator",
    "centroid": "modelfit",
    "triangulate": "epipolar",
    "reference": "romer-serial",
    "register": "ml",
    "measure": "plan",
    "report": "html",
}

SESSION_DEFAULTS: dict[str, Any] = {
    "name": "",
    "output_dir": "recordings",
    "plan": "",
    "record": True,
    "rerun": True,
    "rerun_image_every": 5,  # session.rrd: images of every n-th pair (0 = none); docs/visualisation.md
    "match_tolerance_mm": 0.5,  # rigid-distance agreement for control-point matching
    "signing_key": "",  # Ed25519 station key (PEM) that signs the recording's seal; docs/replay-and-audit.md
    "allow_overdue_instruments": False,  # keep the decisions with an instrument past its due date; docs/report.md
    "monte_carlo": 0,  # GUM-S1 Monte Carlo check of the budget at the session end: draws (0 = off); docs/uncertainty.md
    "compression": "lz4",  # session.mcap chunk compression: "lz4", "zstd" or "none" (lossless); docs/recording.md
}


#: [session] key -> a check giving what the value must be when it is out of range (else None).
_SESSION_CHECKS: dict[str, Callable[[Any], str | None]] = {
    "match_tolerance_mm": lambda v: None if math.isfinite(v) and v > 0 else "a finite number of mm > 0",
    "rerun_image_every": lambda v: None if v >= 0 else "an integer >= 0 (0: no images)",
    "output_dir": lambda v: None if v.strip() else "a folder (not empty)",
    "monte_carlo": lambda v: None if v == 0 or v >= 2 else "0 (off) or a number of draws >= 2",
    "compression": lambda v: None if v in ("zstd", "lz4", "none") else 'one of "zstd", "lz4", "none"',
}


@dataclass(frozen=True)
class StageConfig:
    plugin: str
    options: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Config:
    """A resolved config. ``source`` names the file it came from (or ``<defaults>``)."""

    session: Mapping[str, Any]
    stages: Mapping[str, StageConfig]
    source: str = "<defaults>"
    #: ``[catalog]``: url, station (crossfield.catalog; docs/catalog.md). Not in :meth:`to_dict`
    #: (not recorded with the session: a URL may hold a password).
    catalog: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The resolved config as plain TOML-able data (recorded with the session)."""
        out: dict[str, Any] = {"session": dict(self.session)}
        for stage in STAGES:
            sc = self.stages[stage]
            out[stage] = {"plugin": sc.plugin, **dict(sc.options)}
        return out


def parse_config(data: Mapping[str, Any], source: str = "<config>") -> Config:
    """Validate a config mapping; errors name ``source`` and the key."""
    for key in data:
        if key not in ("session", "catalog") and key not in STAGES:
            raise ConfigError(
                f"{source}: unknown table [{key}]; allowed: session, catalog, {', '.join(STAGES)}"
            )
    catalog = _catalog_table(data.get("catalog", {}), source)
    session = dict(SESSION_DEFAULTS)
    given = data.get("session", {})
    if not isinstance(given, Mapping):
        raise ConfigError(f"{source}: [session] must be a table")
    report = data.get("report")
    if isinstance(report, Mapping) and "monte_carlo" in report:
        # Before 0.2 the Monte Carlo check was the report stage's option (recordings
        # keep their config): it is the session's now, run at the session end.
        data = {**data, "report": {k: v for k, v in report.items() if k != "monte_carlo"}}
        given = {"monte_carlo": report["monte_carlo"], **given}
    for key, value in given.items():
        if key not in SESSION_DEFAULTS:
            raise ConfigError(
                f"{source}: [session] unknown key {key!r}; allowed: {', '.join(SESSION_DEFAULTS)}"
            )
        want = type(SESSION_DEFAULTS[key])
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want) or (want is not bool and isinstance(value, bool)):
            raise ConfigError(
                f"{source}: [session] key {key!r} must be a {want.__name__}, got {value!r}"
            )
        bad = _SESSION_CHECKS.get(key, lambda v: None)(value)
        if bad:
            raise ConfigError(f"{source}: [session] key {key!r} must be {bad}, got {value!r}")
        session[key] = value
    stages: dict[str, StageConfig] = {}
    for stage in STAGES:
        table = data.get(stage, {})
        if not isinstance(table, Mapping):
            raise ConfigError(f"{source}: [{stage}] must be a table")
        options = dict(table)
        plugin = options.pop("plugin", DEFAULT_PLUGINS[stage])
        if not isinstance(plugin, str) or not plugin:
            raise ConfigError(f"{source}: [{stage}] key 'plugin' must be a non-empty string")
        stages[stage] = StageConfig(plugin, options)
    return Config(session, stages, source, catalog)


#: ``[catalog]`` keys (all strings; "" = not set): the catalog's URL and this station's name.
CATALOG_KEYS = ("url", "station")


def _catalog_table(table: Any, source: str) -> dict[str, str]:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{source}: [catalog] must be a table")
    for key, value in table.items():
        if key not in CATALOG_KEYS:
            raise ConfigError(f"{source}: [catalog] unknown key {key!r}; allowed: {', '.join(CATALOG_KEYS)}")
        if not isinstance(value, str):
            raise ConfigError(f"{source}: [catalog] key {key!r} must be a str, got {value!r}")
    return {key: table[key] for key in CATALOG_KEYS if table.get(key)}


def load_config(path: str | Path | None = None) -> Config:
    """Read a config file (or the defaults when ``path`` is None)."""
    if path is None:
        return parse_config({}, "<defaults>")
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a config: a binary file, not UTF-8 TOML text") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return parse_config(data, str(path))


def parse_option(text: str) -> tuple[str, str, Any]:
    """Parse ``stage.key=value`` (value as a TOML value, else a string)."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(f"--option {text!r}: expected stage.key=value")
    lhs, raw = text.split("=", 1)
    stage, key = lhs.split(".", 1)
    if stage != "session" and stage not in STAGES:
        raise ConfigError(f"--option {text!r}: unknown stage {stage!r}; stages: {', '.join(STAGES)}")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return stage, key, value


def with_overrides(
    config: Config,
    plugins: Mapping[str, str | None] | None = None,
    options: Sequence[str] = (),
    values: Mapping[str, Mapping[str, Any]] | None = None,
    *,
    by: str = "command-line overrides",
) -> Config:
    """A copy of ``config`` with stage plugins replaced and options set:
    ``options`` as ``stage.key=value`` texts, then ``values`` as
    ``{stage: {key: value}}`` (``stage`` may be ``session``). Replacing a
    stage's plugin drops that stage's options (they belonged to the old
    implementation) unless given again. ``by`` names the overrides in the
    new config's ``source``."""
    values = {stage: table for stage, table in (values or {}).items() if table}
    if not options and not values and not any(plugins.values() if plugins else ()):
        return config
    data = copy.deepcopy(config.to_dict())
    for stage, plugin in (plugins or {}).items():
        if stage not in STAGES:
            raise ConfigError(f"{by}: unknown stage {stage!r}; stages: {', '.join(STAGES)}")
        if plugin and plugin != data[stage]["plugin"]:
            data[stage] = {"plugin": plugin}
    for text in options:
        stage, key, value = parse_option(text)
        data.setdefault(stage, {})[key] = value
    for stage, table in values.items():
        if stage != "session" and stage not in STAGES:
            raise ConfigError(f"{by}: unknown stage {stage!r}; stages: session, {', '.join(STAGES)}")
        if not isinstance(table, Mapping):
            raise ConfigError(
                f"{by}: the options of {stage!r} must be a mapping of option -> value, got {table!r}"
            )
        data.setdefault(stage, {}).update(table)
    return dataclasses.replace(parse_config(data, f"{config.source} (with {by})"), catalog=config.catalog)


#: Options of the simulator source that ``crossfield run`` and :func:`crossfield.run`
#: take directly (``--scenario``, ``scenario=``).
SIMULATOR_OPTIONS = ("scenario", "frames", "seed")

def session_config(
    path: str | Path | None = None,
    *,
    plugins: Mapping[str, str | None] | None = None,
    simulator: Mapping[str, Any] | None = None,
    session: Mapping[str, Any] | None = None,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    option_texts: Sequence[str] = (),
    spell: Callable[[str], str] = str,
    by: str = "command-line overrides",
) -> Config:
    """The config of a ``crossfield run`` session: one code path for the CLI and the Python API.

    path: the config file (None: the defaults). plugins: stage -> implementation
    name (None: as configured). option_texts: ``stage.key=value`` texts (the
    CLI's ``--option``); options: ``{stage: {key: value}}`` (the API's dicts;
    ``stage`` may be ``session``). simulator: the :data:`SIMULATOR_OPTIONS`
    (scenario, frames, seed), an error for any other source. session:
    ``[session]`` keys (plan, output_dir, name, record, rerun). A value of
    None means "not given". Later wins: file, option_texts, options,
    simulator, session.

    No ``[reference] port`` is added here: with none named, the runner reads
    the arm that the acquisition serves, if it serves one
    (:class:`crossfield.stages.ServesSimulatedArm`). ``spell(key)`` names an argument in errors
    (``--scenario`` on the command line, ``scenario`` in Python).
    """
    base = load_config(path)
    values: dict[str, Any] = {  # copies; a table that is no mapping is named by with_overrides
        stage: dict(table) if isinstance(table, Mapping) else table
        for stage, table in (options or {}).items()
    }
    given = {key: value for key, value in (simulator or {}).items() if value is not None}
    for key in given:
        if key not in SIMULATOR_OPTIONS:
            raise ConfigError(
                f"{spell(key)}: not a simulator option; those are {', '.join(SIMULATOR_OPTIONS)}"
            )
    if given:
        values.setdefault("acquire", {}).update(given)
    session_values = {key: value for key, value in (session or {}).items() if value is not None}
    if session_values:
        values.setdefault("session", {}).update(session_values)
    config = with_overrides(base, plugins, option_texts, values, by=by)
    acquire = config.stages["acquire"].plugin
    if given and acquire != "simulator":
        raise ConfigError(f"{spell(next(iter(given)))} applies to the simulator source, not to {acquire!r}")
    return config
