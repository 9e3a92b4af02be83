"""A third-party plugin through the `crossfield` entry-point group: the example
package docs/examples/crossfield-squared-centroid is installed into a temporary
folder (not into .venv), seen by `crossfield plugins`, used to replay a recorded
session, and the replay audited, each in a subprocess with that folder on PYTHONPATH."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from session_tools import record_session

from crossfield.config import DEFAULT_PLUGINS
from crossfield.errors import PluginError
from crossfield.recording.reader import open_recording
from crossfield.chain.registry import make_plugin_manager
from crossfield.replay import replay_session

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "docs" / "examples" / "crossfield-squared-centroid"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The example installed with pip into its own folder (a copy is built, so the
    source tree gets no build/ or egg-info)."""
    root = tmp_path_factory.mktemp("entry-point")
    source = root / "src"
    shutil.copytree(EXAMPLE, source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    target = root / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--target",
            str(target),
            str(source),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    assert (target / "crossfield_squared_centroid-0.1.0.dist-info" / "entry_points.txt").exists()
    return target


def crossfield(site: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(REPO)]))
    return subprocess.run(
        [sys.executable, "-m", "crossfield.cli", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("entry-point-session")
    # Two pairs: what the replay and its audit (both re-run the session in a
    # subprocess) are checked on is the plugin's use.
    record_session(out, "orig", frames=2)
    return out / "orig" / "session.mcap"


def test_plugins_lists_the_entry_point_plugin(site):
    proc = crossfield(site, "plugins", "--json")
    assert proc.returncode == 0, proc.stderr
    centroid = {e["name"]: e for e in json.loads(proc.stdout)["centroid"]}
    assert set(centroid) >= {"weighted", "ellipse", "squared"}
    squared = centroid["squared"]
    assert (squared["package"], squared["version"]) == ("crossfield-squared-centroid", "0.1.0")
    assert squared["plugin"] and squared["options"] == {
        "threshold_sigma": 8.0,
        "min_area_px": 30,
        "dilate_px": 2,
        "gain_e_per_dn": 2.86,
    }
    text = crossfield(site, "plugins").stdout
    assert "squared" in text and "crossfield-squared-centroid 0.1.0" in text


def test_not_loaded_without_entry_points(recorded, tmp_path):
    """Tests' plugin managers do not load entry points: the name is unknown there,
    and the error says the package may not be installed."""
    with pytest.raises(PluginError, match="available: ellipse, modelfit, weighted.*may not be installed"):
        replay_session(recorded, make_plugin_manager(), plugins={"centroid": "squared"}, output_dir=tmp_path)


def test_replay_and_audit_with_the_entry_point_plugin(site, recorded, tmp_path):
    out = tmp_path / "squared.mcap"
    proc = crossfield(
        site, "replay", str(recorded), "--centroid", "squared", "-o", str(out), "-q", "--no-rerun"
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"centroid: {DEFAULT_PLUGINS['centroid']} -> squared" in proc.stdout and "Result: PASS" in proc.stdout
    with open_recording(out) as rec:
        plugin = rec.metadata_doc("crossfield.plugins")["centroid"]
        methods = {m.decoded["method"] for m in rec.messages("/centroids/upper")}
        report = next(m.decoded for m in rec.messages("/report"))
        parent = rec.metadata_doc("crossfield.session")["parent"]
    assert (plugin["name"], plugin["package"], plugin["version"]) == (
        "squared",
        "crossfield-squared-centroid",
        "0.1.0",
    )
    assert methods == {"squared"}
    assert parent["changed"]["plugins"] == {"centroid": {"from": DEFAULT_PLUGINS["centroid"], "to": "squared"}}
    assert all(abs(c["error_mm"]) < 0.05 for c in report["characteristics"])
    # the audit (with the plugin installed) reproduces the replay's results exactly
    audit = crossfield(site, "audit", str(out), "--json")
    assert audit.returncode == 0, audit.stdout[-2000:] + audit.stderr
    doc = json.loads(audit.stdout)
    assert doc["passed"] and doc["reproduction"]["plugins"]["centroid"] == "squared"
    assert doc["provenance"]["installed_plugins"]["centroid"] == {
        "package": "crossfield-squared-centroid",
        "version": "0.1.0",
    }


def test_the_example_uses_only_the_public_api_and_the_core_blob_detector():
    """The example imports crossfield through the plugin facade only
    (``crossfield.plugin_api``) and leaves blob detection to the core's detector
    (no OpenCV of its own)."""
    import ast
    import importlib

    source = (EXAMPLE / "crossfield_squared_centroid" / "__init__.py").read_text(encoding="utf-8")
    imported: dict[str, set[str]] = {}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            imported.setdefault(node.module, set()).update(a.name for a in node.names)
        elif isinstance(node, ast.Import):
            imported.update({a.name: set() for a in node.names})
    assert "cv2" not in imported
    assert {m for m in imported if m.startswith("crossfield")} == {"crossfield.plugin_api"}
    assert "BlobDetector" in imported["crossfield.plugin_api"]
    assert imported["crossfield.plugin_api"] <= set(importlib.import_module("crossfield.plugin_api").__all__)
