"""Compiled kernels (numba, float64, the GIL released) of :mod:`crossfield.camera.stereo_model`.

The arithmetic of the stereo model, point by point on scalars: for the ~20
targets of a frame the NumPy formulation was ~100 small-array calls per
frame (each ~1-3 us of overhead for a few hundred flops), ~10x the
``cv2.undistortPoints`` + ``cv2.triangulatePoints`` baseline of
``bench/bench_triangulate.py``. Every kernel computes the same formulas in
the same order as the NumPy version it replaced (the tests compare both,
and with OpenCV); the 3x3 solves and inverses use the adjugate instead of
LAPACK's LU, which changes results by rounding only (~1e-12 mm).

Array layouts (both cameras stacked, index 0 = upper, 1 = lower):
R (2, 3, 3), t (2, 3) mm, K (2, 3, 3) px, coeffs (2, 12) k1 k2 p1 p2 k3 k4 k5 k6
s1 s2 s3 s4 (OpenCV's rational + thin-prism model; zero terms cost nothing
in accuracy: they add exact zeros). Points X (N, 3) mm in the upper frame;
image coordinates [u_upper, v_upper, u_lower, v_lower] (N, 4) px.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "all_positive_finite",
    "epipolar_candidates",
    "linear_points",
    "paired_observations",
    "point_covariances",
    "project_into",
    "project_point",
    "project_view",
    "refine",
    "undistort_points",
    "unique_matches",
]


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _project_one(X, i, c, R, t, K, k, uv, J):
    """Camera ``c`` of point ``X[i]``: uv[i, 2c:2c+2] (px) and J[i, 2c:2c+2, :] = d(uv)/dX (px/mm).

    OpenCV's lens model (the OpenCV documentation's ``projectPoints`` equations):
    x' = X_c / Z_c, r^2 = x'^2 + y'^2, x'' = x' (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    + 2 p1 x'y' + p2 (r^2 + 2 x'^2) + s1 r^2 + s2 r^4 (and y'' alike), u = fx x'' + skew y'' + cx, v = fy y'' + cy.
    """
    x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
    xc = R[c, 0, 0] * x0 + R[c, 0, 1] * x1 + R[c, 0, 2] * x2 + t[c, 0]
    yc = R[c, 1, 0] * x0 + R[c, 1, 1] * x1 + R[c, 1, 2] * x2 + t[c, 1]
    zc = R[c, 2, 0] * x0 + R[c, 2, 1] * x1 + R[c, 2, 2] * x2 + t[c, 2]
    k1, k2, p1, p2, k3, k4, k5, k6 = k[c, 0], k[c, 1], k[c, 2], k[c, 3], k[c, 4], k[c, 5], k[c, 6], k[c, 7]
    s1, s2, s3, s4 = k[c, 8], k[c, 9], k[c, 10], k[c, 11]
    inv_z = 1.0 / zc
    x = xc * inv_z
    y = yc * inv_z
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_num = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    d_radial = (d_num * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / (den * den)  # d/d(r2)
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) + (s1 * r2 + s2 * r2 * r2)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy + (s3 * r2 + s4 * r2 * r2)
    fx, skew, cx = K[c, 0, 0], K[c, 0, 1], K[c, 0, 2]
    fy, cy = K[c, 1, 1], K[c, 1, 2]
    uv[i, 2 * c] = fx * xd + skew * yd + cx
    uv[i, 2 * c + 1] = fy * yd + cy
    # d(xd, yd)/d(x, y)
    a = 2.0 * d_radial
    prism_x = 2.0 * (s1 + 2.0 * s2 * r2)
    prism_y = 2.0 * (s3 + 2.0 * s4 * r2)
    cross = a * xy + 2.0 * p1 * x + 2.0 * p2 * y
    dxd_dx = radial + a * xx + 2.0 * p1 * y + 6.0 * p2 * x + prism_x * x
    dxd_dy = cross + prism_x * y
    dyd_dx = cross + prism_y * x
    dyd_dy = radial + a * yy + 6.0 * p1 * y + 2.0 * p2 * x + prism_y * y
    # d(u, v)/d(x, y) = K[:2, :2] d(xd, yd)/d(x, y); d(x, y)/d(Xc) = [[1, 0, -x], [0, 1, -y]] / z; d(Xc)/dX = R
    du_dx = (fx * dxd_dx + skew * dyd_dx) * inv_z
    du_dy = (fx * dxd_dy + skew * dyd_dy) * inv_z
    dv_dx = fy * dyd_dx * inv_z
    dv_dy = fy * dyd_dy * inv_z
    du_dz = -(du_dx * x + du_dy * y)
    dv_dz = -(dv_dx * x + dv_dy * y)
    for col in range(3):
        J[i, 2 * c, col] = du_dx * R[c, 0, col] + du_dy * R[c, 1, col] + du_dz * R[c, 2, col]
        J[i, 2 * c + 1, col] = dv_dx * R[c, 0, col] + dv_dy * R[c, 1, col] + dv_dz * R[c, 2, col]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def project_into(X, R, t, K, k, uv, J):
    """Project X (N, 3) mm into both cameras: uv (N, 4) px and J (N, 4, 3) px/mm, written in place."""
    for i in range(X.shape[0]):
        _project_one(X, i, 0, R, t, K, k, uv, J)
        _project_one(X, i, 1, R, t, K, k, uv, J)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """x = A^-1 b for a symmetric 3x3 A by its adjugate (Cramer's rule); nan when A is singular."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    if det == 0.0:
        return math.nan, math.nan, math.nan
    return (
        (c00 * b0 + c01 * b1 + c02 * b2) / det,
        (c01 * b0 + c11 * b1 + c12 * b2) / det,
        (c02 * b0 + c12 * b1 + c22 * b2) / det,
    )


@numba.njit(cache=True, nogil=True, error_model="numpy")
def refine(X0, uv_obs, w, R, t, K, k, max_iterations, step_tolerance, iterate):
    """Gauss-Newton on sum(w r^2) over both images (H&Z 12.3's cost, H&Z A6.1 iteration), all points at once.

    X0 (N, 3) mm, uv_obs (N, 4) px, w (N, 4) px^-2. Each iteration solves the normal equations
    (J^T W J) dX = -J^T W r of every point and stops when no point moved by more than
    ``step_tolerance`` (mm); then the residual is linearised over the last step (exact to ~1e-15 px)
    and J and the normal matrix are those of the last projection. Returns X (N, 3), the residual
    (N, 4) px, J (N, 4, 3) px/mm, the normal matrices (N, 3, 3) and whether it converged
    (``iterate`` False: no step, not converged). A singular normal matrix leaves its point where it is.
    """
    n = X0.shape[0]
    X = X0.copy()
    uv = np.empty((n, 4))
    J = np.empty((n, 4, 3))
    normal = np.zeros((n, 3, 3))
    step = np.zeros((n, 3))
    project_into(X, R, t, K, k, uv, J)
    residual = uv - uv_obs
    if not iterate or n == 0:
        return X, residual, J, normal, False
    for _ in range(max_iterations):
        largest = 0.0
        for i in range(n):
            a00 = a01 = a02 = a11 = a12 = a22 = g0 = g1 = g2 = 0.0
            for r in range(4):
                j0, j1, j2, wr = J[i, r, 0], J[i, r, 1], J[i, r, 2], w[i, r]
                a00 += j0 * wr * j0
                a01 += j0 * wr * j1
                a02 += j0 * wr * j2
                a11 += j1 * wr * j1
                a12 += j1 * wr * j2
                a22 += j2 * wr * j2
                e = wr * residual[i, r]
                g0 += j0 * e
                g1 += j1 * e
                g2 += j2 * e
            normal[i, 0, 0], normal[i, 0, 1], normal[i, 0, 2] = a00, a01, a02
            normal[i, 1, 0], normal[i, 1, 1], normal[i, 1, 2] = a01, a11, a12
            normal[i, 2, 0], normal[i, 2, 1], normal[i, 2, 2] = a02, a12, a22
            s0, s1, s2 = _solve_sym3(a00, a01, a02, a11, a12, a22, g0, g1, g2)
            if not (math.isfinite(s0) and math.isfinite(s1) and math.isfinite(s2)):
                s0 = s1 = s2 = 0.0
            step[i, 0], step[i, 1], step[i, 2] = -s0, -s1, -s2
            X[i, 0] -= s0
            X[i, 1] -= s1
            X[i, 2] -= s2
            largest = max(largest, abs(s0), abs(s1), abs(s2))
        if largest < step_tolerance:
            for i in range(n):
                for r in range(4):
                    residual[i, r] += J[i, r, 0] * step[i, 0] + J[i, r, 1] * step[i, 1] + J[i, r, 2] * step[i, 2]
            return X, residual, J, normal, True
        project_into(X, R, t, K, k, uv, J)
        for i in range(n):
            for r in range(4):
                residual[i, r] = uv[i, r] - uv_obs[i, r]
    return X, residual, J, normal, False


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _linear_one(xu, yu, xl, yl, R, t_unit):
    """Linear triangulation (H&Z 12.2, inhomogeneous form) of one pair, P1 = [I | 0], P2 = [R | t_unit]:
    the 4x3 system M X = -b of ``x P^3 - P^1 = 0``, ``y P^3 - P^2 = 0`` for both views, solved
    through its normal equations M^T M X = -M^T b (in units of |t|)."""
    # rows of A = [M | b]: (-1, 0, xu | 0), (0, -1, yu | 0), xl P2[2] - P2[0], yl P2[2] - P2[1]
    m20, m21, m22, m23 = xl * R[2, 0] - R[0, 0], xl * R[2, 1] - R[0, 1], xl * R[2, 2] - R[0, 2], xl * t_unit[2] - t_unit[0]
    m30, m31, m32, m33 = yl * R[2, 0] - R[1, 0], yl * R[2, 1] - R[1, 1], yl * R[2, 2] - R[1, 2], yl * t_unit[2] - t_unit[1]
    a00 = 1.0 + m20 * m20 + m30 * m30
    a01 = m20 * m21 + m30 * m31
    a02 = -xu + m20 * m22 + m30 * m32
    a11 = 1.0 + m21 * m21 + m31 * m31
    a12 = -yu + m21 * m22 + m31 * m32
    a22 = xu * xu + yu * yu + m22 * m22 + m32 * m32
    b0 = -(m20 * m23 + m30 * m33)
    b1 = -(m21 * m23 + m31 * m33)
    b2 = -(m22 * m23 + m32 * m33)
    return _solve_sym3(a00, a01, a02, a11, a12, a22, b0, b1, b2)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def linear_points(xn_u, xn_l, R, t_unit, scale):
    """:func:`_linear_one` of each pair of xn_u (N, 2), xn_l (N, 2); X (N, 3) times ``scale``
    (the baseline, mm); nan for an exactly degenerate pair."""
    n = xn_u.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        x0, x1, x2 = _linear_one(xn_u[i, 0], xn_u[i, 1], xn_l[i, 0], xn_l[i, 1], R, t_unit)
        out[i, 0], out[i, 1], out[i, 2] = x0 * scale, x1 * scale, x2 * scale
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def epipolar_candidates(xn_u, xn_l, K_u, K_l, F, sigma_u, sigma_l, R_l, t_l, baseline,
                        fixed_limit, k, calibration_px, z_min, z_max):
    """Every (upper i, lower j) pair's epipolar distance, its limit and, when on the line, its
    linear triangulation and whether it is a candidate (depth in the working range).

    xn_u (N, 2), xn_l (M, 2) normalised undistorted; sigma_u (N, 2), sigma_l (M, 2) px; R_l (3, 3),
    t_l (3,) mm the lower camera's pose, ``baseline`` = |t_l| mm. On undistorted pixels
    ``q = K [x, y, 1]`` the lines are ``l = F q_upper`` (H&Z 9.2), ``e_ij = q_lower[j]^T l_i``, the
    distance ``|e| / |l[:2]|`` (px); its variance to first order, as in the Sampson error (H&Z 4.2.6,
    11.4.3), ``(grad_u^T S_u grad_u + grad_l^T S_l grad_l) / |l[:2]|^2`` with grad_u = (F^T q_l)[:2],
    grad_l = l[:2]. The limit is ``fixed_limit`` when > 0, else ``k sqrt(var + calibration_px^2)``.
    A pair within its limit is triangulated (:func:`linear_points`); it is a candidate when
    z_min <= z_upper <= z_max and z_lower > 0. Returns distance (N, M) px, limit (N, M) px,
    X (N, M, 3) mm (nan off the line) and candidate (N, M) bool.
    """
    n, m = xn_u.shape[0], xn_l.shape[0]
    q_u = np.empty((n, 3))
    q_l = np.empty((m, 3))
    for i in range(n):  # q = K [x, y, 1]
        for r in range(3):
            q_u[i, r] = K_u[r, 0] * xn_u[i, 0] + K_u[r, 1] * xn_u[i, 1] + K_u[r, 2]
    for j in range(m):
        for r in range(3):
            q_l[j, r] = K_l[r, 0] * xn_l[j, 0] + K_l[r, 1] * xn_l[j, 1] + K_l[r, 2]
    lines_in_lower = q_u @ F.T  # (N, 3)
    lines_in_upper = q_l @ F  # (M, 3): de/dq_upper = its first two entries
    # grad_l^T S_l grad_l per pair from per-lower-point terms (no division, one sqrt per pair)
    var_lower = np.empty((m, 2))
    for j in range(m):
        var_lower[j, 0], var_lower[j, 1] = sigma_l[j, 0] ** 2, sigma_l[j, 1] ** 2
    distance = np.empty((n, m))
    limit = np.empty((n, m))
    X = np.full((n, m, 3), np.nan)
    candidate = np.zeros((n, m), dtype=np.bool_)
    t_unit = t_l / baseline
    cal2 = calibration_px * calibration_px
    for i in range(n):
        l0, l1, l2 = lines_in_lower[i, 0], lines_in_lower[i, 1], lines_in_lower[i, 2]  # l[:2] = de/dq_lower
        inv_norm2 = 1.0 / (l0 * l0 + l1 * l1)
        inv_norm = math.sqrt(inv_norm2)
        su0, su1 = sigma_u[i, 0] ** 2, sigma_u[i, 1] ** 2
        g0, g1 = l0 * l0, l1 * l1
        for j in range(m):
            e = l0 * q_l[j, 0] + l1 * q_l[j, 1] + l2 * q_l[j, 2]
            d = abs(e) * inv_norm
            distance[i, j] = d
            if fixed_limit > 0:
                lim = fixed_limit
            else:
                h0, h1 = lines_in_upper[j, 0], lines_in_upper[j, 1]
                var_e = (su0 * h0 * h0 + su1 * h1 * h1) + (g0 * var_lower[j, 0] + g1 * var_lower[j, 1])
                lim = k * math.sqrt(var_e * inv_norm2 + cal2)
            limit[i, j] = lim
            if d <= lim:
                x0, x1, x2 = _linear_one(xn_u[i, 0], xn_u[i, 1], xn_l[j, 0], xn_l[j, 1], R_l, t_unit)
                x0, x1, x2 = x0 * baseline, x1 * baseline, x2 * baseline
                X[i, j, 0], X[i, j, 1], X[i, j, 2] = x0, x1, x2
                z_lower = x0 * R_l[2, 0] + x1 * R_l[2, 1] + x2 * R_l[2, 2] + t_l[2]
                candidate[i, j] = x2 >= z_min and x2 <= z_max and z_lower > 0  # False for nan
    return distance, limit, X, candidate


@numba.njit(cache=True, nogil=True, error_model="numpy")
def unique_matches(candidate):
    """The one-to-one matches of a candidate table (N, M) bool: each row's and column's count of
    candidates, n_upper (N,) and n_lower (M,), and the pairs (i, j) whose row and column both hold
    exactly one candidate, as index arrays upper (K,), lower (K,) in row-major order (sorted by i)."""
    n, m = candidate.shape
    n_upper = np.zeros(n, dtype=np.int64)
    n_lower = np.zeros(m, dtype=np.int64)
    for i in range(n):
        for j in range(m):
            if candidate[i, j]:
                n_upper[i] += 1
                n_lower[j] += 1
    upper = np.empty(n, dtype=np.int64)
    lower = np.empty(n, dtype=np.int64)
    count = 0
    for i in range(n):
        if n_upper[i] == 1:
            for j in range(m):
                if candidate[i, j] and n_lower[j] == 1:
                    upper[count], lower[count] = i, j
                    count += 1
    return n_upper, n_lower, upper[:count].copy(), lower[:count].copy()


@numba.njit(cache=True, nogil=True, error_model="numpy")
def paired_observations(upper, lower, uv_u, uv_l, sigma_u, sigma_l, X_pairs):
    """Gather the matched pairs (upper[k], lower[k]) (K,): their linear points X_pairs[i, j] (K, 3)
    mm, the observations [u_upper, v_upper, u_lower, v_lower] (K, 4) px and the weights
    1 / sigma^2 (K, 4) px^-2 from uv_u (N, 2), uv_l (M, 2), sigma_u (N, 2), sigma_l (M, 2) px."""
    count = upper.shape[0]
    X = np.empty((count, 3))
    uv = np.empty((count, 4))
    w = np.empty((count, 4))
    for k in range(count):
        i, j = upper[k], lower[k]
        X[k, 0], X[k, 1], X[k, 2] = X_pairs[i, j, 0], X_pairs[i, j, 1], X_pairs[i, j, 2]
        uv[k, 0], uv[k, 1], uv[k, 2], uv[k, 3] = uv_u[i, 0], uv_u[i, 1], uv_l[j, 0], uv_l[j, 1]
        for c in range(2):
            su, sl = sigma_u[i, c], sigma_l[j, c]
            w[k, c] = 1.0 / (su * su)
            w[k, 2 + c] = 1.0 / (sl * sl)
    return X, uv, w


@numba.njit(cache=True, nogil=True, error_model="numpy")
def all_positive_finite(values):
    """Whether every element of the 2-D array ``values`` is > 0 and < inf (False for nan)."""
    for i in range(values.shape[0]):
        for c in range(values.shape[1]):
            v = values[i, c]
            if not (v > 0.0 and v < np.inf):
                return False
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def point_covariances(normal, J, w, offset_cov, with_offsets):
    """cov(X) = (J^T W J)^-1 (H&Z 5.2.2) per point from the normal matrices (N, 3, 3); with
    ``with_offsets`` plus G C G^T, G = (J^T W J)^-1 J^T W (3 x 4), C = offset_cov (N, 4, 4) px^2
    (offsets taken off the observations). Returns cov (N, 3, 3) mm^2 and sigma (N, 3) mm = sqrt|diag|."""
    n = normal.shape[0]
    cov = np.empty((n, 3, 3))
    sigma = np.empty((n, 3))
    G = np.empty((3, 4))
    for i in range(n):
        a00, a01, a02 = normal[i, 0, 0], normal[i, 0, 1], normal[i, 0, 2]
        a11, a12, a22 = normal[i, 1, 1], normal[i, 1, 2], normal[i, 2, 2]
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        cov[i, 0, 0], cov[i, 0, 1], cov[i, 0, 2] = c00 / det, c01 / det, c02 / det
        cov[i, 1, 0], cov[i, 1, 1], cov[i, 1, 2] = c01 / det, c11 / det, c12 / det
        cov[i, 2, 0], cov[i, 2, 1], cov[i, 2, 2] = c02 / det, c12 / det, c22 / det
        if with_offsets:
            for r in range(3):
                for q in range(4):
                    G[r, q] = (cov[i, r, 0] * J[i, q, 0] + cov[i, r, 1] * J[i, q, 1] + cov[i, r, 2] * J[i, q, 2]) * w[i, q]
            for r in range(3):
                for s in range(3):
                    acc = 0.0
                    for p in range(4):
                        row = 0.0
                        for q in range(4):
                            row += offset_cov[i, p, q] * G[s, q]
                        acc += G[r, p] * row
                    cov[i, r, s] += acc
        for r in range(3):
            sigma[i, r] = math.sqrt(abs(cov[i, r, r]))
    return cov, sigma


@numba.njit(cache=True, nogil=True, error_model="numpy")
def undistort_points(uv, fx, fy, cx, cy, k, max_iterations, tolerance):
    """Invert OpenCV's lens model (coefficients ``k`` (12,), as :func:`_project_one`)
    by Newton's method: distorted pixels uv (N, 2) -> normalised undistorted (x', y') (N, 2).

    Target x''_0 = (u - cx) / fx, y''_0 = (v - cy) / fy (no skew, as ``cv2.undistortPoints``);
    start at (x', y') = (x''_0, y''_0), step by the 2x2 Jacobian d(x'', y'')/d(x', y') until
    the step is below ``tolerance``. Returns the points and whether all of them converged
    (else the caller takes ``cv2.undistortPoints``' fixed-point iteration).
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7]
    s1, s2, s3, s4 = k[8], k[9], k[10], k[11]
    n = uv.shape[0]
    out = np.empty((n, 2))
    converged = True
    for i in range(n):
        tx = (uv[i, 0] - cx) / fx
        ty = (uv[i, 1] - cy) / fy
        x, y = tx, ty
        done = False
        for _ in range(max_iterations):
            xx, yy, xy = x * x, y * y, x * y
            r2 = xx + yy
            num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_num = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
            radial = num / den
            d_radial = (d_num * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / (den * den)
            fx_ = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) + (s1 * r2 + s2 * r2 * r2) - tx
            fy_ = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy + (s3 * r2 + s4 * r2 * r2) - ty
            a = 2.0 * d_radial
            prism_x = 2.0 * (s1 + 2.0 * s2 * r2)
            prism_y = 2.0 * (s3 + 2.0 * s4 * r2)
            cross = a * xy + 2.0 * p1 * x + 2.0 * p2 * y
            j00 = radial + a * xx + 2.0 * p1 * y + 6.0 * p2 * x + prism_x * x
            j01 = cross + prism_x * y
            j10 = cross + prism_y * x
            j11 = radial + a * yy + 6.0 * p1 * y + 2.0 * p2 * x + prism_y * y
            det = j00 * j11 - j01 * j10
            dx = (j11 * fx_ - j01 * fy_) / det
            dy = (j00 * fy_ - j10 * fx_) / det
            x -= dx
            y -= dy
            if abs(dx) <= tolerance and abs(dy) <= tolerance:
                done = True
                break
        if not (done and math.isfinite(x) and math.isfinite(y)):
            converged = False
        out[i, 0], out[i, 1] = x, y
    return out, converged


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def project_point(X0, X1, X2, fx, fy, cx, cy, k):
    """One view-frame point (X0, X1, X2) mm -> its distorted pixel (u, v): OpenCV's lens model
    with the coefficients k (12,) (as :func:`_project_one`), without skew; the body of
    :func:`project_view`, for the kernels that project points they compute (eccentricity)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7]
    s1, s2, s3, s4 = k[8], k[9], k[10], k[11]
    inv_z = 1.0 / X2
    x = X0 * inv_z
    y = X1 * inv_z
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx) + (s1 * r2 + s2 * r2 * r2)
    yd = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy + (s3 * r2 + s4 * r2 * r2)
    return fx * xd + cx, fy * yd + cy


@numba.njit(cache=True, nogil=True, error_model="numpy")
def project_view(X, fx, fy, cx, cy, k):
    """View-frame points X (N, 3) mm -> distorted pixels (N, 2), OpenCV's lens model with the
    coefficients k (12,) (:func:`project_point`), without skew, as ``cv2.projectPoints`` with
    rvec = tvec = 0 (which ignores K[0, 1] and computes no Jacobian here)."""
    n = X.shape[0]
    uv = np.empty((n, 2))
    for i in range(n):
        uv[i, 0], uv[i, 1] = project_point(X[i, 0], X[i, 1], X[i, 2], fx, fy, cx, cy, k)
    return uv
