"""Plain JSON-able data from numbers, arrays and config values.

JSON has no NaN or infinity: non-finite floats become ``null``. Floats are
Python floats, written by :mod:`json` with ``repr`` precision, so a number
read back is the same float (auditors compare them).
"""

from __future__ import annotations

import datetime as _dt
import math
from pathlib import PurePath
from typing import Any, Mapping

import numpy as np


def real(value: Any) -> float | None:
    """``value`` as a Python float, or None if it is None or not finite."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def reals(values: Any) -> list:
    """An array (any shape) as nested lists of Python floats, non-finite -> None."""
    array = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(array)
    if finite.all():
        return array.tolist()
    objects = array.astype(object)
    objects[~finite] = None
    return objects.tolist()


def vector(values: Any) -> list[float | None]:
    """Any array flattened to a list of Python floats (non-finite -> None)."""
    return reals(np.asarray(values, dtype=np.float64).ravel())


def matrix(values: Any) -> list[list[float | None]]:
    """A 2-D array as a list of rows of Python floats (non-finite -> None)."""
    return reals(np.asarray(values, dtype=np.float64).reshape(len(values), -1))


def ints(values: Any) -> list[int]:
    """Any integer array flattened to a list of Python ints."""
    return [int(v) for v in np.asarray(values).ravel()]


def plain(value: Any) -> Any:
    """Config / metadata values as JSON-able data (unknown types -> str)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return real(value)
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [plain(v) for v in value]
    if isinstance(value, (_dt.datetime, _dt.date, _dt.time)):
        return value.isoformat()
    if isinstance(value, PurePath):
        return str(value)
    return str(value)
