"""The budget's eccentricity term: the standard uncertainty of a circle target's centre
from perspective eccentricity, over a stated tilt distribution (docs/uncertainty.md,
"The eccentricity term"). Used by the plan measurer's budget and by the Monte Carlo check."""

from __future__ import annotations

import numpy as np

__all__ = ["eccentricity_sigma_mm", "off_axis_rad"]


def eccentricity_sigma_mm(
    distance_mm: float, radius_mm: float, max_tilt_deg: float, off_axis_rad: float = 0.0
) -> float:
    """Standard uncertainty (mm, per axis) of a circle target's triangulated centre from
    perspective eccentricity, over the stated tilt distribution.

    The shift. The image ellipse's centre is the image of
    ``X_e = C - (r^2 / Z) (a - (a . n) n)`` (a the optical axis, Z = a . C the depth, n the
    unit normal; H&Z result 2.13: the pole of the line at infinity;
    :func:`crossfield.imaging.eccentricity.ellipse_centre_point`). The rays of both cameras
    of a rig whose axes are parallel and whose baseline is perpendicular to them pass
    through the same X_e, so the triangulated point is X_e: the error ``e = X_e - C`` is one
    vector in the target's plane, ``|e| = (r^2 / Z) sin(theta)``, theta the angle of n to the
    optical axis; across the line of sight ``(r^2 / Z) sin(theta) cos(theta)`` (Ahn, Warnecke
    & Kotowski 1999, Photogramm. Rec. 16(93), eq. (11), referred to the object), along it
    ``(r^2 / Z) sin^2(theta)``.

    The tilt distribution (the assumption): the normal is uniformly distributed over the
    directions within ``max_tilt_deg`` of the line of sight (a spherical cap; the
    rectangular distribution of GUM 4.3.7 for a direction known only by its bound), so the
    tilt tau has the density ``sin(tau) / (1 - cos(tau_max))`` and a uniform azimuth psi:
    ``S = E[sin^2 tau] = (2/3 - cos tau_max + cos^3 tau_max / 3) / (1 - cos tau_max)``
    (~ tau_max^2 / 2). With the line of sight at ``off_axis_rad`` (phi) from the optical
    axis, ``a . n = cos(tau) cos(phi) + sin(tau) sin(phi) cos(psi)``, and
    ``E[sin^2 theta] = sin^2 phi + S (cos^2 phi - sin^2 phi / 2)``.

    The per-axis u: ``u^2 = E|e|^2 / 2 = (r^2 / Z)^2 E[sin^2 theta] / 2``, the shift's mean
    square split over the two axes of the target's plane it lies in (the budget applies
    ``u^2 I``; along the line of sight this overstates the perspective part, sin^2 against
    sin cos). distance_mm: |C| (mm, camera frame); Z = distance cos(phi)."""
    if radius_mm <= 0 or max_tilt_deg <= 0 or distance_mm <= 0:
        return 0.0
    c = float(np.cos(np.radians(min(max_tilt_deg, 90.0))))
    mean_sin2_tilt = (2.0 / 3.0 - c + c**3 / 3.0) / (1.0 - c)
    sin2_phi = float(np.sin(off_axis_rad)) ** 2
    mean_sin2_theta = sin2_phi + mean_sin2_tilt * (1.0 - sin2_phi - sin2_phi / 2.0)
    depth = distance_mm * float(np.cos(off_axis_rad))
    return float(radius_mm**2 / depth * np.sqrt(mean_sin2_theta / 2.0))


def off_axis_rad(xyz: np.ndarray) -> float:
    """Angle (rad) of the line of sight to a camera-frame point xyz (3,) mm from the
    optical axis (z): the phi of :func:`eccentricity_sigma_mm`."""
    xyz = np.asarray(xyz, dtype=np.float64)
    return float(np.arctan2(np.hypot(xyz[0], xyz[1]), xyz[2]))
