"""Stereo triangulation precision (the Cramér-Rao bound of a camera point) and
the batched triangulation kernel of the Monte Carlo routes.

Both use the stereo camera model the ``epipolar`` triangulation uses
(:mod:`crossfield.camera.stereo_model`: OpenCV's lens model with its analytic
Jacobian, linear triangulation H&Z 12.2, Gauss-Newton refinement of the
weighted reprojection error H&Z 12.3), so the bound and the Monte Carlo
describe the estimator the pipeline runs.

Bound: with independent Gaussian centroid errors of standard deviation
``sigma_uv`` (px) on the four image coordinates ``(u_upper, v_upper, u_lower,
v_lower)`` of a point X (mm, upper camera frame), the Fisher information of X
is ``J^T W J`` with J = d(uv)/dX (4 x 3, px/mm) and W = diag(sigma_uv^-2), so
``cov(X) >= (J^T W J)^-1`` (H&Z 5.2.2; the ML triangulation attains it to
first order). For a parallel rig with baseline b (mm) and focal length f (px)
and a point at depth z on the axis this gives the textbook
``sigma_z = z^2 sigma_d / (f b)`` with the disparity sigma ``sigma_d = sqrt(2) sigma_uv``.

:func:`linearised_triangulation` is the same estimator to first order about one
set of image points, for the Monte Carlo's (trials, points) batches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossfield.camera.stereo_model import (
    linear_triangulation,
    project_pair,
    refine_points,
    stereo_geometry,
    undistort,
)
from crossfield.types import StereoCalibration


def project_stereo(calibration: StereoCalibration, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points X (N, 3) mm (upper frame) into both cameras, with distortion.

    Returns uv (N, 4) px ``[u_upper, v_upper, u_lower, v_lower]`` and the
    Jacobian J (N, 4, 3) px/mm.
    """
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    return project_pair(stereo_geometry(calibration), X)


def camera_point_covariance(J: np.ndarray, sigma_uv: np.ndarray) -> np.ndarray:
    """Cramér-Rao covariance (N, 3, 3) mm^2 of triangulated points: ``(J^T W J)^-1``.

    J: (N, 4, 3) px/mm projection Jacobians; sigma_uv: (N, 4) px standard
    deviations of (u_upper, v_upper, u_lower, v_lower), or broadcastable.
    """
    J = np.asarray(J, dtype=np.float64)
    w = 1.0 / np.broadcast_to(np.asarray(sigma_uv, dtype=np.float64), J.shape[:-1]) ** 2
    information = np.matmul(np.swapaxes(J, -1, -2) * w[..., None, :], J)
    return np.linalg.inv(information)


def triangulate_batch(
    calibration: StereoCalibration, uv: np.ndarray, sigma_uv: np.ndarray, *, iterations: int = 5
) -> np.ndarray:
    """Triangulate many point pairs at once, as the ``epipolar`` triangulation does.

    uv: (..., 4) px observed ``[u_upper, v_upper, u_lower, v_lower]`` (distorted
    pixels, any leading batch shape); sigma_uv: (..., 4) px or broadcastable.
    Steps: undistortion (cv2.undistortPoints), linear triangulation (H&Z 12.2),
    Gauss-Newton on the weighted reprojection error (H&Z 12.3), each the
    the ``epipolar`` triangulation's own kernel. Returns X (..., 3) mm in the upper camera frame.
    """
    uv = np.asarray(uv, dtype=np.float64)
    shape = uv.shape[:-1]
    flat = uv.reshape(-1, 4)
    weights = 1.0 / np.broadcast_to(np.asarray(sigma_uv, dtype=np.float64), uv.shape).reshape(-1, 4) ** 2
    geometry = stereo_geometry(calibration)
    xn_u = undistort(flat[:, :2], geometry.upper)
    xn_l = undistort(flat[:, 2:], geometry.lower)
    X = linear_triangulation(xn_u, xn_l, geometry)
    X, _, _, _ = refine_points(X, flat, weights, geometry, max_iterations=iterations)
    return X.reshape(shape + (3,))


@dataclass(frozen=True)
class LinearTriangulation:
    """The ML triangulation linearised about one set of image points: ``X(uv0 + d) ~ X0 + G d``.

    uv0: (M, 4) px the expansion point; X0: (M, 3) mm its triangulation by
    :func:`triangulate_batch` (upper frame); G: (M, 3, 4) mm/px the estimator's
    derivative ``(J^T W J)^-1 J^T W`` at X0 (J = d(uv)/dX, W = diag(sigma_uv^-2): the
    Gauss-Newton normal equations of H&Z 12.3 differentiated at their solution).
    The error of the linear form is second order in ``d`` (~ z (d / disparity)^2): for the
    paper's rig (16 mm lenses, 50 mm baseline, 400 mm, disparity ~450 px) with ``d`` of 0.05 px RMS
    it is below 1e-3 of the first-order term and 5e-4 mm at most, at 0.005 px 100x less
    (``tests/planning/test_plan_fast.py`` bounds it against the full kernel).
    """

    uv0: np.ndarray
    X0: np.ndarray
    G: np.ndarray

    def __call__(self, duv: np.ndarray) -> np.ndarray:
        """X (..., M, 3) mm of image points ``uv0 + duv``, duv (..., M, 4) px."""
        duv = np.asarray(duv, dtype=np.float64)
        shape = duv.shape[:-2]
        M = self.G.shape[0]
        # One (trials x 4) @ (4 x 3) product per point: (M, trials, 4) @ (M, 4, 3).
        flat = np.ascontiguousarray(np.moveaxis(duv.reshape(-1, M, 4), 1, 0))
        dX = np.matmul(flat, np.swapaxes(self.G, 1, 2))  # (M, trials, 3)
        return (self.X0 + np.moveaxis(dX, 0, 1)).reshape(shape + (M, 3))


def linearised_triangulation(
    calibration: StereoCalibration, uv0: np.ndarray, sigma_uv: np.ndarray
) -> LinearTriangulation:
    """:class:`LinearTriangulation` about image points uv0 (M, 4) px with weights sigma_uv^-2
    (sigma_uv (M, 4) px or broadcastable): the full kernel once, then only a (3 x 4) product
    per point and trial (the Monte Carlo's batched triangulation, ``docs/planning.md``)."""
    uv0 = np.asarray(uv0, dtype=np.float64).reshape(-1, 4)
    sigma = np.broadcast_to(np.asarray(sigma_uv, dtype=np.float64), uv0.shape)
    X0 = triangulate_batch(calibration, uv0, sigma, iterations=20)
    _, J = project_stereo(calibration, X0)
    JtW = np.swapaxes(J, 1, 2) / sigma[:, None, :] ** 2  # (M, 3, 4)
    G = np.linalg.solve(JtW @ J, JtW)  # (J^T W J)^-1 J^T W
    return LinearTriangulation(uv0, X0, G)
