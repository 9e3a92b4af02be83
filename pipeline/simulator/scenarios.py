"""Named scenarios: replicas of the paper's station (``docs/simulator.md``).

``station``: the paper's set-up (Figs. 1-2): 8 non-coplanar control targets
and the measured points 1 and 2 in the shared view of the upper/lower pair,
an out-of-view reference point R1 and the axis "line 3" (L3) of a cylinder
about 300 mm away, probed by the ROMER arm.

``table3``: the same rig with ten measured points P1..P10 whose true
distances to the axis L3 are the paper's Table 3 "actual sizes"
(303.1010 ... 311.5354 mm); the plan's nominals are those sizes with the
paper's 0.1 mm claim as the tolerance.

``camera-limited``: a scene where the camera, not the CMM, dominates: a
precise reference (0.001 mm per coordinate, as a laser tracker or a bridge
CMM gives), small 3 mm targets tilted up to 25 degrees at ~380 mm (so the
perspective eccentricity of their centres matters), stronger lens
distortion and a lower camera toed in by 2 degrees towards the upper
camera's view.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from crossfield.plan import parse_plan
from crossfield.simulator.optics import project
from crossfield.simulator.scene import Cylinder, Scene, Target
from crossfield.types import CameraIntrinsics, Line3D, StereoCalibration

__all__ = [
    "BASELINE_MM",
    "CYLINDER_RADIUS_MM",
    "DEFAULT_ARM_SIGMA_MM",
    "FOCAL_LENGTH_MM",
    "IMAGE_SIZE",
    "PIXEL_PITCH_MM",
    "SCENARIOS",
    "TABLE3_ACTUAL_MM",
    "TARGET_RADIUS_MM",
    "VIEW_CENTRE",
    "WORKING_DISTANCE_MM",
    "build_scene",
    "station_calibration",
]

SCENARIOS = ("station", "table3", "camera-limited")

#: Arm (reference) noise per coordinate (mm) of each scenario, when not given.
DEFAULT_ARM_SIGMA_MM = {"station": 0.01, "table3": 0.01, "camera-limited": 0.001}

#: Paper, Table 3, "Actual Size" column (mm).
TABLE3_ACTUAL_MM = (
    308.3500, 311.3778, 305.6009, 308.5791, 311.5354,
    305.8546, 308.7487, 303.1010, 305.9858, 308.8964,
)

IMAGE_SIZE = (1626, 1236)  # Basler scA1600-14gm, px
PIXEL_PITCH_MM = 0.0044  # 4.4 um
FOCAL_LENGTH_MM = 16.0
BASELINE_MM = 50.0  # lower camera below the upper one
WORKING_DISTANCE_MM = 400.0
TARGET_RADIUS_MM = 2.5
CYLINDER_RADIUS_MM = 15.0
VIEW_CENTRE = np.array([0.0, 25.0, WORKING_DISTANCE_MM])  # centre of the shared view, upper frame


def station_calibration() -> StereoCalibration:
    """The rig: two 16 mm lenses on 4.4 um sensors, parallel axes, 50 mm apart."""
    f_px = FOCAL_LENGTH_MM / PIXEL_PITCH_MM
    w, h = IMAGE_SIZE
    upper = CameraIntrinsics(
        np.array([[f_px, 0, (w - 1) / 2 + 3.2], [0, f_px * 1.0002, (h - 1) / 2 - 2.7], [0, 0, 1]]),
        np.array([-0.062, 0.14, 0.00021, -0.00013, 0.0]),
        IMAGE_SIZE,
    )
    lower = CameraIntrinsics(
        np.array([[f_px * 1.0011, 0, (w - 1) / 2 - 4.1], [0, f_px * 1.0013, (h - 1) / 2 + 1.9], [0, 0, 1]]),
        np.array([-0.058, 0.12, -0.00017, 0.00009, 0.0]),
        IMAGE_SIZE,
    )
    # Nearly parallel axes: a few mrad of residual rotation, as a real mount has.
    R_lower_upper = Rotation.from_rotvec([0.0021, -0.0015, 0.0009]).as_matrix()
    lower_centre_in_upper = np.array([0.35, BASELINE_MM, -0.25])
    t_lower_upper = -R_lower_upper @ lower_centre_in_upper  # p_lower = R (p_upper - C)
    return StereoCalibration(upper, lower, R_lower_upper, t_lower_upper, source="simulator")


def _in_view(calibration: StereoCalibration, p_upper: np.ndarray, margin_px: float) -> np.ndarray | None:
    """Blob centres (2, 2) in (upper, lower) if p is visible in both with margin."""
    out = []
    for name in ("upper", "lower"):
        intr = calibration.camera(name)
        P = p_upper if name == "upper" else calibration.R_lower_upper @ p_upper + calibration.t_lower_upper
        uv = project(P[None], intr)[0]
        w, h = intr.image_size
        if not (margin_px <= uv[0] <= w - 1 - margin_px and margin_px <= uv[1] <= h - 1 - margin_px):
            return None
        out.append(uv)
    return np.array(out)


def _layout_ok(
    candidate_uv: np.ndarray,
    placed_uv: list[np.ndarray],
    min_sep_px: float,
    disparity_px: tuple[float, float] = (300.0, 650.0),
) -> bool:
    """Reject crowding and epipolar ambiguity (same column in the other image).

    disparity_px: the range of v-disparity (upper minus lower row, px) over
    which two targets in nearly the same column could be confused."""
    for uv in placed_uv:
        for cam in (0, 1):
            if np.linalg.norm(candidate_uv[cam] - uv[cam]) < min_sep_px:
                return False
        # Near-vertical epipolar lines: two targets in nearly the same column
        # whose disparity-shifted rows coincide would be ambiguous matches.
        for a, b in ((candidate_uv, uv), (uv, candidate_uv)):
            if abs(a[0, 0] - b[1, 0]) < 25 and disparity_px[0] < a[0, 1] - b[1, 1] < disparity_px[1]:
                return False
    return True


def _place(
    rng: np.random.Generator,
    calibration: StereoCalibration,
    placed_uv: list[np.ndarray],
    z_range: tuple[float, float],
    adjust=None,
    min_sep_px: float = 95.0,
    tries: int = 20000,
    disparity_px: tuple[float, float] = (300.0, 650.0),
) -> np.ndarray:
    for _ in range(tries):
        p = np.array([rng.uniform(-80, 80), rng.uniform(-20, 70), rng.uniform(*z_range)])
        if adjust is not None:
            p = adjust(p)
        uv = _in_view(calibration, p, margin_px=60)
        if uv is not None and _layout_ok(uv, placed_uv, min_sep_px, disparity_px):
            placed_uv.append(uv)
            return p
    raise RuntimeError("scenario layout failed: no free place for a target")  # pragma: no cover


def _facing_normal(rng: np.random.Generator, p: np.ndarray, max_tilt_deg: float = 20.0) -> np.ndarray:
    towards_camera = -p / np.linalg.norm(p)
    tilt = Rotation.from_rotvec(np.radians(max_tilt_deg) * rng.uniform(-1, 1, 3) / np.sqrt(3))
    return tilt.apply(towards_camera)


def build_scene(
    name: str = "station", *, arm_sigma_mm: float | None = None, layout_seed: int = 20251122
) -> "Scene":
    """Build a named scenario (``station``, ``table3`` or ``camera-limited``).

    arm_sigma_mm: standard deviation of the simulated arm per coordinate
    (mm); None = the scenario's own (:data:`DEFAULT_ARM_SIGMA_MM`).
    layout_seed: fixes the geometry (not the noise).
    """
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; scenarios: {', '.join(SCENARIOS)}")
    if arm_sigma_mm is None:
        arm_sigma_mm = DEFAULT_ARM_SIGMA_MM[name]
    if name == "camera-limited":
        return _camera_limited_scene(arm_sigma_mm, layout_seed)
    rng = np.random.default_rng(layout_seed)
    calibration = station_calibration()
    # True pose of the camera in the CMM frame (T_global_camera).
    R_global_camera = Rotation.from_rotvec([0.55, -0.42, 2.35]).as_matrix()
    t_global_camera = np.array([842.6, -415.3, 318.9])

    # Axis of the cylinder ("line 3"), out of view ~308 mm from the view centre.
    axis_dir = np.array([0.25, -0.30, 0.92])
    axis_dir /= np.linalg.norm(axis_dir)
    radial = np.array([1.0, 0.8, 0.0])
    radial -= (radial @ axis_dir) * axis_dir
    radial /= np.linalg.norm(radial)
    axis_point_camera = VIEW_CENTRE - 308.0 * radial
    axis_camera = Line3D(axis_point_camera, axis_dir)

    placed: list[np.ndarray] = []
    targets: list[Target] = []

    def add_target(tid: str, p: np.ndarray) -> None:
        targets.append(Target(tid, p, _facing_normal(rng, p), TARGET_RADIUS_MM, rng.uniform(2600, 3300)))


    def on_shell(length_mm: float):
        def adjust(p: np.ndarray) -> np.ndarray:
            # Slide p along the radial direction until its distance to L3 is length_mm.
            return p + (length_mm - axis_camera.distance(p)) * _radial_from_axis(axis_camera, p)

        return adjust

    lengths = TABLE3_ACTUAL_MM if name == "table3" else (306.2, 309.7)
    for k, length in enumerate(lengths):
        add_target(f"P{k + 1}", _place(rng, calibration, placed, (392.0, 408.0), adjust=on_shell(length), min_sep_px=80.0))
    # Eight non-coplanar common control points (depth spread +-18 mm), placed
    # after the measured points, which are bound to their shells around L3.
    for k in range(8):
        add_target(f"C{k + 1}", _place(rng, calibration, placed, (382.0, 418.0), min_sep_px=80.0))

    to_global = lambda p: R_global_camera @ p + t_global_camera  # noqa: E731
    axis_global = Line3D(to_global(axis_camera.point), R_global_camera @ axis_camera.direction)
    cylinder = Cylinder(
        "L3", axis_global, CYLINDER_RADIUS_MM, probe_heights_mm=(-25.0, 0.0, 25.0),
        probe_angles_rad=tuple(np.radians([20.0, 80.0, 140.0, 200.0])),
    )
    r1_camera = VIEW_CENTRE + 300.0 * np.array([-0.30, 0.95, 0.08]) / np.linalg.norm([-0.30, 0.95, 0.08])
    reference_points = {"R1": to_global(r1_camera)}

    scene = Scene(
        name=name,
        calibration=calibration,
        R_global_camera=R_global_camera,
        t_global_camera=t_global_camera,
        targets=tuple(targets),
        reference_points_global=reference_points,
        cylinders=(cylinder,),
        plan=None,  # type: ignore[arg-type]  # set below, needs the truth
        arm_sigma_mm=arm_sigma_mm,
    )
    scene.plan = parse_plan(_plan_text(scene, name, rng), f"<scenario {name}>")
    return scene


# --------------------------------------------------------------------------
# camera-limited
# --------------------------------------------------------------------------

#: camera-limited: target radius (3 mm diameter), working distance, tilt limit, toe-in.
CL_TARGET_RADIUS_MM = 1.5
CL_WORKING_DISTANCE_MM = 380.0
CL_MAX_TILT_DEG = 25.0
CL_TOE_IN_DEG = 2.0
#: camera-limited: true lengths (mm) of the measured points P1..P6 to the axis L3.
CL_LENGTHS_MM = (304.20, 306.85, 309.40, 311.75, 305.30, 308.10)


def camera_limited_calibration() -> StereoCalibration:
    """The camera-limited rig: the station's lenses with stronger distortion
    (k1 ~ -0.13, k2 ~ 0.21, as a 16 mm C-mount lens has) and the lower camera
    toed in by :data:`CL_TOE_IN_DEG` about its x axis, looking up towards the
    upper camera's view (its optical axis tilted towards -y of the upper frame)."""
    f_px = FOCAL_LENGTH_MM / PIXEL_PITCH_MM
    w, h = IMAGE_SIZE
    upper = CameraIntrinsics(
        np.array([[f_px * 0.9994, 0, (w - 1) / 2 - 5.3], [0, f_px * 0.9991, (h - 1) / 2 + 4.1], [0, 0, 1]]),
        np.array([-0.131, 0.214, 0.00034, -0.00027, -0.05]),
        IMAGE_SIZE,
    )
    lower = CameraIntrinsics(
        np.array([[f_px * 1.0017, 0, (w - 1) / 2 + 6.2], [0, f_px * 1.0021, (h - 1) / 2 - 3.4], [0, 0, 1]]),
        np.array([-0.124, 0.197, -0.00029, 0.00041, -0.04]),
        IMAGE_SIZE,
    )
    # Lower optical axis in the upper frame: (0, -sin a, cos a), a = toe-in; R_x(-a) maps
    # upper-frame directions into the lower camera (p_lower = R (p_upper - C)), plus a few
    # mrad of mounting error about the other axes.
    toe = Rotation.from_rotvec([-np.radians(CL_TOE_IN_DEG), 0.0, 0.0])
    R_lower_upper = (Rotation.from_rotvec([0.0008, -0.0019, 0.0013]) * toe).as_matrix()
    lower_centre_in_upper = np.array([-0.42, BASELINE_MM, 0.31])
    t_lower_upper = -R_lower_upper @ lower_centre_in_upper
    return StereoCalibration(upper, lower, R_lower_upper, t_lower_upper, source="simulator camera-limited")


def _tilted_normal(rng: np.random.Generator, p: np.ndarray, max_tilt_deg: float) -> np.ndarray:
    """A unit normal tilted from facing the upper camera by an angle uniform in
    [0.4, 1] * max_tilt_deg, about a random axis perpendicular to the line of sight."""
    towards_camera = -p / np.linalg.norm(p)
    axis = np.cross(towards_camera, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    tilt = np.radians(rng.uniform(0.4 * max_tilt_deg, max_tilt_deg))
    return Rotation.from_rotvec(tilt * axis).apply(towards_camera)


def _camera_limited_scene(arm_sigma_mm: float, layout_seed: int) -> "Scene":
    name = "camera-limited"
    rng = np.random.default_rng([layout_seed, 11])
    calibration = camera_limited_calibration()
    R_global_camera = Rotation.from_rotvec([-0.31, 0.74, 1.92]).as_matrix()
    t_global_camera = np.array([615.4, 288.7, -142.2])
    view_centre = np.array([0.0, 25.0, CL_WORKING_DISTANCE_MM])
    axis_dir = np.array([-0.20, 0.35, 0.91])
    axis_dir /= np.linalg.norm(axis_dir)
    radial = np.array([0.9, -1.0, 0.0])
    radial -= (radial @ axis_dir) * axis_dir
    radial /= np.linalg.norm(radial)
    axis_camera = Line3D(view_centre - 307.0 * radial, axis_dir)

    placed: list[np.ndarray] = []
    targets: list[Target] = []
    # Rows of the toed-in pair: v-disparity ~ f b / z - f tan(toe) ~ 350 px at 380 mm.
    disparity = (200.0, 600.0)
    z_range = (CL_WORKING_DISTANCE_MM - 12.0, CL_WORKING_DISTANCE_MM + 12.0)

    def add_target(tid: str, p: np.ndarray) -> None:
        normal = _tilted_normal(rng, p, CL_MAX_TILT_DEG)
        targets.append(Target(tid, p, normal, CL_TARGET_RADIUS_MM, rng.uniform(2600, 3300)))

    def on_shell(length_mm: float):
        def adjust(p: np.ndarray) -> np.ndarray:
            return p + (length_mm - axis_camera.distance(p)) * _radial_from_axis(axis_camera, p)

        return adjust

    for k, length in enumerate(CL_LENGTHS_MM):
        p = _place(rng, calibration, placed, z_range, adjust=on_shell(length), min_sep_px=70.0, disparity_px=disparity)
        add_target(f"P{k + 1}", p)
    for k in range(8):
        p = _place(rng, calibration, placed, (z_range[0] - 8.0, z_range[1] + 8.0), min_sep_px=70.0, disparity_px=disparity)
        add_target(f"C{k + 1}", p)

    to_global = lambda p: R_global_camera @ p + t_global_camera  # noqa: E731
    axis_global = Line3D(to_global(axis_camera.point), R_global_camera @ axis_camera.direction)
    cylinder = Cylinder(
        "L3", axis_global, CYLINDER_RADIUS_MM, probe_heights_mm=(-25.0, 0.0, 25.0),
        probe_angles_rad=tuple(np.radians([20.0, 80.0, 140.0, 200.0])),
    )
    r1_camera = view_centre + 300.0 * np.array([0.35, -0.93, 0.10]) / np.linalg.norm([0.35, -0.93, 0.10])
    scene = Scene(
        name=name,
        calibration=calibration,
        R_global_camera=R_global_camera,
        t_global_camera=t_global_camera,
        targets=tuple(targets),
        reference_points_global={"R1": to_global(r1_camera)},
        cylinders=(cylinder,),
        plan=None,  # type: ignore[arg-type]  # set below, needs the truth
        arm_sigma_mm=arm_sigma_mm,
    )
    scene.plan = parse_plan(_plan_text(scene, name, rng), f"<scenario {name}>")
    return scene


def _radial_from_axis(axis: Line3D, p: np.ndarray) -> np.ndarray:
    v = p - axis.point
    v = v - (v @ axis.direction) * axis.direction
    return v / np.linalg.norm(v)


def _fmt(x: float) -> str:
    return repr(float(x))


def _plan_text(scene: Scene, name: str, rng: np.random.Generator) -> str:
    """The measurement plan that goes with the scenario, as TOML text.

    Target nominals are the true positions plus a design offset of a few
    hundredths of a mm (the part is never exactly nominal)."""
    truth = scene.ground_truth
    lines = [f'[plan]\nname = "simulator {name}"\n']
    for t in scene.targets:
        if t.id.startswith("C"):
            lines.append(f'[[control]]\nid = "{t.id}"\n')
    for t in scene.targets:
        if t.id.startswith("P"):
            nominal = truth.points_global[t.id] + rng.normal(0, 0.03, 3)
            lines.append(
                f'[[target]]\nid = "{t.id}"\nnominal = [{", ".join(_fmt(round(v, 3)) for v in nominal)}]\n'
                f"search_radius = 3.0\n"
            )
    for rid in scene.reference_points_global:
        lines.append(f'[[reference_point]]\nid = "{rid}"\n')
    for cyl in scene.cylinders:
        probes = len(cyl.probe_heights_mm) * len(cyl.probe_angles_rad)
        lines.append(f'[[reference_line]]\nid = "{cyl.id}"\nprobes = {probes}\nfit = "cylinder"\n')

    def characteristic(cname: str, kind: str, a: str, b: str | None, nominal: float, tol: float) -> None:
        b_line = f'b = "{b}"\n' if b else ""
        lines.append(
            f'[[characteristic]]\nname = "{cname}"\nkind = "{kind}"\na = "{a}"\n{b_line}'
            f"nominal = {_fmt(nominal)}\ntolerance = {_fmt(tol)}\n"
        )

    axis = truth.lines_global["L3"]
    if name == "table3":
        for k, actual in enumerate(TABLE3_ACTUAL_MM):
            characteristic(f"L{k + 1:02d}", "point_line", f"P{k + 1}", "L3", actual, 0.1)
    elif name == "camera-limited":
        for k, actual in enumerate(CL_LENGTHS_MM):
            characteristic(f"P{k + 1}-L3", "point_line", f"P{k + 1}", "L3", actual, 0.02)
        for a, b in (("P1", "P2"), ("P3", "P4"), ("P5", "P6"), ("P1", "P6")):
            pa, pb = truth.points_global[a], truth.points_global[b]
            characteristic(f"{a}-{b}", "point_point", a, b, round(float(np.linalg.norm(pa - pb)), 2), 0.02)
        characteristic("P1-R1", "point_point", "P1", "R1", round(float(np.linalg.norm(truth.points_global["P1"] - truth.points_global["R1"])), 2), 0.02)
    else:
        p1, p2 = truth.points_global["P1"], truth.points_global["P2"]
        characteristic("P1-L3", "point_line", "P1", "L3", round(axis.distance(p1), 1), 0.2)
        characteristic("P2-L3", "point_line", "P2", "L3", round(axis.distance(p2), 1), 0.2)
        characteristic("P1-P2", "point_point", "P1", "P2", round(float(np.linalg.norm(p1 - p2)), 1), 0.2)
        characteristic("P1-R1", "point_point", "P1", "R1", round(float(np.linalg.norm(p1 - truth.points_global["R1"])), 1), 0.2)
        characteristic("P1-depth", "depth", "P1", None, round(float(p1[2]), 1), 0.2)
        characteristic("P2-depth", "depth", "P2", None, round(float(p2[2]), 1), 0.2)
    return "\n".join(lines)
