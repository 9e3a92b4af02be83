"""A station whose images come from the model-mismatch renderer (:mod:`.render_mismatch`).

:func:`mismatch_scene` turns a scenario's scene (its geometry, targets, arm and
plan) into a :class:`MismatchScene`: the estimator still gets a plumb-bob
calibration (``Scene.calibration``), while the images are made through a truth
it does not model:

* each camera's true lens has OpenCV's rational radial terms k4..k6 and a
  thin prism s1..s4 beyond the plumb-bob k1 k2 p1 p2 k3; the calibration
  handed to the estimator holds the plumb-bob least-squares fit of it
  (:func:`render_mismatch.fit_plumb_bob`);
* per session (:meth:`MismatchScene.for_session`, from the session's seed):
  a thin-prism part that differs between sessions, a toe-in error of the
  lower camera (rotation about the upper camera's x axis, the baseline's
  disparity direction), a pixel-aspect error (fy scaled) of each camera,
  an out-of-plane tilt of each target (its normal turned about a random
  axis), and the sensor's fixed pattern (PRNU, DSNU);
* the PSF is a Gaussian with a defocus disc on pixels of fill factor < 1,
  the noise in electrons (EMVA 1288) with a 12-bit ADC.

The ground truth (target centres, T_global_camera, the reference elements) is
the base scene's: the physical discs' centres do not move.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from crossfield.simulator.render import SensorModel
from crossfield.simulator.render_mismatch import (
    PSF,
    MismatchSensor,
    TrueLens,
    apply_sensor,
    fit_plumb_bob,
    fixed_pattern,
    render_disc_electrons,
)
from crossfield.simulator.scene import Scene
from crossfield.types import CAMERAS, CameraIntrinsics, StereoCalibration, StereoFrame

__all__ = ["MismatchOptions", "MismatchScene", "mismatch_scene"]


@dataclass(frozen=True)
class MismatchOptions:
    """What the truth adds to the estimator's model (all standard deviations per session).

    k_extra: (k4, k5, k6) rational radial terms of both lenses; prism: (s1..s4)
    fixed thin prism of both lenses (the lower's sign-flipped); prism_sigma:
    per-session std of each s_i; toe_in_sigma_rad: per-session std of the lower
    camera's extra rotation about x (rad); aspect_sigma: per-session std of
    fy / fx - 1 of each camera; tilt_sigma_deg: per-session out-of-plane tilt of
    each target (deg, RMS of the angle); electrons_per_dn: the target signal in
    photo-electrons per px^2 per DN of the base scene's signal; background_e:
    background level (photo-electrons per px^2); psf, sensor, oversample
    (fine samples per pixel and axis).
    """

    k_extra: tuple[float, float, float] = (0.015, -0.01, 0.005)
    prism: tuple[float, float, float, float] = (1.2e-4, -6e-5, 9e-5, 3e-5)
    prism_sigma: float = 6e-5
    toe_in_sigma_rad: float = 8e-7
    aspect_sigma: float = 5e-6
    tilt_sigma_deg: float = 2.0
    electrons_per_dn: float = 2.4
    background_e: float = 350.0
    psf: PSF = field(default_factory=lambda: PSF(sigma_px=0.6, defocus_px=1.0, fill_factor=0.6))
    sensor: MismatchSensor = field(default_factory=MismatchSensor)
    oversample: int = 4


def _lens_of(intr: CameraIntrinsics, k_extra, prism) -> TrueLens:
    K = intr.camera_matrix
    d = np.zeros(5)
    d[: min(5, len(intr.dist_coeffs))] = intr.dist_coeffs[:5]
    k1, k2, p1, p2, k3 = (float(v) for v in d)
    return TrueLens(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                    (k1, k2, k3, *k_extra), (p1, p2), tuple(prism), intr.image_size)


def _intrinsics_of(lens: TrueLens) -> CameraIntrinsics:
    """The plumb-bob calibration the estimator gets for ``lens`` (its pinhole, the fitted k1 k2 p1 p2 k3)."""
    return CameraIntrinsics(lens.camera_matrix(), fit_plumb_bob(lens), lens.image_size)


@dataclass
class MismatchScene(Scene):
    """A :class:`Scene` rendered by the mismatch renderer (see the module docstring).

    lenses: camera -> its true lens; R_lower_upper_true, t_lower_upper_true: the true
    rig (the calibration's R, t hold the nominal ones); options; session_seed: the
    seed the session's truth was drawn from (None: the nominal truth).
    """

    lenses: dict = field(default_factory=dict)
    R_lower_upper_true: np.ndarray | None = None
    t_lower_upper_true: np.ndarray | None = None
    options: MismatchOptions = field(default_factory=MismatchOptions)
    session_seed: int | None = None

    def true_camera(self, name: str, points_upper: np.ndarray) -> np.ndarray:
        """(N, 3) upper-camera points -> camera ``name``'s frame of the *true* rig (mm)."""
        P = np.asarray(points_upper, dtype=np.float64)
        if name == "upper":
            return P
        return P @ self.R_lower_upper_true.T + self.t_lower_upper_true

    def for_session(self, seed: int) -> "MismatchScene":
        """This station's truth for one session: the per-session parts drawn from ``seed``."""
        o = self.options
        rng = np.random.default_rng([int(seed), 22])
        lenses = {}
        for cam in CAMERAS:
            base = self.lenses[cam]
            prism = tuple(np.asarray(base.s) + o.prism_sigma * rng.standard_normal(4))
            fy = base.fy * (1.0 + o.aspect_sigma * rng.standard_normal())
            lenses[cam] = dataclasses.replace(base, s=prism, fy=fy)
        toe = Rotation.from_rotvec([o.toe_in_sigma_rad * rng.standard_normal(), 0.0, 0.0]).as_matrix()
        # p_lower = R (p_upper - C): the lower camera turned by `toe` about its own x axis
        centre = -self.R_lower_upper_true.T @ self.t_lower_upper_true
        R_true = toe @ self.R_lower_upper_true
        targets = []
        for t in self.targets:
            axis = np.cross(t.normal_camera, rng.normal(size=3))
            axis /= np.linalg.norm(axis)
            angle = np.radians(o.tilt_sigma_deg) / np.sqrt(2.0) * rng.standard_normal()
            normal = Rotation.from_rotvec(angle * axis).apply(t.normal_camera)
            targets.append(dataclasses.replace(t, normal_camera=normal))
        return dataclasses.replace(
            self, lenses=lenses, R_lower_upper_true=R_true, t_lower_upper_true=-R_true @ centre,
            targets=tuple(targets), session_seed=int(seed),
        )

    # ---- images --------------------------------------------------------

    @cached_property
    def _blobs(self) -> dict[str, dict[str, tuple[tuple[int, int], np.ndarray]]]:
        """camera -> target id -> (origin, ROI image in px^2 of blob area per pixel)."""
        o = self.options
        out: dict[str, dict] = {}
        for cam in CAMERAS:
            R = np.eye(3) if cam == "upper" else self.R_lower_upper_true
            out[cam] = {}
            for t in self.targets:
                blob = render_disc_electrons(
                    self.true_camera(cam, t.centre_camera[None])[0], R @ t.normal_camera, t.radius_mm,
                    self.lenses[cam], o.psf, o.oversample,
                )
                if blob is not None:
                    out[cam][t.id] = blob
        return out

    def true_blob_centres(self, camera: str) -> dict[str, np.ndarray]:
        """Target id -> (2,) px, the centroid of the noise-free blob (the PSF and the aperture are
        even: the area centroid of the disc's exact image, to the renderer's ~1e-3 px)."""
        out = {}
        for tid, ((u0, v0), img) in self._blobs[camera].items():
            vv, uu = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
            total = img.sum()
            out[tid] = np.array([(img * uu).sum() / total + u0, (img * vv).sum() / total + v0])
        return out

    @cached_property
    def photo_electrons(self) -> dict[str, np.ndarray]:
        """camera -> (height, width) mean photo-electrons of one exposure (before PRNU)."""
        o = self.options
        images = {}
        for cam in CAMERAS:
            width, height = self.lenses[cam].image_size
            ru = ((np.arange(width) - width / 2) / width) ** 2
            rv = ((np.arange(height) - height / 2) / height) ** 2
            image = o.background_e * (1.0 - 0.4 * (rv[:, None] + ru[None, :]))  # vignetted background
            signal = {t.id: t.signal_dn * o.electrons_per_dn for t in self.targets}
            for tid, ((u0, v0), blob) in self._blobs[cam].items():
                rows, cols = blob.shape
                a0, b0 = max(v0, 0), max(u0, 0)
                a1, b1 = min(v0 + rows, height), min(u0 + cols, width)
                if a1 > a0 and b1 > b0:
                    image[a0:a1, b0:b1] += signal[tid] * blob[a0 - v0 : a1 - v0, b0 - u0 : b1 - u0]
            images[cam] = image
        return images

    @cached_property
    def _fixed_pattern(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        rng = np.random.default_rng([0 if self.session_seed is None else self.session_seed, 23])
        return {cam: fixed_pattern(self.photo_electrons[cam].shape, self.options.sensor, rng) for cam in CAMERAS}

    @cached_property
    def clean_images(self) -> dict[str, np.ndarray]:
        """Noise-free (height, width) float32 DN of each camera (fixed pattern included)."""
        s = self.options.sensor
        out = {}
        for cam in CAMERAS:
            gain, dark = self._fixed_pattern[cam]
            dn = s.gain_dn_per_e * (self.photo_electrons[cam] * gain + dark) + s.offset_dn
            out[cam] = np.clip(dn, 0, s.max_dn).astype(np.float32)
        return out

    def render_pair(self, sequence: int, rng: np.random.Generator, timestamp_ns: int = 0) -> StereoFrame:
        """One noisy stereo pair (uint16, 12-bit DN) through the EMVA 1288 sensor."""
        s = self.options.sensor
        images = {}
        for cam in CAMERAS:
            gain, dark = self._fixed_pattern[cam]
            images[cam] = apply_sensor(self.photo_electrons[cam], gain, dark, s, rng)
        return StereoFrame(sequence=sequence, timestamp_ns=timestamp_ns, upper=images["upper"],
                           lower=images["lower"], bit_depth=s.bit_depth)


def mismatch_scene(base: Scene, name: str, options: MismatchOptions | None = None) -> MismatchScene:
    """The :class:`MismatchScene` of ``base``'s station: its true calibration becomes the truth
    (with the options' extra distortion), the estimator gets the plumb-bob fit of it."""
    o = options or MismatchOptions()
    flip = {"upper": 1.0, "lower": -1.0}
    lenses = {cam: _lens_of(base.calibration.camera(cam), o.k_extra, tuple(flip[cam] * np.asarray(o.prism)))
              for cam in CAMERAS}
    calibration = StereoCalibration(
        _intrinsics_of(lenses["upper"]), _intrinsics_of(lenses["lower"]),
        base.calibration.R_lower_upper, base.calibration.t_lower_upper, source=f"simulator {name} (plumb-bob fit)",
    )
    s = o.sensor
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(Scene)}
    fields.update(name=name, calibration=calibration,
                  sensor=SensorModel(gain_dn_per_e=s.gain_dn_per_e, read_noise_dn=s.read_noise_e * s.gain_dn_per_e,
                                     bit_depth=s.bit_depth, blur_sigma_px=o.psf.sigma_px))
    return MismatchScene(**fields, lenses=lenses, R_lower_upper_true=np.array(base.calibration.R_lower_upper),
                         t_lower_upper_true=np.array(base.calibration.t_lower_upper), options=o)

