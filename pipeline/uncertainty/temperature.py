"""Correction of lengths to the reference temperature 20 degC (ISO 1:2022).

A length L measured on a part at temperature T_p (expansion coefficient
alpha_p, 1/K) with a reference (the CMM scale) at T_r (alpha_r) is, at
20 degC, to first order in alpha * dT (ISO/TR 16015:2003, eq. (3)):

    L_20 = L (1 - alpha_p (T_p - 20) + alpha_r (T_r - 20)),
    correction  dL = -L (alpha_p (T_p - 20) - alpha_r (T_r - 20)).

Its standard uncertainty (GUM eq. (10), independent inputs; ISO/TR 16015 sec. 6):

    u^2 = L^2 [ (alpha_p u(T_p))^2 + (alpha_r u(T_r))^2
                + ((T_p - 20) u(alpha_p))^2 + ((T_r - 20) u(alpha_r))^2 ].

It applies to lengths between features of the part (``point_point``,
``point_line``); a ``depth`` is a coordinate in the CMM frame, whose origin
is not on the part: it is not corrected and gets no temperature term.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["REFERENCE_TEMPERATURE_C", "LENGTH_KINDS", "Temperature", "correction"]

REFERENCE_TEMPERATURE_C = 20.0
LENGTH_KINDS = ("point_point", "point_line")


@dataclass(frozen=True)
class Temperature:
    """Temperatures (degC) with standard uncertainties (K), expansion coefficients
    (1/K) with standard uncertainties (1/K). The defaults: everything at 20 degC,
    exactly: no correction, no contribution."""

    part_c: float = REFERENCE_TEMPERATURE_C
    u_part_k: float = 0.0
    part_alpha_per_k: float = 11.5e-6
    u_part_alpha_per_k: float = 0.0
    reference_c: float = REFERENCE_TEMPERATURE_C
    u_reference_k: float = 0.0
    reference_alpha_per_k: float = 0.0
    u_reference_alpha_per_k: float = 0.0
    stated: bool = False


def correction(length_mm: float, t: Temperature) -> tuple[float, float]:
    """(correction dL, its standard uncertainty u) in mm for a length (mm) measured at ``t``;
    add dL to the measured length to get the length at 20 degC."""
    dp = t.part_c - REFERENCE_TEMPERATURE_C
    dr = t.reference_c - REFERENCE_TEMPERATURE_C
    L = float(length_mm)
    dL = -L * (t.part_alpha_per_k * dp - t.reference_alpha_per_k * dr)
    u = abs(L) * math.sqrt(
        (t.part_alpha_per_k * t.u_part_k) ** 2
        + (t.reference_alpha_per_k * t.u_reference_k) ** 2
        + (dp * t.u_part_alpha_per_k) ** 2
        + (dr * t.u_reference_alpha_per_k) ** 2
    )
    return dL, u
