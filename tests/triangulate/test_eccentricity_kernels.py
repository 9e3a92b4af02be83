"""The compiled eccentricity correction (crossfield.imaging.eccentricity: fit_circles,
centre_offsets, offset_covariance) against the NumPy formulation it replaced (issue 25 item 1).

The reference is the NumPy code kept in the module: ``_fit_circles_numpy`` (with ``_observed``,
``_basis``, ``_normals``, the row gathers and the compiled Gauss-Newton loop over gathered rows),
``_offset_covariance_numpy`` and ``centre_offsets``' per-view path through ``project`` (taken when
``_lens_arrays`` says a lens needs cv2). The kernels do the same floating-point operations in the
same order, so the results are equal bit for bit where NumPy's small matmuls are the fused
multiply-add chains the kernels write (OpenBLAS' dgemm kernels on an FMA machine, checked below);
elsewhere they may differ by rounding, and the test then asserts a relative 1e-12.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield import blas_order as bo
from crossfield.imaging import eccentricity as ecc
from crossfield.simulator.scenarios import build_scene


@numba.njit(cache=False)
def _fma_products(A, B):
    """A (N, m, k) @ B (N, k, p) as fma chains in k (what the kernels assume NumPy computes)."""
    n, m, kk = A.shape
    out = np.empty((n, m, B.shape[2]))
    for i in range(n):
        for r in range(m):
            for c in range(B.shape[2]):
                acc = A[i, r, 0] * B[i, 0, c]
                for k in range(1, kk):
                    acc = bo.fma(A[i, r, k], B[i, k, c], acc)
                out[i, r, c] = acc
    return out


def _numpy_matmul_is_fma():
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=(200, 3, 3)), rng.normal(size=(200, 3, 3))
    return np.array_equal(A @ B, _fma_products(A, B))


#: bit-identical where NumPy's small products are fma chains; otherwise rounding (< 1e-12 relative)
EXACT = _numpy_matmul_is_fma()


def assert_same(new, old):
    new, old = np.asarray(new), np.asarray(old)
    assert new.shape == old.shape
    if EXACT:
        np.testing.assert_array_equal(new, old)
    else:
        np.testing.assert_allclose(new, old, rtol=1e-12, atol=0)


@pytest.fixture(scope="module", params=["station", "camera-limited"])
def views(request):
    return ecc.stereo_views(build_scene(request.param).calibration)


def _circles(rng, n, max_tilt):
    """n circles 400..800 mm in front of the upper camera: centres C (n, 3) mm, unit normals
    (n, 3) tilted up to max_tilt rad from the line of sight, radii (n,) mm."""
    C = np.column_stack([rng.uniform(-120, 120, n), rng.uniform(-90, 90, n), rng.uniform(400, 800, n)])
    sight = -C / np.linalg.norm(C, axis=1, keepdims=True)
    axes = np.cross(sight, rng.normal(size=(n, 3)))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    normal = Rotation.from_rotvec(axes * rng.uniform(0, max_tilt, (n, 1))).apply(sight)
    return C, normal, rng.uniform(2.0, 6.0, n)


def _conics(rng, views, C, normal, radius, with_cov):
    """Each view's pixel conic shape (n, 3) px^-2 of the circles (the normalised shape mapped
    through the lens Jacobian, perturbed by 1e-3 relative) and a covariance (n, 3, 3) or None."""
    ellipses, covs = [], []
    for view, cov_on in zip(views, with_cov):
        Cv, nv = C @ view.R.T + view.t, normal @ view.R.T
        S_n = ecc._sym(ecc.predicted_shape(Cv, nv, radius))
        M_inv = np.linalg.inv(ecc._lens_jacobian(view, Cv))
        S_px = ecc._vec(np.swapaxes(M_inv, 1, 2) @ S_n @ M_inv)
        S_px *= 1.0 + 1e-3 * rng.normal(size=S_px.shape)
        ellipses.append(S_px)
        if cov_on:
            A = rng.normal(size=(len(C), 3, 3)) * (1e-3 * np.abs(S_px).max(axis=1))[:, None, None]
            covs.append(A @ np.swapaxes(A, 1, 2) + np.eye(3) * (1e-4 * np.abs(S_px).max(axis=1)[:, None, None]) ** 2)
        else:
            covs.append(None)
    return tuple(ellipses), tuple(covs)


def _numpy_offsets(X, normal, radius, views, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(ecc, "_lens_arrays", lambda v: None)
        return ecc.centre_offsets(X, normal, radius, views)


CASES = [  # (targets, max tilt rad, covariances of (upper, lower))
    (0, 0.8, (True, True)),
    (1, 0.8, (True, True)),
    (1, 0.8, (False, False)),
    (2, 1e-4, (True, True)),  # nearly face-on: the starts' tilt ~ 0
    (12, 1e-7, (True, False)),
    (12, 0.9, (True, True)),
    (25, 0.9, (False, True)),
    (25, 0.9, (False, False)),
]


@pytest.mark.parametrize("n, max_tilt, with_cov", CASES)
def test_compiled_eccentricity_equals_the_numpy_formulation(views, n, max_tilt, with_cov, monkeypatch):
    rng = np.random.default_rng(1000 * n + int(1e3 * max_tilt) + sum(with_cov))
    C, normal, radius = _circles(rng, n, max_tilt)
    ellipses, covs = _conics(rng, views, C, normal, radius, with_cov)
    X = C + rng.normal(scale=0.01, size=C.shape)  # the triangulated centres
    new = ecc.fit_circles(X, views, ellipses, covs)
    old = ecc._fit_circles_numpy(X, views, ellipses, covs)
    for name in ("normal", "radius_mm", "cov", "cost", "params"):
        assert_same(getattr(new, name), getattr(old, name))
    X2 = X + rng.normal(scale=0.01, size=X.shape)  # the re-triangulated points
    assert_same(ecc.centre_offsets(X2, new.normal, new.radius_mm, views),
                _numpy_offsets(X2, old.normal, old.radius_mm, views, monkeypatch))
    with monkeypatch.context() as m:
        m.setattr(ecc, "_lens_arrays", lambda v: None)
        reference = ecc.offset_covariance(X2, old, views)
    assert_same(ecc.offset_covariance(X2, new, views), reference)
    assert_same(reference, ecc._offset_covariance_numpy(X2, old, views))


def test_degenerate_conics_raise_as_before(views):
    """A conic that is not an ellipse's (zero shape): the NumPy path raises LinAlgError (the
    triangulator then leaves the points uncorrected); the compiled path must too."""
    rng = np.random.default_rng(3)
    C, normal, radius = _circles(rng, 3, 0.5)
    ellipses, covs = _conics(rng, views, C, normal, radius, (True, True))
    ellipses = (np.zeros_like(ellipses[0]), ellipses[1])
    covs = (np.zeros_like(covs[0]), covs[1])
    for fit in (ecc._fit_circles_numpy, ecc.fit_circles):
        with pytest.raises(np.linalg.LinAlgError):
            fit(C, views, ellipses, covs)


def test_transcendentals_left_to_numpy_are_libm_in_the_kernels():
    """The kernels take cos and sin from libm (numba's math) where the NumPy code used np.cos /
    np.sin; arccos, log and exp stay NumPy calls (NumPy's SIMD versions differ from libm's)."""
    x = np.random.default_rng(2).uniform(0.0, 1.6, 200_000)

    @numba.njit(cache=False)
    def cos_sin(values):
        out = np.empty((2, len(values)))
        for i in range(len(values)):
            out[0, i], out[1, i] = np.cos(values[i]), np.sin(values[i])
        return out

    got = cos_sin(x)
    if EXACT:
        np.testing.assert_array_equal(got[0], np.cos(x))
        np.testing.assert_array_equal(got[1], np.sin(x))
    else:
        np.testing.assert_allclose(got, [np.cos(x), np.sin(x)], rtol=1e-15)


def test_centre_offsets_of_one_view_take_the_per_view_path(views):
    """centre_offsets takes any number of views ((N, 2 per view) px); the compiled path is for two."""
    rng = np.random.default_rng(5)
    C, normal, radius = _circles(rng, 4, 0.6)
    both = ecc.centre_offsets(C, normal, radius, views)
    assert_same(ecc.centre_offsets(C, normal, radius, views[:1]), both[:, :2])
    assert_same(ecc.centre_offsets(C, normal, radius, views[1:]), both[:, 2:])
