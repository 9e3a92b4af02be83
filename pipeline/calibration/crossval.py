"""Cross-validation: two calibrations from disjoint halves of the views, compared against their uncertainty.

mrcal's test of a calibration (mrcal docs, "Cross-validation"): calibrate
twice from independent data; the two must agree to within the uncertainty
each states. If they differ by more, the stated uncertainty is too small:
the model does not fit (lens, board), or the views do not constrain it.

Two differences, each with its predicted 1-sigma, first order in both
calibrations' covariances (independent halves: Sigma_d = J_A Sigma_A J_A^T +
J_B Sigma_B J_B^T, the Jacobians by central differences):

* projection: a grid of pixels of each camera, cast out with calibration A
  to the working distance (along the upper camera's z, mm), projected back
  with B (the lower camera's points pass through both rigs), difference px;
* 3-D point: a grid of points at the working distance in the upper frame,
  projected into both cameras with A and triangulated with B, difference mm.

Each difference is a vector (2 px, 3 mm) with a covariance C: its size
against C is the Mahalanobis norm ``m = sqrt(d^T C^-1 d)``, chi-distributed
with 2 (3) degrees of freedom when C is right. The ratios reported are m on
the scale of one normal variable (:func:`normal_equivalent`: the z with
the same tail probability), so "within 2 sigma" holds with 95.4 % for every
point as for a scalar. (Until issue 28's third round the ratio was |d|
over the std along d: for a 2-D difference that exceeds 2 with 13.5 %
probability, for three per-axis tests of a point with ~13 %, not 4.6 %.)

Parameters: the camera + rig vector of ``covariance.camera_param_names``
(fx fy cx cy D per camera, rotation vector rad, T mm).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import stats

from crossfield.types import CameraIntrinsics, StereoCalibration

_CRIT = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def params_of(calibration: StereoCalibration) -> np.ndarray:
    """The camera + rig vector (2 (4 + n_dist) + 6,) of a calibration."""
    out = []
    for cam in (calibration.upper, calibration.lower):
        K = np.asarray(cam.camera_matrix)
        out += [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(cam.dist_coeffs).ravel()]
    out += [*cv2.Rodrigues(np.asarray(calibration.R_lower_upper, float))[0].ravel()]
    out += [*np.asarray(calibration.t_lower_upper, float).ravel()]
    return np.array(out, float)


def calibration_of(theta: np.ndarray, like: StereoCalibration) -> StereoCalibration:
    """The calibration with parameters ``theta`` (image sizes and distortion length of ``like``)."""
    n = 4 + len(like.upper.dist_coeffs)
    cams = []
    for i, ref in enumerate((like.upper, like.lower)):
        p = theta[i * n : (i + 1) * n]
        K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        cams.append(CameraIntrinsics(K, p[4:].copy(), ref.image_size))
    R = cv2.Rodrigues(theta[2 * n : 2 * n + 3].reshape(3, 1))[0]
    return StereoCalibration(cams[0], cams[1], R, theta[2 * n + 3 : 2 * n + 6].copy(), source=like.source)


def _unproject(cam: CameraIntrinsics, uv: np.ndarray, depth_mm: float) -> np.ndarray:
    xy = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), np.asarray(cam.camera_matrix), np.asarray(cam.dist_coeffs), criteria=_CRIT
    ).reshape(-1, 2)
    return np.column_stack([xy * depth_mm, np.full(len(xy), depth_mm)])


def _project(cam: CameraIntrinsics, X: np.ndarray) -> np.ndarray:
    uv, _ = cv2.projectPoints(
        X.reshape(-1, 1, 3),
        np.zeros(3),
        np.zeros(3),
        np.asarray(cam.camera_matrix),
        np.asarray(cam.dist_coeffs),
    )
    return uv.reshape(-1, 2)


def projection_difference(
    a: StereoCalibration, b: StereoCalibration, camera: str, grid_px: np.ndarray, depth_mm: float
) -> np.ndarray:
    """(N, 2) px: pixels cast out with ``a`` to ``depth_mm`` and projected with ``b``, minus the pixels."""
    if camera == "upper":
        X = _unproject(a.upper, grid_px, depth_mm)
        return _project(b.upper, X) - grid_px
    X_lower_a = _unproject(a.lower, grid_px, depth_mm)
    R_a, T_a = np.asarray(a.R_lower_upper), np.asarray(a.t_lower_upper)
    X_upper = (X_lower_a - T_a) @ R_a  # R^T (p - T)
    X_lower_b = X_upper @ np.asarray(b.R_lower_upper).T + np.asarray(b.t_lower_upper)
    return _project(b.lower, X_lower_b) - grid_px


def triangulate(calibration: StereoCalibration, uv_upper: np.ndarray, uv_lower: np.ndarray) -> np.ndarray:
    """(N, 3) upper-frame points (mm) from pixel pairs: DLT (Hartley & Zisserman 12.2) on undistorted points."""
    x1 = cv2.undistortPoints(
        uv_upper.reshape(-1, 1, 2),
        np.asarray(calibration.upper.camera_matrix),
        np.asarray(calibration.upper.dist_coeffs),
        criteria=_CRIT,
    ).reshape(-1, 2)
    x2 = cv2.undistortPoints(
        uv_lower.reshape(-1, 1, 2),
        np.asarray(calibration.lower.camera_matrix),
        np.asarray(calibration.lower.dist_coeffs),
        criteria=_CRIT,
    ).reshape(-1, 2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack(
        [np.asarray(calibration.R_lower_upper), np.asarray(calibration.t_lower_upper).reshape(3, 1)]
    )
    Xh = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
    return (Xh[:3] / Xh[3]).T


def point_difference(a: StereoCalibration, b: StereoCalibration, points_mm: np.ndarray) -> np.ndarray:
    """(N, 3) mm: upper-frame points projected into both cameras with ``a``, triangulated with ``b``, minus them."""
    uv1 = _project(a.upper, points_mm)
    X_l = points_mm @ np.asarray(a.R_lower_upper).T + np.asarray(a.t_lower_upper)
    uv2 = _project(a.lower, X_l)
    return triangulate(b, uv1, uv2) - points_mm


def _difference_covariance(f: Callable[[np.ndarray, np.ndarray], np.ndarray], theta_a, cov_a, theta_b, cov_b):
    """Per-row covariance (N, k, k) of f(theta_a, theta_b) (N, k): J_A S_A J_A^T + J_B S_B J_B^T."""
    out = 0.0
    for which, theta, cov in ((0, theta_a, cov_a), (1, theta_b, cov_b)):
        std = np.sqrt(np.diag(cov))
        cols = []
        for i in range(len(theta)):
            h = 1e-2 * std[i] if std[i] > 0 else 1e-9
            tp, tm = theta.copy(), theta.copy()
            tp[i] += h
            tm[i] -= h
            args_p = (tp, theta_b) if which == 0 else (theta_a, tp)
            args_m = (tm, theta_b) if which == 0 else (theta_a, tm)
            cols.append((f(*args_p) - f(*args_m)) / (2 * h))
        J = np.stack(cols, axis=-1)  # (N, k, p)
        out = out + np.einsum("nip,pq,njq->nij", J, cov, J)
    return out


def normal_equivalent(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,) the Mahalanobis norms of d (N, k) under cov (N, k, k), as standard normal deviates.

    m^2 = d^T C^-1 d is chi^2 with k degrees of freedom; the result is the z
    with P(|N(0, 1)| > z) = P(chi^2_k > m^2) (z = m for k = 1).
    """
    m2 = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[..., None])[..., 0])
    return stats.norm.isf(stats.chi2.sf(m2, d.shape[1]) / 2)


@dataclass(frozen=True)
class CrossValidation:
    """Two half calibrations compared (module docstring).

    halves: the view indices of each half. grid_px[cam]: (N, 2) pixels;
    diff_px[cam]: (N, 2) px; sigma_px[cam]: (N,) the predicted 1-sigma of
    the difference along its own direction (px); cov_px[cam] (N, 2, 2) its
    covariance (px^2). points_mm (M, 3) upper frame at ``depth_mm``; diff_mm
    (M, 3); sigma_mm (M, 3) per axis (mm); cov_mm (M, 3, 3) (mm^2).
    """

    halves: tuple[tuple[int, ...], tuple[int, ...]]
    depth_mm: float
    grid_px: dict[str, np.ndarray]
    diff_px: dict[str, np.ndarray]
    sigma_px: dict[str, np.ndarray]
    points_mm: np.ndarray
    diff_mm: np.ndarray
    sigma_mm: np.ndarray
    cov_px: dict[str, np.ndarray]
    cov_mm: np.ndarray

    def projection_ratio(self, camera: str) -> np.ndarray:
        """(N,) per grid pixel the difference's Mahalanobis norm in normal sigma (:func:`normal_equivalent`)."""
        return normal_equivalent(self.diff_px[camera], self.cov_px[camera])

    def point_ratio(self) -> np.ndarray:
        """(M,) per 3-D point the difference's Mahalanobis norm in normal sigma."""
        return normal_equivalent(self.diff_mm, self.cov_mm)

    def within(self, k: float = 2.0) -> dict[str, float]:
        """Share of the grid within k sigma: per camera's projection and for the 3-D points."""
        out = {cam: float(np.mean(self.projection_ratio(cam) <= k)) for cam in self.diff_px}
        out["points"] = float(np.mean(self.point_ratio() <= k))
        return out

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary and grids."""
        return {
            "halves": [list(h) for h in self.halves],
            "depth_mm": self.depth_mm,
            "within_2_sigma": self.within(2.0),
            "projection": {
                cam: {
                    "grid_px": np.round(self.grid_px[cam], 2).tolist(),
                    "diff_px": np.round(self.diff_px[cam], 5).tolist(),
                    "sigma_px": np.round(self.sigma_px[cam], 5).tolist(),
                    "max_diff_px": float(np.max(np.linalg.norm(self.diff_px[cam], axis=1))),
                    "max_ratio": float(np.max(self.projection_ratio(cam))),
                }
                for cam in self.diff_px
            },
            "points": {
                "points_mm": np.round(self.points_mm, 3).tolist(),
                "diff_mm": np.round(self.diff_mm, 6).tolist(),
                "sigma_mm": np.round(self.sigma_mm, 6).tolist(),
                "max_diff_mm": float(np.max(np.linalg.norm(self.diff_mm, axis=1))),
                "max_ratio": float(np.max(self.point_ratio())),
            },
        }


def compare(
    a: StereoCalibration,
    cov_a: np.ndarray,
    b: StereoCalibration,
    cov_b: np.ndarray,
    *,
    halves: tuple[tuple[int, ...], tuple[int, ...]] = ((), ()),
    depth_mm: float = 400.0,
    grid: tuple[int, int] = (9, 7),
    margin: float = 0.05,
) -> CrossValidation:
    """Compare two calibrations of the same rig with covariances (p, p) of ``params_of`` order."""
    ta, tb = params_of(a), params_of(b)
    if cov_a.shape != (len(ta), len(ta)) or cov_b.shape != (len(tb), len(tb)):
        raise ValueError(f"covariances must be {len(ta)} x {len(ta)} (camera + rig parameters)")
    grids, diffs, sigmas, covs = {}, {}, {}, {}
    for cam in ("upper", "lower"):
        w, h = a.camera(cam).image_size
        gu, gv = np.meshgrid(
            np.linspace(margin, 1 - margin, grid[0]) * (w - 1),
            np.linspace(margin, 1 - margin, grid[1]) * (h - 1),
        )
        g = np.column_stack([gu.ravel(), gv.ravel()])
        f = lambda x, y, cam=cam, g=g: projection_difference(
            calibration_of(x, a), calibration_of(y, b), cam, g, depth_mm
        )
        d = f(ta, tb)
        C = _difference_covariance(f, ta, cov_a, tb, cov_b)
        u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        grids[cam], diffs[cam], covs[cam] = g, d, C
        sigmas[cam] = np.sqrt(np.einsum("ni,nij,nj->n", u, C, u))
    w, h = a.upper.image_size
    gu, gv = np.meshgrid(np.linspace(0.15, 0.85, 5) * (w - 1), np.linspace(0.15, 0.85, 5) * (h - 1))
    P = _unproject(a.upper, np.column_stack([gu.ravel(), gv.ravel()]), depth_mm)
    fp = lambda x, y: point_difference(calibration_of(x, a), calibration_of(y, b), P)
    dX = fp(ta, tb)
    CX = _difference_covariance(fp, ta, cov_a, tb, cov_b)
    sigma_mm = np.sqrt(np.einsum("nii->ni", CX))
    return CrossValidation(halves, depth_mm, grids, diffs, sigmas, P, dX, sigma_mm, covs, CX)


def split_views(views: tuple[int, ...]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Two interleaved halves (even and odd positions): each spans the session's poses and depths."""
    return tuple(views[0::2]), tuple(views[1::2])


def summary_line(cv: CrossValidation) -> str:
    """One line for the terminal: the halves' largest differences and their share within 2 sigma."""
    d = cv.as_dict()
    w = d["within_2_sigma"]
    return (
        f"cross-validation ({len(cv.halves[0])} + {len(cv.halves[1])} views): projection difference max "
        f"upper {d['projection']['upper']['max_diff_px']:.3f} px ({d['projection']['upper']['max_ratio']:.2f} sigma), "
        f"lower {d['projection']['lower']['max_diff_px']:.3f} px ({d['projection']['lower']['max_ratio']:.2f} sigma); "
        f"3-D at {cv.depth_mm:.0f} mm max {d['points']['max_diff_mm'] * 1000:.1f} um "
        f"({d['points']['max_ratio']:.2f} sigma); within 2 sigma: upper {w['upper']:.0%}, lower {w['lower']:.0%}, "
        f"points {w['points']:.0%}"
    )
