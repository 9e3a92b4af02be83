"""The simulated station: stereo rig, targets, CMM arm, ground truth.

A :class:`Scene` is built by :func:`crossfield.simulator.scenarios.build_scene`.
It is deterministic: the geometry comes from the scenario, the noise from
the ``rng`` handed to :meth:`Scene.render_pair` and :meth:`Scene.arm_probes`.
All target geometry is held in the upper-camera frame (mm); the global
(CMM) frame is reached with the true ``T_global_camera``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Mapping

import numpy as np

from crossfield.plan import MeasurementPlan
from crossfield.simulator.render import DiscImage, SensorModel, add_noise, compose_clean_image, render_disc
from crossfield.types import CAMERAS, GroundTruth, Line3D, StereoCalibration, StereoFrame


@dataclass(frozen=True)
class Target:
    """A circular retro-reflective target: centre (3,) and unit normal (3,) in
    the upper-camera frame (mm), radius in mm, signal above background in DN."""

    id: str
    centre_camera: np.ndarray
    normal_camera: np.ndarray
    radius_mm: float
    signal_dn: float


@dataclass(frozen=True)
class ArmProbe:
    """One probe-button point as the simulated ROMER arm reports it (global, mm)."""

    label: str
    xyz: np.ndarray
    probe_vector: np.ndarray
    probe_diameter_mm: float


@dataclass(frozen=True)
class Cylinder:
    """A cylinder whose axis is an out-of-view reference line (global frame)."""

    id: str
    axis: Line3D
    radius_mm: float
    probe_heights_mm: tuple[float, ...]
    probe_angles_rad: tuple[float, ...]


@dataclass
class Scene:
    name: str
    calibration: StereoCalibration
    R_global_camera: np.ndarray
    t_global_camera: np.ndarray
    targets: tuple[Target, ...]
    reference_points_global: Mapping[str, np.ndarray]
    cylinders: tuple[Cylinder, ...]
    plan: MeasurementPlan
    sensor: SensorModel = field(default_factory=SensorModel)
    background_dn: float = 150.0
    arm_sigma_mm: float = 0.01
    probe_diameter_mm: float = 3.0
    frame_rate_hz: float = 14.0
    background_seed: int = 7

    # ---- geometry ------------------------------------------------------

    def to_global(self, points_camera: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame mm -> global mm: p_g = R p_c + t."""
        return np.asarray(points_camera) @ self.R_global_camera.T + self.t_global_camera

    def to_camera(self, name: str, points_upper: np.ndarray) -> np.ndarray:
        """(N, 3) upper-camera points -> camera ``name``'s frame (Formula (4) pose)."""
        P = np.asarray(points_upper, dtype=np.float64)
        if name == "upper":
            return P
        return P @ self.calibration.R_lower_upper.T + self.calibration.t_lower_upper

    @cached_property
    def ground_truth(self) -> GroundTruth:
        points = {t.id: self.to_global(t.centre_camera[None])[0] for t in self.targets}
        points.update({k: np.asarray(v, float) for k, v in self.reference_points_global.items()})
        return GroundTruth(
            points_global=points,
            lines_global={c.id: c.axis for c in self.cylinders},
            R_global_camera=self.R_global_camera,
            t_global_camera=self.t_global_camera,
        )

    # ---- images --------------------------------------------------------

    @cached_property
    def _discs(self) -> dict[str, dict[str, DiscImage]]:
        out: dict[str, dict[str, DiscImage]] = {}
        for cam in CAMERAS:
            intr = self.calibration.camera(cam)
            R = np.eye(3) if cam == "upper" else self.calibration.R_lower_upper
            out[cam] = {}
            for t in self.targets:
                disc = render_disc(
                    self.to_camera(cam, t.centre_camera[None])[0], R @ t.normal_camera, t.radius_mm, intr,
                    self.sensor.blur_sigma_px,
                )
                if disc is not None:
                    out[cam][t.id] = disc
        return out

    def true_blob_centres(self, camera: str) -> dict[str, np.ndarray]:
        """Target id -> true centre (2,) px of its image blob in ``camera``.

        This is the centre of the imaged ellipse, which differs from the
        projection of the circle's centre (perspective bias)."""
        return {k: d.centroid_uv for k, d in self._discs[camera].items()}

    @cached_property
    def clean_images(self) -> dict[str, np.ndarray]:
        """Noise-free (height, width) float32 DN image of each camera."""
        from crossfield.simulator.render import background_image

        images = {}
        for cam in CAMERAS:
            size = self.calibration.camera(cam).image_size
            rng = np.random.default_rng(self.background_seed + (cam == "lower"))
            background = background_image(size, self.background_dn, rng)
            signals = {t.id: t.signal_dn for t in self.targets}
            discs = [(d, signals[k]) for k, d in self._discs[cam].items()]
            images[cam] = compose_clean_image(size, discs, background)
        return images

    def render_pair(self, sequence: int, rng: np.random.Generator, timestamp_ns: int = 0) -> StereoFrame:
        """One noisy stereo pair (uint16, ``sensor.bit_depth``-bit DN)."""
        clean = self.clean_images
        return StereoFrame(
            sequence=sequence,
            timestamp_ns=timestamp_ns,
            upper=add_noise(clean["upper"], self.sensor, rng),
            lower=add_noise(clean["lower"], self.sensor, rng),
            bit_depth=self.sensor.bit_depth,
        )

    # ---- CMM arm -------------------------------------------------------

    def arm_probes(self, rng: np.random.Generator) -> list[ArmProbe]:
        """Points the arm reports, in the plan's probing order, each with
        independent N(0, arm_sigma_mm^2) noise per coordinate."""
        truth = self.ground_truth
        cylinders = {c.id: c for c in self.cylinders}
        normals = {t.id: self.R_global_camera @ t.normal_camera for t in self.targets}
        ball = self.probe_diameter_mm / 2
        probes = []
        for label in self.plan.probing_order():
            element, _, index = label.partition(".")
            if element in cylinders:
                cyl = cylinders[element]
                k = int(index) - 1
                n_angles = len(cyl.probe_angles_rad)
                height = cyl.probe_heights_mm[k // n_angles]
                angle = cyl.probe_angles_rad[k % n_angles]
                e1, e2 = probe_ring_basis(cyl.axis.direction)
                radial = np.cos(angle) * e1 + np.sin(angle) * e2
                # Ball centre on the outside of the shaft: radius + ball radius.
                true_xyz = cyl.axis.point + height * cyl.axis.direction + (cyl.radius_mm + ball) * radial
                vector = -radial
            else:
                true_xyz = truth.points_global[element]
                vector = -normals.get(element, np.array([0.0, 0.0, 1.0]))
            noisy = true_xyz + rng.normal(0.0, self.arm_sigma_mm, size=3)
            probes.append(ArmProbe(label, noisy, vector / np.linalg.norm(vector), self.probe_diameter_mm))
        return probes


def probe_ring_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's own basis (3,), (3,) around a cylinder axis for placing its
    probes (kept as it was so that scenarios reproduce their recorded numbers;
    :func:`crossfield.geometry.perpendicular_basis` picks its helper axis differently)."""
    d = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)
