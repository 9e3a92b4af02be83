"""A station description for layout planning (``docs/planning.md``).

:class:`Station` holds the explicit geometry the two prediction routes need:
the stereo calibration, the camera-frame positions of the measured targets and
of the common control points, the true camera pose in the CMM frame, the
out-of-view reference elements (global frame) and the characteristics, with
the sensor and noise parameters. It comes from a TOML file
(:func:`load_station`, example ``docs/examples/station-paper.toml``) or from a
built-in simulator scenario (:func:`station_from_scenario`: the exact
geometry the simulator renders). The ``with_*`` functions give the design
variants the sweeps evaluate.

Frames and units: the upper camera frame (OpenCV, mm) for the rig side, the
global (CMM) frame for the reference elements, ``p_g = R p_c + t``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from crossfield.errors import ConfigError
from crossfield.precision.centroid import NoiseModel
from crossfield.types import CameraIntrinsics, Line3D, StereoCalibration

KINDS = ("point_point", "point_line", "depth")
#: How the fixed centroid bias is predicted (``Station.bias_model``, docs/planning.md).
BIAS_MODELS = ("rendered", "eccentricity")


@dataclass(frozen=True)
class ReferenceLine:
    """An out-of-view reference line (a cylinder axis), global frame: the true axis and
    the CMM probe points (P, 3) mm fitted to it (``fit``: "cylinder" or "line")."""

    id: str
    axis: Line3D
    probes: np.ndarray
    fit: str = "cylinder"


@dataclass(frozen=True)
class Characteristic:
    """A cross-field characteristic: ``kind`` in point_point, point_line, depth; a, b element ids."""

    name: str
    kind: str
    a: str
    b: str | None = None


@dataclass(frozen=True)
class Station:
    """Everything a prediction needs (see the module docstring). Arrays: (T, 3) / (C, 3) mm."""

    name: str
    calibration: StereoCalibration
    R_global_camera: np.ndarray
    t_global_camera: np.ndarray
    target_ids: tuple[str, ...]
    target_xyz: np.ndarray  # (T, 3) upper camera frame
    target_normal: np.ndarray  # (T, 3)
    control_ids: tuple[str, ...]
    control_xyz: np.ndarray  # (C, 3) upper camera frame
    control_normal: np.ndarray  # (C, 3)
    radius_mm: float
    signal_dn: float
    cmm_sigma_mm: float
    reference_points: dict[str, np.ndarray]  # id -> (3,) global
    reference_lines: tuple[ReferenceLine, ...]
    characteristics: tuple[Characteristic, ...]
    frames: int = 10
    coverage_factor: float = 2.0
    blur_sigma_px: float = 0.9
    noise: NoiseModel = NoiseModel()
    background_dn: float = 150.0
    centroid_efficiency: float = 1.0
    focal_length_mm: float = 16.0
    pixel_pitch_mm: float = 0.0044
    control_box: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0, 0, 400), (80, 45, 18))
    source: str = ""
    design: dict[str, float] = field(default_factory=dict)
    perspective_bias: bool = True  # carry the fixed centroid bias (how: bias_model)
    #: how the fixed centroid bias is predicted: "rendered" (the simulator's renderer and the session's
    #: centroid implementation, planning.image_bias) or "eccentricity" (the conic-centre model alone)
    bias_model: str = "eccentricity"
    centroid: str = "weighted"  # the session's centroid implementation (for the rendered bias)
    #: (T + C,) DN above background per point (targets then controls); None: signal_dn for all
    point_signal_dn: np.ndarray | None = None
    #: the simulator's vignetted background (its seed, Scene.background_seed); None: flat background_dn
    background_seed: int | None = None
    #: the CMM sigma (mm) the reference plugin states, which the runner's weights use; None: cmm_sigma_mm
    weight_cmm_sigma_mm: float | None = None

    @property
    def working_distance_mm(self) -> float:
        return float(self.control_box[0][2])

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.calibration.t_lower_upper))

    @property
    def camera_xyz(self) -> np.ndarray:
        """(T + C, 3): targets then controls, upper camera frame (mm)."""
        return np.vstack([self.target_xyz, self.control_xyz])

    @property
    def camera_normals(self) -> np.ndarray:
        return np.vstack([self.target_normal, self.control_normal])

    @property
    def point_signals(self) -> np.ndarray:
        """(T + C,) DN above background of every target and control (targets then controls)."""
        n = len(self.target_ids) + len(self.control_ids)
        if self.point_signal_dn is not None and len(self.point_signal_dn) == n:
            return np.asarray(self.point_signal_dn, dtype=np.float64)
        return np.full(n, float(self.signal_dn))

    def to_global(self, xyz_camera: np.ndarray) -> np.ndarray:
        return np.asarray(xyz_camera) @ np.asarray(self.R_global_camera).T + np.asarray(self.t_global_camera)

    def in_view(self, margin_px: float = 10.0) -> bool:
        """Every target and control projects inside both images (with its radius and a margin)."""
        from crossfield.precision.stereo import project_stereo

        uv, _ = project_stereo(self.calibration, self.camera_xyz)
        f = self.calibration.upper.camera_matrix[0, 0]
        r = f * self.radius_mm / np.min(self.camera_xyz[:, 2]) + margin_px
        w, h = self.calibration.upper.image_size
        inside = (uv[:, 0::2] >= r) & (uv[:, 0::2] <= w - 1 - r) & (uv[:, 1::2] >= r) & (uv[:, 1::2] <= h - 1 - r)
        return bool(np.all(inside) and np.all(self.camera_xyz[:, 2] > 0))

    def summary(self) -> dict[str, Any]:
        """The design parameters, JSON-able."""
        return {
            "name": self.name,
            "n_controls": len(self.control_ids),
            "n_targets": len(self.target_ids),
            "focal_length_mm": self.focal_length_mm,
            "working_distance_mm": self.working_distance_mm,
            "baseline_mm": round(self.baseline_mm, 6),
            "control_half_size_mm": [float(v) for v in self.control_box[1]],
            "cmm_sigma_mm": self.cmm_sigma_mm,
            "frames": self.frames,
            "centroid_efficiency": self.centroid_efficiency,
            "in_view": self.in_view(),
            **self.design,
        }


# ---------------------------------------------------------------------------------------------
# Design variants (the sweeps)
# ---------------------------------------------------------------------------------------------


def _facing(xyz: np.ndarray) -> np.ndarray:
    return -xyz / np.linalg.norm(xyz, axis=1, keepdims=True)


def _halton_controls(n: int, box) -> np.ndarray:
    """n control positions (n, 3) mm in the box (centre, half sizes), upper frame: a Halton sequence
    (nested: the first n of n + 1), so adding control points keeps the earlier ones."""
    centre, half = (np.asarray(v, dtype=np.float64) for v in box)
    u = qmc.Halton(d=3, scramble=False).random(n + 1)[1:]
    return centre + (2.0 * u - 1.0) * half


def with_controls(station: Station, n: int) -> Station:
    """The station with n control points: its first n, or more added in its control box."""
    if n < 3:
        raise ValueError(f"a registration needs at least 3 control points, got {n}")
    C = len(station.control_ids)
    if n <= C:
        xyz, normal, ids = station.control_xyz[:n], station.control_normal[:n], station.control_ids[:n]
    else:
        extra = _halton_controls(n, station.control_box)[C:n]
        xyz = np.vstack([station.control_xyz, extra])
        normal = np.vstack([station.control_normal, _facing(extra)])
        ids = station.control_ids + tuple(f"C{k + 1}" for k in range(C, n))
    T = len(station.target_ids)
    signals = station.point_signals[: T + C]
    signals = np.concatenate([signals[: T + n], np.full(max(n - C, 0), float(station.signal_dn))])
    return dataclasses.replace(station, control_ids=tuple(ids), control_xyz=xyz, control_normal=normal,
                               point_signal_dn=signals)


def _scaled_intrinsics(intr: CameraIntrinsics, factor: float) -> CameraIntrinsics:
    K = np.array(intr.camera_matrix, dtype=np.float64)
    K[0, 0] *= factor
    K[1, 1] *= factor
    return CameraIntrinsics(K, np.array(intr.dist_coeffs), intr.image_size)


def with_focal_length(station: Station, focal_mm: float) -> Station:
    """Both lenses replaced by focal_mm (same sensor, principal points and distortion; layout fixed)."""
    factor = focal_mm / station.focal_length_mm
    cal = station.calibration
    calibration = StereoCalibration(
        _scaled_intrinsics(cal.upper, factor), _scaled_intrinsics(cal.lower, factor),
        cal.R_lower_upper, cal.t_lower_upper, source=cal.source,
    )
    return dataclasses.replace(station, calibration=calibration, focal_length_mm=float(focal_mm))


def with_working_distance(station: Station, distance_mm: float) -> Station:
    """The rig moved along its optical axis so the control box centre is at distance_mm;
    the object (targets, controls, reference elements) stays where it is in the global frame."""
    dz = distance_mm - station.working_distance_mm
    shift = np.array([0.0, 0.0, dz])
    R = np.asarray(station.R_global_camera)
    centre, half = station.control_box
    return dataclasses.replace(
        station,
        target_xyz=station.target_xyz + shift,
        control_xyz=station.control_xyz + shift,
        t_global_camera=np.asarray(station.t_global_camera) - R @ shift,
        control_box=((centre[0], centre[1], centre[2] + dz), half),
    )


def with_baseline(station: Station, baseline_mm: float) -> Station:
    """The lower camera moved along its baseline direction to baseline_mm (its rotation kept)."""
    cal = station.calibration
    R = np.asarray(cal.R_lower_upper)
    C = -R.T @ np.asarray(cal.t_lower_upper)  # lower camera centre, upper frame
    C = C * (baseline_mm / np.linalg.norm(C))
    calibration = StereoCalibration(cal.upper, cal.lower, R, -R @ C, source=cal.source)
    return dataclasses.replace(station, calibration=calibration)


def with_control_spread(station: Station, scale: float) -> Station:
    """The control points spread by ``scale`` about their centroid (camera frame; box scaled too)."""
    c = station.control_xyz.mean(axis=0)
    centre, half = station.control_box
    return dataclasses.replace(
        station,
        control_xyz=c + scale * (station.control_xyz - c),
        control_box=(centre, tuple(float(h) * scale for h in half)),
        design={**station.design, "control_spread_scale": float(scale)},
    )


def with_cmm_sigma(station: Station, sigma_mm: float) -> Station:
    return dataclasses.replace(station, cmm_sigma_mm=float(sigma_mm))


# ---------------------------------------------------------------------------------------------
# From a simulator scenario
# ---------------------------------------------------------------------------------------------


def station_from_scenario(
    name: str, *, arm_sigma_mm: float = 0.01, frames: int = 10, centroid_efficiency: float | None = None,
    bias_model: str = "rendered", centroid: str = "weighted",
) -> Station:
    """The exact geometry of simulator scenario ``name`` (``station``, ``table3``) as a Station.

    centroid_efficiency: RMS / CRB of the centroid implementation (None: the
    default measured for the ``weighted`` centroid, :data:`WEIGHTED_CENTROID_EFFICIENCY`).
    bias_model: ``rendered`` (default: the scenario's own images, its per-target signals and
    vignetted background, through ``centroid``) or ``eccentricity`` (:data:`BIAS_MODELS`).
    """
    if bias_model not in BIAS_MODELS:
        raise ValueError(f"bias_model must be one of {', '.join(BIAS_MODELS)}, got {bias_model!r}")
    from crossfield.simulator.scenarios import (
        BASELINE_MM,
        FOCAL_LENGTH_MM,
        PIXEL_PITCH_MM,
        SCENARIOS,
        TARGET_RADIUS_MM,
        build_scene,
    )
    from crossfield.simulator.scene import probe_ring_basis

    if name not in SCENARIOS:
        raise ConfigError(f"unknown scenario {name!r}; scenarios: {', '.join(SCENARIOS)}")
    scene = build_scene(name, arm_sigma_mm=arm_sigma_mm)
    targets = [t for t in scene.targets if t.id.startswith("P")]
    controls = [t for t in scene.targets if t.id.startswith("C")]
    lines = []
    ball = scene.probe_diameter_mm / 2
    for cyl in scene.cylinders:
        e1, e2 = probe_ring_basis(cyl.axis.direction)
        probes = [
            cyl.axis.point + h * cyl.axis.direction + (cyl.radius_mm + ball) * (np.cos(a) * e1 + np.sin(a) * e2)
            for h in cyl.probe_heights_mm for a in cyl.probe_angles_rad
        ]
        lines.append(ReferenceLine(cyl.id, cyl.axis, np.array(probes), "cylinder"))
    cxyz = np.array([t.centre_camera for t in controls])
    lo, hi = cxyz.min(axis=0), cxyz.max(axis=0)
    return Station(
        name=f"scenario {name}",
        calibration=scene.calibration,
        R_global_camera=np.asarray(scene.R_global_camera),
        t_global_camera=np.asarray(scene.t_global_camera),
        target_ids=tuple(t.id for t in targets),
        target_xyz=np.array([t.centre_camera for t in targets]),
        target_normal=np.array([t.normal_camera for t in targets]),
        control_ids=tuple(t.id for t in controls),
        control_xyz=cxyz,
        control_normal=np.array([t.normal_camera for t in controls]),
        radius_mm=TARGET_RADIUS_MM,
        signal_dn=float(np.mean([t.signal_dn for t in scene.targets])),
        point_signal_dn=np.array([t.signal_dn for t in targets + controls]),
        background_seed=scene.background_seed,
        bias_model=bias_model,
        centroid=centroid,
        cmm_sigma_mm=float(arm_sigma_mm),
        reference_points={k: np.asarray(v, dtype=np.float64) for k, v in scene.reference_points_global.items()},
        reference_lines=tuple(lines),
        characteristics=tuple(Characteristic(c.name, c.kind, c.a, c.b) for c in scene.plan.characteristics),
        frames=int(frames),
        blur_sigma_px=scene.sensor.blur_sigma_px,
        noise=NoiseModel(scene.sensor.gain_dn_per_e, scene.sensor.read_noise_dn),
        background_dn=scene.background_dn,
        centroid_efficiency=WEIGHTED_CENTROID_EFFICIENCY if centroid_efficiency is None else centroid_efficiency,
        focal_length_mm=FOCAL_LENGTH_MM,
        pixel_pitch_mm=PIXEL_PITCH_MM,
        control_box=(tuple((lo + hi) / 2), tuple((hi - lo) / 2)),
        source=f"<scenario {name}>",
        design={"baseline_nominal_mm": BASELINE_MM},
    )


#: RMS / CRB of the ``weighted`` centroid on the simulator's targets (2.13 upper, 2.14 lower, measured by
#: bench/bench_plan_validation.py --efficiency; docs/planning.md).
WEIGHTED_CENTROID_EFFICIENCY = 2.1

#: The session stages the planner's defaults model (``StationDesign.centroid``, the efficiency
#: above, the weighted Kabsch of :mod:`crossfield.planning.routes`), stage -> plugin: the
#: pipeline it is validated against (bench/bench_plan_validation.py), not the session defaults
#: since issue 11 (``modelfit``, ``ml``).
PLANNED_STAGES: Mapping[str, str] = MappingProxyType({"centroid": "weighted", "register": "svd"})


# ---------------------------------------------------------------------------------------------
# From TOML
# ---------------------------------------------------------------------------------------------


class _Table:
    """A TOML table with key checks that name the file and the key path."""

    def __init__(self, data: Any, path: str, source: str):
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: [{path}] must be a table")
        self.data, self.path, self.source = data, path, source
        self.used: set[str] = set()

    def _where(self, key: str) -> str:
        return f"{self.source}: key '{self.path}.{key}'" if self.path else f"{self.source}: key '{key}'"

    def number(self, key: str, default: float | None = None, *, minimum: float | None = None,
               strict: bool = False) -> float:
        self.used.add(key)
        if key not in self.data:
            if default is None:
                raise ConfigError(f"{self._where(key)} is missing")
            return float(default)
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(f"{self._where(key)} must be a number, got {v!r}")
        if minimum is not None and (v < minimum or (strict and v == minimum)):
            raise ConfigError(f"{self._where(key)} must be {'>' if strict else '>='} {minimum}, got {v!r}")
        return float(v)

    def integer(self, key: str, default: int | None = None, *, minimum: int = 1) -> int:
        self.used.add(key)
        if key not in self.data:
            if default is None:
                raise ConfigError(f"{self._where(key)} is missing")
            return default
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            raise ConfigError(f"{self._where(key)} must be an integer >= {minimum}, got {v!r}")
        return v

    def vector(self, key: str, n: int, default: Any = None) -> np.ndarray:
        self.used.add(key)
        if key not in self.data:
            if default is None:
                raise ConfigError(f"{self._where(key)} is missing")
            return np.asarray(default, dtype=np.float64)
        v = self.data[key]
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise ConfigError(f"{self._where(key)} must be a list of {n} numbers, got {v!r}")
        return np.asarray(v, dtype=np.float64)

    def string(self, key: str, default: str | None = None, choices: tuple[str, ...] | None = None) -> str:
        self.used.add(key)
        if key not in self.data and default is not None:
            return default
        v = self.data.get(key)
        if not isinstance(v, str) or not v:
            raise ConfigError(f"{self._where(key)} must be a non-empty string, got {v!r}")
        if choices and v not in choices:
            raise ConfigError(f"{self._where(key)} must be one of {', '.join(choices)}, got {v!r}")
        return v

    def table(self, key: str) -> "_Table":
        self.used.add(key)
        return _Table(self.data.get(key, {}), f"{self.path}.{key}" if self.path else key, self.source)

    def tables(self, key: str) -> list["_Table"]:
        self.used.add(key)
        v = self.data.get(key, [])
        if not isinstance(v, list):
            raise ConfigError(f"{self._where(key)} must be an array of tables ([[{key}]])")
        name = f"{self.path}.{key}" if self.path else key
        return [_Table(item, f"{name}[{k}]", self.source) for k, item in enumerate(v)]

    def check_unknown(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            where = f"[{self.path}]" if self.path else "the top level"
            raise ConfigError(f"{self.source}: unknown key(s) in {where}: {', '.join(unknown)}")


def load_station(path: str | Path) -> Station:
    """Read a station TOML file (format: ``docs/planning.md``)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the station file ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not a station file: a binary file, not UTF-8 TOML text") from None
    return parse_station(text, str(p))


def parse_station(text: str, source: str = "<station>") -> Station:
    """Parse station TOML text (see :func:`load_station`)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: invalid TOML: {exc}") from None
    top = _Table(data, "", source)
    st, cam, tg, ct, cmm = (top.table(k) for k in ("station", "camera", "targets", "controls", "cmm"))

    # ---- the rig --------------------------------------------------------------------------
    size = cam.vector("image_size", 2)
    if np.any(size < 16) or np.any(size != np.round(size)):
        raise ConfigError(f"{source}: key 'camera.image_size' must be two integers >= 16, got {size.tolist()}")
    image_size = (int(size[0]), int(size[1]))
    pitch = cam.number("pixel_pitch_mm", minimum=0.0, strict=True)
    focal = cam.number("focal_length_mm", minimum=0.0, strict=True)
    baseline = cam.number("baseline_mm", minimum=0.0, strict=True)
    bdir = cam.vector("baseline_direction", 3, [0.0, 1.0, 0.0])
    if np.linalg.norm(bdir) == 0 or abs(bdir[2]) > 0.5 * np.linalg.norm(bdir):
        raise ConfigError(f"{source}: key 'camera.baseline_direction' must be a vector across the optical axis")
    bdir = bdir / np.linalg.norm(bdir)
    toe_in = math.radians(cam.number("toe_in_deg", 0.0))
    dist = cam.vector("distortion", 5, [0.0] * 5)
    f_px = focal / pitch
    K = np.array([[f_px, 0, (image_size[0] - 1) / 2], [0, f_px, (image_size[1] - 1) / 2], [0, 0, 1]])
    intr = CameraIntrinsics(K, dist, image_size)
    # Toe-in: the lower camera's axis turned towards the upper one's by toe_in about baseline x z.
    axis = np.cross(bdir, [0.0, 0.0, 1.0])
    R_lu = Rotation.from_rotvec(axis / np.linalg.norm(axis) * toe_in).as_matrix().T
    C_lower = baseline * bdir
    calibration = StereoCalibration(intr, intr, R_lu, -R_lu @ C_lower, source=source)
    noise = NoiseModel(cam.number("gain_dn_per_e", 0.35, minimum=0.0), cam.number("read_noise_dn", 2.5, minimum=0.0))
    blur = cam.number("blur_sigma_px", 0.9, minimum=0.0, strict=True)
    background = cam.number("background_dn", 150.0, minimum=0.0)
    efficiency = cam.number("centroid_efficiency", WEIGHTED_CENTROID_EFFICIENCY, minimum=1.0)
    centroid = cam.string("centroid", "weighted")
    cam.check_unknown()

    # ---- targets and controls (upper camera frame) ------------------------------------------
    radius = tg.number("radius_mm", minimum=0.0, strict=True)
    signal = tg.number("signal_dn", minimum=0.0, strict=True)
    distance = tg.number("working_distance_mm", minimum=0.0, strict=True)
    centre_xy = tg.vector("view_centre_mm", 2, [0.0, 0.0])
    centre = np.array([centre_xy[0], centre_xy[1], distance])
    perspective = tg.data.get("perspective_bias", True)
    tg.used.add("perspective_bias")
    if not isinstance(perspective, bool):
        raise ConfigError(f"{source}: key 'targets.perspective_bias' must be true or false, got {perspective!r}")
    bias_model = tg.string("bias_model", "eccentricity", choices=BIAS_MODELS)
    if bias_model == "rendered":
        from crossfield.errors import PluginError
        from crossfield.planning.image_bias import centroid_implementation

        try:
            centroid_implementation(centroid)
        except PluginError as exc:
            raise ConfigError(f"{source}: key 'camera.centroid': {exc}") from None
    target_ids, target_xyz, target_normal = [], [], []
    for t in tg.tables("point"):
        target_ids.append(t.string("id"))
        xyz = t.vector("xyz_mm", 3)
        target_xyz.append(xyz)
        normal = t.vector("normal", 3, -xyz / np.linalg.norm(xyz))
        if np.linalg.norm(normal) == 0:
            raise ConfigError(f"{source}: key '{t.path}.normal' is zero")
        target_normal.append(normal / np.linalg.norm(normal))
        t.check_unknown()
    tg.check_unknown()
    if not target_ids:
        raise ConfigError(f"{source}: no measured target: add [[targets.point]] tables (id, xyz_mm)")
    half = ct.vector("half_size_mm", 3, [80.0, 45.0, 18.0])
    if np.any(half < 0):
        raise ConfigError(f"{source}: key 'controls.half_size_mm' must be non-negative")
    explicit = ct.tables("point")
    ids_c = [t.string("id") for t in explicit]
    xyz_c = [t.vector("xyz_mm", 3) for t in explicit]
    for t in explicit:
        t.check_unknown()
    count = ct.integer("count", len(explicit) if explicit else None, minimum=3)
    ct.check_unknown()
    box = (tuple(centre), tuple(half))
    if count > len(explicit):
        extra = _halton_controls(count, box)[len(explicit):]
        ids_c += [f"C{k + 1}" for k in range(len(explicit), count)]
        xyz_c += list(extra)
    control_xyz = np.array(xyz_c[:count])
    ids_c = ids_c[:count]
    for label, ids in (("targets", target_ids), ("controls", ids_c)):
        if len(set(ids)) != len(ids):
            raise ConfigError(f"{source}: duplicate id among the {label}")
    target_xyz = np.array(target_xyz)

    # ---- the CMM and the reference elements (given in the upper camera frame, stored global) --
    sigma = cmm.number("sigma_mm", minimum=0.0)
    R_gc = Rotation.from_rotvec(cmm.vector("R_global_camera_rotvec", 3, [0.0, 0.0, 0.0])).as_matrix()
    t_gc = cmm.vector("t_global_camera_mm", 3, [0.0, 0.0, 0.0])
    cmm.check_unknown()
    to_global = lambda p: R_gc @ p + t_gc  # noqa: E731
    ref_points = {}
    for t in top.tables("reference_point"):
        ref_points[t.string("id")] = to_global(t.vector("xyz_mm", 3))
        t.check_unknown()
    lines = []
    for t in top.tables("reference_line"):
        lid = t.string("id")
        point = t.vector("point_mm", 3)
        direction = t.vector("direction", 3)
        if np.linalg.norm(direction) == 0:
            raise ConfigError(f"{source}: key 'reference_line.direction' of {lid} is zero")
        r_cyl = t.number("radius_mm", 15.0, minimum=0.0)
        heights = t.vector("probe_heights_mm", 3, [-25.0, 0.0, 25.0])
        angles = np.radians(t.vector("probe_angles_deg", 4, [20.0, 80.0, 140.0, 200.0]))
        ball = t.number("probe_ball_mm", 3.0, minimum=0.0) / 2
        fit = t.string("fit", "cylinder", ("cylinder", "line"))
        t.check_unknown()
        axis = Line3D(to_global(point), R_gc @ direction)
        from crossfield.simulator.scene import probe_ring_basis

        e1, e2 = probe_ring_basis(axis.direction)
        probes = np.array([
            axis.point + h * axis.direction + (r_cyl + ball) * (np.cos(a) * e1 + np.sin(a) * e2)
            for h in heights for a in angles
        ])
        lines.append(ReferenceLine(lid, axis, probes, fit))

    known_points = set(target_ids) | set(ids_c) | set(ref_points)
    known_lines = {line.id for line in lines}
    chars = []
    for t in top.tables("characteristic"):
        name = t.string("name")
        kind = t.string("kind", choices=KINDS)
        a = t.string("a")
        b = t.string("b") if kind != "depth" else None
        t.check_unknown()
        if a not in known_points:
            raise ConfigError(f"{source}: characteristic {name!r}: unknown point {a!r}")
        if kind == "point_point" and b not in known_points:
            raise ConfigError(f"{source}: characteristic {name!r}: unknown point {b!r}")
        if kind == "point_line" and b not in known_lines:
            raise ConfigError(f"{source}: characteristic {name!r}: unknown reference line {b!r}")
        chars.append(Characteristic(name, kind, a, b))
    if not chars:
        raise ConfigError(f"{source}: no [[characteristic]]: nothing to predict")
    frames = st.integer("frames", 10)
    k = st.number("coverage_factor", 2.0, minimum=0.0, strict=True)
    name = st.string("name", Path(source).stem)
    st.check_unknown()
    top.check_unknown()
    return Station(
        name=name, calibration=calibration, R_global_camera=R_gc, t_global_camera=t_gc,
        target_ids=tuple(target_ids), target_xyz=target_xyz, target_normal=np.array(target_normal),
        perspective_bias=perspective, bias_model=bias_model, centroid=centroid,
        control_ids=tuple(ids_c), control_xyz=control_xyz, control_normal=_facing(control_xyz),
        radius_mm=radius, signal_dn=signal, cmm_sigma_mm=sigma, reference_points=ref_points,
        reference_lines=tuple(lines), characteristics=tuple(chars), frames=frames, coverage_factor=k,
        blur_sigma_px=blur, noise=noise, background_dn=background, centroid_efficiency=efficiency,
        focal_length_mm=focal, pixel_pitch_mm=pitch, control_box=box, source=source,
    )
