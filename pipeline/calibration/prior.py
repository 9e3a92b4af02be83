"""mrcal's regularisation of the joint solve: a weak prior on the distortion and the principal point.

mrcal (2.2, ``mrcal.c``, "Regularization") adds to the reprojection residuals
one row per distortion coefficient and one per principal-point coordinate:

    r_d = s_d (d_j - 0)                 every distortion coefficient, both cameras
    r_c = s_c (c - (size - 1) / 2)      cx, cy of both cameras, towards the image centre

weighted so that, at "normal" values (|d| = 2, a centre 500 px off) and
1 px reprojection errors, each of the two groups would carry 0.25 % of the
cost (0.5 % in all):

    s_d^2 = M * 1 px^2 * 0.005 / 2 / (N_d * 2^2)
    s_c^2 = M * 1 px^2 * 0.005 / 2 / (N_c * 500^2)

with M the number of reprojection residuals (2 per corner), N_d the number
of distortion coefficients and N_c = 4 the centre coordinates. A row
s (x - x0) is a Gaussian prior of std sigma_px / s on x, sigma_px the corner
noise: on the station simulator's board views (30 views, sigma ~0.04 px)
about 0.06 on each distortion coefficient and 9 px on each centre
coordinate. The data determine k1, k2, p1, p2 and the centre far better
than that (std ~1e-3 and ~0.3 px), so the prior moves them by a small part
of their std; it does pin the poorly determined k3 of a narrow lens (its
term is r^6 with r < 0.3: std of several units from the data alone) near 0,
which stops k3's noise leaking into k1, k2 and the focal lengths. A lens
whose true k3 is large (a wide-angle lens) gets the prior's bias in k3;
`rational` or the data's own k3 then need ``prior=False`` (``refine``).
The prior rows are not measurements: the covariance is mrcal's sandwich
``sigma^2 A^-1 J^T J A^-1``, ``A = J^T J + P^T P`` (:func:`covariance_with_prior`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: mrcal 2.2's constants: the share of the cost at "normal" values, and those values.
COST_SHARE = 0.005
NORMAL_PIXEL_ERROR_PX = 1.0
NORMAL_DISTORTION = 2.0
NORMAL_CENTER_OFFSET_PX = 500.0


@dataclass(frozen=True)
class Prior:
    """The prior rows on the camera block: ``residuals(theta) = scale * (theta[index] - target)``.

    index (k,): positions in the camera + rig (+ warp) block (``covariance.camera_param_names``);
    target (k,): the nominal values (0 for distortion, (size - 1) / 2 px for the centre);
    scale (k,): the row weights (px per unit of the parameter).
    """

    index: np.ndarray
    target: np.ndarray
    scale: np.ndarray

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """(k,) the prior rows' residuals px, sign as the reprojection rows' (target - model)."""
        return self.scale * (self.target - np.asarray(theta)[self.index])

    def jacobian(self, n_params: int) -> np.ndarray:
        """(k, n_params) d(model part) / d(params): the rows' derivatives, as ``residuals_jacobian`` returns them."""
        J = np.zeros((len(self.index), n_params))
        J[np.arange(len(self.index)), self.index] = self.scale
        return J


def mrcal_prior(n_dist: int, image_sizes: tuple[tuple[int, int], tuple[int, int]], n_residuals: int) -> Prior:
    """mrcal 2.2's regularisation for two cameras (module docstring).

    n_dist: distortion coefficients per camera; image_sizes: (width, height)
    px of the upper and lower camera; n_residuals: the reprojection rows M.
    """
    n = 4 + n_dist
    n_d, n_c = 2 * n_dist, 4
    budget = n_residuals * NORMAL_PIXEL_ERROR_PX**2 * COST_SHARE / 2
    s_d = np.sqrt(budget / (n_d * NORMAL_DISTORTION**2))
    s_c = np.sqrt(budget / (n_c * NORMAL_CENTER_OFFSET_PX**2))
    index, target, scale = [], [], []
    for cam, (width, height) in enumerate(image_sizes):
        o = cam * n
        index += [o + 2, o + 3] + list(range(o + 4, o + n))
        target += [0.5 * (width - 1), 0.5 * (height - 1)] + [0.0] * n_dist
        scale += [s_c, s_c] + [s_d] * n_dist
    return Prior(np.array(index), np.array(target, float), np.array(scale, float))


def covariance_with_prior(res: np.ndarray, J: np.ndarray, J_prior: np.ndarray) -> tuple[np.ndarray, float]:
    """The covariance of a regularised least-squares estimate, and sigma (px).

    res (m,), J (m, p): the reprojection rows; J_prior (k, p): the prior rows.
    sigma^2 = SSR / (m - p) over the reprojection rows only, and
    ``Sigma = sigma^2 A^-1 J^T J A^-1`` with ``A = J^T J + J_prior^T J_prior``:
    only the reprojection rows are noisy (mrcal, "uncertainty": the
    regularisation terms carry no noise). With J_prior empty it is
    ``sigma^2 (J^T J)^-1`` (Hartley & Zisserman 5.2.3).
    """
    m, p = J.shape
    if m <= p:
        raise ValueError(f"{m} residuals cannot determine {p} parameters")
    sigma2 = float(res @ res) / (m - p)
    scale = np.linalg.norm(np.vstack([J, J_prior]), axis=0)
    scale[scale == 0] = 1.0
    Js, Ps = J / scale, J_prior / scale
    JtJ = Js.T @ Js
    A = JtJ + Ps.T @ Ps
    # A^-1 from its eigen-decomposition (symmetric, positive definite when the views determine the parameters).
    w, V = np.linalg.eigh(A)
    if w[0] <= w[-1] * 1e-28:
        raise ValueError("the parameters are not determined by the views (singular Jacobian)")
    A_inv = (V / w) @ V.T
    cov = A_inv @ JtJ @ A_inv
    cov = 0.5 * (cov + cov.T)
    return sigma2 * cov / np.outer(scale, scale), float(np.sqrt(sigma2))
