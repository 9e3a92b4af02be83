"""The Cramér-Rao bound of the whole chain: centroid -> camera point ->
registration -> target point in the global frame (``docs/precision.md``).

:func:`image_radius_px` gives a target's image size, :func:`centroid_sigmas`
the centroid bound of every target in both cameras (each a call of
:func:`crossfield.precision.centroid.centroid_crb`), :func:`chain_bound` the
rest from arrays: camera-point covariances from the triangulation Jacobian,
the ML registration covariance from those and the CMM sigmas, and each
point's covariance in the global frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from crossfield.precision.centroid import NoiseModel, centroid_crb
from crossfield.precision.registration import global_point_covariance, registration_crb
from crossfield.precision.stereo import camera_point_covariance, project_stereo
from crossfield.types import StereoCalibration


def image_radius_px(
    calibration: StereoCalibration, X: np.ndarray, normals: np.ndarray, radius_mm: np.ndarray
) -> np.ndarray:
    """Equivalent image radius (N, 2) px of circular targets in (upper, lower).

    X, normals: (N, 3) upper camera frame (mm, unit); radius_mm: (N,). The
    image of a disc at distance d seen at tilt angle a is an ellipse of
    semi-axes ~ f r / d and f r cos(a) / d; the equivalent circle (same area)
    has radius ``f r sqrt(cos a) / d`` (f = mean focal length in px).
    """
    X = np.asarray(X, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    out = np.zeros((len(X), 2))
    for k, name in enumerate(("upper", "lower")):
        intr = calibration.camera(name)
        if name == "upper":
            Xc, nc = X, n
        else:
            Xc = X @ np.asarray(calibration.R_lower_upper).T + np.asarray(calibration.t_lower_upper)
            nc = n @ np.asarray(calibration.R_lower_upper).T
        d = np.linalg.norm(Xc, axis=1)
        cos_a = np.abs(np.sum(nc * Xc, axis=1)) / d
        f = 0.5 * (intr.camera_matrix[0, 0] + intr.camera_matrix[1, 1])
        out[:, k] = f * np.asarray(radius_mm) * np.sqrt(cos_a) / d
    return out


#: Image radii are interpolated between bounds computed at radii 1.02^k px (log-log, exact to ~1e-5).
_KNOT_RATIO = 1.02


@lru_cache(maxsize=8192)
def _crb_at_knot(k: int, blur: float, contrast: float, background: float, gain: float, read: float):
    b = centroid_crb(_KNOT_RATIO**k, blur, contrast, background, NoiseModel(gain, read), centre_px=(0.25, 0.25))
    return math.log(b.sigma_u_px), math.log(b.sigma_v_px)


def _crb_interpolated(radius_px: float, *args) -> tuple[float, float]:
    x = math.log(radius_px) / math.log(_KNOT_RATIO)
    k = math.floor(x)
    a, b = _crb_at_knot(k, *args), _crb_at_knot(k + 1, *args)
    f = x - k
    return math.exp((1 - f) * a[0] + f * b[0]), math.exp((1 - f) * a[1] + f * b[1])


def centroid_sigmas(
    radius_px: np.ndarray, blur_sigma_px: float, contrast_dn: np.ndarray, background_dn: float, noise: NoiseModel
) -> np.ndarray:
    """Centroid bounds (N, 4) px ``[u_upper, v_upper, u_lower, v_lower]`` for image radii (N, 2) px
    and contrasts (N,) DN: :func:`centroid_crb` at a disc centre (0.25, 0.25) px off a pixel
    centre, interpolated in log-log between radii 1.02^k px (computed once, cached)."""
    radius_px = np.asarray(radius_px, dtype=np.float64)
    contrast = np.broadcast_to(np.asarray(contrast_dn, dtype=np.float64), radius_px.shape[:1])
    out = np.zeros((len(radius_px), 4))
    for i in range(len(radius_px)):
        for k in range(2):
            out[i, 2 * k : 2 * k + 2] = _crb_interpolated(
                float(radius_px[i, k]), float(blur_sigma_px), float(contrast[i]),
                float(background_dn), float(noise.gain_dn_per_e), float(noise.read_noise_dn),
            )
    return out


@dataclass(frozen=True)
class ChainBound:
    """The chain's Cramér-Rao bound (all covariances first order).

    centroid_sigma_px: (N, 4) px, ``[u_upper, v_upper, u_lower, v_lower]``.
    camera_cov: (N, 3, 3) mm^2, upper camera frame.
    registration_cov: (6, 6) of (dtheta rad, dt mm) about ``g_bar`` (3,) mm, global.
    global_cov: (N, 3, 3) mm^2, every point mapped to the global frame (camera
    part plus registration part; for controls this is the mapped camera point).
    control_index: (C,) rows of the controls; cmm_sigma_mm: (C,).
    """

    centroid_sigma_px: np.ndarray
    camera_cov: np.ndarray
    registration_cov: np.ndarray
    g_bar: np.ndarray
    global_cov: np.ndarray
    control_index: np.ndarray
    cmm_sigma_mm: np.ndarray

    @property
    def camera_sigma_mm(self) -> np.ndarray:
        """(N, 3) standard deviations of the camera points (mm, upper frame axes)."""
        return np.sqrt(np.diagonal(self.camera_cov, axis1=1, axis2=2))

    @property
    def registration_sigma(self) -> np.ndarray:
        """(6,) standard deviations of (dtheta_x, dtheta_y, dtheta_z) rad and (dt) mm."""
        return np.sqrt(np.diag(self.registration_cov))

    @property
    def global_rms_mm(self) -> np.ndarray:
        """(N,) RMS 3-D error bound of each point in the global frame (sqrt trace)."""
        return np.sqrt(np.trace(self.global_cov, axis1=1, axis2=2))


def chain_bound(
    calibration: StereoCalibration,
    X_camera: np.ndarray,
    centroid_sigma_px: np.ndarray,
    control_index: np.ndarray,
    cmm_sigma_mm: np.ndarray,
    R_global_camera: np.ndarray,
    t_global_camera: np.ndarray,
) -> ChainBound:
    """The bound of every stage for points X_camera (N, 3) mm (upper frame).

    centroid_sigma_px: (N, 4) px; control_index: (C,) rows of X_camera that
    are common control points, probed by the CMM with sigma cmm_sigma_mm (C,)
    mm per coordinate; (R, t): the true T_global_camera.
    """
    X = np.asarray(X_camera, dtype=np.float64)
    R = np.asarray(R_global_camera, dtype=np.float64)
    _, J = project_stereo(calibration, X)
    cam_cov = camera_point_covariance(J, centroid_sigma_px)
    idx = np.asarray(control_index, dtype=int)
    sig = np.broadcast_to(np.asarray(cmm_sigma_mm, dtype=np.float64), idx.shape)
    Xg = X @ R.T + np.asarray(t_global_camera)
    S = R @ cam_cov[idx] @ R.T + sig[:, None, None] ** 2 * np.eye(3)
    reg_cov, g_bar = registration_crb(Xg[idx], S)
    glob = global_point_covariance(R, cam_cov, Xg, reg_cov, g_bar)
    return ChainBound(
        np.asarray(centroid_sigma_px, dtype=np.float64), cam_cov, reg_cov, g_bar, glob, idx, np.array(sig)
    )
