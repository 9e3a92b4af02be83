"""The camera -> global point covariance kernel (crossfield.covariance) against
Monte Carlo propagation through the real transform."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from crossfield.covariance import (
    camera_covariance,
    global_point_covariance,
    global_sigma,
    registration_jacobian,
    skew,
)

R = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
T = np.array([120.5, -340.25, 55.0])


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(1)
    v, w = rng.normal(size=(2, 3))
    assert np.allclose(skew(v) @ w, np.cross(v, w), rtol=0, atol=1e-15)


def test_camera_term_matches_monte_carlo_through_the_transform():
    rng = np.random.default_rng(2)
    sigma = np.array([0.004, 0.006, 0.03])  # mm; depth worst, as from a short baseline
    p_c = np.array([12.0, -8.0, 410.0])
    samples = p_c + rng.normal(size=(200_000, 3)) * sigma
    p_g = samples @ R.T + T
    empirical = np.cov(p_g.T)
    cov = camera_covariance(R, sigma)
    assert np.allclose(cov, cov.T)
    # sampling error of a covariance with n = 2e5: ~ sqrt(2/n) ~ 0.3 % of the scale
    assert np.abs(empirical - cov).max() < 0.02 * sigma.max() ** 2


def test_batched_and_single_point_agree_and_sigma_is_the_diagonal():
    rng = np.random.default_rng(3)
    sigmas = rng.uniform(0.002, 0.05, size=(7, 3))
    A = 1.0002 * R
    batched = camera_covariance(A, sigmas)
    assert batched.shape == (7, 3, 3)
    for k in range(7):
        assert np.allclose(batched[k], A @ np.diag(sigmas[k] ** 2) @ A.T, rtol=1e-14, atol=0)
    assert np.allclose(global_sigma(A, sigmas) ** 2, np.diagonal(batched, axis1=1, axis2=2), rtol=1e-14)


def test_registration_term_matches_monte_carlo_of_a_perturbed_registration():
    rng = np.random.default_rng(4)
    g_bar = np.array([100.0, -300.0, 40.0])
    p_g = np.array([260.0, -150.0, 10.0])
    sd = np.array([2e-5, 3e-5, 1e-5, 0.004, 0.002, 0.003])  # dtheta (rad), dt (mm)
    L = rng.normal(size=(6, 6)) * 0.2 + np.eye(6)
    C_reg = (L * sd) @ (L * sd).T
    xi = rng.multivariate_normal(np.zeros(6), C_reg, size=20_000)
    # A registration error moves p by the small rotation about g_bar and the translation.
    moved = np.array(
        [Rotation.from_rotvec(x[:3]).apply(p_g - g_bar) + g_bar + x[3:] for x in xi]
    )
    empirical = np.cov(moved.T)
    J = registration_jacobian(p_g, g_bar)
    sigma_c = np.array([0.004, 0.006, 0.03])
    total = global_point_covariance(R, sigma_c, J, C_reg)
    reg = total - camera_covariance(R, sigma_c)
    assert np.allclose(reg, J @ C_reg @ J.T, rtol=1e-12, atol=0)
    assert np.abs(empirical - reg).max() < 0.05 * np.abs(reg).max()
    assert np.array_equal(global_point_covariance(R, sigma_c), camera_covariance(R, sigma_c))
