"""Frozen, typed data classes passed between the stages.

Conventions (``docs/conventions.md``):

* lengths in millimetres, angles in radians;
* image coordinates in pixels, (0, 0) at the centre of the top-left pixel
  (OpenCV convention), ``u`` to the right, ``v`` down;
* the camera frame is the upper camera's, OpenCV style (x right, y down,
  z forward); the global frame is the CMM reference frame;
* transforms are named by what they map: ``T_global_camera`` maps
  camera-frame points into the global frame, ``p_g = R @ p_c + t``.

Arrays inside these classes are treated as read-only; the constructors
make them so (``flags.writeable = False``) so that a plugin cannot alter
another stage's output in place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

__all__ = [
    "CAMERAS",
    "DEFAULT_SCALE_U",
    "STAGES",
    "CameraIntrinsics",
    "BudgetTerm",
    "CameraPoints",
    "CentroidSet",
    "CharacteristicResult",
    "Correspondence",
    "GroundTruth",
    "Line3D",
    "Measurement",
    "ProbedPoint",
    "ReferenceData",
    "Registration",
    "RejectedBlob",
    "RegistrationConsistency",
    "RigidFit",
    "StereoCalibration",
    "StereoCentroids",
    "StereoFrame",
    "frozen_array",
]

CAMERAS: tuple[str, str] = ("upper", "lower")

#: Relative scale uncertainty of a calibration that states none (1e-5 = 10 ppm,
#: 3 um over 300 mm; a good target-board calibration of a 50 mm baseline); the
#: budget's calibration term (crossfield.uncertainty.calibration) uses it.
DEFAULT_SCALE_U = 1.0e-5

#: The stages, in data-flow order (the config's tables, the registry hooks, :mod:`crossfield.stages`).
STAGES: tuple[str, ...] = (
    "acquire",
    "centroid",
    "triangulate",
    "reference",
    "register",
    "measure",
    "report",
)


def frozen_array(values, dtype=np.float64, shape: tuple[int | None, ...] | None = None) -> np.ndarray:
    """Return ``values`` as a read-only array of ``dtype``, checking ``shape``.

    ``None`` in ``shape`` matches any length on that axis.
    """
    array = np.array(values, dtype=dtype, copy=True)
    if shape is not None:
        have = array.shape
        ok = len(have) == len(shape)
        for k, want in enumerate(shape if ok else ()):  # a loop, not any(<generator>): on every stage result
            if want is not None and have[k] != want:
                ok = False
        if not ok:
            raise ValueError(f"expected an array of shape {shape}, got {array.shape}")
    array.flags.writeable = False
    return array


def _freeze(obj, name: str, dtype=np.float64, shape=None) -> None:
    object.__setattr__(obj, name, frozen_array(getattr(obj, name), dtype, shape))


# --------------------------------------------------------------------------
# Calibration and frames
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics with OpenCV's distortion model.

    camera_matrix: (3, 3) in pixels, ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
    dist_coeffs: (k,) OpenCV order ``k1 k2 p1 p2 [k3 ...]`` (unitless).
    image_size: (width, height) in pixels.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        _freeze(self, "camera_matrix", shape=(3, 3))
        _freeze(self, "dist_coeffs", shape=(None,))
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))


@dataclass(frozen=True)
class StereoCalibration:
    """Calibration of the upper/lower pair, as OpenCV's ``stereoCalibrate`` gives it.

    ``R_lower_upper`` (3, 3) and ``t_lower_upper`` (3,) in mm map upper-camera
    points into the lower camera: ``p_lower = R @ p_upper + t`` (OpenCV's R, T;
    the paper's Formula (4)).
    """

    upper: CameraIntrinsics
    lower: CameraIntrinsics
    R_lower_upper: np.ndarray
    t_lower_upper: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        _freeze(self, "R_lower_upper", shape=(3, 3))
        _freeze(self, "t_lower_upper", shape=(3,))

    def camera(self, name: str) -> CameraIntrinsics:
        """The intrinsics of camera ``name`` (``"upper"`` or ``"lower"``)."""
        if name not in CAMERAS:
            raise KeyError(f"unknown camera {name!r}; expected one of {CAMERAS}")
        return getattr(self, name)


@dataclass(frozen=True)
class StereoFrame:
    """One synchronised stereo pair.

    upper, lower: (height, width) uint16 images; pixel values are ``bit_depth``-bit
    digital numbers (DN) delivered in 16-bit words.
    timestamp_ns: capture time, nanoseconds since the Unix epoch.
    """

    sequence: int
    timestamp_ns: int
    upper: np.ndarray
    lower: np.ndarray
    bit_depth: int = 12

    def __post_init__(self) -> None:
        for name in CAMERAS:
            image = getattr(self, name)
            if not isinstance(image, np.ndarray) or image.ndim != 2:
                raise ValueError(f"{name} image must be a 2-D array, got {type(image).__name__}")
            if image.flags.writeable:
                image = image.view()
                image.flags.writeable = False
                object.__setattr__(self, name, image)

    def image(self, name: str) -> np.ndarray:
        if name not in CAMERAS:
            raise KeyError(f"unknown camera {name!r}; expected one of {CAMERAS}")
        return getattr(self, name)


# --------------------------------------------------------------------------
# Centroids
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class RejectedBlob:
    """A blob that was found but is not target-like.

    uv: (2,) approximate centre in pixels. reason: short machine-readable
    reason (``"too_small"``, ``"too_large"``, ``"not_round"``, ``"saturated"``,
    ``"touches_border"``, ...).
    """

    uv: tuple[float, float]
    reason: str


@dataclass(frozen=True)
class CentroidSet:
    """Target centroids found in one image.

    uv: (N, 2) sub-pixel centres in pixels (OpenCV convention).
    sigma_uv: (N, 2) standard uncertainty of u and v in pixels.
    area_px: (N,) blob area in pixels. roundness: (N,) minor/major axis ratio
    (1 = circle). peak: (N,) highest background-subtracted value in DN.
    ellipse: optional (N, 3) edge conic of each target, ``(s_uu, s_uv, s_vv)``
    in px^-2: the edge is ``d^T S d = 1`` with d = (u, v) - uv and
    S = [[s_uu, s_uv], [s_uv, s_vv]] (distorted image pixels, blur removed),
    for the perspective-eccentricity correction; None when the implementation
    does not fit one. ellipse_cov: optional (N, 3, 3) its covariance (px^-4).
    """

    camera: str
    sequence: int
    uv: np.ndarray
    sigma_uv: np.ndarray
    area_px: np.ndarray
    roundness: np.ndarray
    peak: np.ndarray
    rejected: tuple[RejectedBlob, ...] = ()
    method: str = ""
    ellipse: np.ndarray | None = None
    ellipse_cov: np.ndarray | None = None

    def __post_init__(self) -> None:
        _freeze(self, "uv", shape=(None, 2))
        n = len(self.uv)
        _freeze(self, "sigma_uv", shape=(n, 2))
        _freeze(self, "area_px", shape=(n,))
        _freeze(self, "roundness", shape=(n,))
        _freeze(self, "peak", shape=(n,))
        if self.ellipse is not None:
            _freeze(self, "ellipse", shape=(n, 3))
        if self.ellipse_cov is not None:
            if self.ellipse is None:
                raise ValueError("ellipse_cov given without ellipse")
            _freeze(self, "ellipse_cov", shape=(n, 3, 3))

    def __len__(self) -> int:
        return len(self.uv)


@dataclass(frozen=True)
class StereoCentroids:
    sequence: int
    upper: CentroidSet
    lower: CentroidSet


# --------------------------------------------------------------------------
# Triangulation
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraPoints:
    """Triangulated target centres in the (upper) camera frame.

    xyz: (N, 3) mm, camera frame. sigma_xyz: (N, 3) mm standard uncertainty
    per axis (propagated from the centroid uncertainties).
    upper_index, lower_index: (N,) indices into the two CentroidSets.
    residual_px: (N,) RMS reprojection residual over both images, pixels.
    rejected: reasons for centroids that were not triangulated
    (e.g. ``"upper[3]: ambiguous (2 candidates)"``).
    cov_xyz: optional (N, 3, 3) mm^2 full covariance of each point, camera
    frame (the stereo depth error is along the line of sight, not an axis);
    its diagonal is sigma_xyz^2. None when the implementation gives axes only.
    chi2: optional (N,) weighted residual sum of squares of each point,
    ``sum_k r_k^2 / sigma_k^2`` over its four image coordinates (1 degree of
    freedom: E = 1 when the centroids' sigma_uv are right); the Type A
    evidence on the camera term (``crossfield.uncertainty.type_a``).
    """

    sequence: int
    xyz: np.ndarray
    sigma_xyz: np.ndarray
    upper_index: np.ndarray
    lower_index: np.ndarray
    residual_px: np.ndarray
    rejected: tuple[str, ...] = ()
    method: str = ""
    cov_xyz: np.ndarray | None = None
    chi2: np.ndarray | None = None

    def __post_init__(self) -> None:
        _freeze(self, "xyz", shape=(None, 3))
        n = len(self.xyz)
        _freeze(self, "sigma_xyz", shape=(n, 3))
        _freeze(self, "upper_index", dtype=np.int64, shape=(n,))
        _freeze(self, "lower_index", dtype=np.int64, shape=(n,))
        _freeze(self, "residual_px", shape=(n,))
        if self.cov_xyz is not None:
            _freeze(self, "cov_xyz", shape=(n, 3, 3))
        if self.chi2 is not None:
            _freeze(self, "chi2", shape=(n,))

    def __len__(self) -> int:
        return len(self.xyz)


# --------------------------------------------------------------------------
# CMM reference data
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ProbedPoint:
    """One point taken with the CMM arm's probe button, in the global frame.

    xyz: (3,) probe-ball centre in mm. sigma_mm: standard uncertainty per
    coordinate in mm. label: the measurement plan's name for this probe
    (``"C1"``, ``"L3.4"``...), from the plan's probing order.
    device_sequence / device_time_s: as sent by the device.
    probe_vector: (3,) unit approach direction. probe_diameter_mm: ball diameter.
    """

    label: str
    xyz: np.ndarray
    sigma_mm: float
    device_sequence: int = -1
    device_time_s: float = float("nan")
    probe_vector: np.ndarray = field(default_factory=lambda: np.zeros(3))
    probe_diameter_mm: float = float("nan")

    def __post_init__(self) -> None:
        _freeze(self, "xyz", shape=(3,))
        _freeze(self, "probe_vector", shape=(3,))


@dataclass(frozen=True)
class ReferenceData:
    """What the reference stage imported.

    points: probed points in import order, labelled from the plan.
    problems: one human-readable line per input line or message that was
    rejected, naming it (``"line 7: bad checksum ..."``); the good points are
    kept.
    source: where the data came from (port URL, file path).
    """

    points: tuple[ProbedPoint, ...]
    problems: tuple[str, ...] = ()
    source: str = ""

    def by_label(self) -> dict[str, ProbedPoint]:
        return {p.label: p for p in self.points}

    def labelled(self, prefix: str) -> list[ProbedPoint]:
        """Points whose label is ``prefix`` or starts with ``prefix + "."``."""
        return [p for p in self.points if p.label == prefix or p.label.startswith(prefix + ".")]


# --------------------------------------------------------------------------
# Registration
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class RigidFit:
    """A rigid transform fitted to corresponding point pairs.

    R: (3, 3) rotation (det = +1), t: (3,) mm, so that ``q ~ R @ p + t``.
    residuals: (N, 3) mm, ``R @ p_i + t - q_i``. rms_mm: sqrt(mean |residual|^2).
    covariance: optional (6, 6) covariance of the pose error (omega, tau),
    rad and mm, where the true pose is ``p_g = exp([omega]x) (R p + t) + tau``
    (a small rotation and translation applied in the global frame); None
    when the implementation does not state one. chi2: optional weighted sum
    of squared residuals at the solution (dimensionless, ~ chi-square with
    3N - 6 degrees of freedom when the stated covariances are right).
    """

    R: np.ndarray
    t: np.ndarray
    residuals: np.ndarray
    rms_mm: float
    method: str = ""
    scale: float = 1.0
    covariance: np.ndarray | None = None
    chi2: float | None = None

    def __post_init__(self) -> None:
        _freeze(self, "R", shape=(3, 3))
        _freeze(self, "t", shape=(3,))
        _freeze(self, "residuals", shape=(None, 3))
        if self.covariance is not None:
            _freeze(self, "covariance", shape=(6, 6))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) points: ``scale * R @ p + t``."""
        return self.scale * np.asarray(points, dtype=np.float64) @ self.R.T + self.t


@dataclass(frozen=True)
class Correspondence:
    """Pairs of camera points and CMM control points.

    camera_index: (M,) indices into CameraPoints; control_ids: (M,) plan ids.
    unmatched_camera: camera-point indices left over (e.g. target points, strays).
    unmatched_control: control ids not seen by the cameras.
    """

    camera_index: np.ndarray
    control_ids: tuple[str, ...]
    unmatched_camera: tuple[int, ...] = ()
    unmatched_control: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _freeze(self, "camera_index", dtype=np.int64, shape=(None,))
        if len(self.camera_index) != len(self.control_ids):
            raise ValueError("camera_index and control_ids differ in length")


@dataclass(frozen=True)
class Registration:
    """``T_global_camera`` for one frame, with its evidence.

    fit.R, fit.t map camera-frame points to the global frame (Formulas (5)-(9)).
    fit.residuals[i] belongs to correspondence.control_ids[i].
    """

    sequence: int
    fit: RigidFit
    correspondence: Correspondence

    @property
    def R_global_camera(self) -> np.ndarray:
        return self.fit.R

    @property
    def t_global_camera(self) -> np.ndarray:
        return self.fit.t


# --------------------------------------------------------------------------
# Measurement
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class BudgetTerm:
    """One line of an uncertainty budget (GUM 5.1.3, JCGM 100 eq. (10)).

    source: what the input is (``crossfield.uncertainty.budget.SOURCES``).
    u: the input's standard uncertainty in ``unit`` (mm, K, 1 for a relative
    scale). sensitivity: the characteristic's change per unit of the input
    (mm per ``unit``; for a source made of several correlated inputs, such as
    the control points through the shared registration, the effective one,
    ``u_mm / u``). u_mm: the contribution ``|sensitivity| * u`` (mm); the
    contributions of the sources add in quadrature to the combined standard
    uncertainty (the sources are independent of each other). dof: the degrees
    of freedom of ``u`` (GUM G.3; infinite for a stated value), which the
    Welch-Satterthwaite coverage factor uses (``crossfield.uncertainty.dof``).
    """

    source: str
    u: float
    unit: str
    sensitivity: float
    u_mm: float
    dof: float = math.inf


@dataclass(frozen=True, eq=False)
class RegistrationConsistency:
    """What one frame's registration residuals say about the stated sigmas, and the
    pose covariance those sigmas give.

    observed_ss_mm2: ``sum_k |r_k|^2`` of the fit residuals (mm^2);
    expected_camera_ss_mm2 / expected_cmm_ss_mm2: its expectation under the
    stated camera and CMM sigmas, ``(1 - 6 / 3n) sum_k tr S_k`` split by
    source (mm^2); dof: ``3n - 6`` for n matched controls.
    expected_residual_mm: control id -> expected RMS of |r_k| (mm),
    ``sqrt((1 - 2 / n) tr S_k)``.
    pose_cov_camera / pose_cov_cmm: (6, 6) covariance of the pose's small
    rotation (rad, rotation vector in the global frame) and of the translation
    t_global_camera (mm), from the camera-side and the CMM sigmas.
    epipolar_chi2 / epipolar_count: the sum of the matched points' ``chi2``
    (``CameraPoints.chi2``) and how many points it sums (0: no such evidence);
    expected_camera_ss_mm2 is the model's, not scaled by that evidence.
    """

    observed_ss_mm2: float
    expected_camera_ss_mm2: float
    expected_cmm_ss_mm2: float
    dof: int
    expected_residual_mm: Mapping[str, float] = field(default_factory=dict)
    pose_cov_camera: np.ndarray | None = None
    pose_cov_cmm: np.ndarray | None = None
    epipolar_chi2: float = 0.0
    epipolar_count: int = 0


@dataclass(frozen=True)
class CharacteristicResult:
    """One evaluated characteristic of the measurement plan.

    All values in mm. deviation_mm = measured_mm - nominal_mm.
    actual_mm / error_mm are set only where ground truth is known
    (simulator): error_mm = measured_mm - actual_mm.
    uncertainty_mm: standard uncertainty of measured_mm propagated from the
    camera points and the registration, where the plugin can state one.
    budget: its per-source split (:class:`BudgetTerm`; the squares of the
    ``u_mm`` add up to ``uncertainty_mm**2``); empty when not stated.
    """

    name: str
    kind: str
    measured_mm: float
    nominal_mm: float
    tolerance_mm: float
    deviation_mm: float
    passed: bool
    uncertainty_mm: float | None = None
    actual_mm: float | None = None
    error_mm: float | None = None
    elements: tuple[str, ...] = ()
    budget: tuple[BudgetTerm, ...] = ()


@dataclass(frozen=True)
class Measurement:
    """Characteristics of one frame.

    target_points: plan id -> (3,) global position in mm of each target found.
    missing_targets: plan ids with no camera point within their search radius.
    consistency: the registration residuals against the stated sigmas
    (:class:`RegistrationConsistency`), None when not evaluated.
    """

    sequence: int
    characteristics: tuple[CharacteristicResult, ...]
    target_points: Mapping[str, tuple[float, float, float]]
    missing_targets: tuple[str, ...] = ()
    consistency: RegistrationConsistency | None = None


# --------------------------------------------------------------------------
# Ground truth (simulator only)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Line3D:
    """An infinite line: point (3,) mm on it and unit direction (3,)."""

    point: np.ndarray
    direction: np.ndarray

    def __post_init__(self) -> None:
        _freeze(self, "point", shape=(3,))
        d = np.asarray(self.direction, dtype=np.float64)
        object.__setattr__(self, "direction", frozen_array(d / np.linalg.norm(d), shape=(3,)))

    def distance(self, p: np.ndarray) -> float:
        """Orthogonal distance in mm from point p (3,) to this line."""
        v = np.asarray(p, dtype=np.float64) - self.point
        return float(np.linalg.norm(v - (v @ self.direction) * self.direction))


@dataclass(frozen=True)
class GroundTruth:
    """The simulator's true geometry, for tests and the report's error column.

    points_global: id -> (3,) true global position (mm) of every control
    target, measured target and reference point.
    lines_global: id -> true reference line (e.g. the cylinder axis "L3").
    R_global_camera, t_global_camera: the true camera pose.
    """

    points_global: Mapping[str, np.ndarray]
    lines_global: Mapping[str, Line3D]
    R_global_camera: np.ndarray
    t_global_camera: np.ndarray

    def camera_points(self, ids) -> np.ndarray:
        """True camera-frame positions (N, 3) mm of the given point ids."""
        P = np.array([self.points_global[i] for i in ids], dtype=np.float64)
        return (P - self.t_global_camera) @ self.R_global_camera
