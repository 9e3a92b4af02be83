"""Rigid registration kernels: the weighted Kabsch fit, rotations, and the shared checks.

One kernel per numeric operation, used by every ``register`` implementation
(``plugins/register_*.py``), the correspondence search, the session's pose
averaging and the report:

* :func:`kabsch`: the weighted least-squares rigid fit ``Q ~ R P + t``
  (paper Formulas (5)-(9)), batched over any leading shape, returning the
  best proper rotation *and* the best improper orthogonal matrix;
* :func:`best_rotations`: its rotation step for a cross-covariance H, by the
  SVD (``method="svd"``, Formulas (7)-(8)) or in closed form by Horn's
  quaternion matrix (``method="quaternion"``, the fast batched route);
* :func:`project_to_rotation`: the rotation nearest to a 3x3 matrix;
* :func:`rotation_angle` / :func:`chord_to_angle`: the angle between two rotations.

The registrations share two decisions so that they agree:

* what input is acceptable (:func:`validate_pairs`): (N, 3) finite arrays of
  equal length, at least 3 points with positive weight, not collinear;
* when a point pair set is a *mirror image* (:func:`check_reflection`).

The reflection criterion
------------------------
Let ``rms_proper`` be the residual RMS of the best proper rotation
(det R = +1) and ``rms_improper`` that of the best improper orthogonal matrix
(det = -1). For exact or noisy data from a real rigid motion,
``rms_proper <= rms_improper`` except when the points are (nearly) coplanar:
a planar set and its mirror image are related by a proper rotation (a 180 degree
turn about an in-plane axis), so both fits are equally good up to noise and
either may come out marginally ahead. Only when the proper fit is *clearly*
worse than the mirrored one do the data say "these sets are mirror images"
(wrong handedness of a frame, swapped axes, a mis-signed stereo baseline...).
So a registration is rejected when::

    rms_proper > ratio * rms_improper   and   rms_proper > floor

with ``ratio`` = 5 by default (the proper fit is five times worse than the
reflected one) and ``floor`` = 1e-9 of the point-set size, which makes exact
coplanar data (both fits ~1e-15 mm) pass. For planar sets with noise the two
RMS values differ by a factor of order 1 (the extra error of the proper fit,
4 * s3 in the sum of squares, is of second order in the noise), and for
genuinely mirrored sets the proper fit's RMS is of the order of the point
spread, far beyond any noise.

Measured false-alarm rate (exactly coplanar points, isotropic noise on both
sets, random rotations): with N = 4 points the ratio exceeded 3 / 4 / 5 in
84 / 14 / 3 of 200 000 trials; with N >= 6 it never exceeded 2.4 in 10 000
trials that came out with det(V U^T) < 0. Mirrored sets whose out-of-plane
extent is only a few times the noise cannot be told from planar ones and
pass with the best proper rotation (which is then a valid fit too).

The differences from Kabsch's usual "det(V U^T) < 0 -> flip the last singular
vector" rule: that rule silently returns a (possibly terrible) proper rotation
for mirrored data; here it is still applied to coplanar data (where it is
harmless), and mirrored data raise :class:`RegistrationError`.

Lengths in mm; all arrays (N, 3) unless stated.
"""

from __future__ import annotations

import math

import numpy as np

from crossfield.errors import RegistrationError
from crossfield.types import RigidFit

__all__ = [
    "COLLINEAR_RATIO",
    "REFLECTION_RATIO",
    "check_ratio",
    "check_reflection",
    "kabsch",
    "point_set_size",
    "residual_rms",
    "rigid_fit",
    "validate_pairs",
    "weighted_rms",
]

#: Default ratio rms_proper / rms_improper above which the pair set is a mirror image.
REFLECTION_RATIO = 5.0

#: The two solvers of :func:`best_rotations` (and :func:`kabsch`); "auto" picks one.
KABSCH_METHODS = ("svd", "quaternion")

#: Collinearity: rms distance from the best-fit line below this fraction of the
#: rms spread along it (singular value ratio s2 / s1 of the centred points).
COLLINEAR_RATIO = 1e-3


def validate_pairs(
    camera_xyz: np.ndarray, global_xyz: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check corresponding point sets and return them as float arrays.

    camera_xyz, global_xyz: (N, 3) mm, row i of one corresponds to row i of
    the other. weights: (N,) non-negative per-point weights (e.g. inverse
    variances) or None for equal weights.

    Returns (P, Q, w): (N, 3), (N, 3), (N,) with w normalised to sum 1.
    Raises RegistrationError for bad shapes, non-finite values, negative
    weights, fewer than 3 points of positive weight, or collinear points.
    """
    P = np.asarray(camera_xyz, dtype=np.float64)
    Q = np.asarray(global_xyz, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or Q.shape != P.shape:
        raise RegistrationError(
            f"registration needs two (N, 3) arrays of corresponding points, got camera {P.shape} "
            f"and global {Q.shape}"
        )
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise RegistrationError("registration input contains non-finite coordinates (NaN or inf)")
    n = len(P)
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (n,):
            raise RegistrationError(f"weights must have shape ({n},), got {w.shape}")
        if not np.isfinite(w).all() or (w < 0).any():
            raise RegistrationError("weights must be finite and non-negative")
    used = int(np.count_nonzero(w > 0))
    if used < 3:
        raise RegistrationError(
            f"registration needs at least 3 corresponding points (with positive weight), got {used}"
        )
    w = w / w.sum()
    # Both sets' weighted centred points in one stacked SVD (2, N, 3): per matrix the same
    # LAPACK call as one at a time, at half the Python overhead.
    root_w = np.sqrt(w)[:, None]
    spreads = np.linalg.svd(np.stack(((P - w @ P) * root_w, (Q - w @ Q) * root_w)), compute_uv=False)
    for name, s in zip(("camera", "global"), spreads.tolist()):
        if s[0] == 0.0 or s[1] <= COLLINEAR_RATIO * s[0]:
            raise RegistrationError(
                f"the {name} points are collinear (or coincident): the rotation about their line "
                f"is undetermined (spread ratio {s[1] / s[0] if s[0] else 0.0:.2e} <= {COLLINEAR_RATIO})"
            )
    return P, Q, w


def point_set_size(P: np.ndarray, w: np.ndarray) -> float:
    """RMS distance (mm) of weighted points (N, 3) from their weighted centroid."""
    return float(np.sqrt(w @ np.sum((P - w @ P) ** 2, axis=1)))


def check_reflection(
    rms_proper: float, rms_improper: float, size_mm: float, ratio: float = REFLECTION_RATIO, method: str = ""
) -> None:
    """Raise RegistrationError when the point sets are mirror images.

    rms_proper / rms_improper: weighted residual RMS (mm) of the best proper
    rotation and of the best improper orthogonal matrix. size_mm: RMS spread
    of the points (sets the floor, see the module docstring).
    """
    floor = 1e-9 * max(size_mm, 1.0)
    if rms_proper > ratio * rms_improper and rms_proper > floor:
        where = f" ({method})" if method else ""
        raise RegistrationError(
            f"registration{where}: the best orthogonal fit is a reflection (det = -1): residual RMS "
            f"{rms_improper:.4g} mm mirrored vs {rms_proper:.4g} mm for the best rotation. The camera "
            f"and global point sets are mirror images; check the handedness of the frames, the sign of "
            f"the stereo baseline and the control-point correspondence"
        )


def check_ratio(ratio: float) -> float:
    """Validate a ``reflection_ratio`` option (> 1)."""
    ratio = float(ratio)
    if not ratio > 1.0:
        raise ValueError(f"reflection_ratio must be > 1, got {ratio}")
    return ratio


def residual_rms(residuals: np.ndarray) -> float:
    """sqrt(mean |r_i|^2) of (N, 3) residuals, mm (unweighted, as RigidFit defines it)."""
    return float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))


def weighted_rms(residuals: np.ndarray, w: np.ndarray) -> float:
    """sqrt(sum_i w_i |r_i|^2) of (N, 3) residuals (mm) with weights (N,) summing to 1."""
    return float(np.sqrt(w @ np.sum(residuals**2, axis=1)))


def rigid_fit(
    camera_xyz: np.ndarray,
    global_xyz: np.ndarray,
    weights: np.ndarray | None,
    *,
    method: str,
    reflection_ratio: float = REFLECTION_RATIO,
    name: str = "",
) -> RigidFit:
    """A checked rigid fit ``global ~ R @ camera + t`` as a RigidFit: validation
    (:func:`validate_pairs`), :func:`kabsch` with ``method``, the reflection decision
    (:func:`check_reflection`) and residuals ``R @ p_i + t - q_i`` (N, 3) mm.

    camera_xyz, global_xyz: (N, 3) mm; weights: (N,) or None. name: the
    implementation, for RigidFit.method and error messages.
    """
    P, Q, w = validate_pairs(camera_xyz, global_xyz, weights)
    R, t, R_mirror, t_mirror = kabsch(P, Q, w, method=method)
    residuals = P @ R.T + t - Q
    check_reflection(
        weighted_rms(residuals, w),
        weighted_rms(P @ R_mirror.T + t_mirror - Q, w),
        point_set_size(P, w),
        reflection_ratio,
        name,
    )
    return RigidFit(R=R, t=t, residuals=residuals, rms_mm=residual_rms(residuals), method=name)


# --------------------------------------------------------------------------
# The Kabsch fit and its rotation step
# --------------------------------------------------------------------------


def kabsch(
    P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None, *, method: str = "auto"
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted Kabsch / Arun fit, batched: ``Q ~ R @ P + t`` (paper Formulas (5)-(9)).

    P, Q: (..., N, 3) mm corresponding points (camera, global); any leading
    batch shape. w: (..., N) or (N,) non-negative weights (normalised here),
    or None for equal weights. No validation: callers check their input
    (:func:`validate_pairs`) once. method: the rotation step,
    ``"quaternion"`` (Horn's matrix; in closed form for batches) or ``"svd"``
    (the paper's Formulas (7)-(8)), which give the same R to ~1e-13 (see
    :func:`best_rotations`); ``"auto"`` takes the faster one for the batch
    size (the closed form from 64 registrations, else the SVD).

    Returns (R, t, R_mirror, t_mirror): (..., 3, 3), (..., 3), the best proper
    rotation (det +1; the SVD route's ``V diag(1, 1, sign det(V U^T)) U^T``,
    Formula (8)) and the best improper orthogonal matrix (det -1) with their
    translations ``t = q_bar - R p_bar`` (Formula (9)), for the one shared
    reflection decision (:func:`check_reflection`).
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    n = P.shape[-2]
    if P.ndim == 2:  # one registration: plain 2-D numpy calls cost less than the batched forms
        if w is None:
            p_bar, q_bar = P.mean(axis=0), Q.mean(axis=0)
            H = (P - p_bar).T @ (Q - q_bar) / n  # Formula (6), w_i = 1 / n
        else:
            w = np.asarray(w, dtype=np.float64)
            w = w / w.sum()
            p_bar, q_bar = w @ P, w @ Q
            H = ((P - p_bar) * w[:, None]).T @ (Q - q_bar)  # Formula (6)
        R, R_mirror = best_rotations(H, method=method)
        return R, q_bar - R @ p_bar, R_mirror, q_bar - R_mirror @ p_bar  # Formula (9)
    if w is None:  # (the sums as einsum: several times faster than matmul on tiny matrices)
        p_bar = np.einsum("...ni->...i", P) / n  # centroids
        q_bar = np.einsum("...ni->...i", Q) / n
        M_c = P - p_bar[..., None, :]  # M'_i (camera, centred)
        P_c = Q - q_bar[..., None, :]  # P'_i (global, centred)
        H = (np.swapaxes(M_c, -1, -2) @ P_c) / n  # Formula (6), w_i = 1 / n
    else:
        w = np.broadcast_to(np.asarray(w, dtype=np.float64), P.shape[:-1])
        w = w / w.sum(axis=-1, keepdims=True)
        p_bar = np.einsum("...n,...ni->...i", w, P)  # weighted centroids
        q_bar = np.einsum("...n,...ni->...i", w, Q)
        M_c = P - p_bar[..., None, :]
        P_c = Q - q_bar[..., None, :]
        H = np.swapaxes(M_c * w[..., None], -1, -2) @ P_c  # Formula (6): sum_i w_i M'_i P'_i^T
    R, R_mirror = best_rotations(H, method=method)
    t = q_bar - np.einsum("...ij,...j->...i", R, p_bar)  # Formula (9)
    t_mirror = q_bar - np.einsum("...ij,...j->...i", R_mirror, p_bar)
    return R, t, R_mirror, t_mirror


def best_rotations(H: np.ndarray, method: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """The orthogonal matrices maximising ``trace(R H)``: (R, R_mirror), each (..., 3, 3).

    H: (..., 3, 3) cross-covariance ``sum_i w_i p_i q_i^T`` of centred point
    pairs, camera index first (Formula (6)), so that R maps camera into
    global. R is the best proper rotation (det +1), R_mirror the best improper
    orthogonal matrix (det -1). With ``H = U S V^T`` they are
    ``V diag(1, 1, +-d) U^T``, d = sign det(V U^T), and
    ``trace(R H) = s1 + s2 + d s3``, ``trace(R_mirror H) = s1 + s2 - d s3``.

    method ``"svd"``: exactly that (Formulas (7)-(8)), ``np.linalg.svd``.

    method ``"quaternion"``: Horn (1987) sec. 4: ``trace(R H) = q^T N q`` for
    the unit quaternion q of R, with N the symmetric traceless 4x4 matrix of
    H's entries (:func:`_horn_matrix`); R is the quaternion of N's largest
    eigenvalue, and since -R_mirror is the rotation that *minimises*
    ``trace(R H)``, R_mirror is minus the rotation of N's smallest eigenvalue
    (both extremes of one eigenproblem).
    N's characteristic polynomial is ``l^4 + c2 l^2 + c1 l + c0`` with
    ``c2 = -2 |H|_F^2``, ``c1 = -8 det H``, ``c0 = det N`` (Horn 1987 sec. 4;
    Theobald 2005, "Rapid calculation of RMSDs using a quaternion-based
    characteristic polynomial", Acta Cryst. A61); its extreme roots
    ``+-(s1 + s2 +- d s3)`` are found by Newton's method from upper bounds of
    them (monotone convergence from outside the roots; :func:`_quaternion_block`), the
    eigenvector as a column of the adjugate of ``N - l I`` (rank 3 at a simple
    root: ``adj = prod_j (l_j - l) q q^T``), refined by one Rayleigh-quotient
    step where the eigenvalue gaps are small (:func:`_eigenvector`).
    Elementwise arithmetic on blocks of the batch, ~1000 operations per H:
    about half the time of the batched 3x3 SVD (``bench/bench_registration.py``),
    and more accurate where two singular values are close. Where the extreme
    eigenvalue is (nearly) repeated the rotation itself is ill-determined
    (collinear points; symmetric point sets for R_mirror); there, and for
    batches under 64, ``np.linalg.eigh`` solves N.

    method ``"auto"`` (default): ``"quaternion"`` for 64 or more matrices,
    else ``"svd"`` (faster for a few).
    """
    H = np.asarray(H, dtype=np.float64)
    if H.shape[-2:] != (3, 3):
        raise ValueError(f"best_rotations needs (..., 3, 3) matrices, got shape {H.shape}")
    if method == "auto":
        method = "quaternion" if H.size // 9 >= _CLOSED_FORM_MIN else "svd"
    if method == "svd":
        return _svd_rotations(H)
    if method == "quaternion":
        return _quaternion_rotations(H)
    raise ValueError(f"unknown Kabsch method {method!r}: expected auto, {', '.join(KABSCH_METHODS)}")


def _svd_rotations(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Formulas (7)-(8): H = U S V^T, R = V diag(1, 1, d) U^T and R_mirror with -d."""
    U, _, Vt = np.linalg.svd(H)  # Formula (7)
    if H.ndim == 2:  # one matrix
        V = Vt.T
        # d = sign det(V U^T) = sign(det V det U): both are +-1 (orthogonal), so the cofactor
        # determinants decide it as np.linalg.det(V @ U.T) does, without the product.
        proper = _det3(V.tolist()) * _det3(U.tolist()) >= 0
        D, D_mirror = (_DIAG_PLUS, _DIAG_MINUS) if proper else (_DIAG_MINUS, _DIAG_PLUS)
        return (V * D) @ U.T, (V * D_mirror) @ U.T  # Formula (8): V diag(1, 1, +-d) U^T
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(d.shape + (3,))
    D[..., 2] = d
    R = (V * D[..., None, :]) @ Ut  # Formula (8): V D U^T
    D[..., 2] = -d
    R_mirror = (V * D[..., None, :]) @ Ut
    return R, R_mirror


#: diag(1, 1, +1) and diag(1, 1, -1) of Formula (8), as scales of the columns of V (read only).
_DIAG_PLUS = np.array([1.0, 1.0, 1.0])
_DIAG_MINUS = np.array([1.0, 1.0, -1.0])
_DIAG_PLUS.flags.writeable = _DIAG_MINUS.flags.writeable = False

#: Newton iterations at most for the extreme roots (convergence is quadratic
#: at a simple root, linear with rate 1/2 at a double one).
_NEWTON_MAX = 80

#: Below this norm of the adjugate's column (for |H|_F = 1) the eigenvector is refined.
_REFINE_BELOW = 0.2

#: Below this |adj(N - l I) q| (for |H|_F = 1, i.e. the product of the three
#: eigenvalue gaps at the root) the closed form hands over to np.linalg.eigh.
_ADJUGATE_FLOOR = 1e-4

#: Batches of fewer registrations take np.linalg.eigh of N (method "quaternion") or,
#: for method "auto", the SVD route: faster there than ~1000 numpy calls on tiny arrays.
_CLOSED_FORM_MIN = 64

#: Registrations per block of the closed form: its ~1000 elementwise operations
#: per registration then run on arrays of 128 kB, which stay in the L2 cache.
_BLOCK = 16384

#: A symmetric 4x4 matrix per registration, as its upper triangle
#: (a00, a01, a02, a03, a11, a12, a13, a22, a23, a33), each a (K,) array.
Sym4 = tuple[np.ndarray, ...]


def _quaternion_rotations(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """method="quaternion" of :func:`best_rotations`: the closed form block by block of
    the batch; np.linalg.eigh of N for batches too small to repay its ~1000 numpy calls."""
    shape = H.shape[:-2]
    flat = H.reshape(-1, 3, 3)
    if len(flat) < _CLOSED_FORM_MIN:
        S = np.moveaxis(flat, 0, -1)
        _, vectors = np.linalg.eigh(np.moveaxis(np.array(_rows(_horn_matrix(S))), -1, 0))
        R = np.moveaxis(_quaternion_matrix(vectors[:, :, -1].T), -1, 0)
        R_mirror = -np.moveaxis(_quaternion_matrix(vectors[:, :, 0].T), -1, 0)
        return R.reshape(shape + (3, 3)), R_mirror.reshape(shape + (3, 3))
    R = np.empty(flat.shape)
    R_mirror = np.empty(flat.shape)
    for start in range(0, len(flat), _BLOCK):
        block = slice(start, start + _BLOCK)
        R[block], R_mirror[block] = _quaternion_block(flat[block])
    return R.reshape(shape + (3, 3)), R_mirror.reshape(shape + (3, 3))


def _quaternion_block(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, R_mirror), each (K, 3, 3), of H (K, 3, 3) by Horn's matrix (see :func:`best_rotations`)."""
    S = np.ascontiguousarray(np.moveaxis(H, 0, -1))  # (3, 3, K): each entry contiguous over the batch
    size = np.sqrt(np.einsum("ijk,ijk->k", S, S))  # |H|_F
    S /= np.where(size > 0, size, 1.0)  # the rotations do not depend on the scale of H
    N = _horn_matrix(S)
    c2 = np.where(size > 0, -2.0, 0.0)  # -2 |S|_F^2
    c1 = -8.0 * _det3(S)
    c0 = _det4(N)
    # The largest root of p(l), and the largest root of p(-l): minus the smallest of p(l).
    # Starts: all roots lie in [-sqrt 3, sqrt 3] (|H|_F = 1), and the roots s1 + s2 +- s3
    # differ by 2 s3 >= 4 |det H| (s1 s2 <= 1/2), the smaller one lying below.
    K = len(c0)
    four_det = -0.5 * c1
    start = math.sqrt(3.0) - np.concatenate([np.maximum(-four_det, 0.0), np.maximum(four_det, 0.0)])
    roots = _newton_largest_root(np.tile(c2, 2), np.concatenate([c1, -c1]), np.tile(c0, 2), start)
    top = np.arange(2 * K) < K
    R2 = _quaternion_matrix(_eigenvector(tuple(np.tile(a, 2) for a in N), np.where(top, roots, -roots), top))
    return np.moveaxis(R2[:, :, :K], -1, 0), -np.moveaxis(R2[:, :, K:], -1, 0)


def _horn_matrix(S: np.ndarray) -> Sym4:
    """Horn's (1987, sec. 4.A) symmetric 4x4 matrix N of S (3, 3, K), S_ab = sum p_a q_b."""
    (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = S
    return (
        Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx,
        Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz,
        -Sxx + Syy - Szz, Syz + Szy,
        -Sxx - Syy + Szz,
    )  # fmt: skip


def _det3(S: np.ndarray) -> np.ndarray:
    """Determinants (K,) of S (3, 3, K), by cofactors of the first row (also of one
    (3, 3) matrix as nested lists, a float)."""
    (a, b, c), (d, e, f), (g, h, i) = S
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def _det4(A: Sym4) -> np.ndarray:
    """Determinant (K,) of symmetric A by the 2x2 minors of rows (0, 1) and (2, 3) (as :func:`_adjugate4`)."""
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = A
    return (
        (a00 * a11 - a01 * a01) * (a22 * a33 - a23 * a23)
        - (a00 * a12 - a01 * a02) * (a12 * a33 - a13 * a23)
        + (a00 * a13 - a01 * a03) * (a12 * a23 - a13 * a22)
        + (a01 * a12 - a11 * a02) * (a02 * a33 - a03 * a23)
        - (a01 * a13 - a11 * a03) * (a02 * a23 - a03 * a22)
        + (a02 * a13 - a12 * a03) * (a02 * a13 - a03 * a12)
    )


def _shifted(N: Sym4, lam: np.ndarray) -> Sym4:
    """N - lam I."""
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = N
    return (a00 - lam, a01, a02, a03, a11 - lam, a12, a13, a22 - lam, a23, a33 - lam)


def _adjugate4(A: Sym4) -> tuple[Sym4, np.ndarray]:
    """Adjugate (symmetric, as its upper triangle) and determinant (K,) of symmetric A,
    by the 2x2 minors of rows (0, 1) and of rows (2, 3) (Laplace expansion by
    complementary minors)."""
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = A
    s0, s1, s2 = a00 * a11 - a01 * a01, a00 * a12 - a01 * a02, a00 * a13 - a01 * a03
    s3, s4, s5 = a01 * a12 - a11 * a02, a01 * a13 - a11 * a03, a02 * a13 - a12 * a03
    c0, c1, c2 = a02 * a13 - a03 * a12, a02 * a23 - a03 * a22, a02 * a33 - a03 * a23
    c3, c4, c5 = a12 * a23 - a13 * a22, a12 * a33 - a13 * a23, a22 * a33 - a23 * a23
    adj = (
        a11 * c5 - a12 * c4 + a13 * c3,
        -a01 * c5 + a02 * c4 - a03 * c3,
        a13 * s5 - a23 * s4 + a33 * s3,
        -a12 * s5 + a22 * s4 - a23 * s3,
        a00 * c5 - a02 * c2 + a03 * c1,
        -a03 * s5 + a23 * s2 - a33 * s1,
        a02 * s5 - a22 * s2 + a23 * s1,
        a03 * s4 - a13 * s2 + a33 * s0,
        -a02 * s4 + a12 * s2 - a23 * s0,
        a02 * s3 - a12 * s1 + a22 * s0,
    )
    det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    return adj, det


def _rows(A: Sym4) -> list[list[np.ndarray]]:
    """The full 4x4 (nested lists of (K,) arrays) of a symmetric upper triangle."""
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = A
    return [[a00, a01, a02, a03], [a01, a11, a12, a13], [a02, a12, a22, a23], [a03, a13, a23, a33]]


def _matvec4(A: Sym4, x: np.ndarray) -> np.ndarray:
    """A x for each registration: symmetric A, x (4, K) -> (4, K)."""
    return np.array([r[0] * x[0] + r[1] * x[1] + r[2] * x[2] + r[3] * x[3] for r in _rows(A)])


def _newton_largest_root(c2: np.ndarray, c1: np.ndarray, c0: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Largest real root (K,) of ``l^4 + c2 l^2 + c1 l + c0`` by Newton's method from
    ``start`` (K,), an upper bound of it.

    Right of the largest root p is increasing and convex (the roots of p' and
    p'' lie between those of p), so the iterates decrease monotonically onto
    it; an iterate stops when its step is no longer positive and shrinking
    (rounding level). Iterates still moving are compacted, so the few slow
    (near-double) roots cost little.
    """
    roots = np.array(start, dtype=np.float64)
    index = np.arange(len(roots))
    x = roots.copy()
    previous = np.full(len(roots), np.inf)
    for _ in range(_NEWTON_MAX):
        x2 = x * x
        p = (x2 + c2) * x2 + c1 * x + c0
        dp = (4.0 * x2 + 2.0 * c2) * x + c1
        with np.errstate(divide="ignore", invalid="ignore"):
            step = p / dp  # dp > 0 right of a simple largest root; NaN/inf fail the test below
        moving = (step > 0) & (step < previous)
        x = np.where(moving, x - step, x)
        moving &= step > 1e-16 * x
        if not moving.all():
            roots[index] = x
            if not moving.any():
                break
            index, x, step = index[moving], x[moving], step[moving]
            c2, c1, c0 = c2[moving], c1[moving], c0[moving]
        previous = step
    else:
        roots[index] = x
    return roots


def _eigenvector(N: Sym4, lam: np.ndarray, top: np.ndarray) -> np.ndarray:
    """Unit eigenvectors (4, K) of symmetric N for its largest (where ``top``, (K,) bool)
    or smallest eigenvalues lam (K,).

    The column of largest norm of ``adj(N - lam I) = prod_j (l_j - lam) q q^T``;
    its norm c is at least half the product of the eigenvalue gaps. The root
    has an error ~3e-14 / c (from the polynomial's rounding), which leaves an
    error ~1e-14 / c^2 in q: where c < ``_REFINE_BELOW``, one Rayleigh-quotient
    step follows (rho = q^T N q, accurate to second order in the error of q;
    ``adj(N - rho I) q`` then removes what the root's error let in, leaving
    ~1e-15 / c). Where even that adjugate is below ``_ADJUGATE_FLOOR`` (a
    (nearly) repeated eigenvalue), np.linalg.eigh solves N.
    """
    adj = _rows(_adjugate4(_shifted(N, lam))[0])
    k = np.argmax(np.abs([adj[0][0], adj[1][1], adj[2][2], adj[3][3]]), axis=0)
    q = np.take_along_axis(np.array(adj), k[None, None, :], axis=1)[:, 0]  # column k of each adjugate
    c = np.sqrt(np.einsum("ik,ik->k", q, q))
    q /= np.where(c > 0, c, 1.0)
    refine = np.flatnonzero(~(c >= _REFINE_BELOW))
    if len(refine):
        Ns = tuple(a[refine] for a in N)
        qs = q[:, refine]
        rho = np.einsum("ik,ik->k", qs, _matvec4(Ns, qs))
        y = _matvec4(_adjugate4(_shifted(Ns, rho))[0], qs)
        norm = np.sqrt(np.einsum("ik,ik->k", y, y))
        unsure = ~(norm > _ADJUGATE_FLOOR)
        q[:, refine] = y / np.where(unsure, 1.0, norm)
        if unsure.any():  # (nearly) repeated extreme eigenvalue: the robust solver
            which = refine[unsure]
            full = np.moveaxis(np.array([[a[which] for a in row] for row in _rows(N)]), -1, 0)
            vectors = np.linalg.eigh(full)[1]
            q[:, which] = np.where(top[which], vectors[:, :, -1].T, vectors[:, :, 0].T)
    return q


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (3, 3, K) of unit quaternions q = (w, x, y, z) (4, K) (Horn 1987 sec. 3.E)."""
    w, x, y, z = q
    R = np.empty((3, 3) + q.shape[1:])
    R[0, 0] = w * w + x * x - y * y - z * z
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = w * w - x * x + y * y - z * z
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = w * w - x * x - y * y + z * z
    return R


# --------------------------------------------------------------------------
# Rotations: nearest rotation, angle between rotations
# --------------------------------------------------------------------------


def project_to_rotation(M: np.ndarray, method: str = "auto") -> np.ndarray:
    """The rotation (det +1) nearest to ``M`` in Frobenius norm, (..., 3, 3) -> (..., 3, 3).

    ``|R - M|_F^2 = 3 + |M|_F^2 - 2 trace(R M^T)``, so it is the Kabsch
    rotation step for ``H = M^T`` (:func:`best_rotations`), by SVD
    ``U diag(1, 1, det(U V^T)) V^T`` of ``M = U S V^T`` (Hartley et al. 2013,
    'Rotation Averaging', sec. 5.3, the chordal L2 mean; the paper's Formula
    (8) with the reflection guard).
    """
    return best_rotations(np.swapaxes(np.asarray(M, dtype=np.float64), -1, -2), method=method)[0]


def chord_to_angle(chord: float) -> float:
    """Rotation angle (rad) of two rotations a Frobenius (chordal) distance ``chord`` apart.

    ``||R_a - R_b||_F = 2 sqrt(2) sin(theta / 2)`` (Hartley et al. 2013, sec. 2),
    which, unlike ``arccos((tr - 1) / 2)``, stays accurate for tiny angles.
    """
    return 2.0 * math.asin(min(1.0, chord / (2.0 * math.sqrt(2.0))))


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in radians of the rotation ``R_a^T R_b`` between (3, 3) rotations
    (from their chordal distance, :func:`chord_to_angle`)."""
    difference = np.asarray(R_a, dtype=np.float64) - np.asarray(R_b, dtype=np.float64)
    return chord_to_angle(float(np.linalg.norm(difference)))
