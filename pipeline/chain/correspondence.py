"""Match triangulated camera points to the CMM control points by rigid distances.

The camera sees the control targets, the measured targets and possibly
strays (reflections, dirt), in no particular order; the CMM gives the control
points in the global frame with their plan ids. A rigid motion preserves
distances, so camera point i can be control a only if its distances to the
other matched camera points equal the distances of a to the other matched
controls (the classic association-graph formulation of point-pattern
matching, e.g. Bolles & Cain 1982; Grimson 1990, "Object Recognition by
Computer", ch. 4):

1. Nodes are candidate pairs (i, a). Two nodes (i, a), (j, b) with i != j,
   a != b are *compatible* when ``| |c_i - c_j| - |g_a - g_b| | <= tolerance``.
   The correspondence is a largest set of pairwise compatible nodes (a
   clique of the association graph).
2. Pruning (compiled, N*M nodes): a node in a clique of size k has
   compatible partners for at least k - 1 other controls. Nodes with
   partners for fewer than 2 controls (no clique of 3) are dropped; a clique
   is then grown greedily from the best-supported node and verified (step
   4); if it verifies with size k, nodes with partners for fewer than k - 1
   controls (among the remaining nodes, repeatedly) cannot belong to a
   clique at least as large and are dropped too.
3. Fast path: when what is left is one-to-one and pairwise compatible, it is
   the only candidate clique. Otherwise the maximal cliques of what is left
   are enumerated (Bron-Kerbosch with pivoting, Tomita et al. 2006, on
   bitsets).
4. Each candidate is verified by a rigid fit (Kabsch, proper rotation only):
   every point's residual must be within the tolerance. Distances do not
   change under a reflection, so this step also rejects the mirrored
   assignment of a mirror-symmetric control layout.
5. The largest verified clique wins. If several different assignments of
   that size verify, the pairs they all share are kept and the contested
   controls are left unmatched (a stray point lies within the tolerance of a
   control: that control cannot be trusted in this frame). A rigid motion
   that keeps 3 non-collinear points in place is the identity, so when the
   layout itself is symmetric (a rectangle, an isosceles triangle) fewer
   than 3 pairs are shared and :class:`CorrespondenceError` is raised naming
   the controls whose assignment is ambiguous.

Tolerance: ``tolerance_mm`` (default 0.5 mm) bounds the disagreement of a
camera distance with the CMM distance, and each point's residual after the
verification fit. It must exceed the measurement error of a distance
(camera depth uncertainty of a short-baseline pair, ~0.02-0.1 mm, plus CMM
~0.01-0.03 mm, both ends: a few tenths of a mm at most) and stay below the
smallest difference between control-point distances that must be told apart
(keep control layouts irregular, with distances differing by > 1 mm).
Loosening it lets more chance coincidences with strays through the pruning,
which the clique search and the fit verification then have to reject.

Implementation: steps 1-4 (the table, the pruning, the greedy clique, the
fast path and the verification fits) are numba kernels; their work is per
node and tiny (~6000 table entries for 10 camera points and 8 controls), where
NumPy spent ~0.2 ms per frame in call overhead. Bron-Kerbosch stays Python on
integer bitsets. The outcome is discrete: the same as the NumPy formulation's,
which ``tests/triangulate/test_correspondence_kernels.py`` keeps as the reference.
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np

from crossfield.errors import CorrespondenceError
from crossfield.types import Correspondence

#: Default agreement of camera and CMM distances (mm); see the module docstring.
DEFAULT_TOLERANCE_MM = 0.5

#: Bron-Kerbosch gives up beyond this many maximal cliques (pathological input).
MAX_CLIQUES = 20000


def match_control_points(
    camera_xyz: np.ndarray,
    control_xyz: np.ndarray,
    control_ids: Sequence[str],
    tolerance_mm: float = DEFAULT_TOLERANCE_MM,
) -> Correspondence:
    """Pair camera points with control points by invariance of rigid distances.

    camera_xyz: (N, 3) mm, camera frame, any order, may include non-control points.
    control_xyz: (M, 3) mm, global frame; control_ids: (M,) their plan ids.
    tolerance_mm: allowed disagreement of corresponding distances and the
        largest per-point residual of the verification fit (mm).

    Returns the correspondence with pairs in the order of ``control_ids``;
    camera points left over and controls not seen are listed as unmatched.
    Raises CorrespondenceError when fewer than 3 controls can be matched,
    when the match is not unique (symmetric layout) or when the camera points
    fit the controls only as a mirror image. Controls whose camera point is
    contested by a stray within the tolerance are left unmatched.
    """
    C = np.asarray(camera_xyz, dtype=np.float64).reshape(-1, 3)
    G = np.asarray(control_xyz, dtype=np.float64).reshape(-1, 3)
    ids = tuple(str(i) for i in control_ids)
    if len(ids) != len(G):
        raise CorrespondenceError(f"{len(G)} control points but {len(ids)} control ids")
    if len(set(ids)) != len(ids):
        raise CorrespondenceError(f"duplicate control ids: {ids}")
    if not (np.isfinite(C).all() and np.isfinite(G).all()):
        raise CorrespondenceError("non-finite coordinates in the camera or control points")
    tol = float(tolerance_mm)
    if not tol > 0:
        raise CorrespondenceError(f"tolerance_mm must be > 0, got {tolerance_mm!r}")
    n, m = len(C), len(G)
    if n < 3 or m < 3:
        raise CorrespondenceError(
            f"need at least 3 camera points and 3 control points to match, got {n} camera, {m} control"
        )

    # Steps 1-2: the compatibility of node (i, a) with node (j, b), stored as [i, a, b, j],
    # and the nodes with partners for at least 2 other controls (no clique of 3 without).
    compatible, alive = _compatibility(C, G, tol)
    if not alive.any():
        raise CorrespondenceError(_none_found(n, m, tol))
    # A verified greedy clique of size k bounds the search: only nodes with
    # partners for k - 1 other controls can be in a clique at least as large.
    checked: dict[tuple[int, ...], tuple[int, ...] | None] = {}
    mirror_size = 0  # largest clique that fits only as a mirror image
    greedy = tuple(_greedy_clique(compatible, alive).tolist())
    checked[greedy], mirrored = _verified_subset(greedy, C, G, tol, minimum=3, m=m)
    if mirrored:
        mirror_size = len(greedy)
    k = len(checked[greedy]) if checked[greedy] is not None else 3
    alive = _prune(compatible, alive, need=k - 1)

    # Step 3: the candidate cliques.
    cliques = _fast_path(compatible, alive) or _maximal_cliques(compatible, alive)

    # Step 4: verify by rigid fits; keep the largest verified assignments.
    verified: list[tuple[int, ...]] = []
    best = 0
    for clique in sorted(cliques, key=len, reverse=True):
        if len(clique) < max(best, 3):
            break
        if clique in checked and (checked[clique] is None or len(checked[clique]) >= max(best, 3)):
            pairs = checked[clique]
        else:
            pairs, mirrored = _verified_subset(clique, C, G, tol, minimum=max(best, 3), m=m)
            if mirrored:
                mirror_size = max(mirror_size, len(clique))
        if pairs is None:
            continue
        if len(pairs) > best:
            best, verified = len(pairs), [pairs]
        elif len(pairs) == best and pairs not in verified:
            verified.append(pairs)
    if mirror_size > best:
        raise CorrespondenceError(
            f"{mirror_size} camera points match control points in all their mutual distances, but only "
            f"as a mirror image (a reflection, det = -1), not by a rigid motion: check the handedness of "
            f"the camera frame (stereo calibration, baseline sign) and of the CMM frame"
        )
    if not verified:
        raise CorrespondenceError(_none_found(n, m, tol))
    chosen = set(verified[0])
    if len(verified) > 1:
        # Pairs common to every best assignment are certain; the others are contested
        # (a stray point within the tolerance of a control). A rigid motion that keeps
        # 3 non-collinear points in place is the identity, so a symmetric layout
        # leaves fewer than 3 common pairs: then nothing is certain.
        chosen = set.intersection(*(set(v) for v in verified))
        if len(chosen) < 3:
            raise CorrespondenceError(_ambiguity(verified, ids, m))

    nodes = sorted(chosen, key=lambda node: node % m)  # control order
    camera_index = [node // m for node in nodes]
    matched_controls = [ids[node % m] for node in nodes]
    return Correspondence(
        camera_index=np.array(camera_index, dtype=np.int64),
        control_ids=tuple(matched_controls),
        unmatched_camera=tuple(i for i in range(n) if i not in set(camera_index)),
        unmatched_control=tuple(cid for cid in ids if cid not in set(matched_controls)),
    )


# ---- compiled kernels (numba): the per-node loops of steps 1-4 on the (N, M, M, N) table ----------
# NumPy did these in ~40 small-array calls per frame (~0.2 ms); the table has ~6000 entries.


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _distances(X):
    """(K, K) Euclidean distances (mm) between the rows of X (K, 3):
    sqrt((dx^2 + dy^2) + dz^2), the order of ``np.linalg.norm(..., axis=-1)``."""
    k = len(X)
    D = np.zeros((k, k))
    for i in range(k):
        for j in range(k):
            dx, dy, dz = X[i, 0] - X[j, 0], X[i, 1] - X[j, 1], X[i, 2] - X[j, 2]
            D[i, j] = np.sqrt(dx * dx + dy * dy + dz * dz)
    return D


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _compatibility(C, G, tol):
    """Step 1-2: compatible (N, M, M, N) bool and alive (N, M) bool.

    compatible[i, a, b, j]: i != j, a != b and ``| |c_i - c_j| - |g_a - g_b| | <= tol``
    (C (N, 3) camera, G (M, 3) global, mm). alive[i, a]: node (i, a) has compatible
    partners for at least 2 controls b (else it is in no clique of 3)."""
    n, m = len(C), len(G)
    Dc, Dg = _distances(C), _distances(G)
    compatible = np.zeros((n, m, m, n), dtype=np.bool_)
    alive = np.zeros((n, m), dtype=np.bool_)
    for i in range(n):
        for a in range(m):
            controls = 0
            for b in range(m):
                if b == a:
                    continue
                found = False
                for j in range(n):
                    if j != i and abs(Dc[i, j] - Dg[a, b]) <= tol:
                        compatible[i, a, b, j] = True
                        found = True
                controls += found
            alive[i, a] = controls >= 2
    return compatible, alive


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _prune(compatible, alive, need):
    """Repeatedly drop nodes compatible with alive nodes of fewer than ``need`` other controls.

    compatible (N, M, M, N) and alive (N, M) bool as :func:`_compatibility`; each round
    judges every node against the alive set of the round before; returns the new alive."""
    n, m = alive.shape
    alive = alive.copy()
    while True:
        keep = alive.copy()
        for i in range(n):
            for a in range(m):
                if not alive[i, a]:
                    continue
                controls = 0
                for b in range(m):
                    for j in range(n):
                        if compatible[i, a, b, j] and alive[j, b]:
                            controls += 1
                            break
                if controls < need:
                    keep[i, a] = False
        if (keep == alive).all():
            return keep
        alive = keep


def _adjacency(compatible: np.ndarray) -> np.ndarray:
    """The association graph as an (N*M, N*M) matrix over nodes i * M + a."""
    n, m = compatible.shape[:2]
    return compatible.transpose(0, 1, 3, 2).reshape(n * m, n * m)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _greedy_clique(compatible, alive):
    """A clique (sorted node indices i * M + a, int64) grown from the best-supported
    alive node, adding the best-supported compatible node (ties: the lowest index).
    Support: the number of alive nodes a node is compatible with."""
    n, m = alive.shape
    candidates = alive.copy().ravel()
    support = np.zeros(n * m, dtype=np.int64)
    for k in range(n * m):
        i, a = k // m, k % m
        for l in range(n * m):
            if candidates[l] and compatible[i, a, l % m, l // m]:
                support[k] += 1
    clique = []
    while candidates.any():
        node, best = -1, -2
        for k in range(n * m):
            value = support[k] if candidates[k] else -1
            if value > best:
                node, best = k, value
        clique.append(node)
        i, a = node // m, node % m
        for l in range(n * m):
            candidates[l] = candidates[l] and compatible[i, a, l % m, l // m]
    return np.sort(np.array(clique, dtype=np.int64))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _one_to_one_clique(compatible, alive):
    """The alive nodes (int64, ascending i * M + a) when they are one-to-one and pairwise
    compatible, else an empty array."""
    n, m = alive.shape
    nodes = np.flatnonzero(alive.ravel())
    used_i = np.zeros(n, dtype=np.bool_)
    used_a = np.zeros(m, dtype=np.bool_)
    for k in nodes:
        i, a = k // m, k % m
        if used_i[i] or used_a[a]:
            return nodes[:0]
        used_i[i] = used_a[a] = True
    for k in nodes:
        for l in nodes:
            if k != l and not compatible[k // m, k % m, l % m, l // m]:
                return nodes[:0]
    return nodes


def _fast_path(compatible: np.ndarray, alive: np.ndarray) -> list[tuple[int, ...]] | None:
    """The single candidate clique when the alive nodes are one-to-one and pairwise compatible."""
    nodes = _one_to_one_clique(compatible, alive)
    return [tuple(nodes.tolist())] if len(nodes) or not alive.any() else None


def _maximal_cliques(compatible: np.ndarray, alive: np.ndarray) -> list[tuple[int, ...]]:
    """Maximal cliques (size >= 3) of the alive association graph; nodes are i * M + a."""
    n, m = alive.shape
    nodes = [int(k) for k in np.flatnonzero(alive.ravel())]
    adjacency = _adjacency(compatible)[np.ix_(nodes, nodes)]
    bits = [sum(1 << int(j) for j in np.flatnonzero(row)) for row in adjacency]
    found: list[int] = []

    def expand(r: int, p: int, x: int, size: int) -> None:
        if p == 0 and x == 0:
            if size >= 3:
                found.append(r)
                if len(found) > MAX_CLIQUES:
                    raise CorrespondenceError(
                        f"more than {MAX_CLIQUES} candidate assignments of camera points to controls: the "
                        f"points are too regular for matching by distances (or the tolerance is too loose)"
                    )
            return
        # Pivot with the most neighbours in P (Tomita et al. 2006).
        pivot_src = p | x
        pivot = max(_bit_indices(pivot_src), key=lambda u: (bits[u] & p).bit_count())
        candidates = p & ~bits[pivot]
        for v in _bit_indices(candidates):
            bit = 1 << v
            expand(r | bit, p & bits[v], x & bits[v], size + 1)
            p &= ~bit
            x |= bit

    expand(0, (1 << len(nodes)) - 1, 0, 0)
    return [tuple(nodes[k] for k in _bit_indices(c)) for c in found]


def _bit_indices(value: int) -> list[int]:
    out = []
    while value:
        low = value & -value
        out.append(low.bit_length() - 1)
        value ^= low
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _kabsch_residuals(P, Q):
    """Per-point residual norms (N,) mm of the best proper rigid fit Q ~ R P + t and of the
    best improper one (det R = -1), for the mirror diagnosis; P, Q (N, 3) mm.

    Unweighted Kabsch (Formulas (6)-(9) as :func:`crossfield.rigid.kabsch`):
    H = sum_i (p_i - p_bar)(q_i - q_bar)^T / N = U S V^T, R = V diag(1, 1, +-d) U^T with
    d = sign det(V U^T) (+1 at 0), t = q_bar - R p_bar."""
    n = len(P)
    p_bar = np.zeros(3)
    q_bar = np.zeros(3)
    for i in range(n):
        p_bar += P[i]
        q_bar += Q[i]
    p_bar /= n
    q_bar /= n
    H = np.zeros((3, 3))
    for i in range(n):
        for r in range(3):
            for c in range(3):
                H[r, c] += (P[i, r] - p_bar[r]) * (Q[i, c] - q_bar[c])
    U, _, Vt = np.linalg.svd(H / n)
    V, Ut = Vt.T.copy(), U.T.copy()
    d = 1.0 if np.linalg.det(V @ Ut) >= 0 else -1.0
    residuals = np.empty((2, n))
    for k, sign in enumerate((d, -d)):
        R = V.copy()
        R[:, 2] *= sign
        R = R @ Ut
        t = q_bar - R @ p_bar
        for i in range(n):
            e = R @ P[i] + t - Q[i]
            residuals[k, i] = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    return residuals[0], residuals[1]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _verified_nodes(clique, C, G, tol, minimum, m):
    """Step 4 for one clique (sorted nodes i * M + a, int64): (nodes, ok, mirrored).

    Fits the clique's pairs (:func:`_kabsch_residuals`) and drops its worst point until
    every residual is <= tol or fewer than ``minimum`` pairs are left (ok False).
    mirrored: the whole clique (more than 3 pairs) fits as a mirror image but not as a
    rigid motion."""
    nodes = clique.copy()
    count = len(nodes)
    mirrored = False
    while count >= minimum:
        P = np.empty((count, 3))
        Q = np.empty((count, 3))
        for k in range(count):
            P[k] = C[nodes[k] // m]
            Q[k] = G[nodes[k] % m]
        residuals, residuals_mirror = _kabsch_residuals(P, Q)
        worst = np.argmax(residuals)
        if residuals[worst] <= tol:
            return np.sort(nodes[:count]), True, mirrored
        if count == len(clique) and count > 3 and residuals_mirror.max() <= tol:
            mirrored = True
        nodes[worst:count - 1] = nodes[worst + 1:count].copy()
        count -= 1
    return nodes[:0], False, mirrored


def _verified_subset(
    clique: tuple[int, ...], C: np.ndarray, G: np.ndarray, tol: float, minimum: int, m: int
) -> tuple[tuple[int, ...] | None, bool]:
    """The clique, minus its worst points if need be, with all fit residuals <= tol,
    and whether the whole clique fits as a mirror image but not as a rigid motion."""
    nodes, ok, mirrored = _verified_nodes(np.array(clique, dtype=np.int64), C, G, tol, minimum, m)
    return (tuple(nodes.tolist()) if ok else None), mirrored


def _none_found(n: int, m: int, tol: float) -> str:
    return (
        f"no 3 camera points (of {n}) match 3 control points (of {m}) in their mutual distances "
        f"within {tol} mm with a proper rigid motion: are the control targets in view, the CMM points "
        f"labelled in the plan's probing order, and the stereo calibration right?"
    )


def _ambiguity(verified: list[tuple[int, ...]], ids: tuple[str, ...], m: int) -> str:
    assignments = [{ids[k % m]: k // m for k in nodes} for nodes in verified]
    differing = sorted(
        {cid for a in assignments for cid in ids if len({b.get(cid) for b in assignments}) > 1},
        key=ids.index,
    )
    shown = "; ".join(
        ", ".join(f"{cid}->camera[{a[cid]}]" if cid in a else f"{cid}->none" for cid in differing)
        for a in assignments[:3]
    )
    return (
        f"ambiguous correspondence: {len(verified)} different assignments of {len(verified[0])} "
        f"control points fit equally well (the control layout is symmetric, or a stray point lies "
        f"where a control would be); controls in question: {', '.join(differing)}; candidates: {shown}"
    )
