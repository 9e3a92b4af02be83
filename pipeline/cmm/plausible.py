"""What a CMM coordinate may be: finite and inside the measuring volume.

Every decoder (:mod:`crossfield.cmm.protocol`, :mod:`crossfield.cmm.formats`)
and every point-file reader (:mod:`crossfield.cmm.point_files`) checks its
points here, so that a value no arm can produce (``1e999`` read as inf, a
``1e12`` mm typo, a negative probe radius) is refused at the line it came
from, for what it is, instead of reaching the registration.

The measuring volume is an axis-aligned cube centred on the CMM origin:
``|X|, |Y|, |Z| <= volume_mm`` (option ``measuring_volume_mm`` of every
reference plugin). The default, 5000 mm, is generous for a portable arm
(the largest ROMER Absolute Arm reaches 4.5 m across, i.e. about 2.25 m
from its base) and still refuses values off by orders of magnitude.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["DEFAULT_VOLUME_MM", "VOLUME_OPTION", "check_volume", "coordinate_problem", "size_problem"]

#: Default half-width of the measuring volume (mm): every |coordinate| must be <= this.
DEFAULT_VOLUME_MM = 5000.0
#: The name of the option that sets it, in every reference plugin.
VOLUME_OPTION = "measuring_volume_mm"


def check_volume(value: object) -> float:
    """The option ``measuring_volume_mm`` as a float (mm), or a ValueError naming the key."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and value > 0):  # type: ignore[arg-type]
        raise ValueError(
            f"option {VOLUME_OPTION!r} must be a positive number of mm (the largest |X|, |Y|, |Z| "
            f"a point may have), got {value!r}"
        )
    return float(value)  # type: ignore[arg-type]


def coordinate_problem(xyz: Sequence[float], volume_mm: float, names: str = "XYZ") -> str | None:
    """Why ``xyz`` (3,) mm cannot be a probed point, or None if it can.

    Non-finite values (NaN, inf) and values with ``|v| > volume_mm`` are refused.
    """
    for name, value in zip(names, xyz):
        if not math.isfinite(value):
            return f"{name} is not finite ({value})"
    for name, value in zip(names, xyz):
        if abs(value) > volume_mm:
            return (
                f"{name} = {value:.6g} mm is outside the measuring volume "
                f"(|{name}| <= {volume_mm:g} mm, option {VOLUME_OPTION})"
            )
    return None


def size_problem(value: float, name: str, limit_mm: float, *, allow_zero: bool = False) -> str | None:
    """Why a probe radius or diameter ``value`` (mm) is impossible, or None:
    not finite, negative (or zero unless ``allow_zero``), or above
    ``limit_mm`` (a ball cannot be larger than the measuring volume: the
    volume's half-width for a radius, its width for a diameter)."""
    if not math.isfinite(value):
        return f"{name} is not finite ({value})"
    if value < 0 or (value == 0 and not allow_zero):
        return f"{name} must be {'>= 0' if allow_zero else '> 0'} mm, got {value}"
    if value > limit_mm:
        return f"{name} = {value:.6g} mm is larger than the measuring volume (option {VOLUME_OPTION})"
    return None
