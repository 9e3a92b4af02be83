"""Step 6 of the calibration: the joint bundle adjustment, the board's bow, honest standard deviations.

After OpenCV's stereo solution (``calibrate.solve_stereo`` steps 2-5):

1. :func:`crossfield.calibration.joint.refine_joint` over every corner each
   camera saw in the stereo views (not only the common ones), with the
   board's bow (mrcal's ``calobject_warp``) when ``settings.estimate_warp``
   and at least ``WARP_MIN_VIEWS`` views; then, as mrcal does, the outlier
   corners (``joint.outlier_corners``: a coordinate beyond 5 sigma starts a
   round that drops those beyond 4 sigma) are dropped and the problem solved
   again, until a solve marks none (``MAX_REJECTION_ROUNDS`` at most); then
   (``weight_views``) each view and camera weighted by its own corner noise
   (:func:`view_weights`), solved again, and the rejection once more;
2. the Jacobian covariance sigma^2 (J^T J)^-1 (Hartley & Zisserman 5.2.3),
   the board poses marginalised;
3. the jackknife over views (:mod:`crossfield.calibration.jackknife`) when
   there are at least ``JACKKNIFE_MIN_VIEWS`` views; the stated covariance is
   the Jacobian's with each std raised to the larger of the two;
4. the residual maps per camera (:mod:`crossfield.calibration.residuals`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from crossfield.calibration.detect import BoardDetection
from crossfield.calibration.jackknife import combined_covariance, jackknife
from crossfield.calibration.joint import (
    JointSolution,
    ViewPoints,
    camera_residuals,
    outlier_corners,
    refine_joint,
    without_corners,
)
from crossfield.calibration.prior import covariance_with_prior
from crossfield.calibration.residuals import ResidualMap, residual_map
from crossfield.types import CAMERAS, CameraIntrinsics, StereoCalibration

WARP_MIN_VIEWS = 8
JACKKNIFE_MIN_VIEWS = 6
MAX_REJECTION_ROUNDS = 10


@dataclass(frozen=True)
class Refinement:
    """The refined solution and its uncertainty.

    calibration: the refined rig. params (p,), the camera + rig block
    (``camera_param_names`` order); covariance (p, p): the stated one
    (std = max(Jacobian, jackknife)); std_jacobian, std_jackknife (p,) (the
    latter NaN without a jackknife); warp_mm (2,) and warp_std_mm (2,) (NaN
    when not estimated); sigma_px: corner noise from the residuals;
    rms_px: per camera over all its corners; residual_maps per camera;
    outlier_corners: corners dropped by the rejection (step 1).
    """

    calibration: StereoCalibration
    params: np.ndarray
    covariance: np.ndarray
    std_jacobian: np.ndarray
    std_jackknife: np.ndarray
    warp_mm: np.ndarray
    warp_std_mm: np.ndarray
    sigma_px: float
    rms_px: dict[str, float]
    residual_maps: dict[str, ResidualMap]
    solution: JointSolution
    outlier_corners: int = 0


def board_grid(object_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) board-frame (x, y) mm of the corner grid: the bow's [-1, 1] span."""
    return object_points[:, :2].min(axis=0), object_points[:, :2].max(axis=0)


def view_weights(
    views: list[ViewPoints], solution: JointSolution, prior_dof: float = 20.0
) -> list[ViewPoints]:
    """The views with per view and camera weights w = sigma_ref / sigma_view from the residuals.

    A view's corners are as noisy as its blur, tilt and distance make them
    (on the model renderer one view's RMS reaches 4x the median): weighted
    least squares with w = 1 / sigma is the minimum-variance estimate
    (Gauss-Markov; Hartley & Zisserman A6.8). sigma_view^2 = (SSR_view +
    prior_dof sigma_all^2) / (dof_view + prior_dof), dof_view = 2 n - 3 (the
    view's 6 pose parameters shared by two cameras), shrunk towards the
    pooled sigma_all^2 so that a view of a few corners does not get an
    extreme weight; sigma_ref^2 = the corners' mean sigma_view^2, so the
    weighted residuals stay in px on average. Residuals are taken unweighted.
    """
    per_cam = []
    row = 0
    for v in views:
        for u, w in ((v.pixels_upper, v.weight_upper), (v.pixels_lower, v.weight_lower)):
            k = 2 * len(u)
            r = solution.residuals[row : row + k] / w
            per_cam.append((float(r @ r), max(k - 3, 1), len(u)))
            row += k
    ssr, dof, n = map(np.array, zip(*per_cam))
    s2_all = ssr.sum() / dof.sum()
    s2 = (ssr + prior_dof * s2_all) / (dof + prior_dof)
    s2_ref = float(np.sum(n * s2) / max(n.sum(), 1))
    w = np.sqrt(s2_ref / s2).reshape(-1, 2)
    return [replace(v, weight_upper=float(a), weight_lower=float(b)) for v, (a, b) in zip(views, w)]


def initial_poses(views: list[ViewPoints], K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(V, 6) board poses in the upper camera (rvec, t mm) from its corners: ``cv2.solvePnP``."""
    poses = []
    for v in views:
        _, r, t = cv2.solvePnP(v.object_upper, v.pixels_upper, K, D, flags=cv2.SOLVEPNP_ITERATIVE)
        poses.append(np.concatenate([r.ravel(), t.ravel()]))
    return np.array(poses)


def refine(
    stereo_views: dict[int, tuple[BoardDetection, BoardDetection]],
    params0: np.ndarray,
    like: StereoCalibration,
    object_points: np.ndarray,
    *,
    estimate_warp: bool = True,
    jackknife_views: bool = True,
    reject_corners: bool = True,
    weight_views: bool = True,
    prior: bool = True,
) -> Refinement:
    """Steps 1-4 of the module docstring.

    stereo_views: view -> (upper, lower) detections (all their corners);
    params0 (p,): the stereo solution (``camera_param_names`` order); like:
    a calibration with the image sizes; object_points (n, 3) mm: the whole
    board's points (the bow's span); prior: mrcal's regularisation in every
    solve (``crossfield.calibration.prior``; needs the image sizes).
    """
    n_dist = len(like.upper.dist_coeffs)
    n = 4 + n_dist
    keys = sorted(stereo_views)
    views = [
        ViewPoints(a.object_points, a.image_points, b.object_points, b.image_points)
        for a, b in (stereo_views[k] for k in keys)
    ]
    grid = board_grid(object_points)
    K1 = np.array([[params0[0], 0, params0[2]], [0, params0[1], params0[3]], [0, 0, 1.0]])
    poses0 = initial_poses(views, K1, params0[4:n])
    warp = estimate_warp and len(views) >= WARP_MIN_VIEWS
    sizes = (like.upper.image_size, like.lower.image_size)
    image_sizes = sizes if prior and all(s is not None for s in sizes) else None
    sol = refine_joint(views, params0, poses0, n_dist, warp=warp, grid=grid, image_sizes=image_sizes)
    resolve = lambda views, sol: refine_joint(
        views,
        sol.theta[: sol.n_camera_params],
        sol.poses,
        n_dist,
        warp=warp,
        grid=grid,
        warp_start=sol.warp_mm,
        image_sizes=image_sizes,
    )
    n_outliers = 0
    for stage in ("unweighted", "weighted") if weight_views else ("unweighted",):
        if stage == "weighted":
            views = view_weights(views, sol)
            sol = resolve(views, sol)
        for _ in range(MAX_REJECTION_ROUNDS if reject_corners else 0):
            bad = outlier_corners(sol.residuals)
            if not bad.any():
                break
            n_outliers += int(bad.sum())
            views = without_corners(views, bad)
            sol = resolve(views, sol)
    n_cam = sol.n_camera_params
    n_block = n_cam + (2 if warp else 0)
    cov_full, sigma = covariance_with_prior(sol.residuals, sol.jacobian, sol.prior_jacobian)
    cov_j = cov_full[:n_block, :n_block]
    if jackknife_views and len(views) >= JACKKNIFE_MIN_VIEWS:
        jk = jackknife(views, sol, grid=grid)
        cov = combined_covariance(cov_j, jk.covariance)
        std_jk = jk.std
    else:
        cov, std_jk = cov_j, np.full(n_block, np.nan)
    cams = []
    for i, ref in enumerate((like.upper, like.lower)):
        K, D = sol.camera(i)
        cams.append(CameraIntrinsics(K, D, ref.image_size))
    calibration = StereoCalibration(
        cams[0], cams[1], cv2.Rodrigues(sol.rvec.reshape(3, 1))[0], sol.T, source=like.source
    )
    per_cam = camera_residuals(views, sol)
    maps = {
        cam: residual_map(cam, per_cam[cam][0], per_cam[cam][1], like.camera(cam).image_size)
        for cam in CAMERAS
    }
    rms = {cam: float(np.sqrt(np.mean(np.sum(per_cam[cam][1] ** 2, axis=1)))) for cam in CAMERAS}
    std_j = np.sqrt(np.diag(cov_j))
    warp_std = np.sqrt(np.diag(cov)[n_cam:]) if warp else np.full(2, np.nan)
    return Refinement(
        calibration=calibration,
        params=sol.theta[:n_cam].copy(),
        covariance=cov[:n_cam, :n_cam],
        std_jacobian=std_j[:n_cam],
        std_jackknife=std_jk[:n_cam],
        warp_mm=sol.warp_mm if warp else np.full(2, np.nan),
        warp_std_mm=warp_std,
        sigma_px=sigma,
        rms_px=rms,
        residual_maps=maps,
        solution=sol,
        outlier_corners=n_outliers,
    )
