"""The cross-validation's "within 2 sigma" for vector differences: Mahalanobis norms on the normal scale."""

from __future__ import annotations

import numpy as np

from crossfield.calibration.crossval import CrossValidation, normal_equivalent


def _draws(cov: np.ndarray, n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).multivariate_normal(np.zeros(len(cov)), cov, size=n)


def test_a_scalar_difference_is_its_ratio_to_sigma():
    d = np.array([[0.3], [-1.7], [2.5]])
    np.testing.assert_allclose(
        normal_equivalent(d, np.full((3, 1, 1), 0.25)), np.abs(d[:, 0]) / 0.5, rtol=1e-9
    )


def test_differences_drawn_from_their_covariance_are_within_2_sigma_as_often_as_a_normal_variable():
    """95.45 % of 2-D and 3-D differences drawn from the stated covariance: 'within 2 sigma' means the same
    for a pixel's (du, dv) and a point's (dx, dy, dz) as for one number. |d| over the std along d
    (the statistic before) puts an isotropic 2-D difference beyond 2 with probability exp(-2) = 13.5 %."""
    n = 20000
    C2 = np.array([[0.04, 0.015], [0.015, 0.02]])
    C3 = np.array([[4e-4, 1e-4, 0.0], [1e-4, 3e-4, 5e-5], [0.0, 5e-5, 9e-4]])
    d2, d3 = _draws(C2, n, 1), _draws(C3, n, 2)
    sigma_along = np.sqrt(np.einsum("ni,ij,nj->n", d2, C2, d2) / np.einsum("ni,ni->n", d2, d2))
    cv = CrossValidation(
        halves=((), ()),
        depth_mm=400.0,
        grid_px={"upper": np.zeros((n, 2))},
        diff_px={"upper": d2},
        sigma_px={"upper": sigma_along},
        points_mm=np.zeros((n, 3)),
        diff_mm=d3,
        sigma_mm=np.tile(np.sqrt(np.diag(C3)), (n, 1)),
        cov_px={"upper": np.tile(C2, (n, 1, 1))},
        cov_mm=np.tile(C3, (n, 1, 1)),
    )
    within = cv.within(2.0)
    assert abs(within["upper"] - 0.9545) < 0.005 and abs(within["points"] - 0.9545) < 0.005
    # the statistic before, on an isotropic difference: 86.5 % within 2
    iso = _draws(0.03 * np.eye(2), n, 3)
    assert abs(np.mean(np.linalg.norm(iso, axis=1) / np.sqrt(0.03) <= 2) - (1 - np.exp(-2))) < 0.01
