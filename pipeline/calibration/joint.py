"""The joint stereo bundle adjustment: every corner of both cameras, the board's bow, one solve.

``cv2.stereoCalibrate`` fits only the corners both cameras saw in a view;
a ChArUco view seen partly by one camera loses the rest. This refinement
(started from stereoCalibrate's solution) minimises the reprojection error
of **every** detected corner of each camera, as mrcal does
(mrcal docs, "Formulation"):

    min  sum_views sum_cams sum_points | u_obs - pi_cam(X_point; theta) |^2

over the parameters, in this order:

* upper camera fx fy cx cy (px) and its distortion (OpenCV order), the
  lower camera's the same (``covariance.camera_param_names``);
* the rig: rotation vector r (rad), T (mm): ``p_lower = R(r) p_upper + T``;
* the board's bow (wx, wy) mm when ``warp`` is on: the board point
  (x, y, 0) is at (x, y, wx (1 - xn^2) + wy (1 - yn^2)), xn, yn in [-1, 1]
  across the corner grid (mrcal's ``calobject_warp``);
* per view the board pose in the upper camera (rotation vector, t mm).

Levenberg-Marquardt (Hartley & Zisserman A6.2) on the dense Jacobian with
column scaling; the Jacobian comes from ``cv2.projectPoints`` and
``cv2.composeRT`` (chain rule through ``R_lower = R R_i``,
``t_lower = R t_i + T``), and for the bow ``d(uv)/dz_board = d(uv)/dt R e_z``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from crossfield.calibration.covariance import project_with_jacobians
from crossfield.calibration.prior import Prior, mrcal_prior

#: Parameters of the rig block (after both cameras' intrinsics).
RIG_SIZE = 6


@dataclass(frozen=True)
class ViewPoints:
    """One view's detections: per camera the board points (N, 3) mm and their pixels (N, 2) px.

    weight_upper, weight_lower: the weight of each camera's residuals in this
    view (1 / its corner noise relative to the others', ``refine.view_weights``).
    """

    object_upper: np.ndarray
    pixels_upper: np.ndarray
    object_lower: np.ndarray
    pixels_lower: np.ndarray
    weight_upper: float = 1.0
    weight_lower: float = 1.0


@dataclass(frozen=True)
class JointSolution:
    """The refined parameters, and the residuals (m,) px and Jacobian (m, p) at the solution.

    theta: camera + rig (+ warp) block, (p_cam,); poses: (V, 6) rvec, t per view.
    residuals, jacobian: the reprojection rows only; image_sizes: the cameras'
    (width, height) px when the solve had mrcal's prior (``prior``: its rows), else None.
    """

    theta: np.ndarray
    poses: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    n_dist: int
    warp: bool
    iterations: int
    image_sizes: tuple[tuple[int, int], tuple[int, int]] | None = None

    @property
    def prior(self) -> Prior | None:
        """mrcal's regularisation rows of this solve (``crossfield.calibration.prior``), or None."""
        if self.image_sizes is None:
            return None
        return mrcal_prior(self.n_dist, self.image_sizes, len(self.residuals))

    @property
    def prior_jacobian(self) -> np.ndarray:
        """(k, p) the prior rows' Jacobian over all parameters (k = 0 without a prior)."""
        prior = self.prior
        n = self.jacobian.shape[1]
        return np.zeros((0, n)) if prior is None else prior.jacobian(n)

    @property
    def n_camera_params(self) -> int:
        """Length of the camera + rig block (without the bow)."""
        return 2 * (4 + self.n_dist) + RIG_SIZE

    def camera(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(K (3, 3) px, D (n_dist,)) of camera 0 (upper) or 1 (lower)."""
        n = 4 + self.n_dist
        p = self.theta[index * n : (index + 1) * n]
        K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        return K, p[4:].copy()

    @property
    def rvec(self) -> np.ndarray:
        o = 2 * (4 + self.n_dist)
        return self.theta[o : o + 3].copy()

    @property
    def T(self) -> np.ndarray:
        o = 2 * (4 + self.n_dist)
        return self.theta[o + 3 : o + 6].copy()

    @property
    def warp_mm(self) -> np.ndarray:
        """(2,) the board's bow (wx, wy) mm; zeros if not estimated."""
        return self.theta[self.n_camera_params :].copy() if self.warp else np.zeros(2)


def warp_basis(object_points: np.ndarray, grid_lo: np.ndarray, grid_hi: np.ndarray) -> np.ndarray:
    """(N, 2) d z / d (wx, wy): (1 - xn^2, 1 - yn^2) with xn, yn in [-1, 1] over the grid."""
    n = 2 * (object_points[:, :2] - grid_lo) / (grid_hi - grid_lo) - 1
    return 1.0 - n * n


def _project_view(X, basis, pose, K, D, rig, warp_mm):
    """uv, J_pose (2N, 6), J_cam, J_rig (2N, 6) or None, J_warp (2N, 2) of one camera's points."""
    Xw = X.copy()
    Xw[:, 2] += basis @ warp_mm
    r_i, t_i = pose[:3].reshape(3, 1), pose[3:].reshape(3, 1)
    if rig is None:
        uv, J_pose, J_cam = project_with_jacobians(Xw, r_i, t_i, K, D)
        R_c = cv2.Rodrigues(r_i)[0]
        J_rig = None
    else:
        r_l, t_l, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            r_i, t_i, rig[:3].reshape(3, 1), rig[3:].reshape(3, 1)
        )
        uv, J_l, J_cam = project_with_jacobians(Xw, r_l, t_l, K, D)
        Jr, Jt = J_l[:, :3], J_l[:, 3:]
        J_pose = np.hstack([Jr @ dr3dr1 + Jt @ dt3dr1, Jr @ dr3dt1 + Jt @ dt3dt1])
        J_rig = np.hstack([Jr @ dr3dr2 + Jt @ dt3dr2, Jr @ dr3dt2 + Jt @ dt3dt2])
        R_c = cv2.Rodrigues(r_l)[0]
        J_l_t = Jt
    Jt_cam = J_pose[:, 3:] if rig is None else J_l_t
    # d(uv)/d(z_board) = d(uv)/d(X_cam) R e_z and d(uv)/d(X_cam) = d(uv)/dt (X_cam = R X + t).
    dz = Jt_cam @ R_c[:, 2]
    J_warp = dz.reshape(-1, 2, 1) * basis[:, None, :]
    return uv, J_pose, J_cam, J_rig, J_warp.reshape(-1, 2)


def residuals_jacobian(
    views: Sequence[ViewPoints],
    theta: np.ndarray,
    poses: np.ndarray,
    n_dist: int,
    warp: bool,
    grid: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted residuals (m,) w (observed - projected) px and Jacobian (m, p) w d(projected)/d(params).

    Parameter order: the module docstring's (camera + rig [+ warp], then the poses).
    Rows: per view the upper camera's points, then the lower's, u and v interleaved;
    w: the view's ``weight_upper`` / ``weight_lower`` (weighted least squares,
    Hartley & Zisserman A6.8: the rows scaled by the inverse noise).
    """
    n = 4 + n_dist
    n_cam = 2 * n + RIG_SIZE + (2 if warp else 0)
    K = [np.array([[t[0], 0, t[2]], [0, t[1], t[3]], [0, 0, 1.0]]) for t in (theta[:n], theta[n : 2 * n])]
    D = [theta[4:n], theta[n + 4 : 2 * n]]
    rig = theta[2 * n : 2 * n + RIG_SIZE]
    warp_mm = theta[2 * n + RIG_SIZE : 2 * n + RIG_SIZE + 2] if warp else np.zeros(2)
    m = sum(2 * (len(v.object_upper) + len(v.object_lower)) for v in views)
    J = np.zeros((m, n_cam + 6 * len(views)))
    res = np.zeros(m)
    row = 0
    for i, v in enumerate(views):
        cols = slice(n_cam + 6 * i, n_cam + 6 * i + 6)
        for c, (X, u, w) in enumerate(
            (
                (v.object_upper, v.pixels_upper, v.weight_upper),
                (v.object_lower, v.pixels_lower, v.weight_lower),
            )
        ):
            if len(X) == 0:
                continue
            k = 2 * len(X)
            basis = warp_basis(X, *grid)
            uv, J_pose, J_cam, J_rig, J_warp = _project_view(
                np.asarray(X, float), basis, poses[i], K[c], D[c], None if c == 0 else rig, warp_mm
            )
            res[row : row + k] = (np.asarray(u, float) - uv).ravel()
            J[row : row + k, c * n : (c + 1) * n] = J_cam
            if J_rig is not None:
                J[row : row + k, 2 * n : 2 * n + RIG_SIZE] = J_rig
            if warp:
                J[row : row + k, 2 * n + RIG_SIZE : n_cam] = J_warp
            J[row : row + k, cols] = J_pose
            if w != 1.0:
                res[row : row + k] *= w
                J[row : row + k] *= w
            row += k
    return res, J


def refine_joint(
    views: Sequence[ViewPoints],
    theta0: np.ndarray,
    poses0: np.ndarray,
    n_dist: int,
    *,
    warp: bool,
    grid: tuple[np.ndarray, np.ndarray],
    max_iterations: int = 60,
    tolerance: float = 1e-10,
    warp_start: np.ndarray | None = None,
    image_sizes: tuple[tuple[int, int], tuple[int, int]] | None = None,
) -> JointSolution:
    """Levenberg-Marquardt from (theta0, poses0) (stereoCalibrate's solution).

    theta0: camera + rig block (2 (4 + n_dist) + 6,); poses0: (V, 6);
    warp_start: (2,) mm, the bow to start from (default flat); image_sizes:
    (width, height) px of both cameras to add mrcal's prior on the distortion
    and the centre (``crossfield.calibration.prior.mrcal_prior``; None: no
    prior). Stops when the cost changes by less than ``tolerance`` relative.
    """
    theta = np.asarray(theta0, float)
    if warp:
        theta = np.concatenate([theta, np.zeros(2) if warp_start is None else np.asarray(warp_start, float)])
    x = np.concatenate([theta, np.asarray(poses0, float).ravel()])
    n_cam = len(theta)
    lam = 1e-3
    split = lambda x: (x[:n_cam], x[n_cam:].reshape(-1, 6))
    n_rows = sum(2 * (len(v.object_upper) + len(v.object_lower)) for v in views)
    prior = None if image_sizes is None else mrcal_prior(n_dist, image_sizes, n_rows)

    def rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        res, J = residuals_jacobian(views, *split(x), n_dist, warp, grid)
        if prior is None:
            return res, J
        return np.concatenate([res, prior.residuals(x)]), np.vstack([J, prior.jacobian(len(x))])

    res, J = rows(x)
    cost = float(res @ res)
    it = 0
    for it in range(1, max_iterations + 1):
        scale = np.linalg.norm(J, axis=0)
        scale[scale == 0] = 1.0
        Js = J / scale
        A = Js.T @ Js
        g = Js.T @ res
        improved = False
        for _ in range(10):
            step = np.linalg.solve(A + lam * np.diag(np.diag(A)), g) / scale
            x_new = x + step
            res_new, J_new = rows(x_new)
            cost_new = float(res_new @ res_new)
            if cost_new <= cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        done = cost - cost_new <= tolerance * cost
        x, res, J, cost = x_new, res_new, J_new, cost_new
        lam = max(lam / 10.0, 1e-9)
        if done:
            break
    theta, poses = split(x)
    return JointSolution(theta.copy(), poses.copy(), res[:n_rows], J[:n_rows], n_dist, warp, it, image_sizes)


def camera_residuals(
    views: Sequence[ViewPoints], solution: JointSolution
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per camera ("upper", "lower"): observed points (N, 2) px and residuals (N, 2) px at the solution.

    Splits ``solution.residuals`` by the row order of :func:`residuals_jacobian`
    and undoes the weights (the residuals in px).
    """
    out: dict[str, tuple[list, list]] = {"upper": ([], []), "lower": ([], [])}
    row = 0
    for v in views:
        for cam, u, w in (
            ("upper", v.pixels_upper, v.weight_upper),
            ("lower", v.pixels_lower, v.weight_lower),
        ):
            k = 2 * len(u)
            if k:
                out[cam][0].append(np.asarray(u, float))
                out[cam][1].append(solution.residuals[row : row + k].reshape(-1, 2) / w)
            row += k
    return {
        cam: (
            np.concatenate(p) if p else np.zeros((0, 2)),
            np.concatenate(r) if r else np.zeros((0, 2)),
        )
        for cam, (p, r) in out.items()
    }


#: mrcal's outlier thresholds (mrcal.c, ``markOutliers``): a round of rejection starts when a corner
#: coordinate's residual exceeds K_TRIGGER sigma and then drops every coordinate beyond K_DROP sigma.
K_TRIGGER = 5.0
K_DROP = 4.0


def outlier_corners(residuals: np.ndarray) -> np.ndarray:
    """(N,) bool: the corners that mrcal's rule marks as outliers, from the (2N,) residuals px.

    sigma^2 = mean of the squared residual coordinates (u and v) over the
    corners; when some |du| or |dv| > K_TRIGGER sigma, every corner with
    |du| or |dv| > K_DROP sigma is an outlier (mrcal, ``markOutliers``: the
    lower second threshold leaves margin so that the next solve is usually
    the last); otherwise none is. For Gaussian corners a 5-sigma coordinate
    occurs once in 1.7e6, so a clean calibration drops nothing.
    """
    r2 = np.asarray(residuals, float).reshape(-1, 2) ** 2
    var = float(np.mean(r2))
    if not np.any(r2 > K_TRIGGER**2 * var):
        return np.zeros(len(r2), bool)
    return np.any(r2 > K_DROP**2 * var, axis=1)


def without_corners(views: Sequence[ViewPoints], bad: np.ndarray) -> list[ViewPoints]:
    """The views without the corners flagged in ``bad`` ((N,) bool in :func:`residuals_jacobian`'s row order)."""
    out, row = [], 0
    for v in views:
        keep = []
        for X, u in ((v.object_upper, v.pixels_upper), (v.object_lower, v.pixels_lower)):
            b = bad[row : row + len(X)]
            row += len(X)
            keep.append((np.asarray(X)[~b], np.asarray(u)[~b]))
        out.append(
            replace(
                v,
                object_upper=keep[0][0],
                pixels_upper=keep[0][1],
                object_lower=keep[1][0],
                pixels_lower=keep[1][1],
            )
        )
    return out
