"""Register implementation "svd": the paper's SVD (Kabsch / Arun) solution, Formulas (5)-(9).

Given camera-frame points p_i (the paper's local set P) and the corresponding
global CMM points q_i (the reference set Q), find R, t minimising

    sum_i w_i |R p_i + t - q_i|^2                                  Formula (5)

Matrices, named as in the paper:

* M'_i = p_i - p_bar : camera (local) points centred on their centroid;
* P'_i = q_i - q_bar : global (reference) points centred on their centroid;
* H = sum_i w_i M'_i P'_i^T  (3x3, camera index first)             Formula (6)
* H = U S V^T                                                      Formula (7)
* R = V D U^T, D = diag(1, 1, sign det(V U^T))                     Formula (8) + Kabsch/Umeyama correction
* t = q_bar - R p_bar                                              Formula (9)

With H built camera-first, R = V U^T maximises trace(R H) = sum_i P'_i^T R M'_i,
so R maps camera into global: q ~ R @ p + t (``T_global_camera``). D only
differs from the identity when V U^T is a reflection; then the proper
rotation is the best fit only if the data are (nearly) coplanar, otherwise the
point sets are mirror images and a RegistrationError is raised
(:mod:`crossfield.rigid` states the criterion).

The numbers are computed by :func:`crossfield.rigid.rigid_fit`: the shared
validation, the one Kabsch kernel :func:`crossfield.rigid.kabsch` with
``method="svd"`` (exactly the formulas above) and the shared reflection
decision.
"""

from __future__ import annotations

import numpy as np

from crossfield.plugin_api import REFLECTION_RATIO, RigidFit, check_ratio, hookimpl, rigid_fit


class SvdRegistrar:
    """Rigid registration by SVD of the cross-covariance matrix (paper Formulas (5)-(9)).

    Options:
        reflection_ratio: the fit is rejected as a mirror image when the best
            proper rotation's residual RMS exceeds this multiple of the best
            reflection's (default 5; see :mod:`crossfield.rigid`).
    """

    def __init__(self, *, reflection_ratio: float = REFLECTION_RATIO):
        self.reflection_ratio = check_ratio(reflection_ratio)

    def fit(
        self, camera_xyz: np.ndarray, global_xyz: np.ndarray, weights: np.ndarray | None = None
    ) -> RigidFit:
        """R, t with ``global ~ R @ camera + t`` from (N, 3) mm corresponding points.

        weights: (N,) non-negative per-point weights (e.g. 1 / variance), or None.
        Residuals in the result are ``R @ p_i + t - q_i`` (mm, global frame).
        """
        # Formulas (6)-(9) with the determinant correction, and the best improper fit.
        return rigid_fit(
            camera_xyz, global_xyz, weights, method="svd", reflection_ratio=self.reflection_ratio, name="svd"
        )


@hookimpl
def register_registers(register):
    register("svd", SvdRegistrar, "SVD / Kabsch rigid fit, paper Formulas (5)-(9), reflections rejected")
