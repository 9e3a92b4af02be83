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
is found the same way after mirroring the camera points (z -> -z):
R_improper = R' diag(1, 1, -1), where R' is Horn's rotation for the mirrored set.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from crossfield.hookspecs import hookimpl
from crossfield.rigid import (
    REFLECTION_RATIO,
    check_ratio,
    check_reflection,
    point_set_size,
    residual_rms,
    validate_pairs,
)
from crossfield.types import RigidFit

_MIRROR = np.diag([1.0, 1.0, -1.0])


def horn_rotation(camera_centred: np.ndarray, global_centred: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Horn's rotation (3, 3) maximising sum w_i r_r,i . R r_l,i for centred (N, 3) sets."""
    M = (camera_centred * w[:, None]).T @ global_centred
    (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = M
    N = np.array(
        [
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ]
    )
    _, vectors = np.linalg.eigh(N)  # ascending eigenvalues
    q0, qx, qy, qz = vectors[:, -1]
    return Rotation.from_quat([qx, qy, qz, q0]).as_matrix()  # scipy order: (x, y, z, w)


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
        P, Q, w = validate_pairs(camera_xyz, global_xyz, weights)
        p_bar, q_bar = w @ P, w @ Q
        Pc, Qc = P - p_bar, Q - q_bar
        R = horn_rotation(Pc, Qc, w)
        R_m = horn_rotation(Pc @ _MIRROR, Qc, w) @ _MIRROR  # best det = -1 fit
        t = q_bar - R @ p_bar  # Horn section 2.C
        residuals = P @ R.T + t - Q
        residuals_m = Pc @ R_m.T - Qc
        check_reflection(
            float(np.sqrt(w @ np.sum(residuals**2, axis=1))),
            float(np.sqrt(w @ np.sum(residuals_m**2, axis=1))),
            point_set_size(P, w),
            self.reflection_ratio,
            "horn",
        )
        return RigidFit(R=R, t=t, residuals=residuals, rms_mm=residual_rms(residuals), method="horn")


@hookimpl
def register_registers(register):
    register("horn", HornRegistrar, "Horn 1987 unit-quaternion rigid fit, reflections rejected")
