"""The NumPy formulation of the measure stage "plan" (plugins/measure_plan.py as of a926baf,
before issue 25's kernels), kept unchanged as the reference the compiled one must reproduce
bit for bit (tests/measure/test_measure_kernels.py). Not a plugin: nothing registers it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from crossfield.plugin_api import (
    DEFAULT_SCALE_U,
    AxisFit,
    CameraPoints,
    CharacteristicResult,
    CharacteristicSpec,
    GroundTruth,
    Measurement,
    MeasurementError,
    MeasurementPlan,
    ReferenceData,
    Registration,
    RegistrationConsistency,
    camera_covariance,
    combined,
    eccentricity_sigma_mm,
    excess_dof,
    fit_reference_element,
    merge,
    off_axis_rad,
    point_line_distance,
    registration_jacobian,
)

#: Budget sources of a point's own covariance and of the registration covariance.
_POINT_SOURCES = ("camera", "eccentricity", "reference_cmm")
_REGISTRATION_SOURCES = ("camera", "eccentricity", "control_cmm")


@dataclass(frozen=True)
class _Point:
    """A point of a characteristic, global frame: xyz (3,) mm; its own covariance
    (3, 3) mm^2 per budget source; its Jacobian (3, 6) with respect to the
    registration error (dtheta, dt); d_cal (3,) mm, how it moves per unit relative
    scale error of the calibration (``p - g_bar`` for camera points, 0 for CMM points)."""

    xyz: np.ndarray
    cov: dict[str, np.ndarray]
    J_reg: np.ndarray
    d_cal: np.ndarray


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
        spec_u = plan.uncertainty
        ecc_factor = spec_u.eccentricity_residual if spec_u.eccentricity_corrected else 1.0

        # The eccentricity covariance (3, 3) mm^2 of each camera point, computed once per
        # point and frame: the budget inputs, the registration's controls and the targets
        # asked 20 times for 10 points (~0.25 ms a pair under cProfile, issue 25).
        # Read-only: the same array goes to every use.
        ecc_covs = [
            self._eccentricity_cov(xyz, ecc_factor, spec_u.target_radius_mm, spec_u.max_tilt_deg)
            for xyz in points.xyz
        ]

        C_reg, g_bar, consistency = self._registration_covariance(reference, points, registration, ecc_covs)

        def camera_point(index: int) -> _Point:
            cov = {"camera": camera_covariance(R, points.sigma_xyz[index]), "eccentricity": ecc_covs[index]}
            J = registration_jacobian(global_xyz[index], g_bar)
            return _Point(global_xyz[index], cov, J, global_xyz[index] - g_bar)

        found, missing = self._identify_targets(plan, global_xyz, registration)
        elements: dict[str, _Point] = {tid: camera_point(i) for tid, i in found.items()}
        by_label = reference.by_label()
        for pid in list(plan.control_ids) + list(plan.reference_point_ids):
            if pid in by_label:
                probe = by_label[pid]
                cov = {"reference_cmm": probe.sigma_mm**2 * np.eye(3)}
                elements[pid] = _Point(np.array(probe.xyz), cov, np.zeros((3, 6)), np.zeros(3))
        inputs = {
            "camera": (float(np.mean(points.sigma_xyz)) if len(points.xyz) else 0.0, "mm"),
            "eccentricity": (float(np.sqrt(np.mean([cov[0, 0] for cov in ecc_covs])))
                             if len(points.xyz) else 0.0, "mm"),
            "calibration": (self._calibration_u(plan), "1"),
            "control_cmm": (self._control_sigma(reference, registration), "mm"),
        }

        results = []
        for spec in plan.characteristics:
            result = self._evaluate(spec, plan, reference, elements, C_reg, ground_truth, inputs)
            if result is not None:
                results.append(result)
        return Measurement(
            sequence=points.sequence,
            characteristics=tuple(results),
            target_points={tid: tuple(float(v) for v in global_xyz[i]) for tid, i in found.items()},
            missing_targets=tuple(missing),
            consistency=consistency,
        )

    @staticmethod
    def _eccentricity_cov(
        xyz: np.ndarray, factor: float, radius_mm: float, max_tilt_deg: float
    ) -> np.ndarray:
        """The eccentricity covariance (3, 3) mm^2, isotropic, of a circle centre at camera
        point ``xyz`` (3,) mm (targets of radius ``radius_mm``, tilted up to ``max_tilt_deg``):
        ``(factor * eccentricity_sigma_mm)^2 I``, read-only."""
        s_e = factor * eccentricity_sigma_mm(
            float(np.linalg.norm(xyz)), radius_mm, max_tilt_deg, off_axis_rad(xyz)
        )
        cov = s_e**2 * np.eye(3)
        cov.flags.writeable = False
        return cov

    @staticmethod
    def _calibration_u(plan: MeasurementPlan) -> float:
        u = plan.uncertainty.calibration_scale_u
        return DEFAULT_SCALE_U if u is None else u

    @staticmethod
    def _control_sigma(reference: ReferenceData, registration: Registration) -> float:
        by_label = reference.by_label()
        sigmas = [by_label[c].sigma_mm for c in registration.correspondence.control_ids if c in by_label]
        return float(np.mean(sigmas)) if sigmas else 0.0

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
        self, reference: ReferenceData, points: CameraPoints, registration: Registration, ecc_covs
    ) -> tuple[dict[str, np.ndarray], np.ndarray, RegistrationConsistency | None]:
        """Per budget source, the (6, 6) covariance of (dtheta, dt); the control centroid
        g_bar (3,), global mm; the residuals against the stated sigmas. ``ecc_covs``: each
        camera point's (3, 3) mm^2 eccentricity covariance, by camera index."""
        corr = registration.correspondence
        by_label = reference.by_label()
        pairs = [(cid, int(i)) for cid, i in zip(corr.control_ids, corr.camera_index) if cid in by_label]
        zero = {src: np.zeros((6, 6)) for src in _REGISTRATION_SOURCES}
        if not pairs:
            return zero, np.zeros(3), None
        G = np.array([by_label[cid].xyz for cid, _ in pairs])
        g_bar = G.mean(axis=0)
        # Linearised least squares (equal weights): the residual of control k moves by
        # J_k xi with J_k = [-[y_k]x, I], xi = (dtheta, dt), y_k = g_k - g_bar, and its
        # noise e_k has covariance S_k = R Sigma_cam,k R^T + Sigma_ecc,k + sigma_cmm,k^2 I,
        # so Cov(xi) = (J^T J)^-1 (J^T S J) (J^T J)^-1 (sandwich form), linear in S:
        # one sandwich per independent source.
        R = registration.fit.R * registration.fit.scale
        JtJ = np.zeros((6, 6))
        JtSJ = {src: np.zeros((6, 6)) for src in _REGISTRATION_SOURCES}
        trace = dict.fromkeys(_REGISTRATION_SOURCES, 0.0)
        trace_k: dict[str, float] = {}
        for g, (cid, index) in zip(G, pairs):
            J = registration_jacobian(g, g_bar)
            S = {
                "camera": camera_covariance(R, points.sigma_xyz[index]),
                "eccentricity": ecc_covs[index],
                "control_cmm": by_label[cid].sigma_mm ** 2 * np.eye(3),
            }
            JtJ += J.T @ J
            for src in _REGISTRATION_SOURCES:
                JtSJ[src] += J.T @ S[src] @ J
                trace[src] += float(np.trace(S[src]))
            trace_k[cid] = float(sum(np.trace(S[src]) for src in _REGISTRATION_SOURCES))
        inverse = np.linalg.pinv(JtJ)
        cov = {src: inverse @ JtSJ[src] @ inverse for src in _REGISTRATION_SOURCES}
        if not self.registration_uncertainty:
            cov = zero
        # Residuals against the stated sigmas: E sum |r_k|^2 = (1 - 6 / 3n) sum tr S_k
        # (3n coordinates, 6 parameters); the test is made over the session
        # (crossfield.uncertainty.consistency).
        n = len(pairs)
        consistency = None
        if n > 2:
            residuals = np.asarray(registration.fit.residuals)
            keep = [k for k, cid in enumerate(corr.control_ids) if cid in by_label]
            factor = 1.0 - 2.0 / n
            # The pose (R, t_global_camera): t is where the camera origin goes, a point
            # moved by J(t) xi (crossfield.covariance.registration_jacobian).
            J_t = registration_jacobian(registration.fit.t, g_bar)
            to_pose = np.vstack([np.hstack([np.eye(3), np.zeros((3, 3))]), J_t])
            camera_side = cov["camera"] + cov["eccentricity"]
            consistency = RegistrationConsistency(
                observed_ss_mm2=float(np.sum(residuals[keep] ** 2)),
                expected_camera_ss_mm2=factor * (trace["camera"] + trace["eccentricity"]),
                expected_cmm_ss_mm2=factor * trace["control_cmm"],
                dof=3 * n - 6,
                expected_residual_mm={cid: float(np.sqrt(factor * t)) for cid, t in trace_k.items()},
                pose_cov_camera=to_pose @ camera_side @ to_pose.T,
                pose_cov_cmm=to_pose @ cov["control_cmm"] @ to_pose.T,
                **_epipolar_evidence(points),
            )
        return cov, g_bar, consistency

    def _evaluate(
        self,
        spec: CharacteristicSpec,
        plan: MeasurementPlan,
        reference: ReferenceData,
        elements: dict[str, _Point],
        C_reg: dict[str, np.ndarray],
        truth: GroundTruth | None,
        inputs: dict[str, tuple[float, str]],
    ) -> CharacteristicResult | None:
        if spec.a not in elements or (spec.kind == "point_point" and spec.b not in elements):
            return None  # a target not found or a CMM point not imported: nothing to report
        a = elements[spec.a]
        actual = None
        line_var = 0.0
        line_sigma = 0.0
        line_dof = float("inf")
        if spec.kind == "point_point":
            b = elements[spec.b]
            diff = a.xyz - b.xyz
            measured = float(np.linalg.norm(diff))
            u = diff / measured if measured > 0 else np.zeros(3)
            gradients = [(a, u), (b, -u)]
            if truth is not None and spec.a in truth.points_global and spec.b in truth.points_global:
                true_a, true_b = truth.points_global[spec.a], truth.points_global[spec.b]
                actual = float(np.linalg.norm(np.asarray(true_a) - np.asarray(true_b)))
        elif spec.kind == "point_line":
            line = self.reference_line(plan, reference, spec.b)
            measured, line_sd, g_p = point_line_distance(a.xyz, line, None)
            line_var = line_sd**2  # the axis fit's own covariance (its CMM probes, posterior sigma)
            line_sigma = line.sigma_mm  # max(stated, observed): geometry.fit_cylinder_axis
            stated = max((p.sigma_mm for p in reference.points if p.label.startswith(f"{spec.b}.")), default=0.0)
            line_dof = _fit_dof(line, stated)
            gradients = [(a, g_p)]
            if truth is not None and spec.a in truth.points_global and spec.b in truth.lines_global:
                actual = truth.lines_global[spec.b].distance(truth.points_global[spec.a])
        else:  # depth: global Z of a
            measured = float(a.xyz[2])
            gradients = [(a, np.array([0.0, 0.0, 1.0]))]
            if truth is not None and spec.a in truth.points_global:
                actual = float(truth.points_global[spec.a][2])
        budget = self._budget(spec, gradients, C_reg, inputs, line_var, line_sigma, elements)
        if spec.kind == "point_line":  # the fit's own residuals set its sigma: Type A with the fit's dof
            budget = tuple(replace(t, dof=line_dof) if t.source == "reference_line" else t for t in budget)
        deviation = measured - spec.nominal_mm
        return CharacteristicResult(
            name=spec.name,
            kind=spec.kind,
            measured_mm=measured,
            nominal_mm=spec.nominal_mm,
            tolerance_mm=spec.tolerance_mm,
            deviation_mm=deviation,
            passed=bool(-spec.lower_tol_mm <= deviation <= spec.upper_tol_mm),
            uncertainty_mm=combined(budget),
            actual_mm=actual,
            error_mm=None if actual is None else measured - actual,
            elements=(spec.a,) + ((spec.b,) if spec.b else ()),
            budget=budget,
        )

    def _budget(
        self,
        spec: CharacteristicSpec,
        gradients: list[tuple[_Point, np.ndarray]],
        C_reg: dict[str, np.ndarray],
        inputs: dict[str, tuple[float, str]],
        line_var: float,
        line_sigma: float,
        elements: dict[str, _Point],
    ) -> tuple:
        """Per-source variance of the characteristic y = f(points): with g_j = dy/dp_j,
        ``var_src = sum_j g_j^T Sigma_src,j g_j + (sum_j g_j^T J_j) C_src (sum_j J_j^T g_j)``
        (the registration is shared by the points: its effect enters through the sum of
        their Jacobians, GUM eq. (13)); calibration ``(u_s sum_j g_j . d_cal,j)^2``."""
        variance = dict.fromkeys(("camera", "eccentricity", "control_cmm", "reference_cmm"), 0.0)
        J_sum = np.zeros(6)
        c_cal = 0.0
        for point, g in gradients:
            for src, cov in point.cov.items():
                variance[src] += float(g @ cov @ g)
            J_sum += g @ point.J_reg
            c_cal += float(g @ point.d_cal)
        for src in _REGISTRATION_SOURCES:
            variance[src] += float(J_sum @ C_reg[src] @ J_sum)
        cmm_points = [p for p, _ in gradients if "reference_cmm" in p.cov]
        ref_u = max([float(np.sqrt(p.cov["reference_cmm"][0, 0])) for p in cmm_points], default=0.0)
        u_cal = inputs["calibration"][0]
        table = {
            "camera": (*inputs["camera"], variance["camera"]),
            "eccentricity": (*inputs["eccentricity"], variance["eccentricity"]),
            "calibration": (u_cal, "1", (c_cal * u_cal) ** 2),
            "control_cmm": (*inputs["control_cmm"], variance["control_cmm"]),
            "reference_cmm": (ref_u, "mm", variance["reference_cmm"]),
        }
        if spec.kind == "point_line":  # the axis fit's own covariance, its sigma data-supported
            table["reference_line"] = (line_sigma, "mm", line_var)
        return merge(table)


def _fit_dof(fit: AxisFit, stated_mm: float) -> float:
    """The degrees of freedom of a line fit's sigma (crossfield.uncertainty.dof): its excess over
    the stated sigma ``stated_mm`` is estimated with the fit's nu (a cylinder of N probes N - 5, a
    line 2N - 4), so the term has ``nu / w^2``, w = 1 - stated^2 / sigma^2 (infinite where the
    stated sigma set it; ``dof.excess_dof``)."""
    n = len(fit.residuals_mm)
    nu = n - 5 if fit.kind == "cylinder" else 2 * n - 4
    if nu <= 0 or not fit.sigma_mm > 0:
        return float("inf")
    return excess_dof(nu, 1.0 - (stated_mm / fit.sigma_mm) ** 2)


def _epipolar_evidence(points: CameraPoints) -> dict[str, float | int]:
    """The frame's Type A evidence on the camera term: the sum of its matched points' epipolar
    chi-square (``CameraPoints.chi2``, 1 dof each) and their number (``crossfield.uncertainty.type_a``)."""
    chi2 = getattr(points, "chi2", None)
    if chi2 is None:
        return {}
    finite = np.asarray(chi2)[np.isfinite(chi2)]
    return {"epipolar_chi2": float(finite.sum()), "epipolar_count": int(finite.size)}


