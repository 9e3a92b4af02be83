"""The camera's share of the registration excess, propagated along the controls' lines of sight.

The registration residuals' excess that the session puts on the camera
(:mod:`crossfield.uncertainty.consistency`, ``camera_registration_excess``) is what the
epipolar residuals cannot see: a centroid bias along the epipolar lines, i.e. a
disparity (depth) error, which moves a control along its line of sight from the
upper camera, the unit vector ``l_k = p_k / |p_k|`` (camera frame, mm). Independent
errors ``N(0, v)`` along ``l_k`` at the n controls leave the expected residual sum of
squares ``(1 - 2/n) n v`` (the expectation's factor of
:class:`crossfield.types.RegistrationConsistency`), so the camera's share
``X_cam`` (mm^2) states ``v = X_cam / ((1 - 2/n) n)``, and a characteristic y takes

    u^2 = v sum_k s_k^2,      s_k = dy / d(control k moved by 1 mm along l_k)

(GUM eq. (10)). The sensitivities are numerical: the controls moved by
``+-delta l_k``, the rigid fit's answer ``N_j = R d_j + J_j xi`` for every camera point
(:func:`crossfield.uncertainty.calibration.registered_displacements`), the frame
measured again by the session's own measurer, ``s_k = (y+ - y-) / (2 delta)``
(2n measurements of one frame, once per session). Only the registration carries
it: the targets' own errors are the epipolar evidence's (``camera_systematic``'s
first part).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from crossfield.uncertainty.calibration import registered_displacements

__all__ = ["DELTA_MM", "line_of_sight_sensitivities", "per_control_variance"]

#: The step of the central differences (mm): linear for the rigid fit, far above rounding.
DELTA_MM = 1e-3


def line_of_sight_sensitivities(plan, reference, points, registration, measurer) -> dict[str, float]:
    """Characteristic name -> ``sum_k s_k^2`` (dimensionless, mm^2 per mm^2) over the frame's
    controls (``points`` :class:`crossfield.types.CameraPoints`, its ``registration``; see the
    module docstring); {} with fewer than 3 controls."""
    xyz = np.asarray(points.xyz, dtype=np.float64)
    by_label = reference.by_label()
    corr = registration.correspondence
    controls = [int(i) for cid, i in zip(corr.control_ids, corr.camera_index) if cid in by_label]
    if len(controls) < 3:
        return {}
    q = len(controls)
    d_camera = np.zeros((len(xyz), 3, q))
    for col, index in enumerate(controls):
        d_camera[index, :, col] = DELTA_MM * xyz[index] / np.linalg.norm(xyz[index])
    d_global = registered_displacements(xyz, d_camera, registration, reference)
    # back to the camera frame, so that the measurer's own registration maps each point to its
    # displaced global position (as crossfield.uncertainty.calibration.calibration_contributions)
    fit = registration.fit
    back = np.einsum("ji,njq->niq", np.asarray(fit.R), d_global) / float(fit.scale)
    sums: dict[str, float] = {}
    for col in range(q):
        values = []
        for sign in (1.0, -1.0):
            moved = dataclasses.replace(points, xyz=xyz + sign * back[:, :, col])
            m = measurer.measure(plan, reference, moved, registration, None)
            values.append({c.name: c.measured_mm for c in m.characteristics})
        for name, plus in values[0].items():
            minus = values[1].get(name)
            if minus is not None and math.isfinite(plus) and math.isfinite(minus):
                sums[name] = sums.get(name, 0.0) + ((plus - minus) / (2.0 * DELTA_MM)) ** 2
    return sums


def per_control_variance(excess_mm2: float, n_controls: int) -> float:
    """``v = X_cam / ((1 - 2/n) n)`` (mm^2): the variance along each control's line of sight that
    leaves the excess ``excess_mm2`` in the registration residuals' mean sum of squares."""
    n = int(n_controls)
    if n <= 2 or not excess_mm2 > 0:
        return 0.0
    return float(excess_mm2) / ((1.0 - 2.0 / n) * n)
