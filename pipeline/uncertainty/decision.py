"""ISO 14253-1 decision rules: conformance with a specification, uncertainty taken into account.

The specification zone of a characteristic is
``[nominal - lower_tol, nominal + upper_tol]`` (deviation ``d = measured -
nominal``). With the expanded uncertainty U (ISO 14253-1:2017, 5.2/5.3;
ILAC-G8:09/2019 4.2):

* ``simple`` (simple acceptance, ISO 14253-5 / ILAC-G8 4.2.1, no guard band):
  ``conforms`` inside the zone, else ``does_not_conform``; accepted when it conforms.
* ``guarded_acceptance`` (the supplier proves conformance; guard band w = U
  inside the zone): ``conforms`` when ``-lower_tol + U <= d <= upper_tol - U``;
  ``does_not_conform`` outside the zone; ``not_proven`` in the guard band.
  Accepted only when it conforms.
* ``guarded_rejection`` (the customer proves non-conformance; guard band
  w = U outside the zone): ``does_not_conform`` when ``d < -lower_tol - U`` or
  ``d > upper_tol + U``; ``conforms`` inside the zone; ``not_proven`` in the
  guard band. Accepted unless non-conformance is proven.

Band edges belong to the inner zone (``<=``). With U unknown see :func:`decide`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["DECISIONS", "RULES", "Decision", "decide"]

RULES = ("simple", "guarded_acceptance", "guarded_rejection")
DECISIONS = ("conforms", "does_not_conform", "not_proven")


@dataclass(frozen=True)
class Decision:
    """verdict: one of :data:`DECISIONS`; accepted: the part is accepted under ``rule``;
    acceptance_zone_mm: (low, high) deviations accepted (mm), empty (low > high) when
    the guard band consumes the zone."""

    rule: str
    verdict: str
    accepted: bool
    acceptance_zone_mm: tuple[float, float]


def decide(
    deviation_mm: float,
    lower_tol_mm: float,
    upper_tol_mm: float,
    expanded_uncertainty_mm: float | None,
    rule: str = "simple",
) -> Decision:
    """The verdict on a deviation (mm) for the zone ``[-lower_tol, +upper_tol]`` under ``rule``.

    A NaN deviation (not measured) is ``not_proven`` and not accepted. For the
    guarded rules an unknown U (None) gives ``not_proven`` wherever the
    verdict would depend on U (inside the zone for guarded acceptance, outside
    it for guarded rejection).
    """
    if rule not in RULES:
        raise ValueError(f"unknown decision rule {rule!r}; rules: {', '.join(RULES)}")
    low, high = -float(lower_tol_mm), float(upper_tol_mm)
    d = float(deviation_mm)
    if d != d:  # NaN
        return Decision(rule, "not_proven", False, (low, high))
    inside = low <= d <= high
    if rule == "simple":
        verdict = "conforms" if inside else "does_not_conform"
        return Decision(rule, verdict, inside, (low, high))
    U = expanded_uncertainty_mm
    if rule == "guarded_acceptance":
        if U is None:
            verdict = "not_proven" if inside else "does_not_conform"
            return Decision(rule, verdict, False, (low, high))
        zone = (low + U, high - U)
        if zone[0] <= d <= zone[1]:
            verdict = "conforms"
        else:
            verdict = "not_proven" if inside else "does_not_conform"
        return Decision(rule, verdict, verdict == "conforms", zone)
    # guarded rejection
    if U is None:
        verdict = "conforms" if inside else "not_proven"
        return Decision(rule, verdict, True, (-float("inf"), float("inf")))
    zone = (low - U, high + U)
    if inside:
        verdict = "conforms"
    elif zone[0] <= d <= zone[1]:
        verdict = "not_proven"
    else:
        verdict = "does_not_conform"
    return Decision(rule, verdict, verdict != "does_not_conform", zone)
