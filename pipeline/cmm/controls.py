"""Degenerate control sets, found in the CMM coordinates at import.

The registration (:mod:`crossfield.rigid`) needs the plan's control points
to span 3-D space. A control set that cannot do it is reported as a
*problem* of the reference import (``ReferenceData.problems``), naming the
controls, before any frame is processed:

* **coincident**: two controls closer than :data:`COINCIDENT_MM` (the same
  target probed twice under two labels, a copy-paste in a point file). The
  correspondence search cannot tell them apart.
* **collinear**: all controls within ``COLLINEAR_RATIO`` of a line (the
  singular-value test of :func:`crossfield.rigid.validate_pairs`): the
  rotation about that line is undetermined.
* **coplanar** (4 or more controls; 3 always are, the plan chose that): the
  RMS distance of the controls from their best-fit plane is at most
  :data:`COPLANAR_SIGMAS` times their stated uncertainty. A planar set and
  its mirror image fit equally well (:mod:`crossfield.rigid`, "The
  reflection criterion"), so a mirrored registration cannot be detected.

Points outside the measuring volume never get here: the decoders refuse
them (:mod:`crossfield.cmm.plausible`).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from crossfield.plan import MeasurementPlan
from crossfield.rigid import COLLINEAR_RATIO
from crossfield.types import ProbedPoint

__all__ = ["COINCIDENT_MM", "COPLANAR_SIGMAS", "control_problems"]

#: Two controls closer than this (mm) are the same point.
COINCIDENT_MM = 1e-3
#: Controls whose RMS distance from their best-fit plane is at most this
#: many times their standard uncertainty are coplanar.
COPLANAR_SIGMAS = 3.0


def control_problems(points: Sequence[ProbedPoint], plan: MeasurementPlan, where: str = "") -> list[str]:
    """Problems of the plan's control points among ``points`` (global frame, mm)."""
    controls = set(plan.control_ids)
    found = [p for p in points if p.label in controls]
    prefix = f"{where}: " if where else ""
    problems: list[str] = []
    distinct: list[ProbedPoint] = []
    for a, b in itertools.combinations(found, 2):
        gap = float(np.linalg.norm(np.asarray(a.xyz) - np.asarray(b.xyz)))
        if gap < COINCIDENT_MM:
            problems.append(
                f"{prefix}controls {a.label} and {b.label} have the same CMM coordinates ({gap:.4f} mm apart): "
                f"one target probed twice? The registration cannot tell them apart"
            )
    seen: list[np.ndarray] = []
    for p in found:
        xyz = np.asarray(p.xyz, dtype=np.float64)
        if all(np.linalg.norm(xyz - q) >= COINCIDENT_MM for q in seen):
            seen.append(xyz)
            distinct.append(p)
    if len(distinct) < 3:
        return problems
    X = np.array([p.xyz for p in distinct], dtype=np.float64)
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    labels = ", ".join(p.label for p in distinct)
    if s[1] <= COLLINEAR_RATIO * s[0]:
        problems.append(
            f"{prefix}the controls {labels} are collinear (spread ratio {s[1] / s[0]:.2e}): "
            f"the rotation about their line is undetermined"
        )
    elif len(distinct) >= 4:
        off_plane_mm = float(s[2] / np.sqrt(len(distinct)))
        sigma_mm = float(np.median([p.sigma_mm for p in distinct]))
        if off_plane_mm <= COPLANAR_SIGMAS * sigma_mm:
            problems.append(
                f"{prefix}the {len(distinct)} controls {labels} are coplanar (RMS {off_plane_mm:.4f} mm from "
                f"their plane, <= {COPLANAR_SIGMAS:g} x sigma {sigma_mm:g} mm): a mirrored registration "
                f"fits them as well and cannot be detected"
            )
    return problems
