"""The structure of the package, checked from its source and its plugin manager:

* no module imports another module's private name (``from X import _name``);
* the core's module-level imports have no circle (config, stages, registry,
  hookspecs and session in particular);
* every module in plugins/ registers at least one implementation;
* every built-in implementation satisfies its stage's protocol, and a plugin
  whose object does not is refused when it is created, naming the plugin;
* every hook in the plugin manager is documented in docs/plugins.md with its
  signature as written in pipeline/hookspecs.py (the datasette way);
* every core module the built-in plugins import declares ``__all__``, names
  only what it defines, and the plugins import only those names; the list in
  docs/plugins.md is that set of modules.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from pathlib import Path

import pytest

from crossfield import hookspecs
from crossfield.errors import PluginError
from crossfield.hookspecs import hookimpl
from crossfield.chain.registry import BUILTIN_PLUGINS, get_implementation, implementations, make_plugin_manager
from crossfield.stages import STAGE_PROTOCOLS, STAGES, check_implementation, protocol_members

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"pipeline": "crossfield", "plugins": "crossfield.plugins"}
PLUGINS_DOC = ROOT / "docs" / "plugins.md"


def modules() -> dict[str, Path]:
    """crossfield module name -> source file, for pipeline/ and plugins/."""
    found = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package, *parts])] = path
    return found


MODULES = modules()


def tree(name: str) -> ast.Module:
    return ast.parse(MODULES[name].read_text(encoding="utf-8"), str(MODULES[name]))


def absolute(name: str, node: ast.ImportFrom) -> str:
    """The module an ``ImportFrom`` in module ``name`` names (relative ones resolved)."""
    if not node.level:
        return node.module or ""
    package = name.split(".") if MODULES[name].name == "__init__.py" else name.split(".")[:-1]
    base = package[: len(package) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def test_the_scan_sees_the_package():
    assert {"crossfield.chain.runner", "crossfield.stages", "crossfield.recording.recorder"} <= set(MODULES)
    assert "crossfield.plugins.register_svd" in MODULES and len(MODULES) > 40


# ---- no private names across modules --------------------------------------------


def private_imports(name: str) -> list[str]:
    out = []
    for node in ast.walk(tree(name)):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            for alias in node.names:
                dunder = alias.name.startswith("__") and alias.name.endswith("__")  # __version__: public
                if alias.name.startswith("_") and not dunder:
                    out.append(f"{MODULES[name].relative_to(ROOT)}:{node.lineno}: from {absolute(name, node)} import {alias.name}")
    return out


def test_no_module_imports_a_private_name_of_another():
    found = [line for name in MODULES for line in private_imports(name)]
    assert found == []


def test_the_private_import_scan_finds_one(tmp_path, monkeypatch):
    """The scan is not blind: a module with such an import is reported."""
    bad = tmp_path / "bad.py"
    bad.write_text("import os\nfrom crossfield.chain.runner import run_session, _registered\n")
    monkeypatch.setitem(MODULES, "crossfield.bad", bad)
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    assert private_imports("crossfield.bad") == ["bad.py:2: from crossfield.chain.runner import _registered"]


# ---- no import circle ------------------------------------------------------------------


def module_level_imports(name: str) -> set[str]:
    """The crossfield modules ``name`` imports when it is imported (top-level
    statements, ``try`` blocks included, ``if TYPE_CHECKING:`` blocks and
    function bodies not)."""
    out: set[str] = set()

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, ast.If):
                test = ast.unparse(node.test)
                if "TYPE_CHECKING" not in test:
                    visit(node.body)
                    visit(node.orelse)
            elif isinstance(node, ast.Try):
                for block in (node.body, node.orelse, node.finalbody, *[h.body for h in node.handlers]):
                    visit(block)
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                module = absolute(name, node)
                out.add(module)
                out.update(f"{module}.{a.name}" for a in node.names)  # ``from pkg import module``

    visit(tree(name).body)
    return {m for m in out if m in MODULES and m != name}


def every_import(name: str) -> set[str]:
    """The crossfield modules ``name`` imports anywhere: module level, ``if
    TYPE_CHECKING:`` blocks and function bodies alike (a circle hidden in a function or
    behind TYPE_CHECKING is still a circle of the design)."""
    out: set[str] = set()
    for node in ast.walk(tree(name)):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = absolute(name, node)
            out.add(module)
            out.update(f"{module}.{a.name}" for a in node.names)
    return {m for m in out if m in MODULES and m != name}


def import_graph(imports) -> dict[str, set[str]]:
    """module -> the modules it imports (by ``imports(name)``), without the edge from a
    module to its own package (a package's ``__init__`` is imported with it)."""
    graph = {name: imports(name) for name in MODULES}
    return {n: {m for m in deps if not n.startswith(m + ".")} for n, deps in graph.items()}


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (module -> imported modules), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def walk(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for other in sorted(graph.get(node, ())):
            if state.get(other) == 1:
                return stack[stack.index(other) :] + [other]
            if other not in state:
                found = walk(other)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = walk(node)
            if found:
                return found
    return None


def test_the_core_imports_have_no_circle():
    graph = import_graph(module_level_imports)
    assert cycle(graph) is None
    assert "crossfield.chain.registry" not in graph["crossfield.config"]  # STAGES comes from stages.py
    assert graph["crossfield.stages"] <= {"crossfield.errors", "crossfield.plan", "crossfield.types"}


def test_no_circle_hides_in_a_function_or_behind_type_checking():
    assert cycle(import_graph(every_import)) is None


def test_the_full_scan_sees_function_and_type_checking_imports(tmp_path, monkeypatch):
    hidden = tmp_path / "hidden.py"
    hidden.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from crossfield.session import SessionSummary\n"
        "def f():\n    from crossfield.chain.runner import run_session\n"
    )
    monkeypatch.setitem(MODULES, "crossfield.hidden", hidden)
    assert {"crossfield.session", "crossfield.chain.runner"} <= every_import("crossfield.hidden")
    assert not module_level_imports("crossfield.hidden") & {"crossfield.session", "crossfield.chain.runner"}


def test_the_circle_finder_finds_one():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


# ---- the session's facts and summary are each made in one place --------------------

#: class -> the modules that construct it. SessionSummary: the chain's aggregate module
#: (session_summary; session.py holds data only). SessionInfo: the runner (every session
#: run) and the viewer, which reads a recorded session's facts back for display.
CONSTRUCTED_IN = {
    "SessionSummary": {"crossfield.chain.aggregate"},
    "SessionInfo": {"crossfield.chain.runner", "crossfield.viz.rerun_mcap"},
}


def test_session_info_and_summary_are_each_built_in_one_place():
    found: dict[str, set[str]] = {k: set() for k in CONSTRUCTED_IN}
    for name in MODULES:
        for node in ast.walk(tree(name)):
            if isinstance(node, ast.Call):
                called = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
                if called in found:
                    found[called].add(name)
    assert found == CONSTRUCTED_IN
    runner = ast.unparse(tree("crossfield.chain.runner"))
    assert runner.count("SessionInfo(") == 1 and "session_summary(" in runner


# ---- plugins/ holds implementations only ---------------------------------------------


PLUGIN_MODULES = sorted(n for n in MODULES if n.startswith("crossfield.plugins.") and not n.endswith("__init__"))


def registered_by(module_name: str) -> dict[str, list[str]]:
    pm = make_plugin_manager(builtins=False, extra=[importlib.import_module(module_name)])
    return {stage: sorted(implementations(pm, stage)) for stage in STAGES if implementations(pm, stage)}


def test_every_plugins_module_is_a_builtin_plugin():
    assert PLUGIN_MODULES and sorted(BUILTIN_PLUGINS) == PLUGIN_MODULES


@pytest.mark.parametrize("module_name", PLUGIN_MODULES)
def test_every_plugins_module_registers_an_implementation(module_name):
    offered = registered_by(module_name)
    assert offered, f"{module_name} registers nothing: library code belongs in the core"
    # and it is named after what it registers: <stage>_<name>.py
    stage = module_name.rsplit(".", 1)[1].split("_", 1)[0]
    assert stage in offered


# ---- implementations satisfy their protocol -----------------------------------------


def instance_attributes(klass: type) -> set[str]:
    """Names a class defines on itself or assigns as ``self.NAME`` in its methods."""
    names = {n for k in klass.__mro__ for n in vars(k)}
    try:
        source = ast.parse(inspect.getsource(klass).lstrip())
    except (OSError, TypeError, SyntaxError):  # pragma: no cover
        return names
    for node in ast.walk(source):
        is_self = isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self"
        if is_self and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
    return names


#: Options that let a factory with required options be built without a device.
CREATE_OPTIONS = {
    ("reference", "romer-serial"): {"port": "/dev/null-not-opened"},
    ("reference", "csv"): {"path": "points.csv"},
    ("reference", "spatialanalyzer"): {"path": "points.txt"},
    ("reference", "pcdmis-xyz"): {"path": "points.xyz"},
}


def every_implementation():
    pm = make_plugin_manager()
    return [(stage, name, impl) for stage in STAGES for name, impl in sorted(implementations(pm, stage).items())]


@pytest.mark.parametrize("stage, name, impl", every_implementation(), ids=lambda v: v if isinstance(v, str) else "")
def test_every_builtin_implementation_satisfies_its_protocol(stage, name, impl):
    protocol = STAGE_PROTOCOLS[stage]
    methods, attributes = protocol_members(protocol)
    required = [k for k, v in impl.options().items() if v is inspect.Parameter.empty]
    if not required or (stage, name) in CREATE_OPTIONS:
        made = impl.create(dict(CREATE_OPTIONS.get((stage, name), {})))
        assert isinstance(made, protocol)
        assert check_implementation(made, stage, name) is made
        return
    # A device source (cameras, a folder of images): checked on its class.
    klass = impl.factory
    assert inspect.isclass(klass)
    for method, spec in methods.items():
        assert callable(getattr(klass, method, None)), f"{klass.__name__} lacks {method}()"
        have = list(inspect.signature(getattr(klass, method)).parameters)
        want = list(inspect.signature(spec).parameters)
        assert have[: len(want)] == want, (klass.__name__, method, have, want)
    assert set(attributes) <= instance_attributes(klass), klass.__name__


class Incomplete:
    """A centroid 'implementation' without extract()."""

    def find(self, image):  # pragma: no cover
        return []


class WrongArity:
    def extract(self, image):  # pragma: no cover - the protocol's takes (image, camera, sequence)
        return []


class BadPlugin:
    @hookimpl
    def register_centroids(self, register):
        register("incomplete", Incomplete, "lacks extract()")
        register("wrong-arity", WrongArity, "extract(image) only")


@pytest.mark.parametrize(
    "name, missing",
    [("incomplete", r"no method extract\(\)"), ("wrong-arity", r"extract\(image, camera, sequence\) cannot be called")],
)
def test_an_implementation_that_breaks_its_protocol_is_refused_naming_the_plugin(name, missing):
    pm = make_plugin_manager(extra=[BadPlugin()])
    impl = get_implementation(pm, "centroid", name)
    with pytest.raises(PluginError, match=rf"centroid plugin '{name}' \(registered by .*\).*CentroidExtractor.*{missing}"):
        impl.create({})


# ---- every hook is documented ----------------------------------------------------------


def spec_signature(function) -> str:
    """``name(param: Type, ...) -> None`` exactly as annotated in hookspecs.py."""
    annotations = dict(function.__annotations__)
    returns = annotations.pop("return", "None")
    params = ", ".join(f"{p}: {annotations[p]}" for p in inspect.signature(function).parameters)
    return f"{function.__name__}({params}) -> {returns}"


def hook_names() -> list[str]:
    pm = make_plugin_manager()
    return sorted(name for name in vars(pm.hook) if not name.startswith("_"))


def test_the_plugin_manager_has_every_hookspec():
    specs = sorted(n for n, f in vars(hookspecs).items() if callable(f) and hasattr(f, "crossfield_spec"))
    assert hook_names() == specs and len(specs) == 7 + 13


@pytest.mark.parametrize("name", hook_names())
def test_every_hook_is_documented_with_its_signature(name):
    text = PLUGINS_DOC.read_text(encoding="utf-8")
    signature = spec_signature(getattr(hookspecs, name))
    assert f"`{signature}`" in text, f"docs/plugins.md does not document {signature}"


# ---- the public API the plugins use: one facade ------------------------------------


def plugin_imports() -> dict[str, set[str]]:
    """Core module -> names the built-in plugins import from it (every import, function level too)."""
    used: dict[str, set[str]] = {}
    for name in PLUGIN_MODULES:
        for node in ast.walk(tree(name)):
            if isinstance(node, ast.ImportFrom):
                module = absolute(name, node)
                if module.startswith("crossfield") and not module.startswith("crossfield.plugins"):
                    used.setdefault(module, set()).update(a.name for a in node.names)
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("crossfield"):
                        used.setdefault(a.name, set())
    return used


PUBLIC = plugin_imports()


def test_the_plugins_import_the_core_through_the_facade_only():
    assert set(PUBLIC) == {"crossfield.plugin_api"}
    import crossfield.plugin_api as api

    assert PUBLIC["crossfield.plugin_api"] <= set(api.__all__)


def test_the_facade_names_only_public_names_of_their_home_modules():
    """Every name of crossfield.plugin_api is re-exported from the module it lives in,
    whose own ``__all__`` declares it; the facade defines nothing itself."""
    import crossfield.plugin_api as api

    declared = api.__all__
    assert sorted(set(declared)) == sorted(declared) == declared, "__all__ sorted, no duplicates"
    for name in declared:
        value = getattr(api, name)
        home = FACADE_HOMES[name]
        module = importlib.import_module(home)
        assert getattr(module, name) is value and name in module.__all__, (name, home)


def facade_homes() -> dict[str, str]:
    """facade name -> the module its ``from X import`` in plugin_api.py names."""
    out = {}
    for node in tree("crossfield.plugin_api").body:
        if isinstance(node, ast.ImportFrom):
            for a in node.names:
                out[a.asname or a.name] = node.module
    return out


FACADE_HOMES = facade_homes()


def test_docs_list_the_public_api():
    """docs/plugins.md's table lists every facade name in the row of its home module."""
    text = PLUGINS_DOC.read_text(encoding="utf-8")
    section = text.split("## The public API", 1)[1].split("\n## ", 1)[0]
    rows = {
        m.group(1): m.group(0)
        for m in re.finditer(r"^\| `(crossfield(?:\.\w+)+)` \|.*$", section, flags=re.MULTILINE)
    }
    assert set(rows) == set(FACADE_HOMES.values())
    for name, home in FACADE_HOMES.items():
        assert f"`{name}`" in rows[home], (home, name)
