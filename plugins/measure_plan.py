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
``Cov(dtheta) = sigma_f^2 (sum_k |y_k|^2 I - y_k y_k^T)^-1``. The fit
residuals against the stated sigmas go with each frame's measurement
(``Measurement.consistency``); the session tests them (chi-square) and
inflates the CMM sigma when they contradict it (``crossfield.uncertainty``).
Two camera points share the registration, so its effect is
propagated through the difference of their Jacobians (it cancels for nearby
points). CMM points carry ``sigma_mm`` per coordinate; a fitted line carries
its parameter covariance. The solver's own weights are not modelled (the
estimate assumes equal weights).

Budget (``docs/uncertainty.md``): the variance is split by independent source
(camera centroid noise, eccentricity of circle centres, calibration scale,
control-point CMM, reference CMM); each source's contribution holds the
correlations of the shared registration, and the squares add up to
``uncertainty_mm**2``.

Implementation (issue 25): what depends only on the plan and the CMM data (the
CMM points, their covariances, the targets' nominal positions, the fitted lines
and their dof) is prepared once per session (:class:`_Session`); per frame the
eccentricity covariances of all camera points are one vectorised evaluation,
the targets are identified in one broadcast, and the registration's normal
equations, its covariance and every characteristic's budget are three numba
kernels instead of ~250 small NumPy calls. The kernels carry out the very
floating-point operations the NumPy formulation made, in the same order: each
small product is summed as OpenBLAS's kernels sum it (measured on this
machine's kernels, ``tests/measure/test_measure_kernels.py``): a dot product, a
matrix product (dgemm, dsyrk) and a 3-wide vector-matrix product as one fused
multiply-add chain over the inner index, the wider vector-matrix products
(dgemv_n) in the blocks its micro-kernels use (:func:`vecmat`). The reports
are bit-identical with the NumPy formulation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from crossfield.plugin_api import (
    dot,
    matmul,
    matmul_at,
    matmul_bt,
    quadratic,
    vecmat,
    DEFAULT_SCALE_U,
    AxisFit,
    CameraPoints,
    CharacteristicResult,
    GroundTruth,
    Measurement,
    MeasurementError,
    MeasurementPlan,
    ReferenceData,
    Registration,
    RegistrationConsistency,
    combined,
    excess_dof,
    fit_reference_element,
    hookimpl,
    merge,
)

#: Budget sources of a point's own covariance and of the registration covariance.
_POINT_SOURCES = ("camera", "eccentricity", "reference_cmm")
_REGISTRATION_SOURCES = ("camera", "eccentricity", "control_cmm")

#: Characteristic kinds, as the budget kernel numbers them.
_KINDS = {"point_point": 0, "point_line": 1, "depth": 2}
#: Element references of the budget kernel: a camera point (index into CameraPoints) or a
#: CMM point (index into :attr:`_Session.cmm_xyz`).
_CAMERA, _CMM = 0, 1

_njit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_njit
def _jacobian(p, g_bar):
    """``J = [-[p - g_bar]_x, I_3]`` (3, 6), entry for entry as
    ``crossfield.covariance.registration_jacobian`` (its diagonal -0.0 included)."""
    y0, y1, y2 = p[0] - g_bar[0], p[1] - g_bar[1], p[2] - g_bar[2]
    J = np.zeros((3, 6))
    J[0, 0], J[0, 1], J[0, 2] = -0.0, y2, -y1
    J[1, 0], J[1, 1], J[1, 2] = -y2, -0.0, y0
    J[2, 0], J[2, 1], J[2, 2] = y1, -y0, -0.0
    J[0, 3] = J[1, 4] = J[2, 5] = 1.0
    return J


@_njit
def _camera_cov(A, sigma):
    """``A diag(sigma^2) A^T`` (3, 3) mm^2 (``crossfield.covariance.camera_covariance``):
    ``(A * sigma^2) @ A.T``."""
    M = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            M[i, j] = A[i, j] * (sigma[j] * sigma[j])
    return matmul_bt(M, A)


@_njit
def _isotropic(var):
    """``var * I_3`` (3, 3), as ``var * np.eye(3)`` (off-diagonal ``var * 0.0``)."""
    S = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            S[i, j] = var * (1.0 if i == j else 0.0)
    return S


# --------------------------------------------------------------------------
# Frame kernels
# --------------------------------------------------------------------------


@_njit
def _normal_equations(G, g_bar, A, sigma, ecc_var, cmm_var):
    """The registration's linearised least squares over its K matched controls.

    G (K, 3): the controls' CMM positions (global mm); g_bar (3,) their centroid; A (3, 3)
    ``scale R`` (global <- camera); sigma (K, 3) mm: the controls' camera points' per-axis
    sigmas (camera frame); ecc_var (K,) mm^2 their eccentricity variances; cmm_var (K,) mm^2
    the CMM variances (``sigma_mm**2``). With J_k = [-[g_k - g_bar]_x, I] and per source
    S_k (camera ``A diag(sigma^2) A^T``, eccentricity and CMM isotropic), returns
    ``sum_k J_k^T J_k`` (6, 6), ``sum_k J_k^T S_k J_k`` (3, 6, 6) in the order of
    ``_REGISTRATION_SOURCES``, ``sum_k tr S_k`` (3,) mm^2 and per control
    ``tr S_cam + tr S_ecc + tr S_cmm`` (K,) mm^2 (the sums in control order)."""
    K = G.shape[0]
    JtJ = np.zeros((6, 6))
    JtSJ = np.zeros((3, 6, 6))
    trace = np.zeros(3)
    trace_k = np.empty(K)
    S = np.empty((3, 3, 3))
    for k in range(K):
        J = _jacobian(G[k], g_bar)
        S[0] = _camera_cov(A, sigma[k])
        S[1] = _isotropic(ecc_var[k])
        S[2] = _isotropic(cmm_var[k])
        JtJ += matmul_at(J, J)
        total = 0.0
        for s in range(3):
            JtSJ[s] += matmul(matmul_at(J, S[s]), J)
            tr = (S[s, 0, 0] + S[s, 1, 1]) + S[s, 2, 2]  # np.trace
            trace[s] = trace[s] + tr
            total = total + tr
        trace_k[k] = total
    return JtJ, JtSJ, trace, trace_k


@_njit
def _sandwich(inverse, JtSJ):
    """``Cov(xi)_src = (J^T J)^+ (J^T S_src J) (J^T J)^+`` (3, 6, 6) for the pseudo-inverse
    ``inverse`` (6, 6) and the (3, 6, 6) middle terms."""
    C = np.empty((3, 6, 6))
    for s in range(3):
        C[s] = matmul(matmul(inverse, JtSJ[s]), inverse)
    return C


@_njit
def _pose_covariances(t, g_bar, C):
    """The covariances (6, 6) of the pose (rotation, t_global_camera), camera side (camera +
    eccentricity) and CMM side, from the registration's ``C`` (3, 6, 6): ``T Cov T^T`` with
    ``T = [[I, 0], J(t)]`` (t (3,) mm, where the camera origin goes, moves by J(t) xi)."""
    to_pose = np.zeros((6, 6))
    to_pose[0, 0] = to_pose[1, 1] = to_pose[2, 2] = 1.0
    to_pose[3:, :] = _jacobian(t, g_bar)
    camera_side = C[0] + C[1]
    return (matmul_bt(matmul(to_pose, camera_side), to_pose),
            matmul_bt(matmul(to_pose, C[2]), to_pose))


@_njit
def _point_line(p, point, direction, e1, e2, cov):
    """Distance (mm) of p (3,) to the line (point, unit direction), the variance (mm^2) of the
    line's own parameters along it and the gradient d(dist)/dp (3,): the arithmetic of
    ``crossfield.geometry.point_line_distance`` without a point covariance (its
    ``g_l^T C_l g_l``, g_l = -(n^.e1, n^.e2, (v.u) n^.e1, (v.u) n^.e2), C_l (4, 4))."""
    v = p - point
    along = dot(v, direction)
    normal = v - along * direction
    d = math.sqrt(dot(normal, normal))
    g_p = normal / d if d > 0 else np.zeros(3)
    n1, n2 = dot(g_p, e1), dot(g_p, e2)
    g_l = np.array([-n1, -n2, -along * n1, -along * n2])
    return d, quadratic(g_l, cov), g_p


@_njit
def _characteristics(kinds, refs, lines, X, sigma, ecc_var, A, g_bar, cmm_xyz, cmm_var,
                     line_point, line_dir, line_basis, line_cov, C_reg):
    """Value and budget variances of M characteristics (global frame, mm).

    kinds (M,): ``_KINDS``; refs (M, 2, 2): per element a (kind, index), ``_CAMERA`` into
    X (N, 3) (the camera points, global), sigma (N, 3) and ecc_var (N,), ``_CMM`` into
    cmm_xyz (P, 3), cmm_var (P,); lines (M,): the line of a point_line into line_point,
    line_dir (L, 3), line_basis (L, 2, 3), line_cov (L, 4, 4). A (3, 3) ``scale R``, g_bar (3,)
    the control centroid, C_reg (3, 6, 6) the registration covariance per source.

    With g_j = dy/dp_j (``u, -u`` for |a - b|, the line normal, e_z for a depth), GUM eq. (13):
    ``var_src = sum_j g_j^T Sigma_src,j g_j + (sum_j g_j^T J_j) C_src (sum_j J_j^T g_j)``,
    J_j = [-[p_j - g_bar]_x, I] for camera points, 0 for CMM points, and the calibration
    sensitivity ``c_cal = sum_j g_j . (p_j - g_bar)`` (camera points).

    Returns measured (M,) mm, variances (M, 4) mm^2 (camera, eccentricity, control_cmm,
    reference_cmm), c_cal (M,) mm and the line's own variance (M,) mm^2 (0 off point_line)."""
    M = kinds.shape[0]
    measured = np.empty(M)
    variance = np.zeros((M, 4))
    c_cal = np.zeros(M)
    line_var = np.zeros(M)
    zero_J = np.zeros((3, 6))
    zero3 = np.zeros(3)
    grads = np.empty((2, 3))
    for c in range(M):
        pa = X[refs[c, 0, 1]] if refs[c, 0, 0] == _CAMERA else cmm_xyz[refs[c, 0, 1]]
        n_grad = 1
        if kinds[c] == 0:  # point_point: |a - b|
            pb = X[refs[c, 1, 1]] if refs[c, 1, 0] == _CAMERA else cmm_xyz[refs[c, 1, 1]]
            diff = pa - pb
            value = math.sqrt(dot(diff, diff))
            u = diff / value if value > 0 else np.zeros(3)
            grads[0] = u
            grads[1] = -u
            n_grad = 2
        elif kinds[c] == 1:  # point_line
            ln = lines[c]
            value, own, g_p = _point_line(
                pa, line_point[ln], line_dir[ln], line_basis[ln, 0], line_basis[ln, 1], line_cov[ln])
            line_var[c] = own
            grads[0] = g_p
        else:  # depth: global Z
            value = pa[2]
            grads[0, 0], grads[0, 1], grads[0, 2] = 0.0, 0.0, 1.0
        measured[c] = value
        J_sum = np.zeros(6)
        cal = 0.0
        for e in range(n_grad):
            g = grads[e]
            index = refs[c, e, 1]
            if refs[c, e, 0] == _CAMERA:
                variance[c, 0] += quadratic(g, _camera_cov(A, sigma[index]))
                variance[c, 1] += quadratic(g, _isotropic(ecc_var[index]))
                J = _jacobian(X[index], g_bar)
                d_cal = X[index] - g_bar
            else:
                variance[c, 3] += quadratic(g, _isotropic(cmm_var[index]))
                J = zero_J
                d_cal = zero3
            J_sum = J_sum + vecmat(g, J)
            cal = cal + dot(g, d_cal)
        c_cal[c] = cal
        for s in range(3):
            variance[c, s] += quadratic(J_sum, C_reg[s])
    return measured, variance, c_cal, line_var


@_njit
def _row_norms(X):
    """|x| (N,) of the rows of X (N, 3), as ``np.linalg.norm`` of one (``sqrt(x @ x)``)."""
    out = np.empty(X.shape[0])
    for i in range(X.shape[0]):
        out[i] = math.sqrt(dot(X[i], X[i]))
    return out


# --------------------------------------------------------------------------
# Per session
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Characteristic:
    """A plan characteristic as the frames evaluate it: its kind number, the line index of a
    point_line (-1 otherwise) or the reason its line has no fit, its elements' names, and for a
    point_line the fit's sigma (mm) and dof (:func:`_fit_dof`)."""

    spec: object
    kind: int
    line: int
    line_error: str | None
    elements: tuple[str, ...]
    line_sigma: float = 0.0
    line_dof: float = math.inf


class _Session:
    """What one (plan, reference) pair fixes for every frame: the CMM points the plan uses
    (positions (P, 3) mm, variances ``sigma_mm**2`` and sigmas (P,)), the control points' CMM
    positions and variances by label, the targets' nominal positions (T, 3) mm and search radii
    (T,), the fitted reference lines as arrays, each characteristic's kind and line, and the
    eccentricity model's constants."""

    def __init__(self, measurer: PlanMeasurer, plan: MeasurementPlan, reference: ReferenceData):
        self.plan, self.reference = plan, reference
        by_label = self.by_label = reference.by_label()
        self.control_xyz = {label: np.array(p.xyz, dtype=np.float64) for label, p in by_label.items()}
        self.control_var = {label: p.sigma_mm ** 2 for label, p in by_label.items()}
        self._control_sigma: dict[tuple[str, ...], float] = {}
        # the CMM points of the plan (controls, reference points): a later id replaces an earlier one
        self.cmm_index: dict[str, int] = {}
        xyz, var, u = [], [], []
        for pid in list(plan.control_ids) + list(plan.reference_point_ids):
            if pid in by_label:
                probe = by_label[pid]
                self.cmm_index[pid] = len(xyz)
                xyz.append(np.array(probe.xyz))
                var.append(probe.sigma_mm**2)
                u.append(float(np.sqrt(probe.sigma_mm**2 * 1.0)))  # sqrt of its covariance's (0, 0)
        self.cmm_xyz = np.array(xyz, dtype=np.float64).reshape(-1, 3)
        self.cmm_var = np.array(var, dtype=np.float64)
        self.cmm_u = u
        self.target_ids = [t.id for t in plan.targets]
        nominal = [np.asarray(t.nominal, dtype=np.float64) for t in plan.targets]
        self.target_nominal = np.array(nominal).reshape(-1, 3)
        self.target_radius = np.array([t.search_radius_mm for t in plan.targets], dtype=np.float64)
        self.characteristics = self._characteristics(measurer, plan, reference)
        spec_u = plan.uncertainty
        self.ecc_factor = spec_u.eccentricity_residual if spec_u.eccentricity_corrected else 1.0
        self.ecc_radius, self.ecc_tilt = spec_u.target_radius_mm, spec_u.max_tilt_deg
        stated_u = spec_u.calibration_scale_u
        self.calibration_u = DEFAULT_SCALE_U if stated_u is None else stated_u

    def _characteristics(self, measurer, plan, reference) -> list[_Characteristic]:
        lines: dict[str, int] = {}
        point, direction, basis, cov = [], [], [], []
        out = []
        for spec in plan.characteristics:
            elements = (spec.a,) + ((spec.b,) if spec.b else ())
            if spec.kind != "point_line":
                out.append(_Characteristic(spec, _KINDS[spec.kind], -1, None, elements))
                continue
            try:
                fit = measurer.reference_line(plan, reference, spec.b)
            except MeasurementError as exc:
                out.append(_Characteristic(spec, 1, -1, str(exc), elements))
                continue
            if spec.b not in lines:
                lines[spec.b] = len(point)
                point.append(fit.line.point)
                direction.append(fit.line.direction)
                basis.append(np.array(fit.basis))
                cov.append(fit.covariance)
            probes = f"{spec.b}."
            stated = max((p.sigma_mm for p in reference.points if p.label.startswith(probes)), default=0.0)
            dof = _fit_dof(fit, stated)
            out.append(_Characteristic(spec, 1, lines[spec.b], None, elements, fit.sigma_mm, dof))
        self.line_point = np.array(point, dtype=np.float64).reshape(-1, 3)
        self.line_dir = np.array(direction, dtype=np.float64).reshape(-1, 3)
        self.line_basis = np.array(basis, dtype=np.float64).reshape(-1, 2, 3)
        self.line_cov = np.array(cov, dtype=np.float64).reshape(-1, 4, 4)
        return out

    def control_sigma(self, control_ids) -> float:
        """The mean CMM sigma (mm) of the matched controls ``control_ids`` (0 for none)."""
        key = tuple(control_ids)
        sigma = self._control_sigma.get(key)
        if sigma is None:
            sigmas = [self.by_label[c].sigma_mm for c in key if c in self.by_label]
            sigma = self._control_sigma[key] = float(np.mean(sigmas)) if sigmas else 0.0
        return sigma

    def eccentricity_variances(self, xyz: np.ndarray) -> np.ndarray:
        """Per camera point (camera frame, xyz (N, 3) mm) its eccentricity variance (N,) mm^2:
        ``(factor * eccentricity_sigma_mm(|xyz|, r, tilt_max, off_axis_rad(xyz)))**2``, the
        diagonal of its isotropic covariance (``crossfield.uncertainty.eccentricity``), the same
        operations on all points at once (Python's ``**`` where it took a square)."""
        n = len(xyz)
        if n == 0:
            return np.zeros(0)
        radius, tilt = self.ecc_radius, self.ecc_tilt
        if radius <= 0 or tilt <= 0:
            sigma = np.zeros(n)
        else:
            distance = _row_norms(xyz)
            phi = np.arctan2(np.hypot(xyz[:, 0], xyz[:, 1]), xyz[:, 2])  # off_axis_rad
            c = float(np.cos(np.radians(min(tilt, 90.0))))
            mean_sin2_tilt = (2.0 / 3.0 - c + c**3 / 3.0) / (1.0 - c)
            sin2_phi = np.array([s**2 for s in np.sin(phi).tolist()])
            mean_sin2_theta = sin2_phi + mean_sin2_tilt * (1.0 - sin2_phi - sin2_phi / 2.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = distance * np.cos(phi)
                sigma = radius**2 / depth * np.sqrt(mean_sin2_theta / 2.0)
            sigma = np.where(distance <= 0, 0.0, sigma)
        return np.array([s**2 for s in (self.ecc_factor * sigma).tolist()])


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
        self._session: _Session | None = None

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

    def _session_for(self, plan: MeasurementPlan, reference: ReferenceData) -> _Session:
        """The per-session constants of (plan, reference), made on their first frame."""
        session = self._session
        if session is None or session.plan is not plan or session.reference is not reference:
            session = self._session = _Session(self, plan, reference)
        return session

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
        session = self._session_for(plan, reference)
        fit = registration.fit
        R = fit.R * fit.scale
        global_xyz = fit.apply(points.xyz)
        sigma = np.ascontiguousarray(points.sigma_xyz, dtype=np.float64).reshape(-1, 3)
        # each camera point's eccentricity variance (its covariance is that times I), once per frame
        ecc_var = session.eccentricity_variances(np.asarray(points.xyz, dtype=np.float64).reshape(-1, 3))
        C_reg, g_bar, consistency = self._registration_covariance(
            session, points, registration, sigma, ecc_var)
        found, missing = _identify_targets(session, global_xyz, registration)
        n = len(points.xyz)
        inputs = {
            "camera": (float(np.mean(points.sigma_xyz)) if n else 0.0, "mm"),
            "eccentricity": (float(np.sqrt(np.mean(ecc_var))) if n else 0.0, "mm"),
            "calibration": (session.calibration_u, "1"),
            "control_cmm": (session.control_sigma(registration.correspondence.control_ids), "mm"),
        }
        results = self._evaluate(
            session, found, global_xyz, sigma, ecc_var, R, g_bar, C_reg, ground_truth, inputs)
        return Measurement(
            sequence=points.sequence,
            characteristics=tuple(results),
            target_points={tid: tuple(global_xyz[i].tolist()) for tid, i in found.items()},
            missing_targets=tuple(missing),
            consistency=consistency,
        )

    def _registration_covariance(
        self, session: _Session, points: CameraPoints, registration: Registration, sigma: np.ndarray,
        ecc_var: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, RegistrationConsistency | None]:
        """The (3, 6, 6) covariance of (dtheta, dt) per source of ``_REGISTRATION_SOURCES``;
        the control centroid g_bar (3,), global mm; the residuals against the stated sigmas.
        ``sigma`` (N, 3) mm and ``ecc_var`` (N,) mm^2: each camera point's per-axis sigma
        (camera frame) and eccentricity variance, by camera index."""
        corr = registration.correspondence
        by_label = session.by_label
        pairs = [(cid, int(i)) for cid, i in zip(corr.control_ids, corr.camera_index) if cid in by_label]
        if not pairs:
            return np.zeros((3, 6, 6)), np.zeros(3), None
        G = np.array([session.control_xyz[cid] for cid, _ in pairs])
        g_bar = G.mean(axis=0)
        index = np.array([i for _, i in pairs], dtype=np.int64)
        # Linearised least squares (equal weights): the residual of control k moves by
        # J_k xi with J_k = [-[y_k]x, I], xi = (dtheta, dt), y_k = g_k - g_bar, and its
        # noise e_k has covariance S_k = R Sigma_cam,k R^T + Sigma_ecc,k + sigma_cmm,k^2 I,
        # so Cov(xi) = (J^T J)^-1 (J^T S J) (J^T J)^-1 (sandwich form), linear in S:
        # one sandwich per independent source.
        R = registration.fit.R * registration.fit.scale
        cmm_var = np.array([session.control_var[cid] for cid, _ in pairs])
        JtJ, JtSJ, trace, trace_k = _normal_equations(G, g_bar, R, sigma[index], ecc_var[index], cmm_var)
        inverse = np.linalg.pinv(JtJ)
        cov = _sandwich(inverse, JtSJ) if self.registration_uncertainty else np.zeros((3, 6, 6))
        # Residuals against the stated sigmas: E sum |r_k|^2 = (1 - 6 / 3n) sum tr S_k
        # (3n coordinates, 6 parameters); the test is made over the session
        # (crossfield.uncertainty.consistency).
        n = len(pairs)
        consistency = None
        if n > 2:
            residuals = np.asarray(registration.fit.residuals)
            keep = [k for k, cid in enumerate(corr.control_ids) if cid in by_label]
            factor = 1.0 - 2.0 / n
            trace_cam, trace_ecc, trace_cmm = trace.tolist()
            # The pose (R, t_global_camera): t is where the camera origin goes, a point
            # moved by J(t) xi (crossfield.covariance.registration_jacobian).
            pose_camera, pose_cmm = _pose_covariances(
                np.asarray(registration.fit.t, dtype=np.float64), g_bar, cov)
            consistency = RegistrationConsistency(
                observed_ss_mm2=float(np.sum(residuals[keep] ** 2)),
                expected_camera_ss_mm2=factor * (trace_cam + trace_ecc),
                expected_cmm_ss_mm2=factor * trace_cmm,
                dof=3 * n - 6,
                expected_residual_mm={
                    cid: math.sqrt(factor * t) for (cid, _), t in zip(pairs, trace_k.tolist())},
                pose_cov_camera=pose_camera,
                pose_cov_cmm=pose_cmm,
                **_epipolar_evidence(points),
            )
        return cov, g_bar, consistency

    def _evaluate(
        self,
        session: _Session,
        found: dict[str, int],
        global_xyz: np.ndarray,
        sigma: np.ndarray,
        ecc_var: np.ndarray,
        R: np.ndarray,
        g_bar: np.ndarray,
        C_reg: np.ndarray,
        truth: GroundTruth | None,
        inputs: dict[str, tuple[float, str]],
    ) -> list[CharacteristicResult]:
        """The characteristics whose elements this frame has (a target found, a CMM point
        imported), in plan order, with their budgets (:func:`_characteristics`, :func:`_budget`)."""
        cmm_index = session.cmm_index
        chosen, kinds, refs, lines = [], [], [], []
        for char in session.characteristics:
            spec = char.spec
            a = _element(spec.a, cmm_index, found)
            b = _element(spec.b, cmm_index, found) if char.kind == 0 else (_CAMERA, 0)
            if a is None or b is None:
                continue  # a target not found or a CMM point not imported: nothing to report
            if char.line_error is not None:
                raise MeasurementError(char.line_error)
            chosen.append(char)
            kinds.append(char.kind)
            refs.append((a, b))
            lines.append(char.line)
        if not chosen:
            return []
        measured, variance, c_cal, line_var = _characteristics(
            np.array(kinds, dtype=np.int64), np.array(refs, dtype=np.int64), np.array(lines, dtype=np.int64),
            np.ascontiguousarray(global_xyz), sigma, ecc_var, R, g_bar, session.cmm_xyz, session.cmm_var,
            session.line_point, session.line_dir, session.line_basis, session.line_cov, C_reg,
        )
        results = []
        for c, char in enumerate(chosen):
            results.append(_result(char, refs[c], float(measured[c]), variance[c].tolist(), float(c_cal[c]),
                                   float(line_var[c]), session, truth, inputs))
        return results


def _element(name: str, cmm_index: dict[str, int], found: dict[str, int]) -> tuple[int, int] | None:
    """A characteristic's element as the budget kernel refers to it: (``_CMM``, index) for a
    CMM point of the plan (these take precedence), (``_CAMERA``, camera index) for a target
    found in this frame, None otherwise."""
    if name in cmm_index:
        return (_CMM, cmm_index[name])
    if name in found:
        return (_CAMERA, found[name])
    return None


def _result(char: _Characteristic, refs, measured: float, variance: list[float], c_cal: float,
            line_var: float, session: _Session, truth: GroundTruth | None, inputs) -> CharacteristicResult:
    """One characteristic's result from the kernel's value (mm) and per-source variances (mm^2)."""
    spec = char.spec
    actual = None
    if char.kind == 0:
        if truth is not None and spec.a in truth.points_global and spec.b in truth.points_global:
            true_a, true_b = truth.points_global[spec.a], truth.points_global[spec.b]
            actual = float(np.linalg.norm(np.asarray(true_a) - np.asarray(true_b)))
        n_points = 2
    elif char.kind == 1:
        if truth is not None and spec.a in truth.points_global and spec.b in truth.lines_global:
            actual = truth.lines_global[spec.b].distance(truth.points_global[spec.a])
        n_points = 1
    else:
        if truth is not None and spec.a in truth.points_global:
            actual = float(truth.points_global[spec.a][2])
        n_points = 1
    ref_u = max([session.cmm_u[index] for kind, index in refs[:n_points] if kind == _CMM], default=0.0)
    budget = _budget(spec, char, variance, c_cal, line_var, ref_u, inputs)
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
        elements=char.elements,
        budget=budget,
    )


def _budget(spec, char: _Characteristic, variance: list[float], c_cal: float, line_var: float, ref_u: float,
            inputs: dict[str, tuple[float, str]]) -> tuple:
    """The budget terms of one characteristic from its per-source variances (mm^2; camera,
    eccentricity, control_cmm, reference_cmm, :func:`_characteristics`), its calibration
    sensitivity ``c_cal`` (mm: the term is ``(u_s c_cal)^2``) and, for a point_line, the axis
    fit's own variance ``line_var`` (mm^2; its sigma data-supported: a Type A term with the
    fit's dof)."""
    u_cal = inputs["calibration"][0]
    table = {
        "camera": (*inputs["camera"], variance[0]),
        "eccentricity": (*inputs["eccentricity"], variance[1]),
        "calibration": (u_cal, "1", (c_cal * u_cal) ** 2),
        "control_cmm": (*inputs["control_cmm"], variance[2]),
        "reference_cmm": (ref_u, "mm", variance[3]),
    }
    if char.kind != 1:
        return merge(table)
    line_sd = math.sqrt(max(line_var, 0.0))
    table["reference_line"] = (char.line_sigma, "mm", line_sd**2)
    budget = merge(table)
    if char.line_dof == math.inf:
        return budget
    return tuple(type(t)(t.source, t.u, t.unit, t.sensitivity, t.u_mm, char.line_dof)
                 if t.source == "reference_line" else t for t in budget)


def _identify_targets(
    session: _Session, global_xyz: np.ndarray, registration: Registration
) -> tuple[dict[str, int], list[str]]:
    """Target id -> camera index for unambiguous targets; the others (missing or ambiguous),
    in plan order. A target's candidates are the camera points not used as controls within its
    search radius of its nominal position (global mm); it is found when it has one and no
    other target claims that point."""
    free = _free_points(len(global_xyz), registration.correspondence.camera_index)
    ids = session.target_ids
    if not len(free) or not ids:
        return {}, list(ids)
    d = np.linalg.norm(global_xyz[free][None, :, :] - session.target_nominal[:, None, :], axis=2)  # (T, F)
    within = d <= session.target_radius[:, None]
    per_target = within.sum(axis=1).tolist()
    claims = within.sum(axis=0).tolist()
    first = within.argmax(axis=1).tolist()
    free_list = free.tolist()
    found, missing = {}, []
    for t, tid in enumerate(ids):
        if per_target[t] == 1 and claims[first[t]] == 1:
            found[tid] = int(free_list[first[t]])
        else:
            missing.append(tid)
    return found, missing


def _free_points(n: int, control_index) -> np.ndarray:
    """The camera indices (ascending, int64) of n points not used as controls:
    ``np.setdiff1d(np.arange(n), control_index)`` by a mask (indices outside 0 .. n-1 ignored)."""
    index = np.asarray(control_index, dtype=np.int64)
    free = np.ones(n, dtype=bool)
    free[index[(index >= 0) & (index < n)]] = False
    return np.flatnonzero(free).astype(np.int64, copy=False)


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


@hookimpl
def register_measures(register):
    register("plan", PlanMeasurer, "Plan characteristics: point-point, point-line (fitted axes), depth")
