"""A scale bar in the station's measuring volume: the truth for ``crossfield verify``.

A bar carries two circular targets ``length_mm`` apart (its certified
length). VDI/VDE 2634 Part 1 asks for at least 7 positions and orientations
spread over the measuring volume; here: three along x (middle, near, far,
high and low in the shared view) and the four space diagonals of the
volume around the view centre. The shared view of the station is wide (x)
and shallow (y, the baseline direction), so the diagonals lean mostly
along x. All coordinates in the upper-camera frame, mm.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from crossfield.simulator.optics import project
from crossfield.simulator.scenarios import TARGET_RADIUS_MM, VIEW_CENTRE, build_scene
from crossfield.simulator.scene import Scene, Target
from crossfield.types import CAMERAS


@dataclass(frozen=True)
class BarPosition:
    """One placement of the bar: its centre (3,), unit direction (3,), upper-camera frame (mm)."""

    name: str
    centre: np.ndarray
    direction: np.ndarray

    def targets(self, length_mm: float) -> tuple[np.ndarray, np.ndarray]:
        half = 0.5 * length_mm * self.direction
        return self.centre - half, self.centre + half


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def scale_bar_positions() -> tuple[BarPosition, ...]:
    """The 7 positions (module docstring)."""
    c = VIEW_CENTRE
    positions = [
        BarPosition("x, middle", c.copy(), _unit([1, 0, 0])),
        BarPosition("x, high and near", c + [0, -22, -25], _unit([1, 0, 0.15])),
        BarPosition("x, low and far", c + [0, 28, 30], _unit([1, 0, -0.15])),
    ]
    for sy in (-1, 1):
        for sz in (-1, 1):
            name = f"diagonal {'+' if sy > 0 else '-'}y {'+' if sz > 0 else '-'}z"
            positions.append(BarPosition(name, c.copy(), _unit([0.8, 0.42 * sy, 0.42 * sz])))
    return tuple(positions)


def bar_scene(position: BarPosition, length_mm: float, scenario: str = "station") -> Scene:
    """The scenario's rig seeing only the bar's two targets (facing the upper camera)."""
    scene = build_scene(scenario)
    targets = []
    for name, p in zip(("A", "B"), position.targets(length_mm)):
        targets.append(Target(name, p, _unit(-p), TARGET_RADIUS_MM, 3000.0))
    for cam in CAMERAS:  # both targets must be imaged, with room for the blob
        intr = scene.calibration.camera(cam)
        pts = np.array([scene.to_camera(cam, t.centre_camera[None])[0] for t in targets])
        uv = project(pts, intr)
        w, h = intr.image_size
        if np.any(uv < 40) or np.any(uv[:, 0] > w - 41) or np.any(uv[:, 1] > h - 41):
            raise ValueError(f"scale bar position {position.name!r} leaves the {cam} camera's view")
    return dataclasses.replace(scene, targets=tuple(targets))
