"""Reference-element fits and distances (global frame, mm).

* :func:`fit_line`: orthogonal least-squares line (total least squares, PCA):
  the line through the centroid along the principal axis of the scatter
  matrix minimises the sum of squared orthogonal distances (Pearson 1901;
  Forbes, NIST IR 4672 "Least-squares best-fit geometric elements", 1989, sec. 3).
* :func:`fit_cylinder_axis`: least-squares cylinder, residual
  ``d_i = |(p_i - x0) x a| - r`` (Forbes 1989, sec. 7), solved with
  :func:`scipy.optimize.least_squares` from PCA / circle-fit starts.
* :func:`fit_reference_element`: the fit of a plan's reference line to its
  CMM probes, the one used by the measurement (``plugins/measure_plan.py``)
  and drawn by the viewer (``crossfield.viz.rerun_log``).
* Distances point-point and point-line, with first-order uncertainties.

Both fits return an :class:`AxisFit`: the line, the residuals and the
covariance of the line's four degrees of freedom in a local parametrisation
(see :meth:`AxisFit.perturbed`), so that the uncertainty of any quantity
computed from the line can be propagated to first order
(:func:`point_line_distance`).

All lengths in mm; points are (N, 3) arrays in one frame (the global frame
when called by the measurement plugin).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from crossfield.types import Line3D, ProbedPoint, frozen_array

if TYPE_CHECKING:
    from crossfield.plan import ReferenceLineSpec

#: Fewest probes each reference-element fit accepts.
MIN_PROBES = {"line": 2, "cylinder": 5}

__all__ = [
    "AxisFit",
    "distance_point_line",
    "distance_point_point",
    "fit_cylinder_axis",
    "fit_line",
    "fit_reference_element",
    "perpendicular_basis",
    "point_line_distance",
]


def perpendicular_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing unit ``direction`` to a right-handed orthonormal basis.

    direction: (3,) or (N, 3) (one basis per row); returns e1, e2 of the same shape. The
    helper axis is the one along the direction's smallest component.
    """
    d = np.asarray(direction, dtype=np.float64)
    if d.ndim == 1:
        d = d / np.linalg.norm(d)
        helper = np.eye(3)[np.argmin(np.abs(d))]
        e1 = np.cross(d, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d, e1)
        return e1, e2
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    helper = np.eye(3)[np.argmin(np.abs(d), axis=-1)]
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(d, e1)


@dataclass(frozen=True)
class AxisFit:
    """A fitted line or cylinder axis.

    line: the axis; ``line.point`` is the foot of the data centroid on it.
    radius_mm: cylinder radius (None for a line fit).
    residuals_mm: (N,) signed orthogonal residuals; for a line the distance of
        each point from it (>= 0), for a cylinder ``distance - radius``.
    rms_mm: sqrt(mean residual^2).
    sigma_mm: standard uncertainty of one point used for the covariance
        (the larger of the a-priori value given and the a-posteriori
        sqrt(SSE / degrees of freedom)).
    covariance: (4, 4) covariance of (x, y, a, b), the line offsets along the
        basis (e1, e2) perpendicular to it and the direction tilts, mm and rad:
        ``point' = point + x e1 + y e2``, ``direction' ~ direction + a e1 + b e2``.
    basis: (e1, e2), each (3,).
    kind: "line" or "cylinder".
    """

    line: Line3D
    radius_mm: float | None
    residuals_mm: np.ndarray
    rms_mm: float
    sigma_mm: float
    covariance: np.ndarray
    basis: tuple[np.ndarray, np.ndarray]
    kind: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "residuals_mm", frozen_array(self.residuals_mm, shape=(None,)))
        object.__setattr__(self, "covariance", frozen_array(self.covariance, shape=(4, 4)))
        object.__setattr__(self, "basis", tuple(frozen_array(e, shape=(3,)) for e in self.basis))

    def perturbed(self, delta: np.ndarray) -> Line3D:
        """The line moved by delta = (x, y, a, b) (mm, mm, rad, rad) in the local parametrisation."""
        x, y, a, b = delta
        e1, e2 = self.basis
        return Line3D(self.line.point + x * e1 + y * e2, self.line.direction + a * e1 + b * e2)


def _posterior_sigma(residuals: np.ndarray, dof: int, prior_sigma_mm: float) -> float:
    s = float(np.sqrt(np.sum(residuals**2) / dof)) if dof > 0 else 0.0
    return max(s, float(prior_sigma_mm))


def _as_points(points: np.ndarray, minimum: int, what: str) -> np.ndarray:
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"{what}: expected (N, 3) points in mm, got shape {P.shape}")
    if len(P) < minimum:
        raise ValueError(f"{what}: needs at least {minimum} points, got {len(P)}")
    if not np.isfinite(P).all():
        raise ValueError(f"{what}: points contain NaN or inf")
    return P


def fit_line(points: np.ndarray, *, sigma_mm: float = 0.0) -> AxisFit:
    """Orthogonal least-squares line through (N >= 2, 3) points, mm.

    The line passes through the centroid along the right singular vector of
    the largest singular value of the centred points (Forbes 1989, sec. 3).
    sigma_mm: a-priori standard uncertainty per coordinate of each point.

    Covariance (first order, isotropic point noise sigma): with s_i the
    position of point i along the line from the centroid, the perpendicular
    offsets are ``x_i = x + a s_i`` (likewise y, b), so
    ``var(x) = sigma^2 / N`` and ``var(a) = sigma^2 / sum s_i^2``, all
    uncorrelated (the centroid makes sum s_i = 0).
    """
    P = _as_points(points, 2, "line fit")
    centroid = P.mean(axis=0)
    centred = P - centroid
    _, s, Vt = np.linalg.svd(centred, full_matrices=False)
    if s[0] == 0.0:
        raise ValueError("line fit: all points coincide")
    direction = Vt[0]
    line = Line3D(centroid, direction)
    e1, e2 = perpendicular_basis(line.direction)
    along = centred @ line.direction
    perp = centred - np.outer(along, line.direction)
    residuals = np.linalg.norm(perp, axis=1)
    n = len(P)
    sigma = _posterior_sigma(residuals, 2 * n - 4, sigma_mm)
    sum_s2 = float(along @ along)
    covariance = np.diag([sigma**2 / n, sigma**2 / n, sigma**2 / sum_s2, sigma**2 / sum_s2])
    return AxisFit(
        line=line,
        radius_mm=None,
        residuals_mm=residuals,
        rms_mm=float(np.sqrt(np.mean(residuals**2))),
        sigma_mm=sigma,
        covariance=covariance,
        basis=(e1, e2),
        kind="line",
    )


def _circle_fit_2d(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle fit to (N, 2) points: centre (2,), radius."""
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    b = np.sum(xy**2, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    centre = sol[:2]
    r2 = sol[2] + centre @ centre
    return centre, float(np.sqrt(max(r2, 0.0)))


def _tilted(d0: np.ndarray, e1: np.ndarray, e2: np.ndarray, a: float, b: float) -> np.ndarray:
    """Unit d0 turned by the angle theta = |(a, b)| towards a e1 + b e2 (exponential map;
    to first order d0 + a e1 + b e2, and able to reach any direction, which a
    normalised d0 + a e1 + b e2 cannot beyond 90 degrees)."""
    theta = float(np.hypot(a, b))
    if theta < 1e-12:
        return d0 + a * e1 + b * e2
    return np.cos(theta) * d0 + np.sin(theta) * (a * e1 + b * e2) / theta


def _cylinder_residuals(params: np.ndarray, P: np.ndarray, origin: np.ndarray, d0: np.ndarray,
                        e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """d_i = |(p_i - x0) x a| - r with x0 = origin + x e1 + y e2 and the axis direction
    d0 turned by the angle |(a, b)| towards a e1 + b e2 (:func:`_tilted`)."""
    x, y, a, b, r = params
    axis_point = origin + x * e1 + y * e2
    direction = _tilted(d0, e1, e2, a, b)
    v = P - axis_point
    perp = v - np.outer(v @ direction, direction)
    return np.linalg.norm(perp, axis=1) - r


def _tilted_jacobian(d0: np.ndarray, e1: np.ndarray, e2: np.ndarray, a: float, b: float) -> np.ndarray:
    """(3, 2) derivative of :func:`_tilted` with respect to (a, b). With theta = |(a, b)|,
    u = a e1 + b e2 and s(theta) = sin(theta) / theta:
    d = cos(theta) d0 + s u, so dd/da = -sin(theta) (a / theta) d0 + s e1 + s'(theta) (a / theta) u,
    s' = (theta cos(theta) - sin(theta)) / theta^2 (and (e1, e2) at theta = 0)."""
    theta = float(np.hypot(a, b))
    if theta < 1e-12:
        return np.column_stack([e1, e2])
    s = np.sin(theta) / theta
    ds = (theta * np.cos(theta) - np.sin(theta)) / theta**2
    u = a * e1 + b * e2
    return np.column_stack([
        -np.sin(theta) * (w / theta) * d0 + s * e + ds * (w / theta) * u for w, e in ((a, e1), (b, e2))
    ])


def _cylinder_jacobian(params: np.ndarray, P: np.ndarray, origin: np.ndarray, d0: np.ndarray,
                       e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """(N, 5) analytic Jacobian of :func:`_cylinder_residuals` over (x, y, a, b, r).
    With v = p - x0, the foot-normal n = perp / |perp| (perpendicular to the axis a):
    dd/dx0 = -n (so dd/dx = -n.e1, dd/dy = -n.e2), dd/da = -(v.a) n (the axis turned by da),
    chained with :func:`_tilted_jacobian`; dd/dr = -1."""
    x, y, a, b, _ = params
    axis_point = origin + x * e1 + y * e2
    direction = _tilted(d0, e1, e2, a, b)
    v = P - axis_point
    along = v @ direction
    perp = v - np.outer(along, direction)
    n = perp / np.maximum(np.linalg.norm(perp, axis=1), 1e-300)[:, None]
    J = np.empty((len(P), 5))
    J[:, 0] = -n @ e1
    J[:, 1] = -n @ e2
    J[:, 2:4] = -along[:, None] * (n @ _tilted_jacobian(d0, e1, e2, a, b))
    J[:, 4] = -1.0
    return J


def _cylinder_from(direction: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Start values for an axis along ``direction``: circle fit in the perpendicular plane."""
    e1, e2 = perpendicular_basis(direction)
    centroid = P.mean(axis=0)
    xy = np.column_stack([(P - centroid) @ e1, (P - centroid) @ e2])
    centre, radius = _circle_fit_2d(xy)
    return centroid + centre[0] * e1 + centre[1] * e2, e1, e2, radius


def fit_cylinder_axis(
    points: np.ndarray,
    *,
    sigma_mm: float = 0.0,
    direction_hint: np.ndarray | None = None,
) -> AxisFit:
    """Least-squares cylinder through (N >= 5, 3) surface points (mm); returns its axis.

    Minimises sum_i (|(p_i - x0) x a| - r)^2 over the axis (4 degrees of
    freedom) and the radius (Forbes 1989, sec. 7). Starts: each principal
    axis of the point scatter and the four diagonals between them (and first
    ``direction_hint`` if given), each with the circle fitted to the points
    projected on the perpendicular plane. Of the converged solutions the best
    (smallest sum of squares) is returned, but when another start
    converged to a clearly different cylinder that fits about as well, the
    probe pattern cannot determine the axis and ValueError is raised
    (:func:`_check_unique_cylinder`). Probe at three or more heights, at
    angles that are not symmetric: two rings of four probes at 90 degrees
    (the corners of a square prism) lie on a whole family of cylinders.

    Probe-ball centres lie on a cylinder of radius r +/- ball radius with the
    same axis, so they may be fitted directly: the axis is what matters.

    sigma_mm: a-priori standard uncertainty per coordinate of each point.
    The (4, 4) axis covariance is ``sigma^2 (J^T J)^-1`` (Gauss-Newton,
    first order), with J the Jacobian of the residuals with respect to
    (x, y, a, b, r) at the solution, reduced to the axis block.
    """
    P = _as_points(points, 5, "cylinder fit")
    _, _, Vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
    # The principal axes, then the four body diagonals of the principal frame:
    # more starts find more of the alternative cylinders of a poor probe pattern.
    diagonals = [Vt.T @ np.array([1.0, sy, sz]) / np.sqrt(3) for sy in (1, -1) for sz in (1, -1)]
    starts = [Vt[k] for k in range(3)] + diagonals
    if direction_hint is not None:
        hint = np.asarray(direction_hint, dtype=np.float64)
        starts.insert(0, hint / np.linalg.norm(hint))

    solutions = []
    for d0 in starts:
        origin, e1, e2, r0 = _cylinder_from(d0, P)
        if not np.isfinite(r0) or r0 <= 0:
            continue
        params = np.array([0.0, 0.0, 0.0, 0.0, r0])
        for _ in range(8):
            result = least_squares(
                _cylinder_residuals, params, jac=_cylinder_jacobian, args=(P, origin, d0, e1, e2),
                method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=60,
            )
            if result.status > 0:  # converged (0: evaluation budget used up)
                solutions.append((float(result.fun @ result.fun), result.x, origin, d0, e1, e2))
                break
            # Re-centre the parametrisation on the current axis: after a large turn the
            # axis point's offsets (x, y) include a slide along the axis, a flat direction
            # that stalls Levenberg-Marquardt.
            line, radius, e1, e2 = _axis_line(*result.x, origin, d0, e1, e2, P)
            origin, d0 = line.point, line.direction
            params = np.array([0.0, 0.0, 0.0, 0.0, radius])
    if not solutions:
        raise ValueError(f"cylinder fit: no start converged for these {len(P)} points (degenerate?)")
    best = min(solutions, key=lambda sol: sol[0])
    _, (x, y, a, b, r), origin, d0, e1, e2 = best
    line, radius, f1, f2 = _axis_line(x, y, a, b, r, origin, d0, e1, e2, P)
    residuals = _cylinder_residuals(np.array([0, 0, 0, 0, radius]), P, line.point, line.direction, f1, f2)
    n = len(P)
    sigma = _posterior_sigma(residuals, n - 5, sigma_mm)
    J = _cylinder_jacobian(np.array([0.0, 0.0, 0.0, 0.0, radius]), P, line.point, line.direction, f1, f2)
    JtJ = J.T @ J
    if not np.isfinite(JtJ).all() or np.linalg.cond(JtJ) > 1e14:
        raise ValueError(
            f"cylinder fit: the axis is undetermined by these {n} points (singular normal equations)"
        )
    full = sigma**2 * np.linalg.inv(JtJ)
    _check_unique_cylinder(solutions, best[0], sigma, line, radius, f1, f2, full, P)
    return AxisFit(
        line=line,
        radius_mm=radius,
        residuals_mm=residuals,
        rms_mm=float(np.sqrt(np.mean(residuals**2))),
        sigma_mm=sigma,
        covariance=full[:4, :4],
        basis=(f1, f2),
        kind="cylinder",
    )


def _axis_line(x, y, a, b, r, origin, d0, e1, e2, P):
    """The solution as a Line3D with its point at the foot of the data centroid, radius, basis."""
    direction = _tilted(d0, e1, e2, a, b)
    axis_point = origin + x * e1 + y * e2
    foot = axis_point + ((P.mean(axis=0) - axis_point) @ direction) * direction
    line = Line3D(foot, direction)
    f1, f2 = perpendicular_basis(line.direction)
    return line, abs(float(r)), f1, f2


def _check_unique_cylinder(solutions, best_cost, sigma, line, radius, f1, f2, covariance, P) -> None:
    """Raise ValueError when another start converged to a different cylinder that fits
    about as well: sum of squares within 4x the best + 25 sigma^2 (a 5 sigma
    difference for one point) + a numerical floor.

    Sparse probe patterns admit several cylinders: the eight corners of two
    rings of four probes at 90 degrees lie on a family of tilted cylinders,
    any coplanar ring lies on plane-like cylinders of huge radius. "Different"
    means more than 5 standard deviations of the best fit (Mahalanobis, full
    5x5 covariance) and more than 1e-7 of the point spread (numerical floor).
    """
    extent = max(float(np.ptp(P, axis=0).max()), 1.0)
    floor = len(P) * (1e-9 * extent) ** 2
    information = np.linalg.pinv(covariance)
    for cost, (x, y, a, b, r), origin, d0, e1, e2 in solutions:
        if cost > 4.0 * best_cost + 25.0 * sigma**2 + floor:
            continue  # clearly worse: a local minimum
        other, other_r, _, _ = _axis_line(x, y, a, b, r, origin, d0, e1, e2, P)
        u = other.direction if other.direction @ line.direction > 0 else -other.direction
        v = other.point - line.point
        offset = v - (v @ u) * u  # where the other axis crosses the plane through line.point
        delta = np.array([offset @ f1, offset @ f2, u @ f1, u @ f2, other_r - radius])
        scaled = np.abs(delta) / np.array([extent, extent, 1.0, 1.0, extent])
        if scaled.max() > 1e-7 and float(delta @ information @ delta) > 25.0:
            raise ValueError(
                f"cylinder fit: the {len(P)} points fit more than one cylinder about equally well "
                f"(radius {radius:.4f} mm vs {other_r:.4f} mm, axes "
                f"{np.degrees(np.arccos(min(1.0, abs(u @ line.direction)))):.3f} deg apart); the probe "
                f"pattern cannot determine the axis: probe at three or more heights, at angles that "
                f"are not symmetric (e.g. 20, 80, 140, 200 deg)"
            )


# --------------------------------------------------------------------------
# The plan's reference elements
# --------------------------------------------------------------------------


def element_probes(element_id: str, points: Iterable[ProbedPoint]) -> list[ProbedPoint]:
    """The probes of reference element ``element_id``: the points labelled
    ``<id>.<k>`` (``L3.1``, ``L3.2``...), in import order."""
    prefix = element_id + "."
    return [p for p in points if p.label.startswith(prefix)]


def fit_reference_element(element: ReferenceLineSpec, points: Iterable[ProbedPoint]) -> AxisFit:
    """The fit of a plan's reference line to its CMM probes (global frame, mm).

    element: the plan's ``[[reference_line]]`` (``id``, ``fit`` = "line" or
    "cylinder", ``probes`` = the planned count). points: the imported probed
    points (``ReferenceData.points``); the element's are those labelled
    ``<id>.<k>`` (:func:`element_probes`). The fit is :func:`fit_line` or
    :func:`fit_cylinder_axis`, with the a-priori sigma the largest of the
    probes' ``sigma_mm``.

    This one function is what the measurement measures against and what the
    viewer draws. Raises ValueError naming the element when too few probes
    were imported (:data:`MIN_PROBES`) or the fit fails.

    Fits are cached for the process (:func:`_fit_probes`), keyed on the element's
    id and fit kind, its probes' coordinates (bytes) and the a-priori sigma: the
    measurement, the session's CMM evidence, the report and the viewer fit the same
    probes, and a cylinder fit of 12 probes takes ~14 ms. The result is shared between callers:
    :class:`AxisFit` is frozen and its arrays are read-only.
    """
    probes = element_probes(element.id, points)
    minimum = MIN_PROBES.get(element.fit)
    if minimum is None:
        raise ValueError(f"reference line {element.id}: unknown fit {element.fit!r} (line or cylinder)")
    if len(probes) < minimum:
        raise ValueError(
            f"reference line {element.id}: {len(probes)} of {element.probes} probes imported, "
            f"a {element.fit} fit needs at least {minimum}"
        )
    xyz = np.array([p.xyz for p in probes], dtype=np.float64)
    sigma = max(float(p.sigma_mm) for p in probes)
    return _fit_probes(element.id, element.fit, xyz.tobytes(), sigma)


@functools.lru_cache(maxsize=64)
def _fit_probes(element_id: str, fit: str, xyz_bytes: bytes, sigma_mm: float) -> AxisFit:
    """The ``fit`` ("line" or "cylinder") of the probes ``xyz_bytes`` ((N, 3) float64
    mm, C order) with a-priori sigma ``sigma_mm`` (mm): :func:`fit_reference_element`.

    Cached: a station session fitted the same probes twice (the measurement and the
    session's CMM evidence, 47-52 ms a session under cProfile, issue 25), and again
    in every later session of the process with the same reference. The key holds
    every input of the fit, so a hit returns what the fit would; the result is
    immutable (frozen :class:`AxisFit`, read-only arrays). Bounded: a Monte Carlo
    fits a new draw of the probes each time. A failed fit raises and is not cached.
    """
    xyz = frozen_array(np.frombuffer(xyz_bytes, dtype=np.float64).reshape(-1, 3))  # a read-only copy
    try:
        if fit == "cylinder":
            return fit_cylinder_axis(xyz, sigma_mm=sigma_mm)
        return fit_line(xyz, sigma_mm=sigma_mm)
    except ValueError as exc:
        raise ValueError(f"reference line {element_id}: {exc}") from None


# --------------------------------------------------------------------------
# Distances with first-order uncertainties
# --------------------------------------------------------------------------


def distance_point_point(a: np.ndarray, b: np.ndarray) -> float:
    """|a - b| in mm for (3,) points."""
    return float(np.linalg.norm(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)))


def distance_point_line(p: np.ndarray, line: Line3D) -> float:
    """Orthogonal distance in mm from (3,) point p to the line."""
    return line.distance(p)


def point_line_distance(
    p: np.ndarray, line_fit: AxisFit, point_cov: np.ndarray | None = None
) -> tuple[float, float, np.ndarray]:
    """Distance from p (3,) to a fitted axis, its standard uncertainty and d(dist)/dp.

    Returns (distance_mm, sigma_mm, gradient (3,)): first-order propagation of
    the point covariance ``point_cov`` (3, 3) (None = exact point) and of the
    fit's axis covariance: ``var = g_p^T C_p g_p + g_l^T C_l g_l``, where g_p is
    the unit normal from the line to p and g_l the gradient with respect to the
    axis parameters (x, y, a, b), analytic: with v = p - c, n = v - (v.u) u
    and n^ = n / |n|, d|n|/dx = -n^.e1, d|n|/dy = -n^.e2 (the point moves by
    x e1 + y e2) and d|n|/da = -(v.u) n^.e1, d|n|/db = -(v.u) n^.e2 (the
    direction tilts to u + a e1 + b e2; first order, n^ is normal to u).
    """
    p = np.asarray(p, dtype=np.float64)
    line = line_fit.line
    v = p - line.point
    along = float(v @ line.direction)
    normal = v - along * line.direction
    d = float(np.linalg.norm(normal))
    g_p = normal / d if d > 0 else np.zeros(3)
    e1, e2 = line_fit.basis
    n1, n2 = float(g_p @ e1), float(g_p @ e2)
    g_l = np.array([-n1, -n2, -along * n1, -along * n2])
    var = float(g_l @ line_fit.covariance @ g_l)
    if point_cov is not None:
        var += float(g_p @ np.asarray(point_cov) @ g_p)
    return d, float(np.sqrt(max(var, 0.0))), g_p
