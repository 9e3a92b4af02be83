"""The jackknife over views: the spread of the calibration when one view is left out at a time.

The Jacobian covariance sigma^2 (J^T J)^-1 assumes independent corner
errors that the model explains; real corners are neither (a bent board, a
lens the model does not fit, blur: errors correlated within a view). The
delete-one jackknife over the V views (Efron & Tibshirani 1993, eq. 11.5)
makes no such assumption:

    Sigma_jk = (V - 1) / V  sum_i (theta_(i) - theta_(.)) (theta_(i) - theta_(.))^T

with theta_(i) the solution without view i and theta_(.) their mean. The
stated standard deviation of each parameter is the larger of the two
(``combined_covariance``): the Jacobian's covariance with its rows and
columns scaled so that its diagonal holds the larger variance, the
correlations kept from the Jacobian (which are well determined; the
jackknife's with 16 views are not).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from crossfield.calibration.joint import JointSolution, ViewPoints, refine_joint


@dataclass(frozen=True)
class Jackknife:
    """Leave-one-view-out solutions: thetas (V, p) of the camera + rig (+ warp) block; cov (p, p)."""

    thetas: np.ndarray
    covariance: np.ndarray

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def jackknife(
    views: Sequence[ViewPoints],
    solution: JointSolution,
    *,
    grid: tuple[np.ndarray, np.ndarray],
    max_iterations: int = 20,
) -> Jackknife:
    """Re-solve without each view in turn, starting from the full solution (needs >= 3 views)."""
    V = len(views)
    if V < 3:
        raise ValueError(f"a jackknife needs at least 3 views, got {V}")
    n_cam = solution.n_camera_params
    thetas = []
    for i in range(V):
        keep = [k for k in range(V) if k != i]
        sol = refine_joint(
            [views[k] for k in keep],
            solution.theta[:n_cam],
            solution.poses[keep],
            solution.n_dist,
            warp=solution.warp,
            grid=grid,
            max_iterations=max_iterations,
            warp_start=solution.warp_mm,
            image_sizes=solution.image_sizes,
        )
        thetas.append(sol.theta)
    thetas = np.array(thetas)
    d = thetas - thetas.mean(axis=0)
    return Jackknife(thetas, (V - 1) / V * d.T @ d)


def combined_covariance(cov_jacobian: np.ndarray, cov_jackknife: np.ndarray) -> np.ndarray:
    """The Jacobian covariance scaled so that each std is max(std_jacobian, std_jackknife).

    Sigma = S Sigma_J S with S = diag(max(1, std_jk / std_J)): positive
    semi-definite, the Jacobian's correlations, the larger variance.
    """
    s_j = np.sqrt(np.diag(cov_jacobian))
    s_k = np.sqrt(np.diag(cov_jackknife))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(s_j > 0, np.maximum(1.0, s_k / s_j), 1.0)
    return cov_jacobian * np.outer(scale, scale)
