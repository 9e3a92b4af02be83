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

Implementation: NumPy, the stacked 3x3 products and inverses in the order they
always had, so that results are the same to the last bit
(``tests/register/test_register_ml_reference.py`` keeps the former code as the
reference); what was cut is per-call overhead (``skew``, ``concatenate``,
``eye`` per iteration: the Jacobian's constant part is set once per fit). A
compiled (numba) Gauss-Newton was measured and not taken: the normal equations
in (omega rad, tau mm) with points ~1 m from the origin are ill-conditioned,
so its different rounding moved R by ~1e-15 and report figures by up to
~3e-10 relative (residuals are differences of large numbers).
"""

from __future__ import annotations

import math
from typing import NamedTuple

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


def _jacobian_buffer(m: int) -> np.ndarray:
    """A (M, 3, 6) Jacobian [-[g_i]x, I] with its constant part set: the I block and
    the zeros of -[g]x; :func:`_fill_jacobian` writes the g-dependent entries."""
    J = np.zeros((m, 3, 6))
    J[:, 0, 3] = J[:, 1, 4] = J[:, 2, 5] = 1.0
    return J


def _fill_jacobian(J: np.ndarray, g: np.ndarray) -> np.ndarray:
    """dr_i / d(omega, tau) = [-[g_i]x, I] into J (M, 3, 6) from g (M, 3) mm (global frame).

    -[g]x = [[0, g2, -g1], [-g2, 0, g0], [g1, -g0, 0]]: its six entries, ``g[:, k] * (+-1)``
    (exact), in one indexed write of J's rows flattened (index 6 r + c)."""
    J.reshape(len(g), 18)[:, _J_ENTRIES] = g[:, _J_SOURCES] * _J_SIGNS
    return J


#: Where the entries of -[g]x go in the flattened 3x6 Jacobian, the component of g, its sign.
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
        C, s2 = _error_model(len(P), weights, camera_cov, control_sigma)
        use = w > 0  # zero-weight pairs are left out of the likelihood
        n_use = int(use.sum())
        used = slice(None) if n_use == len(P) else use  # (views when every pair is used)
        R, t = _kabsch_start(P, Q, C, s2, use, self.reflection_ratio)
        model = _Model(P, Q[used], C[used], (s2[:, None, None] * _I3)[used], used)
        R, t = _gauss_newton(model, R, t, self.max_iterations)
        residuals = P @ R.T + t - Q
        covariance, chi2 = _covariance(model, R, t)
        dof = 3 * n_use - 6
        if camera_cov is None and weights is None and dof > 0:  # no absolute uncertainty given
            covariance = covariance * (chi2 / dof)
        return RigidFit(
            R=R, t=t, residuals=residuals, rms_mm=residual_rms(residuals), method="ml",
            covariance=0.5 * (covariance + covariance.T), chi2=chi2,
        )


def _error_model(
    n: int, weights: np.ndarray | None, camera_cov: np.ndarray | None, control_sigma: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """The camera covariances C (N, 3, 3) mm^2 and CMM variances s^2 (N,) mm^2 of the model.

    Given camera covariances: those and the CMM sigmas squared (0 without sigmas).
    Else an isotropic error per pair: C = 0 and s^2 = 1 / weight (1 for a pair of zero
    weight, which the fit leaves out), or 1 for every pair without weights."""
    if camera_cov is not None:
        C = np.asarray(camera_cov, dtype=np.float64)
        if C.shape != (n, 3, 3) or not np.isfinite(C).all():
            raise RegistrationError(f"camera_cov must be a finite ({n}, 3, 3) array, got {C.shape}")
        s2 = np.zeros(n) if control_sigma is None else np.asarray(control_sigma, dtype=np.float64) ** 2
        if s2.shape != (n,) or not np.isfinite(s2).all():
            raise RegistrationError(f"control_sigma must be a finite ({n},) array")
        return C, s2
    raw = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    return np.zeros((n, 3, 3)), 1.0 / np.where(raw > 0, raw, 1.0)


def _kabsch_start(
    P: np.ndarray, Q: np.ndarray, C: np.ndarray, s2: np.ndarray, use: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """The start: R (3, 3), t (3,) mm of the Kabsch fit with weights 1 / tr(S_i), after
    the shared reflection test on it (:func:`crossfield.rigid.check_reflection`).

    tr(S_i) = tr(C_i + s_i^2 I) at any R (the trace is rotation invariant), summed in
    the order of ``np.trace``; pairs not in ``use`` get weight 0."""
    trace = (C[:, 0, 0] + s2) + (C[:, 1, 1] + s2) + (C[:, 2, 2] + s2)
    w0 = np.where(use, 1.0 / np.maximum(trace, 1e-300), 0.0)
    R, t, R_m, t_m = kabsch(P, Q, w0)
    w0n = w0 / w0.sum()
    rms = float(np.sqrt(w0n @ ((P @ R.T + t - Q) ** 2).sum(axis=1)))
    rms_m = float(np.sqrt(w0n @ ((P @ R_m.T + t_m - Q) ** 2).sum(axis=1)))
    check_reflection(rms, rms_m, point_set_size(P, w0n), ratio, "ml")
    return R, t


class _Model(NamedTuple):
    """What the likelihood needs of the M used pairs, fixed for the fit.

    P: (N, 3) mm all camera points; Q: (M, 3) mm the used controls (global frame);
    C: (M, 3, 3) mm^2 their camera covariances; s2I: (M, 3, 3) mm^2 ``s_i^2 I``;
    used: the used rows of P (a boolean mask, or ``slice(None)`` for all)."""

    P: np.ndarray
    Q: np.ndarray
    C: np.ndarray
    s2I: np.ndarray
    used: np.ndarray | slice

    def linearise(self, R: np.ndarray, t: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, ...]:
        """(J^T S^-1 (M, 6, 3), S^-1 (M, 3, 3), r (M, 3) mm) at (R, t), with J (M, 3, 6)
        written: g_i = R p_i + t, r_i = g_i - q_i, S_i = R C_i R^T + s_i^2 I,
        J_i = [-[g_i]x, I] (:func:`_fill_jacobian`)."""
        g = (self.P @ R.T + t)[self.used]
        Winv = np.linalg.inv(R @ self.C @ R.T + self.s2I)
        _fill_jacobian(J, g)
        return np.swapaxes(J, 1, 2) @ Winv, Winv, g - self.Q


def _gauss_newton(model: _Model, R: np.ndarray, t: np.ndarray, max_iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on SE(3) from (R, t): solve ``H step = -b`` for step = (omega rad, tau mm),
    ``H = sum_i J_i^T S_i^-1 J_i``, ``b = sum_i J_i^T S_i^-1 r_i``; apply
    ``g -> exp([omega]x) g + tau`` (R <- E R, t <- E t + tau) until max |step| <
    :data:`STEP_TOLERANCE`; then R re-orthonormalised (U V^T of its SVD: products of
    exponentials drift by ~1e-16 per step). Returns R (3, 3), t (3,) mm."""
    J = _jacobian_buffer(len(model.Q))
    for _ in range(max_iterations):
        JtW, _, r = model.linearise(R, t, J)
        H = (JtW @ J).sum(axis=0)
        b = (JtW @ r[:, :, None]).sum(axis=0)[:, 0]
        step = -np.linalg.solve(H, b)
        E = _exp_so3(step[:3])
        R = E @ R
        t = E @ t + step[3:]
        if np.abs(step).max() < STEP_TOLERANCE:
            break
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt, t


def _covariance(model: _Model, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """``(J^T S^-1 J)^-1`` (6, 6), (omega rad, tau mm), at (R, t) and
    chi2 = sum_i r_i^T S_i^-1 r_i over the used pairs."""
    J = _jacobian_buffer(len(model.Q))
    JtW, Winv, r = model.linearise(R, t, J)
    chi2 = float(np.einsum("ni,nij,nj->", r, Winv, r))
    return np.linalg.inv((JtW @ J).sum(axis=0)), chi2


@hookimpl
def register_registers(register):
    register(
        "ml",
        MaximumLikelihoodRegistrar,
        "Maximum-likelihood rigid fit: full camera-point covariances and CMM sigmas, Gauss-Newton on SE(3)",
    )
