"""The compiled measure stage (plugins/measure_plan.py, issue 25) against its NumPy formulation.

Two levels, both asserting bit-identical float64 results where this machine's OpenBLAS sums
small products the way the kernels do (``EXACT``, probed below: the kernels mirror the
OpenBLAS kernels of the machine they were written on, fused multiply-add chains); on another
CPU or BLAS the same comparisons assert agreement to 1e-12 relative, the rounding of a
different summation order, so the tests hold there and still catch a wrong formula:

* each scalar kernel against the NumPy expression it replaces, on random inputs: the dot
  products, matrix and vector-matrix products against ``@`` (whose small products OpenBLAS
  sums in a fixed order: the kernels reproduce this machine's OpenBLAS kernels, see the
  module docstring of measure_plan), the registration Jacobian and camera covariance against
  crossfield.covariance, the point-line distance against crossfield.geometry, the vectorised
  eccentricity variances against crossfield.uncertainty.eccentricity point by point;
* whole frames against ``measure_plan_numpy.py`` (the stage's code before the kernels, kept
  as the reference), including a target missing in the frame, an ambiguous target, a CMM
  point not imported, a registration whose controls have no CMM data, one of two controls
  (no consistency), no ground truth, the registration term switched off and a line without a fit.
"""

from __future__ import annotations

import dataclasses
import math
import struct

import measure_plan_numpy
import numpy as np
import pytest
from test_measure import Station, register

from crossfield.covariance import camera_covariance, registration_jacobian
from crossfield.errors import MeasurementError
from crossfield.geometry import fit_line, point_line_distance
from crossfield import blas_order as bo
from crossfield.plugins import measure_plan as mp
from crossfield.types import Correspondence, Registration
from crossfield.uncertainty.eccentricity import eccentricity_sigma_mm, off_axis_rad

RNG = np.random.default_rng(20261204)


def bits(a) -> np.ndarray:
    """The float64 bit patterns of ``a`` (signed zeros and NaN payloads told apart)."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def scaled(shape, rng=RNG):
    """Random values over several orders of magnitude (mm, mm^2, rad)."""
    return rng.normal(size=shape) * 10.0 ** rng.uniform(-4, 3, size=shape)


def _kernels_sum_like_numpy() -> bool:
    """Whether ``@`` here rounds as the kernels do: the products, vector-matrix products and
    Gram matrices of the shapes the stage uses, on random inputs (its own generator)."""
    rng = np.random.default_rng(1)
    for _ in range(50):
        A, B, x, J = scaled((6, 3), rng), scaled((3, 6), rng), scaled(6, rng), scaled((3, 6), rng)
        C = scaled((6, 6), rng)
        if not (np.array_equal(bo.matmul(A, B), A @ B) and np.array_equal(bo.vecmat(x, C), x @ C)
                and np.array_equal(bo.matmul_at(J, J), J.T @ J)):
            return False
    return True


#: bit-identical where NumPy's small products round as the kernels' (true on the machine the
#: kernels were written for); otherwise agreement to 1e-12 relative of each array's largest value
EXACT = _kernels_sum_like_numpy()


def assert_bits_equal(new, old):
    assert np.shape(new) == np.shape(old)
    if EXACT:
        assert np.array_equal(bits(new), bits(old)), (new, old)
    else:
        old = np.asarray(old, dtype=np.float64)
        scale = np.max(np.abs(old[np.isfinite(old)]), initial=0.0)
        np.testing.assert_allclose(new, old, rtol=1e-12, atol=1e-12 * scale)


# ---- the scalar kernels ------------------------------------------------------------------


@pytest.mark.parametrize("n", [3, 4, 6])
def test_dot_and_norm_are_numpys(n):
    for _ in range(500):
        x, y = scaled(n), scaled(n)
        assert_bits_equal(bo.dot(x, y), x @ y)
    X = scaled((500, 3))
    assert_bits_equal(mp._row_norms(X), [np.linalg.norm(x) for x in X])


@pytest.mark.parametrize("m, k, n", [(6, 3, 3), (6, 3, 6), (3, 3, 3), (6, 6, 6)])
def test_matrix_products_are_numpys(m, k, n):
    for _ in range(300):
        A, B = scaled((m, k)), scaled((k, n))
        assert_bits_equal(bo.matmul(A, B), A @ B)
        At = np.ascontiguousarray(A.T)
        assert_bits_equal(bo.matmul_at(At, B), At.T @ B)  # a transposed view, as J.T @ S
        Bt = np.ascontiguousarray(B.T)
        assert_bits_equal(bo.matmul_bt(A, Bt), A @ Bt.T)


def test_gram_matrix_is_numpys_syrk():
    """``J.T @ J`` of one array is OpenBLAS's dsyrk (numpy detects the shared buffer)."""
    for _ in range(300):
        J = scaled((3, 6))
        assert_bits_equal(bo.matmul_at(J, J), J.T @ J)


@pytest.mark.parametrize("k, n", [(3, 3), (3, 6), (4, 4), (6, 6)])
def test_vector_matrix_products_are_numpys(k, n):
    for _ in range(500):
        x, B = scaled(k), scaled((k, n))
        assert_bits_equal(bo.vecmat(x, B), x @ B)
        if k == n:
            assert_bits_equal(bo.quadratic(x, B), x @ B @ x)


def test_sums_of_zero_products_are_numpys_positive_zero():
    """OpenBLAS's accumulators start at +0.0: products that are all -0.0 sum to +0.0."""
    for k, n in [(3, 3), (3, 6), (4, 4), (6, 6)]:
        x, B = -np.ones(k), np.zeros((k, n))
        assert_bits_equal(bo.vecmat(x, B), x @ B)
        assert_bits_equal(bo.dot(x, B[:, 0].copy()), x @ B[:, 0])
        assert_bits_equal(bo.matmul(-np.ones((n, k)), B), -np.ones((n, k)) @ B)
    J = np.zeros((3, 6))
    J[:, 0] = -1.0
    assert_bits_equal(bo.matmul_at(J, J), J.T @ J)


def test_jacobian_and_camera_covariance_are_the_covariance_modules():
    for _ in range(300):
        p, g_bar, sigma = scaled(3), scaled(3), np.abs(scaled(3))
        A = scaled((3, 3))
        assert_bits_equal(mp._jacobian(p, g_bar), registration_jacobian(p, g_bar))  # -0.0 diagonal too
        assert_bits_equal(mp._camera_cov(A, sigma), camera_covariance(A, sigma))
        assert_bits_equal(mp._isotropic(sigma[0] ** 2), sigma[0] ** 2 * np.eye(3))


@pytest.mark.parametrize("kind", ["line", "cylinder"])
def test_point_line_is_geometrys(kind):
    station = Station(kind)
    reference = station.reference(np.random.default_rng(5))
    fits = [mp.PlanMeasurer().reference_line(station.plan, reference, "L3")]
    fits += [fit_line(scaled((8, 3)) + RNG.normal(size=3) * 100, sigma_mm=0.01) for _ in range(20)]
    for fit in fits:
        e1, e2 = fit.basis
        for p in list(scaled((50, 3)) * 100) + [fit.line.point.copy()]:  # on the line: d = 0
            d, var, g = mp._point_line(p, fit.line.point, fit.line.direction, e1, e2, fit.covariance)
            d_ref, sd_ref, g_ref = point_line_distance(p, fit, None)
            assert_bits_equal(d, d_ref)
            assert_bits_equal(float(np.sqrt(max(var, 0.0))), sd_ref)
            assert_bits_equal(g, g_ref)


@pytest.mark.parametrize("corrected", [False, True])
def test_eccentricity_variances_are_the_scalar_functions(corrected):
    station = Station()
    plan = station.plan
    spec_u = dataclasses.replace(plan.uncertainty, eccentricity_corrected=corrected)
    plan = dataclasses.replace(plan, uncertainty=spec_u)
    session = mp._Session(mp.PlanMeasurer(), plan, station.reference())
    xyz = np.vstack([scaled((300, 3)) * 100, [[0.0, 0.0, 0.0], [0.0, 0.0, 400.0], [10.0, -5.0, -300.0]]])
    factor = spec_u.eccentricity_residual if corrected else 1.0
    expected = [
        (factor * eccentricity_sigma_mm(float(np.linalg.norm(x)), spec_u.target_radius_mm,
                                        spec_u.max_tilt_deg, off_axis_rad(x))) ** 2
        for x in xyz
    ]
    assert_bits_equal(session.eccentricity_variances(xyz), expected)
    assert session.eccentricity_variances(np.zeros((0, 3))).shape == (0,)


# ---- whole frames against the NumPy formulation ------------------------------------------


def assert_same_value(new, old, where):
    if isinstance(old, float) or isinstance(new, float):
        if EXACT:
            assert struct.pack("<d", new) == struct.pack("<d", old), (where, new, old)
        else:
            assert new == pytest.approx(old, rel=1e-12, abs=1e-300, nan_ok=True), (where, new, old)
    elif isinstance(old, np.ndarray):
        assert_bits_equal(new, old)
    elif isinstance(old, dict):
        assert list(new) == list(old), where
        for key in old:
            assert_same_value(new[key], old[key], f"{where}[{key}]")
    elif isinstance(old, tuple):
        assert len(new) == len(old), where
        for k, (a, b) in enumerate(zip(new, old)):
            assert_same_value(a, b, f"{where}[{k}]")
    elif dataclasses.is_dataclass(old):
        assert type(new) is type(old), where
        for f in dataclasses.fields(old):
            assert_same_value(getattr(new, f.name), getattr(old, f.name), f"{where}.{f.name}")
    else:
        assert new == old, (where, new, old)


def assert_same_measurement(plan, reference, points, registration, truth, **options):
    new = mp.PlanMeasurer(**options)
    old = measure_plan_numpy.PlanMeasurer(**options)
    for _ in range(2):  # the second frame of a session: its cached constants
        m_new = new.measure(plan, reference, points, registration, truth)
        m_old = old.measure(plan, reference, points, registration, truth)
        assert_same_value(m_new, m_old, "measurement")
    return m_new


@pytest.mark.parametrize("fit", ["cylinder", "line"])
@pytest.mark.parametrize("seed", range(6))
def test_frames_are_the_numpy_formulations(fit, seed):
    station = Station(fit, seed=seed)
    rng = np.random.default_rng(100 + seed)
    reference = station.reference(rng)
    points = station.camera_points(seed, rng)
    registration = register(points, reference, station.plan)
    m = assert_same_measurement(station.plan, reference, points, registration, station.truth)
    assert len(m.characteristics) == 5 and m.consistency is not None
    assert_same_measurement(station.plan, reference, points, registration, None)  # no ground truth
    assert_same_measurement(station.plan, reference, points, registration, station.truth,
                            registration_uncertainty=False)


def test_missing_and_ambiguous_targets_and_cmm_points():
    station = Station()
    rng = np.random.default_rng(7)
    reference = station.reference(rng)
    # P2 not seen: P1-P2 and P2-depth are not reported
    points = station.camera_points(1, rng, targets=("P1",))
    m = assert_same_measurement(station.plan, reference, points, register(points, reference, station.plan),
                                station.truth)
    assert m.missing_targets == ("P2",) and len(m.characteristics) == 3
    # a stray next to P1: P1 is ambiguous
    points = station.camera_points(2, rng, extra=(station.targets_c["P1"] + [0.5, 0.0, 0.0],))
    m = assert_same_measurement(station.plan, reference, points, register(points, reference, station.plan),
                                station.truth)
    assert m.missing_targets == ("P1",)
    # R1 not imported from the CMM: P1-R1 is not reported
    reference = station.reference(rng, drop=("R1",))
    points = station.camera_points(3, rng)
    m = assert_same_measurement(station.plan, reference, points, register(points, reference, station.plan),
                                station.truth)
    assert "P1-R1" not in {c.name for c in m.characteristics}


def test_registrations_without_cmm_controls_and_with_two():
    station = Station()
    rng = np.random.default_rng(8)
    reference = station.reference(rng)
    points = station.camera_points(4, rng)
    registration = register(points, reference, station.plan)
    corr = registration.correspondence
    # its controls unknown to the CMM data: no registration term, no consistency
    renamed = Registration(registration.sequence, registration.fit,
                           Correspondence(corr.camera_index, tuple(f"X{c}" for c in corr.control_ids)))
    m = assert_same_measurement(station.plan, reference, points, renamed, station.truth)
    assert m.consistency is None
    # two of its controls in the CMM data: a covariance, no consistency test (n <= 2)
    kept = set(corr.control_ids[:2])
    dropped = tuple(c for c in corr.control_ids if c not in kept)
    fewer = station.reference(np.random.default_rng(8), drop=dropped)
    m = assert_same_measurement(station.plan, fewer, points, registration, station.truth)
    assert m.consistency is None and math.isfinite(m.characteristics[0].uncertainty_mm)


def test_a_line_without_a_fit_is_the_same_error():
    station = Station()
    reference = station.reference(drop=tuple(f"L3.{k}" for k in range(1, 9)))
    points = station.camera_points()
    registration = register(points, reference, station.plan)
    messages = []
    for impl in (mp.PlanMeasurer(), measure_plan_numpy.PlanMeasurer()):
        with pytest.raises(MeasurementError) as err:
            impl.measure(station.plan, reference, points, registration, None)
        messages.append(str(err.value))
    assert messages[0] == messages[1]


def test_merge_is_term_by_term():
    """budget.merge makes its terms inline (issue 25): the same as term() of each known source."""
    from crossfield.uncertainty.budget import SOURCES, merge, term

    def reference(variances):  # merge as it was
        return tuple(term(s, variances[s][0], variances[s][1], math.sqrt(max(variances[s][2], 0.0)))
                     for s in SOURCES if s in variances)

    for _ in range(200):
        table = {s: (float(RNG.choice([0.0, -1.0, 1.0]) * abs(scaled(()))), "mm", float(scaled(())))
                 for s in RNG.permutation(SOURCES)[: RNG.integers(0, len(SOURCES))]}
        table["not_a_source"] = (1.0, "mm", 1.0)  # left out by both
        assert_same_value(merge(table), reference(table), "merge")
