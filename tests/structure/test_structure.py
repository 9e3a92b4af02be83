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
    graph = {name: module_level_imports(name) for name in MODULES}
    # packages import their __init__: drop the edge from a module to its own package
    graph = {n: {m for m in deps if not n.startswith(m + ".")} for n, deps in graph.items()}
    assert cycle(graph) is None
    assert "crossfield.chain.registry" not in graph["crossfield.config"]  # STAGES comes from stages.py
    assert graph["crossfield.stages"] <= {"crossfield.errors", "crossfield.plan", "crossfield.types"}


def test_the_circle_finder_finds_one():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


# ---- the session's facts and summary are each made in one place --------------------

#: class -> the modules that construct it. SessionInfo: the runner (every session
#: run) and the viewer, which reads a recorded session's facts back for display.
CONSTRUCTED_IN = {
    "SessionSummary": {"crossfield.session"},
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
                elif called == "cls" and name == "crossfield.session":
                    found["SessionSummary"].add(name)
    assert found == CONSTRUCTED_IN
    runner = ast.unparse(tree("crossfield.chain.runner"))
    assert runner.count("SessionInfo(") == 1 and "SessionSummary.of_session(" in runner


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
    assert hook_names() == specs and len(specs) == 7 + 12


@pytest.mark.parametrize("name", hook_names())
def test_every_hook_is_documented_with_its_signature(name):
    text = PLUGINS_DOC.read_text(encoding="utf-8")
    signature = spec_signature(getattr(hookspecs, name))
    assert f"`{signature}`" in text, f"docs/plugins.md does not document {signature}"


# ---- the public API the plugins use ------------------------------------------------


def plugin_imports() -> dict[str, set[str]]:
    """Core module -> names the built-in plugins import from it."""
    used: dict[str, set[str]] = {}
    for name in PLUGIN_MODULES:
        for node in ast.walk(tree(name)):
            if isinstance(node, ast.ImportFrom):
                module = absolute(name, node)
                if module.startswith("crossfield.") and not module.startswith("crossfield.plugins"):
                    used.setdefault(module, set()).update(a.name for a in node.names)
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("crossfield."):
                        used.setdefault(a.name, set())
        # ``from crossfield.report import document as doc``: the names used are ``doc.NAME``
        aliases = {}
        for node in ast.walk(tree(name)):
            if isinstance(node, ast.ImportFrom):
                module = absolute(name, node)
                for a in node.names:
                    if f"{module}.{a.name}" in MODULES:
                        aliases[a.asname or a.name] = f"{module}.{a.name}"
                        used[module].discard(a.name)
                        used.setdefault(f"{module}.{a.name}", set())
        for node in ast.walk(tree(name)):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                used[aliases[node.value.id]].add(node.attr)
    return {m: names for m, names in used.items() if m in MODULES and (names or MODULES[m].name != "__init__.py")}


PUBLIC = plugin_imports()


def test_the_plugins_use_the_core():
    assert {"crossfield.hookspecs", "crossfield.types", "crossfield.imaging.blobs"} <= set(PUBLIC)


@pytest.mark.parametrize("module_name", sorted(PUBLIC))
def test_core_modules_the_plugins_import_declare_their_public_api(module_name):
    module = importlib.import_module(module_name)
    declared = getattr(module, "__all__", None)
    assert declared is not None, f"{module_name} has no __all__"
    assert sorted(set(declared)) == sorted(declared), "duplicates in __all__"
    assert all(hasattr(module, n) for n in declared), [n for n in declared if not hasattr(module, n)]
    assert PUBLIC[module_name] <= set(declared), sorted(PUBLIC[module_name] - set(declared))


def test_docs_list_the_public_api():
    text = PLUGINS_DOC.read_text(encoding="utf-8")
    section = text.split("## The public API", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"^\| `(crossfield(?:\.\w+)+)` \|", section, flags=re.MULTILINE))
    assert listed == set(PUBLIC)
    for module_name in PUBLIC:
        row = next(line for line in section.splitlines() if line.startswith(f"| `{module_name}` |"))
        for name in importlib.import_module(module_name).__all__:
            assert f"`{name}`" in row, (module_name, name)
