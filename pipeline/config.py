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
    plugin = "weighted"
    ...

Stage options are checked against the implementation's factory signature
when the session starts; every error names the file and the key.
"""

from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from crossfield.errors import ConfigError
from crossfield.registry import STAGES

DEFAULT_PLUGINS: dict[str, str] = {
    "acquire": "simulator",
    "centroid": "weighted",
    "triangulate": "epipolar",
    "reference": "romer-serial",
    "register": "svd",
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
        if key != "session" and key not in STAGES:
            raise ConfigError(
                f"{source}: unknown table [{key}]; allowed: session, {', '.join(STAGES)}"
            )
    session = dict(SESSION_DEFAULTS)
    given = data.get("session", {})
    if not isinstance(given, Mapping):
        raise ConfigError(f"{source}: [session] must be a table")
    for key, value in given.items():
        if key not in SESSION_DEFAULTS:
            raise ConfigError(
                f"{source}: [session] unknown key {key!r}; allowed: {', '.join(SESSION_DEFAULTS)}"
            )
        want = type(SESSION_DEFAULTS[key])
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want):
            raise ConfigError(
                f"{source}: [session] key {key!r} must be a {want.__name__}, got {value!r}"
            )
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
    return Config(session, stages, source)


def load_config(path: str | Path | None = None) -> Config:
    """Read a config file (or the defaults when ``path`` is None)."""
    if path is None:
        return parse_config({}, "<defaults>")
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config: {exc.strerror}") from None
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
    options: list[str] | tuple[str, ...] = (),
) -> Config:
    """A copy of ``config`` with stage plugins replaced and ``stage.key=value``
    options set. Replacing a stage's plugin drops that stage's options (they
    belonged to the old implementation) unless given again."""
    if not options and not any(plugins.values() if plugins else ()):
        return config
    data = copy.deepcopy(config.to_dict())
    for stage, plugin in (plugins or {}).items():
        if plugin and plugin != data[stage]["plugin"]:
            data[stage] = {"plugin": plugin}
    for text in options:
        stage, key, value = parse_option(text)
        data.setdefault(stage, {})[key] = value
    return parse_config(data, config.source + " (with command-line overrides)")
