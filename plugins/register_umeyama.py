"""Register implementation "umeyama": Umeyama (1991), least-squares similarity/rigid fit.

S. Umeyama, "Least-squares estimation of transformation parameters between
two point patterns", IEEE TPAMI 13(4), 1991. With x_i the camera points and
y_i the global points (weights w_i summing to 1):

    mu_x = sum w_i x_i,  mu_y = sum w_i y_i                       Umeyama (34), (35)
    sigma_x^2 = sum w_i |x_i - mu_x|^2                             (36)
    Sigma_xy = sum w_i (y_i - mu_y)(x_i - mu_x)^T  (global first)  (38)
    Sigma_xy = U D V^T
    S = I, or diag(1, 1, -1) when det(U) det(V) < 0                (39), (43)
    R = U S V^T                                                    (40)
    c = trace(D S) / sigma_x^2   (only with with_scale=True)       (42)
    t = mu_y - c R mu_x                                            (41)

Note the orientation: Umeyama's Sigma_xy is the transpose of the paper's
Formula (6) H, hence R = U S V^T here and R = V U^T there; both map camera
into global (``y ~ c R x + t``). The improper alternative (S with the other
sign) is also evaluated so that mirrored point sets raise a
RegistrationError (criterion in :mod:`crossfield.rigid`).

The rotation (and for the rigid fit the translation) comes from the shared
kernel :func:`crossfield.rigid.kabsch` (``method="svd"``): Umeyama's
R = U S V^T of Sigma_xy is the Kabsch V D U^T of its transpose. The scale
(36), (41), (42) is computed here.
"""

from __future__ import annotations

import numpy as np

from crossfield.plugin_api import (
    REFLECTION_RATIO,
    RigidFit,
    check_ratio,
    check_reflection,
    hookimpl,
    kabsch,
    point_set_size,
    residual_rms,
    validate_pairs,
    weighted_rms,
)


class UmeyamaRegistrar:
    """Weighted least-squares rigid (or similarity) fit by Umeyama's method.

    Options:
        with_scale: also estimate a uniform scale c (``global ~ c R camera + t``);
            off by default, the camera and CMM both measure in mm.
        reflection_ratio: mirror-image threshold, as for "svd" (default 5).

    ``fit(..., weights=w)`` takes per-point weights, typically the inverse
    variance of each pair, ``1 / (sigma_camera^2 + sigma_cmm^2)``.
    """

    def __init__(self, *, with_scale: bool = False, reflection_ratio: float = REFLECTION_RATIO):
        if not isinstance(with_scale, bool):
            raise ValueError(f"with_scale must be true or false, got {with_scale!r}")
        self.with_scale = with_scale
        self.reflection_ratio = check_ratio(reflection_ratio)

    def fit(
        self, camera_xyz: np.ndarray, global_xyz: np.ndarray, weights: np.ndarray | None = None
    ) -> RigidFit:
        """Transform with ``global ~ scale * R @ camera + t`` from (N, 3) mm pairs.

        weights: (N,) non-negative per-point weights or None. Residuals (N, 3) mm
        in the global frame: ``scale * R @ p_i + t - q_i``.
        """
        X, Y, w = validate_pairs(camera_xyz, global_xyz, weights)
        # The rotation of (39)-(40), R = U S V^T, is the shared Kabsch kernel's (Sigma_xy
        # is the transpose of its camera-first H); R_m is the best improper alternative.
        R, t, R_m, t_m = kabsch(X, Y, w, method="svd")
        c, c_m = 1.0, 1.0
        if self.with_scale:
            mu_x, mu_y = w @ X, w @ Y  # (34), (35)
            Xc, Yc = X - mu_x, Y - mu_y
            sigma_x2 = float(w @ np.sum(Xc**2, axis=1))  # (36)
            # (42): c = trace(D S) / sigma_x^2, and trace(D S) = trace(R^T Sigma_xy)
            # = sum_i w_i (y_i - mu_y) . R (x_i - mu_x).
            c = float(w @ np.sum((Xc @ R.T) * Yc, axis=1)) / sigma_x2
            c_m = float(w @ np.sum((Xc @ R_m.T) * Yc, axis=1)) / sigma_x2
            t = mu_y - c * R @ mu_x  # (41)
            t_m = mu_y - c_m * R_m @ mu_x
        residuals = c * X @ R.T + t - Y
        check_reflection(
            weighted_rms(residuals, w),
            weighted_rms(c_m * X @ R_m.T + t_m - Y, w),
            point_set_size(Y, w),
            self.reflection_ratio,
            "umeyama",
        )
        return RigidFit(
            R=R, t=t, residuals=residuals, rms_mm=residual_rms(residuals), method="umeyama", scale=c
        )


@hookimpl
def register_registers(register):
    register("umeyama", UmeyamaRegistrar, "Umeyama 1991 weighted rigid/similarity fit, reflections rejected")
