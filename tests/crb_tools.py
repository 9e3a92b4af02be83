"""Cramer-Rao bounds of centroids on the synthetic target images (test/bench helper).

Independent of the centroid implementations and of crossfield.precision: the
Fisher information of the *renderer's own* image model
(tests/synthetic_targets.py), computed exactly rather than from a fitted model.

Model of target k: mu = B + A * G (x) c(p), with c the pixel coverage of the
ellipse p = (u0, v0, a, b, theta), G the renderer's discrete Gaussian blur
(cv2.GaussianBlur), pixel variance var = mu / gain + read^2 + 1/12 (Poisson
photons, read noise, 1-DN rounding). The derivative of a pixel's coverage by
a boundary parameter is the flux of the boundary's velocity through the part
of the boundary inside the pixel (Reynolds transport theorem):

    d c_ij / d p = sum over boundary elements in pixel ij of (dx/dp . n) ds

evaluated on a dense sampling of the ellipse boundary. Fisher information
F = sum_i (d mu_i / d q)(d mu_i / d q)^T / var_i over q = (p, A, B), and the
bound on (u0, v0) is the (2, 2) upper-left block of F^-1 (pixels^2).
"""

from __future__ import annotations

import cv2
import numpy as np

from synthetic_targets import Ellipse, coverage


def centre_crb(
    e: Ellipse,
    *,
    shape: tuple[int, int],
    background_dn: float = 150.0,
    blur_sigma_px: float = 0.9,
    read_noise_dn: float = 3.0,
    gain_e_per_dn: float = 2.86,
    samples: int = 20000,
) -> np.ndarray:
    """(2, 2) Cramer-Rao bound (px^2) on the centre of one rendered ellipse."""
    cov, r0, c0 = coverage(e, shape, supersample=16)
    h, w = cov.shape
    phi = (np.arange(samples) + 0.5) * (2 * np.pi / samples)
    ct, st = np.cos(e.theta), np.sin(e.theta)
    R = np.array([[ct, -st], [st, ct]])
    local = np.stack([e.a * np.cos(phi), e.b * np.sin(phi)])  # (2, S)
    x = R @ local + np.array([[e.u0], [e.v0]])
    tangent = R @ np.stack([-e.a * np.sin(phi), e.b * np.cos(phi)]) * (2 * np.pi / samples)
    # outward normal * ds for this (counter-clockwise in u-right, v-down axes) orientation
    nds = np.stack([tangent[1], -tangent[0]])
    velocity = {
        "u0": np.array([[1.0], [0.0]]) * np.ones_like(phi),
        "v0": np.array([[0.0], [1.0]]) * np.ones_like(phi),
        "a": R @ np.stack([np.cos(phi), np.zeros_like(phi)]),
        "b": R @ np.stack([np.zeros_like(phi), np.sin(phi)]),
        "theta": np.array([[-st, -ct], [ct, -st]]) @ local,
    }
    col = np.rint(x[0]).astype(int) - c0
    row = np.rint(x[1]).astype(int) - r0
    inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    derivs = []
    for name in ("u0", "v0", "a", "b", "theta"):
        flux = np.sum(velocity[name] * nds, axis=0)
        dc = np.zeros((h, w))
        np.add.at(dc, (row[inside], col[inside]), flux[inside])
        derivs.append(e.amplitude * cv2.GaussianBlur(dc.astype(np.float32), (0, 0), blur_sigma_px,
                                                     borderType=cv2.BORDER_REPLICATE).astype(np.float64))
    signal = cv2.GaussianBlur(cov.astype(np.float32), (0, 0), blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
    derivs.append(signal.astype(np.float64))  # d mu / d A
    derivs.append(np.ones((h, w)))  # d mu / d B
    mu = background_dn + e.amplitude * signal.astype(np.float64)
    var = mu / gain_e_per_dn + read_noise_dn**2 + 1.0 / 12.0
    D = np.stack([d.ravel() for d in derivs])  # (7, h*w)
    F = (D / var.ravel()) @ D.T
    return np.linalg.inv(F)[:2, :2]
