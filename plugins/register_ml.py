"""Register implementation "ml": maximum-likelihood rigid fit with full per-point covariances.

Model (``docs/registration.md``, "Maximum likelihood"): each camera point
p_i (camera frame) has covariance C_i (3x3, e.g. the stereo depth along the
line of sight several times the lateral error: ``CameraPoints.cov_xyz``),
each control q_i (global frame) an isotropic CMM sigma s_i. With
independent Gaussian errors, eliminating the true points gives the
negative log-likelihood (up to constants)

    L(R, t) = sum_i r_i^T S_i^-1 r_i,   r_i = R p_i + t - q_i,   S_i = R C_i R^T + s_i^2 I

(the errors-in-variables form; det S_i does not depend on R, so no
log-det term). It is minimised by Gauss-Newton on SE(3) (e.g. Barfoot,
State Estimation for Robotics, 7.1): a perturbation (omega, tau) acts in the
global frame, ``g -> exp([omega]x) g + tau``, so dr_i / d(omega, tau) =
[-[g_i]x, I] with g_i = R p_i + t, and S_i is re-evaluated at every
iterate. Start: the weighted Kabsch fit (:func:`crossfield.rigid.kabsch`,
weights 1 / tr(S_i)); the same reflection test as every registration
(:func:`crossfield.rigid.check_reflection`) runs on it.

Covariance: ``(J^T S^-1 J)^-1`` (6x6, (omega rad, tau mm)) at the solution;
when no absolute uncertainty is given (no weights, no covariances) it is
scaled by the variance factor chi2 / (3N - 6). ``RigidFit.chi2`` holds the
weighted sum of squares, ~ chi-square(3N - 6) when the stated covariances
are right.
"""

from __future__ import annotations

import math

import numpy as np

from crossfield.plugin_api import (
    REFLECTION_RATIO,
    RegistrationError,
    RigidFit,
    check_ratio,
    check_reflection,
    hookimpl,
    kabsch,
    point_set_size,
    residual_rms,
    validate_pairs,
)

#: Gauss-Newton stops when the step is below this (rad and mm). It converges quadratically
#: (steps ~1e-6, ~1e-10, ~1e-14 from the Kabsch start), so the error left after a step below
#: 1e-10 is far below the rounding noise of the translation (~1e-13 mm at 1 m), which a
#: tolerance of 1e-13 could not get under: every fit ran all ``max_iterations``.
STEP_TOLERANCE = 1e-10


def _exp_so3(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: exp([omega]x), (3,) rad -> (3, 3).

    ``I + sin(a) / a K + (1 - cos a) / a^2 K^2`` with K = [omega]x, a = |omega|
    (``I + K`` below 1e-12 rad)."""
    angle = math.sqrt(omega.dot(omega))  # = np.linalg.norm(omega), the same sqrt of the same dot
    w0, w1, w2 = omega.tolist()
    K = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])  # [omega]x
    if angle < 1e-12:
        return _I3 + K
    return _I3 + np.sin(angle) / angle * K + (1 - np.cos(angle)) / angle**2 * (K @ K)


def _jacobian(g: np.ndarray) -> np.ndarray:
    """dr_i / d(omega, tau) = [-[g_i]x, I]: (M, 3, 6) of g (M, 3) mm (global frame).

    -[g]x = [[0, g2, -g1], [-g2, 0, g0], [g1, -g0, 0]]: its six entries are written as
    ``g[:, k] * (+-1)`` (exact) into a copy of the constant [0, I] part."""
    J = np.tile(_J_CONSTANT, (len(g), 1))
    J[:, _J_ENTRIES] = g[:, _J_SOURCES] * _J_SIGNS
    return J.reshape(len(g), 3, 6)


#: The constant part of :func:`_jacobian` (the I block, row-major 3x6 flattened) and where
#: its -[g]x entries go: flat index, component of g, sign.
_J_CONSTANT = np.zeros((1, 18))
_J_CONSTANT[0, [3, 10, 17]] = 1.0
_J_ENTRIES = np.array([1, 2, 6, 8, 12, 13])
_J_SOURCES = np.array([2, 1, 2, 0, 1, 0])
_J_SIGNS = np.array([1.0, -1.0, -1.0, 1.0, 1.0, -1.0])


#: The 3x3 identity (read only), built once.
_I3 = np.eye(3)
_I3.flags.writeable = False


class MaximumLikelihoodRegistrar:
    """ML rigid registration: full camera-point covariances, CMM sigmas, Gauss-Newton on SE(3).

    Options:
        reflection_ratio: as for "svd" (mirror-image test, :mod:`crossfield.rigid`).
        max_iterations: Gauss-Newton iteration limit.
    """

    #: the runner hands this implementation the camera points' covariances (docs/registration.md)
    accepts_covariance = True

    def __init__(self, *, reflection_ratio: float = REFLECTION_RATIO, max_iterations: int = 20):
        self.reflection_ratio = check_ratio(reflection_ratio)
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
            raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
        self.max_iterations = max_iterations

    def fit(
        self,
        camera_xyz: np.ndarray,
        global_xyz: np.ndarray,
        weights: np.ndarray | None = None,
        *,
        camera_cov: np.ndarray | None = None,
        control_sigma: np.ndarray | None = None,
    ) -> RigidFit:
        """R, t with ``global ~ R @ camera + t`` from (N, 3) mm corresponding points.

        camera_cov: (N, 3, 3) mm^2 covariance of each camera point (camera frame);
        control_sigma: (N,) mm CMM sigma per coordinate of each control. Without
        them, ``weights`` (N,) are taken as 1 / variance of an isotropic error
        per pair (as the runner's weights are), or all pairs alike.
        """
        P, Q, w = validate_pairs(camera_xyz, global_xyz, weights)
        n = len(P)
        absolute = camera_cov is not None or weights is not None
        if camera_cov is not None:
            C = np.asarray(camera_cov, dtype=np.float64)
            if C.shape != (n, 3, 3) or not np.isfinite(C).all():
                raise RegistrationError(f"camera_cov must be a finite ({n}, 3, 3) array, got {C.shape}")
            s2 = np.zeros(n) if control_sigma is None else np.asarray(control_sigma, dtype=np.float64) ** 2
            if s2.shape != (n,) or not np.isfinite(s2).all():
                raise RegistrationError(f"control_sigma must be a finite ({n},) array")
        else:
            raw = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
            C = np.zeros((n, 3, 3))
            s2 = 1.0 / np.where(raw > 0, raw, 1.0)  # zero-weight pairs are left out below
        use = w > 0
        n_use = int(use.sum())
        C_use, s2I, Q_use = C[use], (s2[:, None, None] * _I3)[use], Q[use]  # s2I: s_i^2 I (M, 3, 3)

        # Kabsch start with weights 1 / tr(S_i), and the shared reflection test on it.
        # tr(S_i) at R = I: tr(C_i + s_i^2 I) (trace is rotation invariant), summed as np.trace does.
        trace = (C[:, 0, 0] + s2) + (C[:, 1, 1] + s2) + (C[:, 2, 2] + s2)
        w0 = np.where(use, 1.0 / np.maximum(trace, 1e-300), 0.0)
        R, t, R_m, t_m = kabsch(P, Q, w0)
        w0n = w0 / w0.sum()
        rms = float(np.sqrt(w0n @ ((P @ R.T + t - Q) ** 2).sum(axis=1)))
        rms_m = float(np.sqrt(w0n @ ((P @ R_m.T + t_m - Q) ** 2).sum(axis=1)))
        check_reflection(rms, rms_m, point_set_size(P, w0n), self.reflection_ratio, "ml")

        for _ in range(self.max_iterations):
            g = (P @ R.T + t)[use]  # g_i = R p_i + t
            Winv = np.linalg.inv(R @ C_use @ R.T + s2I)  # S_i^-1, S_i = R C_i R^T + s_i^2 I
            J = _jacobian(g)
            JtW = np.swapaxes(J, 1, 2) @ Winv  # (M, 6, 3)
            H = (JtW @ J).sum(axis=0)  # sum_i J_i^T S_i^-1 J_i
            b = (JtW @ (g - Q_use)[:, :, None]).sum(axis=0)[:, 0]  # sum_i J_i^T S_i^-1 r_i
            step = -np.linalg.solve(H, b)
            E = _exp_so3(step[:3])
            R = E @ R
            t = E @ t + step[3:]
            if np.abs(step).max() < STEP_TOLERANCE:
                break
        # re-orthonormalise (products of exponentials drift by ~1e-16 per step)
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
        g = P @ R.T + t
        residuals = g - Q
        g = g[use]
        Winv = np.linalg.inv(R @ C_use @ R.T + s2I)
        J = _jacobian(g)
        H = (np.swapaxes(J, 1, 2) @ Winv @ J).sum(axis=0)
        r_use = residuals[use]
        chi2 = float(np.einsum("ni,nij,nj->", r_use, Winv, r_use))
        covariance = np.linalg.inv(H)
        dof = 3 * n_use - 6
        if not absolute and dof > 0:
            covariance = covariance * (chi2 / dof)
        return RigidFit(
            R=R, t=t, residuals=residuals, rms_mm=residual_rms(residuals), method="ml",
            covariance=0.5 * (covariance + covariance.T), chi2=chi2,
        )


@hookimpl
def register_registers(register):
    register(
        "ml",
        MaximumLikelihoodRegistrar,
        "Maximum-likelihood rigid fit: full camera-point covariances and CMM sigmas, Gauss-Newton on SE(3)",
    )
