"""Length test of the stereo station in the manner of VDI/VDE 2634 Part 1 (``crossfield verify``).

A scale bar carrying two targets at a certified length L (standard
uncertainty u_L) is measured in at least 7 positions and orientations
across the measuring volume. Per position the length measurement error is
``E = L_measured - L_certified`` (mm), L_measured the distance of the two
triangulated target centres averaged over the position's stereo pairs. The
station passes when every |E| <= E_MPE, the stated maximum permissible
error (simple acceptance, ISO 14253-1; the report gives u_L next to the
MPE, and VDI/VDE 2634-1 wants u_L small against it).

Centroiding and triangulation are the session's own stages (by default
``weighted`` and ``epipolar``), with the calibration under test.

A verification is a session (``crossfield verify --record VERIFY.mcap``):
the raw scale-bar pairs, the bar's certified length and the MPE, which pairs
belong to which position, the stage plugins and the calibration file under
test, and the per-position results go into one MCAP file with the integrity
chain and seal of a measurement session
(:mod:`crossfield.verification.record`).
``crossfield verify --recording VERIFY.mcap --calibration CALIB.yml``
evaluates the recorded pairs again,
e.g. a real bar measured at a real station, verified later or with another
calibration; it never trusts the recorded results.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from crossfield.errors import CrossfieldError
from crossfield.progress import bar
from crossfield.types import StereoCalibration, StereoCentroids, StereoFrame

MIN_POSITIONS = 7


@dataclass(frozen=True)
class PositionResult:
    """One bar position: per-frame lengths (mm), their mean, E = mean - certified (mm), pass."""

    name: str
    lengths_mm: tuple[float, ...]
    length_mm: float
    error_mm: float
    passed: bool


@dataclass(frozen=True)
class VerificationResult:
    certified_mm: float
    certified_u_mm: float
    mpe_mm: float
    positions: tuple[PositionResult, ...]
    calibration_source: str

    @property
    def max_abs_error_mm(self) -> float:
        return max(abs(p.error_mm) for p in self.positions)

    @property
    def passed(self) -> bool:
        return len(self.positions) >= MIN_POSITIONS and all(p.passed for p in self.positions)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "crossfield length verification (VDI/VDE 2634-1 style)",
            "certified_length_mm": self.certified_mm,
            "certified_u_mm": self.certified_u_mm,
            "mpe_mm": self.mpe_mm,
            "max_abs_error_mm": self.max_abs_error_mm,
            "passed": self.passed,
            "positions_required": MIN_POSITIONS,
            "calibration": self.calibration_source,
            "positions": [
                {
                    "name": p.name,
                    "length_mm": p.length_mm,
                    "error_mm": p.error_mm,
                    "passed": p.passed,
                    "frames": list(p.lengths_mm),
                }
                for p in self.positions
            ],
        }


def bar_length(frame: StereoFrame, centroid, triangulate, calibration: StereoCalibration) -> float:
    """Distance (mm) between the two targets of one stereo pair; an error unless exactly two are triangulated."""
    centroids = StereoCentroids(
        frame.sequence,
        centroid.extract(frame.upper, "upper", frame.sequence),
        centroid.extract(frame.lower, "lower", frame.sequence),
    )
    points = triangulate.triangulate(centroids, calibration)
    if len(points) != 2:
        raise CrossfieldError(
            f"pair {frame.sequence}: {len(points)} targets triangulated, the scale bar has 2 "
            f"({'; '.join(points.rejected) or 'no rejections'})"
        )
    return float(np.linalg.norm(points.xyz[0] - points.xyz[1]))


def evaluate(
    named_frames: Sequence[tuple[str, Sequence[StereoFrame]]],
    calibration: StereoCalibration,
    centroid,
    triangulate,
    *,
    certified_mm: float,
    certified_u_mm: float,
    mpe_mm: float,
) -> VerificationResult:
    """E per position from its frames (see the module docstring)."""
    if len(named_frames) < MIN_POSITIONS:
        raise CrossfieldError(
            f"{len(named_frames)} scale-bar positions; VDI/VDE 2634-1 needs at least {MIN_POSITIONS}"
        )
    results = []
    for name, frames in bar(named_frames, desc="verify: measuring the bar", unit="position"):
        lengths = tuple(bar_length(f, centroid, triangulate, calibration) for f in frames)
        mean = float(np.mean(lengths))
        error = mean - certified_mm
        results.append(PositionResult(name, lengths, mean, error, abs(error) <= mpe_mm))
    return VerificationResult(certified_mm, certified_u_mm, mpe_mm, tuple(results), calibration.source)


def simulate_positions(
    calibration: StereoCalibration, length_mm: float, frames: int, seed: int, scenario: str = "station"
) -> list[tuple[str, list[StereoFrame]]]:
    """Rendered stereo pairs of the simulated bar in each of its positions (truth: ``length_mm``)."""
    from crossfield.simulator.scale_bar import bar_scene, scale_bar_positions

    out = []
    rng = np.random.default_rng([seed, 5])
    for position in bar(scale_bar_positions(), desc="simulating the bar positions", unit="position"):
        scene = bar_scene(position, length_mm, scenario)
        out.append((position.name, [scene.render_pair(k, rng) for k in range(frames)]))
    return out


def create_stages(specs: Mapping[str, Mapping[str, Any]], where: str) -> dict[str, Any]:
    """The centroid and triangulate implementations named in ``specs`` ({stage: {plugin, options}})."""
    from crossfield.chain.registry import get_implementation, make_plugin_manager

    pm = make_plugin_manager(entry_points=True)
    out = {}
    for stage in ("centroid", "triangulate"):
        spec = specs.get(stage)
        if not isinstance(spec, Mapping) or not isinstance(spec.get("plugin"), str):
            raise CrossfieldError(f"{where}: no {stage} plugin named")
        out[stage] = get_implementation(pm, stage, spec["plugin"]).create(dict(spec.get("options") or {}), stage)
    return out
