"""Work that depends on the process, not on the session, is done once per process (issue 25).

A station session looked up the recorded package versions (``crossfield.packages``,
17 ``importlib.metadata`` lookups), the distribution of every built-in plugin
(``registry.implementations``, 19 lookups) and fitted its reference cylinder twice (the
measurement and the session's CMM evidence), in every session of a process. Now the
second session of a process does none of that, and its results are the same.
"""

from __future__ import annotations

import types
from importlib import metadata
from unittest import mock

from crossfield import geometry
from crossfield.chain import provenance, registry
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.chain.runner import run_session
from crossfield.config import parse_config
from crossfield.stages import STAGES


def counting_metadata() -> types.SimpleNamespace:
    """An ``importlib.metadata`` stand-in whose ``version`` counts its calls."""
    return types.SimpleNamespace(
        version=mock.Mock(wraps=metadata.version),
        PackageNotFoundError=metadata.PackageNotFoundError,
        packages_distributions=metadata.packages_distributions,
    )


def station_session(tmp_path, name: str):
    data = {
        "session": {"output_dir": str(tmp_path), "name": name, "rerun": False, "record": False},
        "acquire": {"plugin": "simulator", "scenario": "station", "frames": 2, "seed": 5},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
        "report": {"plugin": "json"},
    }
    return run_session(parse_config(data, "<test>"), make_plugin_manager())


def test_package_versions_are_looked_up_once_per_process():
    first = provenance.package_versions()
    shim = counting_metadata()
    with mock.patch.object(provenance, "metadata", shim):
        second = provenance.package_versions()
        third = provenance.package_versions()
    assert shim.version.call_count == 0  # before: 17 lookups per call
    assert first == second == third
    assert second["numpy"] == metadata.version("numpy")
    second["numpy"] = "changed"  # each caller has its own dict
    assert provenance.package_versions()["numpy"] == metadata.version("numpy")


def test_plugin_distributions_are_looked_up_once_per_process():
    pm = make_plugin_manager()
    first = {stage: implementations(pm, stage) for stage in STAGES}
    shim = counting_metadata()
    with mock.patch.object(registry, "metadata", shim):
        again = {stage: implementations(make_plugin_manager(), stage) for stage in STAGES}
    assert shim.version.call_count == 0  # before: one lookup per built-in plugin (19)
    assert {s: {n: (i.package, i.version) for n, i in impls.items()} for s, impls in again.items()} == {
        s: {n: (i.package, i.version) for n, i in impls.items()} for s, impls in first.items()
    }
    assert first["measure"]["plan"].package == "crossfield"
    assert first["measure"]["plan"].version == metadata.version("crossfield")


def test_a_warm_process_repeats_no_per_process_work(tmp_path):
    cold = station_session(tmp_path, "cold")
    versions, distributions = counting_metadata(), counting_metadata()
    with (
        mock.patch.object(provenance, "metadata", versions),
        mock.patch.object(registry, "metadata", distributions),
        mock.patch.object(geometry, "fit_cylinder_axis", wraps=geometry.fit_cylinder_axis) as cylinder,
        mock.patch.object(geometry, "fit_line", wraps=geometry.fit_line) as line,
    ):
        warm = station_session(tmp_path, "warm")
    # before: 17 version lookups, 19 distribution lookups and 2 cylinder fits per session
    assert versions.version.call_count == 0
    assert distributions.version.call_count == 0
    assert cylinder.call_count == 0 and line.call_count == 0
    assert warm.frames_processed == cold.frames_processed == 2
    for a, b in zip(cold.characteristics, warm.characteristics, strict=True):
        assert (a.name, a.measured_mm, a.uncertainty_mm) == (b.name, b.measured_mm, b.uncertainty_mm)
