"""Measure implementation "plan": evaluate the measurement plan's characteristics.

For one stereo pair:

1. Camera points go to the global frame with the registration
   (``p_g = R p_c + t``, paper Formula (5)/(9) transform).
2. Each plan target is identified as the camera point, not used as a control
   by the correspondence, within ``search_radius`` of its nominal global
   position. None -> missing; more than one, or a point claimed by two
   targets -> ambiguous, also reported in ``missing_targets``.
3. Reference lines are fitted once per :class:`ReferenceData` (cached) to
   their CMM probes ``L3.1 .. L3.n``: ``fit = "line"`` by orthogonal least
   squares, ``fit = "cylinder"`` by a least-squares cylinder whose axis is
   the line (:mod:`crossfield.geometry`).
4. Characteristics: ``point_point`` |a - b|, ``point_line`` distance of point a
   to line b, ``depth`` global Z of point a. Points may be targets (camera),
   controls or reference points (CMM coordinates).

Uncertainty (first order, standard uncertainties, documented in
``docs/registration.md``): a camera point's covariance is its triangulation
covariance rotated into the global frame, ``R diag(sigma_xyz^2) R^T``, plus the
registration's contribution (target registration error; cf. Fitzpatrick,
West & Maurer 1998): the registration error moves a point p by
``dtheta x (p - g_bar) + dt``, g_bar the centroid of the matched controls,
and the covariance of (dtheta, dt) is the linearised least-squares one,
``(J^T J)^-1 J^T S J (J^T J)^-1`` with J_k = [-[g_k - g_bar]x, I] and S_k the
covariance of control k's camera point (rotated) plus its CMM covariance;
for isotropic errors sigma_f this is Fitzpatrick's ``Cov(dt) = sigma_f^2/n I``,
``Cov(dtheta) = sigma_f^2 (sum_k |y_k|^2 I - y_k y_k^T)^-1``. When the fit
residuals exceed what the stated sigmas predict, the covariance is scaled up
by their ratio. Two camera points share the registration, so its effect is
propagated through the difference of their Jacobians (it cancels for nearby
points). CMM points carry ``sigma_mm`` per coordinate; a fitted line carries
its parameter covariance. The solver's own weights are not modelled (the
estimate assumes equal weights).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crossfield.covariance import camera_covariance, registration_jacobian
from crossfield.errors import MeasurementError
from crossfield.geometry import AxisFit, fit_reference_element, point_line_distance
from crossfield.hookspecs import hookimpl
from crossfield.plan import CharacteristicSpec, MeasurementPlan
from crossfield.types import (
    CameraPoints,
    CharacteristicResult,
    GroundTruth,
    Measurement,
    ReferenceData,
    Registration,
)


@dataclass(frozen=True)
class _Point:
    """A point of a characteristic, global frame: xyz (3,) mm, own covariance (3, 3) mm^2,
    and its Jacobian (3, 6) with respect to the registration error (dtheta, dt)."""

    xyz: np.ndarray
    cov: np.ndarray
    J_reg: np.ndarray


class PlanMeasurer:
    """Evaluates the plan's characteristics per frame (see the module docstring).

    Options:
        registration_uncertainty: include the registration's contribution in
            each characteristic's uncertainty (default true).
    """

    def __init__(self, *, registration_uncertainty: bool = True):
        if not isinstance(registration_uncertainty, bool):
            raise ValueError(
                f"registration_uncertainty must be true or false, got {registration_uncertainty!r}"
            )
        self.registration_uncertainty = registration_uncertainty
        self._lines_for: ReferenceData | None = None
        self._lines: dict[str, AxisFit | str] = {}

    # ---- reference lines (cached per ReferenceData) -------------------------

    def reference_line(self, plan: MeasurementPlan, reference: ReferenceData, line_id: str) -> AxisFit:
        """The fit of reference line ``line_id`` to its probes (global frame, mm)."""
        if self._lines_for is not reference:
            self._lines_for, self._lines = reference, {}
        if line_id not in self._lines:
            self._lines[line_id] = self._fit_line(plan, reference, line_id)
        fit = self._lines[line_id]
        if isinstance(fit, str):
            raise MeasurementError(fit)
        return fit

    @staticmethod
    def _fit_line(plan: MeasurementPlan, reference: ReferenceData, line_id: str) -> AxisFit | str:
        spec = next(line for line in plan.reference_lines if line.id == line_id)
        try:
            return fit_reference_element(spec, reference.points)  # the viewer draws this same fit
        except ValueError as exc:
            return str(exc)

    # ---- per frame -----------------------------------------------------------

    def measure(
        self,
        plan: MeasurementPlan,
        reference: ReferenceData,
        points: CameraPoints,
        registration: Registration,
        ground_truth: GroundTruth | None,
    ) -> Measurement:
        """Evaluate ``plan``'s characteristics for one stereo pair (all lengths mm, global frame)."""
        fit = registration.fit
        R = fit.R * fit.scale
        global_xyz = fit.apply(points.xyz)
        C_reg, g_bar = self._registration_covariance(reference, points, registration)

        def camera_point(index: int) -> _Point:
            cov = camera_covariance(R, points.sigma_xyz[index])
            J = registration_jacobian(global_xyz[index], g_bar)
            return _Point(global_xyz[index], cov, J)

        found, missing = self._identify_targets(plan, global_xyz, registration)
        elements: dict[str, _Point] = {tid: camera_point(i) for tid, i in found.items()}
        by_label = reference.by_label()
        for pid in list(plan.control_ids) + list(plan.reference_point_ids):
            if pid in by_label:
                probe = by_label[pid]
                elements[pid] = _Point(np.array(probe.xyz), probe.sigma_mm**2 * np.eye(3), np.zeros((3, 6)))

        results = []
        for spec in plan.characteristics:
            result = self._evaluate(spec, plan, reference, elements, C_reg, ground_truth)
            if result is not None:
                results.append(result)
        return Measurement(
            sequence=points.sequence,
            characteristics=tuple(results),
            target_points={tid: tuple(float(v) for v in global_xyz[i]) for tid, i in found.items()},
            missing_targets=tuple(missing),
        )

    @staticmethod
    def _identify_targets(
        plan: MeasurementPlan, global_xyz: np.ndarray, registration: Registration
    ) -> tuple[dict[str, int], list[str]]:
        """Target id -> camera index for unambiguous targets; the others (missing or ambiguous)."""
        free = np.setdiff1d(np.arange(len(global_xyz)), registration.correspondence.camera_index)
        candidates: dict[str, list[int]] = {}
        for target in plan.targets:
            d = np.linalg.norm(global_xyz[free] - target.nominal, axis=1) if len(free) else np.zeros(0)
            candidates[target.id] = [int(i) for i in free[d <= target.search_radius_mm]]
        claimed: dict[int, int] = {}
        for indices in candidates.values():
            for i in indices:
                claimed[i] = claimed.get(i, 0) + 1
        found, missing = {}, []
        for target in plan.targets:
            indices = candidates[target.id]
            if len(indices) == 1 and claimed[indices[0]] == 1:
                found[target.id] = indices[0]
            else:
                missing.append(target.id)
        return found, missing

    def _registration_covariance(
        self, reference: ReferenceData, points: CameraPoints, registration: Registration
    ) -> tuple[np.ndarray, np.ndarray]:
        """(6, 6) covariance of (dtheta, dt) and the control centroid g_bar (3,), global mm."""
        corr = registration.correspondence
        by_label = reference.by_label()
        pairs = [(cid, int(i)) for cid, i in zip(corr.control_ids, corr.camera_index) if cid in by_label]
        if not pairs:
            return np.zeros((6, 6)), np.zeros(3)
        G = np.array([by_label[cid].xyz for cid, _ in pairs])
        g_bar = G.mean(axis=0)
        if not self.registration_uncertainty:
            return np.zeros((6, 6)), g_bar
        # Linearised least squares (equal weights): the residual of control k moves by
        # J_k xi with J_k = [-[y_k]x, I], xi = (dtheta, dt), y_k = g_k - g_bar, and its
        # noise e_k has covariance S_k = R Sigma_cam,k R^T + sigma_cmm,k^2 I, so
        # Cov(xi) = (J^T J)^-1 (J^T S J) (J^T J)^-1 (sandwich form).
        R = registration.fit.R * registration.fit.scale
        JtJ = np.zeros((6, 6))
        JtSJ = np.zeros((6, 6))
        trace_S = 0.0
        for g, (cid, index) in zip(G, pairs):
            J = registration_jacobian(g, g_bar)
            S = camera_covariance(R, points.sigma_xyz[index]) + by_label[cid].sigma_mm ** 2 * np.eye(3)
            JtJ += J.T @ J
            JtSJ += J.T @ S @ J
            trace_S += float(np.trace(S))
        inverse = np.linalg.pinv(JtJ)
        cov = inverse @ JtSJ @ inverse
        # A-posteriori check: when the fit residuals are larger than the stated sigmas
        # predict (E sum |r_k|^2 ~ (1 - 6 / 3n) sum tr S_k), scale the covariance up.
        n = len(pairs)
        if n > 2 and trace_S > 0:
            observed = float(np.sum(np.asarray(registration.fit.residuals) ** 2))
            cov *= max(1.0, observed / ((1.0 - 2.0 / n) * trace_S))
        return cov, g_bar

    def _evaluate(
        self,
        spec: CharacteristicSpec,
        plan: MeasurementPlan,
        reference: ReferenceData,
        elements: dict[str, _Point],
        C_reg: np.ndarray,
        truth: GroundTruth | None,
    ) -> CharacteristicResult | None:
        if spec.a not in elements or (spec.kind == "point_point" and spec.b not in elements):
            return None  # a target not found or a CMM point not imported: nothing to report
        a = elements[spec.a]
        actual = None
        if spec.kind == "point_point":
            b = elements[spec.b]
            diff = a.xyz - b.xyz
            measured = float(np.linalg.norm(diff))
            u = diff / measured if measured > 0 else np.zeros(3)
            J = a.J_reg - b.J_reg  # shared registration: correlated, propagate the difference
            var = u @ (a.cov + b.cov + J @ C_reg @ J.T) @ u
            if truth is not None and spec.a in truth.points_global and spec.b in truth.points_global:
                true_a, true_b = truth.points_global[spec.a], truth.points_global[spec.b]
                actual = float(np.linalg.norm(np.asarray(true_a) - np.asarray(true_b)))
        elif spec.kind == "point_line":
            line = self.reference_line(plan, reference, spec.b)
            point_cov = a.cov + a.J_reg @ C_reg @ a.J_reg.T
            measured, sigma, _ = point_line_distance(a.xyz, line, point_cov)
            var = sigma**2
            if truth is not None and spec.a in truth.points_global and spec.b in truth.lines_global:
                actual = truth.lines_global[spec.b].distance(truth.points_global[spec.a])
        else:  # depth: global Z of a
            measured = float(a.xyz[2])
            var = (a.cov + a.J_reg @ C_reg @ a.J_reg.T)[2, 2]
            if truth is not None and spec.a in truth.points_global:
                actual = float(truth.points_global[spec.a][2])
        deviation = measured - spec.nominal_mm
        return CharacteristicResult(
            name=spec.name,
            kind=spec.kind,
            measured_mm=measured,
            nominal_mm=spec.nominal_mm,
            tolerance_mm=spec.tolerance_mm,
            deviation_mm=deviation,
            passed=bool(abs(deviation) <= spec.tolerance_mm),
            uncertainty_mm=float(np.sqrt(max(float(var), 0.0))),
            actual_mm=actual,
            error_mm=None if actual is None else measured - actual,
            elements=(spec.a,) + ((spec.b,) if spec.b else ()),
        )


@hookimpl
def register_measures(register):
    register("plan", PlanMeasurer, "Plan characteristics: point-point, point-line (fitted axes), depth")
