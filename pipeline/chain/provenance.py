"""Provenance: what a session's results depend on, besides its inputs.

One module for the three facts recorded with every session
(``docs/recording.md``): the crossfield version, the versions of the
packages the numbers depend on (the ``crossfield.packages`` metadata
record), and the machine the session ran on (``crossfield.machine``). The
runner, the recorder, the registry and the audit all ask here, so a
recording and its audit name versions the same way.
"""

from __future__ import annotations

import functools
import os
import platform
import socket
import sys
from collections.abc import Mapping
from importlib import metadata
from typing import Any

__all__ = ["RECORDED_PACKAGES", "UNKNOWN_VERSION", "crossfield_version", "machine_info", "package_versions"]

#: Distributions whose versions are recorded with every session.
RECORDED_PACKAGES: tuple[str, ...] = (
    "crossfield",
    "numpy",
    "scipy",
    "opencv-python-headless",
    "pluggy",
    "mcap",
    "mcap-protobuf-support",
    "foxglove-schemas-protobuf",
    "protobuf",
    "rerun-sdk",
    "pyserial",
    "cryptography",
    "matplotlib",
    "jinja2",
    "dask",
    "distributed",
    "numba",  # compiles the modelfit centroid's fit and the blob detector's per-pixel sums
)

#: The version of a crossfield that runs from a source tree without being installed.
UNKNOWN_VERSION = "0+unknown"


def package_versions() -> dict[str, str]:
    """Python's version and each of :data:`RECORDED_PACKAGES`' installed version
    ("not installed" when absent): the ``crossfield.packages`` record.

    The versions are looked up once per process (:func:`_installed_versions`); each
    call returns a new dict, so a caller that changes its copy changes no other's."""
    return dict(_installed_versions())


@functools.cache
def _installed_versions() -> tuple[tuple[str, str], ...]:
    # One importlib.metadata lookup per package scans sys.path's dist-info folders:
    # 19-24 ms a session under cProfile, 7.9 ms without (issue 25). Cached for the process: the
    # installed versions do not change while it runs (an upgrade takes effect in a
    # new process, whose imported modules are the new ones).
    versions = [("python", sys.version.split()[0])]
    for name in RECORDED_PACKAGES:
        try:
            versions.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:
            versions.append((name, "not installed"))
    return tuple(versions)


def crossfield_version(packages: Mapping[str, str] | None = None) -> str:
    """The crossfield version: ``packages["crossfield"]`` when given (a session's
    recorded packages), else the installed distribution's, else
    :data:`UNKNOWN_VERSION` (a source tree)."""
    if packages and packages.get("crossfield"):
        return str(packages["crossfield"])
    try:
        return metadata.version("crossfield")
    except metadata.PackageNotFoundError:
        return UNKNOWN_VERSION


def machine_info() -> dict[str, Any]:
    """The machine a session runs on (the ``crossfield.machine`` metadata record)."""
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "hostname": socket.gethostname(),
        "platform": platform.platform(),
        "system": platform.system(),
        "release": platform.release(),
        "machine": platform.machine(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
    }
