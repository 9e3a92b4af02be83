"""The distribution: one import name (`crossfield`), its data files, license and
typing marker in the wheel, and the Python API working from a folder that has
its own `pipeline/` and `plugins/` packages."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from crossfield.simulator.scenarios import TABLE3_ACTUAL_MM

REPO = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]


def _package_folder(package: str) -> Path:
    """The folder of ``package`` through pyproject's package-dir (longest prefix)."""
    mapping = SETUPTOOLS["package-dir"]
    parts = package.split(".")
    for k in range(len(parts), 0, -1):
        prefix = ".".join(parts[:k])
        if prefix in mapping:
            return REPO / mapping[prefix] / Path(*parts[k:])
    raise AssertionError(f"{package}: not mapped by package-dir")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[zipfile.ZipFile, str]:
    """crossfield's wheel, built with pip from a copy of the source (the tree gets no build/)."""
    root = tmp_path_factory.mktemp("wheel")
    source = root / "src"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, source / name)
    for folder in ("pipeline", "plugins"):
        shutil.copytree(REPO / folder, source / folder, ignore=shutil.ignore_patterns("__pycache__"))
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
         "-w", str(root / "dist"), str(source)],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    output = proc.stdout + proc.stderr
    # No setuptools warning while building (pip shows the backend's as BuildBackendWarning)
    assert not re.search(r"BuildBackendWarning|Setuptools(Deprecation)?Warning", output), output
    (path,) = (root / "dist").glob("crossfield-*.whl")
    return zipfile.ZipFile(path), path.name


def test_the_only_top_level_name_is_crossfield(wheel):
    archive, name = wheel
    version = name.split("-")[1]
    dist_info = f"crossfield-{version}.dist-info"
    assert {n.split("/")[0] for n in archive.namelist()} == {"crossfield", dist_info}
    assert archive.read(f"{dist_info}/top_level.txt").decode().split() == ["crossfield"]
    modules = {n for n in archive.namelist() if n.endswith(".py")}
    assert "crossfield/plugins/register_svd.py" in modules and "crossfield/api.py" in modules
    assert not any(n.startswith(("pipeline/", "plugins/")) for n in archive.namelist())


def test_every_source_file_is_in_the_wheel(wheel):
    """Every module and data file of every listed package, and no package folder left unlisted."""
    archive, _ = wheel
    names = set(archive.namelist())
    listed = set(SETUPTOOLS["packages"])
    for package in listed:
        folder = _package_folder(package)
        assert folder.is_dir(), f"packages lists {package}, but {folder} does not exist"
        for path in folder.iterdir():
            if path.is_file() and path.suffix == ".py":
                assert f"{package.replace('.', '/')}/{path.name}" in names, path
    for top, name in (("pipeline", "crossfield"), ("plugins", "crossfield.plugins")):
        for module in (REPO / top).rglob("*.py"):
            package = ".".join([name, *module.parent.relative_to(REPO / top).parts])
            assert package in listed, f"{module.parent} holds modules; {package} is not in packages"


def test_package_data_globs_match_and_ship(wheel):
    """No stale glob: every package-data pattern matches a file, and each file is in the wheel."""
    archive, _ = wheel
    names = set(archive.namelist())
    for package, patterns in SETUPTOOLS["package-data"].items():
        folder = _package_folder(package)
        for pattern in patterns:
            matched = sorted(folder.glob(pattern))
            assert matched, f"package-data {package}: {pattern!r} matches nothing in {folder}"
            for path in matched:
                assert f"{package.replace('.', '/')}/{path.relative_to(folder).as_posix()}" in names, path
    assert "crossfield/py.typed" in names
    assert any(n.startswith("crossfield/recording/schemas/") and n.endswith(".json") for n in names)


def test_license_metadata_and_console_script(wheel):
    archive, name = wheel
    dist_info = f"crossfield-{name.split('-')[1]}.dist-info"
    meta = archive.read(f"{dist_info}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in meta.splitlines()
    assert "License-File: LICENSE" in meta.splitlines()
    license_text = archive.read(f"{dist_info}/licenses/LICENSE").decode()
    assert license_text == (REPO / "LICENSE").read_text()
    assert "Apache License" in license_text and "Version 2.0, January 2004" in license_text
    assert "END OF TERMS AND CONDITIONS" in license_text  # the full text, not a notice
    entry_points = archive.read(f"{dist_info}/entry_points.txt").decode()
    assert re.search(r"^crossfield = crossfield\.cli:main$", entry_points, re.M)


def _python_example(doc: Path) -> str:
    """The first ```python block of a docs page (the worked example)."""
    match = re.search(r"```python\n(.*?)```", doc.read_text(), re.S)
    assert match, f"{doc}: no python example"
    return match.group(1)


def test_worked_example_runs_beside_folders_named_pipeline_and_plugins(tmp_path):
    """docs/python-api.md's example, run as a user would, in a folder that has its
    own ``pipeline`` and ``plugins`` packages first on sys.path."""
    for name in ("pipeline", "plugins"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("")
    script = tmp_path / "notebook.py"
    script.write_text(
        _python_example(REPO / "docs" / "python-api.md")
        + "\nimport json, pipeline, plugins\n"
        + "print(json.dumps({'pipeline': pipeline.__file__, 'plugins': plugins.__file__, 'chars': "
        + "[[c.name, c.measured_mm, c.actual_mm] for c in summary.characteristics]}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, script.name],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # The folder's own packages are what `import pipeline` / `import plugins` give there...
    assert Path(result["pipeline"]).parent == tmp_path / "pipeline"
    assert Path(result["plugins"]).parent == tmp_path / "plugins"
    # ... and crossfield ran beside them, to the simulator's truth.
    chars = result["chars"]
    assert [name for name, _, _ in chars] == [f"L{k:02d}" for k in range(1, 11)]
    for (_, measured, actual), truth in zip(chars, TABLE3_ACTUAL_MM):
        assert actual == pytest.approx(truth, abs=1e-9)
        assert abs(measured - truth) < 0.03
    assert (tmp_path / "recordings").is_dir()
