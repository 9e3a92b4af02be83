"""Plugin manager factory and the per-stage registries.

The registry pattern (as in simonw's ``llm``): pluggy calls every
``register_<stage>s(register)`` implementation; each calls ``register(name,
factory, description)``. The config names the implementation that runs.
"""

from __future__ import annotations

import collections.abc
import functools
import importlib
import inspect
import numbers
import types
import typing
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path, PurePath
from typing import Any, Generic, TypeVar

import pluggy

from crossfield import hookspecs
from crossfield.chain.provenance import crossfield_version
from crossfield.errors import ConfigError, PluginError
from crossfield.hookspecs import Factory
from crossfield.stages import STAGES, check_implementation

__all__ = [
    "BUILTIN_PLUGINS",
    "STAGES",
    "Implementation",
    "get_implementation",
    "implementations",
    "make_plugin_manager",
]

T = TypeVar("T")

#: Modules of the built-in plugins, loaded by every plugin manager.
BUILTIN_PLUGINS: tuple[str, ...] = (
    "crossfield.plugins.acquire_simulator",
    "crossfield.plugins.acquire_folder",
    "crossfield.plugins.acquire_basler",
    "crossfield.plugins.acquire_opencv",
    "crossfield.plugins.centroid_weighted",
    "crossfield.plugins.centroid_ellipse",
    "crossfield.plugins.centroid_modelfit",
    "crossfield.plugins.triangulate_epipolar",
    "crossfield.plugins.reference_romer_serial",
    "crossfield.plugins.reference_csv",
    "crossfield.plugins.reference_spatialanalyzer",
    "crossfield.plugins.reference_pcdmis_xyz",
    "crossfield.plugins.register_svd",
    "crossfield.plugins.register_umeyama",
    "crossfield.plugins.register_horn",
    "crossfield.plugins.register_ml",
    "crossfield.plugins.measure_plan",
    "crossfield.plugins.report_html",
)


@dataclass(frozen=True)
class Implementation(Generic[T]):
    """One named implementation of a stage; ``T`` is the stage's protocol
    (:data:`crossfield.stages.STAGE_PROTOCOLS`)."""

    stage: str
    name: str
    factory: Factory[T]
    description: str
    plugin: str  # name of the pluggy plugin (module) that registered it
    package: str  # distribution that ships it
    version: str

    def options(self) -> dict[str, Any]:
        """Option name -> default (``inspect.Parameter.empty`` if required)."""
        signature = inspect.signature(self.factory)
        return {
            p.name: p.default
            for p in signature.parameters.values()
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
        }

    def option_types(self) -> dict[str, Any]:
        """Option name -> its declared type: the factory's annotation, else the
        type of its default (an option with neither is not in the mapping)."""
        try:
            signature = inspect.signature(self.factory, eval_str=True)
        except (NameError, TypeError, SyntaxError, ValueError):  # an annotation that cannot be resolved
            signature = inspect.signature(self.factory)
        out: dict[str, Any] = {}
        for p in signature.parameters.values():
            if p.kind not in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD):
                continue
            annotation = p.annotation
            if annotation is inspect.Parameter.empty or isinstance(annotation, str):
                annotation = type(p.default) if p.default not in (inspect.Parameter.empty, None) else None
            if annotation is not None and _checkable(annotation):
                out[p.name] = annotation
        return out

    def create(self, options: dict[str, Any], where: str = "") -> T:
        """Build the implementation; unknown or missing options name the key.

        Each value is checked against its declared type (:meth:`option_types`):
        the factory's own ``ValueError`` wins (its message is the most
        specific); a value of another type that the factory accepts, or that
        makes it fail with a ``TypeError``, is a :class:`ConfigError` naming
        the key and the type it must have.

        The object built is checked against the stage's protocol: one that
        lacks a method or attribute is a :class:`PluginError` naming the
        implementation, the plugin that registered it and what is missing."""
        known = self.options()
        prefix = f"{where}: " if where else ""
        for key in options:
            if key not in known:
                allowed = ", ".join(sorted(known)) or "none"
                raise ConfigError(
                    f"{prefix}unknown option {key!r} for {self.stage} plugin {self.name!r}; "
                    f"known options: {allowed}"
                )
        for key, default in known.items():
            if default is inspect.Parameter.empty and key not in options:
                raise ConfigError(f"{prefix}{self.stage} plugin {self.name!r} needs option {key!r}")
        declared = self.option_types()
        mismatch = next(
            (
                f"{prefix}option {key!r} of {self.stage} plugin {self.name!r} must be "
                f"{_describe(declared[key])}, got {value!r}"
                for key, value in options.items()
                if key in declared and not _is_instance(value, declared[key])
            ),
            None,
        )
        try:
            made = self.factory(**options)
        except ValueError as exc:  # the plugin's own check: its message is the most specific
            raise ConfigError(f"{prefix}{self.stage} plugin {self.name!r}: {exc}") from None
        except TypeError as exc:  # e.g. "'>' not supported ...": the declared type says more
            raise ConfigError(mismatch or f"{prefix}{self.stage} plugin {self.name!r}: {exc}") from None
        if mismatch is not None:  # accepted by the factory, but not of the declared type: refused
            close = getattr(made, "close", None)
            if callable(close):
                close()
            raise ConfigError(mismatch)
        who = f"{self.stage} plugin {self.name!r} (registered by {self.plugin}, {self.package} {self.version})"
        return check_implementation(made, self.stage, who)


#: Types an option value from TOML is checked against (others are left to the factory).
_PLAIN = (bool, int, float, str, list, tuple, dict)


def _alternatives(annotation: Any) -> tuple[Any, ...]:
    """The members of a union annotation (``int | None`` -> (int, NoneType)), else (annotation,)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return typing.get_args(annotation)
    return (annotation,)


def _checkable(annotation: Any) -> bool:
    """True when every alternative of ``annotation`` is a type this module checks."""
    for alt in _alternatives(annotation):
        origin = typing.get_origin(alt) or alt
        if origin is typing.Literal or alt is type(None) or origin in (Path, PurePath):
            continue
        if isinstance(origin, type) and (origin in _PLAIN or issubclass(origin, (collections.abc.Sequence, collections.abc.Mapping))):
            continue
        return False
    return True


def _is_instance(value: Any, annotation: Any) -> bool:
    """Whether a config value fits ``annotation`` (a TOML integer fits a float; a bool is no number)."""
    for alt in _alternatives(annotation):
        origin = typing.get_origin(alt) or alt
        if origin is typing.Literal:
            if value in typing.get_args(alt):
                return True
        elif alt is type(None):
            if value is None:
                return True
        elif origin is bool:
            if isinstance(value, bool):
                return True
        elif origin is float:
            if isinstance(value, numbers.Real) and not isinstance(value, bool):
                return True
        elif origin is int:
            if isinstance(value, numbers.Integral) and not isinstance(value, bool):
                return True
        elif origin in (Path, PurePath, str):  # a path given from Python fits a str option
            if isinstance(value, (str, PurePath)):
                return True
        elif isinstance(origin, type) and issubclass(origin, collections.abc.Mapping):
            if isinstance(value, collections.abc.Mapping):
                return True
        elif isinstance(origin, type) and issubclass(origin, collections.abc.Sequence):
            if isinstance(value, (list, tuple)):
                return True
        else:  # pragma: no cover - _checkable admits no other type
            return True
    return False


def _describe(annotation: Any) -> str:
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string", type(None): "none"}
    parts = []
    for alt in _alternatives(annotation):
        origin = typing.get_origin(alt) or alt
        if origin is typing.Literal:
            parts.append("one of " + ", ".join(repr(a) for a in typing.get_args(alt)))
        elif origin in (Path, PurePath):
            parts.append("a path (string)")
        elif origin in names:
            parts.append(names[origin])
        elif isinstance(origin, type) and issubclass(origin, collections.abc.Mapping):
            parts.append("a table")
        else:
            parts.append("a list")
    return " or ".join(dict.fromkeys(parts))


@functools.cache
def _packages_distributions() -> dict[str, list[str]]:
    # Scans every installed distribution's file list (~0.1 s): once per process.
    return metadata.packages_distributions()


@functools.cache
def _distribution_of(module_name: str) -> tuple[str, str]:
    """The (distribution, version) a plugin module ``module_name`` comes from.

    Cached per module name for the process: each ``metadata.version`` reads a
    dist-info folder (19 lookups, 12-14 ms a session under cProfile,
    issue 25), and what is installed does not change while the process runs (the
    module-to-distribution map above is read once per process already)."""
    top = module_name.split(".")[0]
    for dist_name in _packages_distributions().get(top, []):
        try:
            return dist_name, metadata.version(dist_name)
        except metadata.PackageNotFoundError:  # pragma: no cover
            continue
    if top == "crossfield":
        return "crossfield", crossfield_version()
    return top, "unknown"


def make_plugin_manager(
    *, entry_points: bool = False, builtins: bool = True, extra: Iterable[object] = ()
) -> pluggy.PluginManager:
    """A fresh plugin manager with the hook specs and the built-in plugins.

    entry_points: also load third-party plugins from the ``crossfield``
    entry-point group (the CLI does; tests do only when they test that).
    extra: further plugin objects (modules or instances) to register.
    """
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    if builtins:
        for module_name in BUILTIN_PLUGINS:
            pm.register(importlib.import_module(module_name), name=module_name)
    if entry_points:
        pm.load_setuptools_entrypoints(hookspecs.PROJECT)
    for plugin in extra:
        pm.register(plugin)
    return pm


def implementations(pm: pluggy.PluginManager, stage: str) -> dict[str, Implementation]:
    """All implementations of ``stage`` offered by the registered plugins."""
    if stage not in STAGES:
        raise PluginError(f"unknown stage {stage!r}; stages are {', '.join(STAGES)}")
    found: dict[str, Implementation] = {}
    hook = getattr(pm.hook, f"register_{stage}s")
    for impl in hook.get_hookimpls():
        plugin_name = pm.get_name(impl.plugin) or repr(impl.plugin)
        module = getattr(impl.plugin, "__name__", type(impl.plugin).__module__)
        package, version = _distribution_of(module)
        entry = _entry_point_dist(pm, impl.plugin)
        if entry is not None:
            package, version = entry

        def register(name: str, factory: Factory[Any], description: str = "") -> None:
            if not isinstance(name, str) or not name:
                raise PluginError(f"plugin {plugin_name} registered a {stage} with no name")
            if name in found:
                raise PluginError(
                    f"duplicate {stage} implementation {name!r}: registered by "
                    f"{found[name].plugin} and by {plugin_name}"
                )
            found[name] = Implementation(
                stage, name, factory, description or (inspect.getdoc(factory) or "").split("\n")[0],
                plugin_name, package, version,
            )

        impl.function(register=register)
    return found


def _entry_point_dist(pm: pluggy.PluginManager, plugin: object) -> tuple[str, str] | None:
    for loaded, dist in pm.list_plugin_distinfo():
        if loaded is plugin:
            return dist.metadata["name"], dist.version
    return None


def get_implementation(pm: pluggy.PluginManager, stage: str, name: str) -> Implementation:
    """The implementation ``name`` of ``stage``, or an error listing the choices."""
    available = implementations(pm, stage)
    if name not in available:
        choices = ", ".join(sorted(available)) or "none"
        raise PluginError(
            f"no {stage} implementation named {name!r}; available: {choices}. "
            f"If it comes from a third-party package, that package may not be installed."
        )
    return available[name]
