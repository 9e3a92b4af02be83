"""register "ml" and the shared validation against the NumPy formulation they replaced.

``reference_ml_fit`` is ``MaximumLikelihoodRegistrar.fit`` as it was before its
per-call overhead was cut (``skew``, ``concatenate``, ``eye`` and the ``covariances``
closure per iteration), ``reference_validate_pairs`` is ``crossfield.rigid.validate_pairs``
before its two SVDs became one stacked call. The new code runs the same floating-point
operations in the same order, so the results must be *equal* (bit for bit), and the
same RegistrationError (message and all) must be raised: random anisotropic covariances,
3 points, zero weights, weights only, no weights, collinear and coplanar sets, mirror images.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.covariance import skew
from crossfield.errors import RegistrationError
from crossfield.rigid import COLLINEAR_RATIO, check_reflection, kabsch, point_set_size, validate_pairs

IMPL = implementations(make_plugin_manager(), "register")


# ---- the reference: the NumPy formulation ------------------------------------------------------


def reference_validate_pairs(camera_xyz, global_xyz, weights=None):
    P = np.asarray(camera_xyz, dtype=np.float64)
    Q = np.asarray(global_xyz, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or Q.shape != P.shape:
        raise RegistrationError(
            f"registration needs two (N, 3) arrays of corresponding points, got camera {P.shape} "
            f"and global {Q.shape}"
        )
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise RegistrationError("registration input contains non-finite coordinates (NaN or inf)")
    n = len(P)
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (n,):
            raise RegistrationError(f"weights must have shape ({n},), got {w.shape}")
        if not np.isfinite(w).all() or (w < 0).any():
            raise RegistrationError("weights must be finite and non-negative")
    used = int(np.count_nonzero(w > 0))
    if used < 3:
        raise RegistrationError(
            f"registration needs at least 3 corresponding points (with positive weight), got {used}"
        )
    w = w / w.sum()
    for name, X in (("camera", P), ("global", Q)):
        centred = (X - w @ X) * np.sqrt(w)[:, None]
        s = np.linalg.svd(centred, compute_uv=False)
        if s[0] == 0.0 or s[1] <= COLLINEAR_RATIO * s[0]:
            raise RegistrationError(
                f"the {name} points are collinear (or coincident): the rotation about their line "
                f"is undetermined (spread ratio {s[1] / s[0] if s[0] else 0.0:.2e} <= {COLLINEAR_RATIO})"
            )
    return P, Q, w


def _reference_exp_so3(omega):
    angle = float(np.linalg.norm(omega))
    K = skew(omega)
    if angle < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(angle) / angle * K + (1 - np.cos(angle)) / angle**2 * (K @ K)


def reference_ml_fit(camera_xyz, global_xyz, weights=None, *, camera_cov=None, control_sigma=None,
                     reflection_ratio=5.0, max_iterations=20):
    """(R, t, residuals, covariance, chi2) of the former implementation."""
    P, Q, w = reference_validate_pairs(camera_xyz, global_xyz, weights)
    n = len(P)
    absolute = camera_cov is not None or weights is not None
    if camera_cov is not None:
        C = np.asarray(camera_cov, dtype=np.float64)
        s2 = np.zeros(n) if control_sigma is None else np.asarray(control_sigma, dtype=np.float64) ** 2
    else:
        raw = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
        C = np.zeros((n, 3, 3))
        s2 = 1.0 / np.where(raw > 0, raw, 1.0)
    use = w > 0

    def covariances(R):
        return R @ C @ R.T + s2[:, None, None] * np.eye(3)

    S0 = covariances(np.eye(3))
    w0 = np.where(use, 1.0 / np.maximum(np.trace(S0, axis1=1, axis2=2), 1e-300), 0.0)
    R, t, R_m, t_m = kabsch(P, Q, w0)
    w0n = w0 / w0.sum()
    rms = float(np.sqrt(w0n @ np.sum((P @ R.T + t - Q) ** 2, axis=1)))
    rms_m = float(np.sqrt(w0n @ np.sum((P @ R_m.T + t_m - Q) ** 2, axis=1)))
    check_reflection(rms, rms_m, point_set_size(P, w0n), reflection_ratio, "ml")
    I3 = np.eye(3)
    for _ in range(max_iterations):
        g = P @ R.T + t
        r = g - Q
        Winv = np.linalg.inv(covariances(R)[use])
        J = np.concatenate([-skew(g[use]), np.broadcast_to(I3, (int(use.sum()), 3, 3))], axis=2)
        JtW = np.swapaxes(J, 1, 2) @ Winv
        H = np.sum(JtW @ J, axis=0)
        b = np.sum(JtW @ r[use][:, :, None], axis=0)[:, 0]
        step = -np.linalg.solve(H, b)
        E = _reference_exp_so3(step[:3])
        R = E @ R
        t = E @ t + step[3:]
        if np.max(np.abs(step)) < 1e-10:
            break
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    g = P @ R.T + t
    residuals = g - Q
    Winv = np.linalg.inv(covariances(R)[use])
    J = np.concatenate([-skew(g[use]), np.broadcast_to(I3, (int(use.sum()), 3, 3))], axis=2)
    JtW = np.swapaxes(J, 1, 2) @ Winv
    H = np.sum(JtW @ J, axis=0)
    chi2 = float(np.einsum("ni,nij,nj->", residuals[use], Winv, residuals[use]))
    covariance = np.linalg.inv(H)
    dof = 3 * int(use.sum()) - 6
    if not absolute and dof > 0:
        covariance = covariance * (chi2 / dof)
    return R, t, residuals, 0.5 * (covariance + covariance.T), chi2


# ---- the comparison ----------------------------------------------------------------------------


def problem(rng, n, kind):
    """(camera (N, 3), global (N, 3), weights or None, covariances (N, 3, 3) or None, sigmas)."""
    P = np.column_stack([rng.uniform(-70, 70, n), rng.uniform(-20, 70, n), rng.uniform(365, 395, n)])
    if kind == "coplanar":
        P[:, 2] = 380.0
    if kind == "collinear":
        P = np.outer(np.linspace(-50, 50, n), [0.6, 0.0, 0.8]) + [0, 0, 380] + rng.normal(0, 1e-6, (n, 3))
    A = rng.normal(size=(n, 3, 3)) * [0.0005, 0.0005, 0.004]
    covs = A @ np.swapaxes(A, 1, 2) + 1e-9 * np.eye(3)
    sigma = rng.uniform(0.001, 0.02, n)
    R = Rotation.random(random_state=rng).as_matrix()
    Q = (P * ([-1.0, 1.0, 1.0] if kind == "mirror" else 1.0)) @ R.T + rng.uniform(-800, 800, 3)
    cam = P + rng.normal(0, 0.003, P.shape)
    glob = Q + rng.normal(0, 0.01, P.shape)
    weights = 1.0 / (np.trace(covs, axis1=1, axis2=2) / 3 + sigma**2)
    if kind == "zero weights":
        weights[rng.choice(n, size=n - 3, replace=False)] = 0.0
    return cam, glob, weights, covs, sigma


def outcome(fit, *args, **kwargs):
    try:
        return fit(*args, **kwargs)
    except RegistrationError as exc:
        return ("error", str(exc))


def is_error(result) -> bool:
    return isinstance(result, tuple) and isinstance(result[0], str)


KINDS = ["plain", "coplanar", "collinear", "mirror", "zero weights"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("inputs", ["covariances", "weights", "none"])
def test_the_ml_fit_equals_the_numpy_formulation_bit_for_bit(kind, inputs):
    rng = np.random.default_rng(KINDS.index(kind))
    registrar = IMPL["ml"].create({})
    errors = 0
    for trial in range(40):
        n = 3 + trial % 10
        cam, glob, weights, covs, sigma = problem(rng, n, kind)
        kwargs = {"camera_cov": covs, "control_sigma": sigma} if inputs == "covariances" else {}
        w = None if inputs == "none" else weights
        expected = outcome(reference_ml_fit, cam, glob, w, **kwargs)
        got = outcome(registrar.fit, cam, glob, w, **kwargs)
        if is_error(expected):
            assert got == expected
            errors += 1
            continue
        assert not is_error(got), got
        R, t, residuals, covariance, chi2 = expected
        assert np.array_equal(got.R, R) and np.array_equal(got.t, t)
        assert np.array_equal(got.residuals, residuals)
        assert np.array_equal(got.covariance, covariance) and got.chi2 == chi2
    assert (errors > 0) == (kind in ("collinear", "mirror"))  # those raise the same RegistrationError


def test_validate_pairs_equals_the_numpy_formulation():
    rng = np.random.default_rng(3)
    for trial in range(600):
        n = int(rng.integers(3, 12))
        P, Q = rng.normal(size=(n, 3)) * 100, rng.normal(size=(n, 3)) * 100
        if trial % 4 == 0:  # (nearly) collinear camera points
            P = np.outer(rng.normal(size=n), [1.0, 2.0, 1.0]) + 10.0 ** rng.uniform(-8, 0) * rng.normal(size=(n, 3))
        if trial % 4 == 1:  # collinear global points
            Q = np.outer(rng.normal(size=n), [0.0, 1.0, -1.0])
        w = None if trial % 3 == 0 else rng.uniform(0, 2, n) * (rng.uniform(size=n) > 0.2)
        expected = outcome(reference_validate_pairs, P, Q, w)
        got = outcome(validate_pairs, P, Q, w)
        if is_error(expected):
            assert got == expected
        else:
            assert all(np.array_equal(a, b) for a, b in zip(got, expected))
