"""Register implementation "horn": Horn (1987) closed-form unit-quaternion solution.

B. K. P. Horn, "Closed-form solution of absolute orientation using unit
quaternions", J. Opt. Soc. Am. A 4(4), 1987. With r_l the camera points and
r_r the global points, both about their (weighted) centroids:

    M = sum_i w_i r_l,i r_r,i^T,  S_ab = M[a, b]                    Horn section 4.A
    N = [[Sxx+Syy+Szz, Syz-Szy,      Szx-Sxz,      Sxy-Syx     ],
         [Syz-Szy,     Sxx-Syy-Szz,  Sxy+Syx,      Szx+Sxz     ],
         [Szx-Sxz,     Sxy+Syx,     -Sxx+Syy-Szz,  Syz+Szy     ],
         [Sxy-Syx,     Szx+Sxz,      Syz+Szy,     -Sxx-Syy+Szz ]]   Horn (section 4.A)
    q = unit eigenvector of N's largest eigenvalue lambda_max       Horn section 4.B
    R = rotation of q (camera -> global), t = r_r_bar - R r_l_bar   Horn section 2.C

A quaternion is always a proper rotation, so the method cannot return a
reflection; it can however return a poor rotation for mirrored point sets.
To apply the shared criterion (:mod:`crossfield.rigid`) the best improper fit
is needed too: it maximises ``trace(R_m H)`` over det = -1, so ``-R_m`` is the
rotation that *minimises* ``trace(R H) = q^T N q``, the quaternion of N's
smallest eigenvalue (the same eigenproblem; Horn 1987 sec. 4.B).

The numbers are computed by :func:`crossfield.rigid.rigid_fit`: the shared
validation, the one Kabsch kernel :func:`crossfield.rigid.kabsch` with
``method="quaternion"`` (Horn's N and its extreme eigenpairs,
:func:`crossfield.rigid.best_rotations`) and the shared reflection decision.
"""

from __future__ import annotations

import numpy as np

from crossfield.plugin_api import REFLECTION_RATIO, RigidFit, check_ratio, hookimpl, rigid_fit


class HornRegistrar:
    """Rigid registration by Horn's unit-quaternion method (weighted).

    Options:
        reflection_ratio: mirror-image threshold, as for "svd" (default 5).
    """

    def __init__(self, *, reflection_ratio: float = REFLECTION_RATIO):
        self.reflection_ratio = check_ratio(reflection_ratio)

    def fit(
        self, camera_xyz: np.ndarray, global_xyz: np.ndarray, weights: np.ndarray | None = None
    ) -> RigidFit:
        """R, t with ``global ~ R @ camera + t`` from (N, 3) mm corresponding points."""
        # Horn's N, its largest eigenvector -> R, its smallest -> the best improper fit.
        return rigid_fit(
            camera_xyz, global_xyz, weights, method="quaternion", reflection_ratio=self.reflection_ratio, name="horn"
        )


@hookimpl
def register_registers(register):
    register("horn", HornRegistrar, "Horn 1987 unit-quaternion rigid fit, reflections rejected")
