"""The registration's weights (paper Formula (5) as weighted least squares) and the
one call of a register implementation.

Formula (5) minimises ``sum_i |R p_i + t - q_i|^2`` over the control points. With a
camera point ``p_i`` of per-axis variance ``v_i`` (mm^2, the mean of its covariance's
diagonal, ``tr(C_i) / 3``) and a CMM point ``q_i`` of per-coordinate sigma ``s_i``
(mm), the residual of pair i has per-axis variance ``v_i + s_i^2``, and the
maximum-likelihood fit under isotropic errors weights it by

    w_i = 1 / (v_i + s_i^2)                                          (Formula (5), weighted)

(Arun et al. 1987 with weights; docs/registration.md). Equal sigmas give the paper's
unweighted fit. A register implementation that takes full covariances
(:class:`~crossfield.stages.AcceptsCovariance`, e.g. ``ml``) is given the camera
points' (N, 3, 3) covariances and the CMM sigmas as well.

Used by the runner (every stereo pair), the session's joint pose
(:mod:`crossfield.chain.session_pose`) and the planner's routes
(:mod:`crossfield.planning.routes`), so that the three weigh alike.
"""

from __future__ import annotations

import numpy as np

from crossfield.stages import Registrar
from crossfield.types import RigidFit

__all__ = ["VARIANCE_FLOOR_MM2", "fit_registration", "registration_weights"]

#: Smallest variance a pair is given (mm^2): a point stated exact gets a finite weight.
VARIANCE_FLOOR_MM2 = 1e-12


def registration_weights(camera_var_mm2: np.ndarray, control_sigma_mm: np.ndarray) -> np.ndarray:
    """(N,) Formula (5) weights ``1 / (v_i + s_i^2)``.

    camera_var_mm2: (N,) per-axis variance of each camera point (mm^2, ``tr(C_i) / 3``);
    control_sigma_mm: (N,) CMM sigma per coordinate of its control point (mm)."""
    var = np.asarray(camera_var_mm2, dtype=np.float64) + np.asarray(control_sigma_mm, dtype=np.float64) ** 2
    return 1.0 / np.maximum(var, VARIANCE_FLOOR_MM2)


def fit_registration(
    registrar: Registrar,
    camera_xyz: np.ndarray,
    control_xyz: np.ndarray,
    camera_var_mm2: np.ndarray,
    control_sigma_mm: np.ndarray,
    camera_cov: np.ndarray | None = None,
) -> RigidFit:
    """Fit ``control ~ R @ camera + t`` with ``registrar``: the one place a register
    implementation is called.

    camera_xyz, control_xyz: (N, 3) corresponding points, camera and global frame (mm);
    camera_var_mm2, control_sigma_mm: (N,) as :func:`registration_weights`;
    camera_cov: (N, 3, 3) camera-point covariances (mm^2), given to a registrar that
    accepts them (with the CMM sigmas), else only the weights are."""
    weights = registration_weights(camera_var_mm2, control_sigma_mm)
    if camera_cov is not None and _accepts_covariance(registrar):
        return registrar.fit(
            camera_xyz, control_xyz, weights, camera_cov=camera_cov, control_sigma=np.asarray(control_sigma_mm)
        )
    return registrar.fit(camera_xyz, control_xyz, weights)


def _accepts_covariance(registrar: Registrar) -> bool:
    """Whether the registrar takes the covariances (``stages.AcceptsCovariance``: a Registrar's
    ``fit`` and a true ``accepts_covariance``), read from the attribute: the runtime protocol
    ``isinstance`` check cost ~20 us per stereo pair."""
    return bool(getattr(registrar, "accepts_covariance", False))
