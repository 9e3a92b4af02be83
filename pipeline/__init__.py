"""crossfield: local stereo vision registered to out-of-view CMM references.

The Python API (docs/python-api.md)::

    import crossfield

    summary = crossfield.run(scenario="table3", frames=3)
    print(summary)

:func:`run` and :func:`run_config` (:mod:`crossfield.api`), :func:`open_recording`
(:mod:`crossfield.recording.reader`) and the summary types are imported on
first use, so that ``import crossfield.<module>`` stays light.
"""

from __future__ import annotations

import importlib
from importlib import metadata
from typing import TYPE_CHECKING, Any

try:
    __version__: str = metadata.version("crossfield")
except metadata.PackageNotFoundError:  # run from a source tree that is not installed
    __version__ = "0+unknown"

__all__ = ["__version__", "run", "run_config", "open_recording", "Recording", "SessionSummary"]

if TYPE_CHECKING:
    from crossfield.api import Recording, SessionSummary, open_recording, run, run_config


def __getattr__(name: str) -> Any:
    """The API names of :mod:`crossfield.api`, imported when first asked for (PEP 562)."""
    if name in __all__:
        value = getattr(importlib.import_module("crossfield.api"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'crossfield' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
