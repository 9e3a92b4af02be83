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
2. Pruning (vectorised, N*M nodes): a node in a clique of size k has
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
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from crossfield.errors import CorrespondenceError
from crossfield.rigid import kabsch
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

    # Step 1: compatibility of node (i, a) with node (j, b), stored as [i, a, b, j]
    # so that "has a partner for control b" reduces over the last, contiguous axis.
    Dc = np.linalg.norm(C[:, None, :] - C[None, :, :], axis=2)
    Dg = np.linalg.norm(G[:, None, :] - G[None, :, :], axis=2)
    compatible = np.abs(Dc[:, None, None, :] - Dg[None, :, :, None]) <= tol
    compatible &= ~np.eye(n, dtype=bool)[:, None, None, :]  # i != j
    compatible &= ~np.eye(m, dtype=bool)[None, :, :, None]  # a != b

    # Step 2: nodes with partners for fewer than 2 other controls are in no clique of 3.
    alive = compatible.any(axis=3).sum(axis=2) >= 2
    if not alive.any():
        raise CorrespondenceError(_none_found(n, m, tol))
    # A verified greedy clique of size k bounds the search: only nodes with
    # partners for k - 1 other controls can be in a clique at least as large.
    checked: dict[tuple[int, ...], tuple[int, ...] | None] = {}
    mirror_size = 0  # largest clique that fits only as a mirror image
    greedy = _greedy_clique(compatible, alive)
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


def _prune(compatible: np.ndarray, alive: np.ndarray, need: int) -> np.ndarray:
    """Repeatedly drop nodes compatible with alive nodes of fewer than ``need`` other controls."""
    while True:
        partners = (compatible & alive.T[None, None, :, :]).any(axis=3)  # (N, M, M): (i, a) has a b-partner
        keep = alive & (partners.sum(axis=2) >= need)
        if (keep == alive).all():
            return keep
        alive = keep


def _adjacency(compatible: np.ndarray) -> np.ndarray:
    """The association graph as an (N*M, N*M) matrix over nodes i * M + a."""
    n, m = compatible.shape[:2]
    return compatible.transpose(0, 1, 3, 2).reshape(n * m, n * m)


def _greedy_clique(compatible: np.ndarray, alive: np.ndarray) -> tuple[int, ...]:
    """A clique grown from the best-supported node, adding the best-supported compatible node."""
    n, m = alive.shape
    adjacency = _adjacency(compatible)
    candidates = alive.ravel().copy()
    support = (adjacency & candidates[None, :]).sum(axis=1)
    clique: list[int] = []
    while candidates.any():
        node = int(np.argmax(np.where(candidates, support, -1)))
        clique.append(node)
        candidates &= adjacency[node]
    return tuple(sorted(clique))


def _fast_path(compatible: np.ndarray, alive: np.ndarray) -> list[tuple[int, ...]] | None:
    """The single candidate clique when the alive nodes are one-to-one and pairwise compatible."""
    i_idx, a_idx = np.nonzero(alive)
    if len(np.unique(i_idx)) != len(i_idx) or len(np.unique(a_idx)) != len(a_idx):
        return None
    sub = compatible[i_idx[:, None], a_idx[:, None], a_idx[None, :], i_idx[None, :]]
    if not (sub | np.eye(len(i_idx), dtype=bool)).all():
        return None
    m = compatible.shape[1]
    return [tuple(int(i * m + a) for i, a in zip(i_idx, a_idx))]


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


def _kabsch_residuals(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point residual norms (N,) of the best proper rigid fit Q ~ R P + t (Kabsch,
    :func:`crossfield.rigid.kabsch`) and of the best improper one (det R = -1), for the
    mirror diagnosis."""
    R, t, R_mirror, t_mirror = kabsch(P, Q)
    return (
        np.linalg.norm(P @ R.T + t - Q, axis=1),
        np.linalg.norm(P @ R_mirror.T + t_mirror - Q, axis=1),
    )


def _verified_subset(
    clique: tuple[int, ...], C: np.ndarray, G: np.ndarray, tol: float, minimum: int, m: int
) -> tuple[tuple[int, ...] | None, bool]:
    """The clique, minus its worst points if need be, with all fit residuals <= tol,
    and whether the whole clique fits as a mirror image but not as a rigid motion."""
    nodes = list(clique)
    mirrored = False
    while len(nodes) >= minimum:
        cam = np.array([k // m for k in nodes])
        ctl = np.array([k % m for k in nodes])
        residuals, residuals_mirror = _kabsch_residuals(C[cam], G[ctl])
        worst = int(np.argmax(residuals))
        if residuals[worst] <= tol:
            return tuple(sorted(nodes)), mirrored
        if len(nodes) == len(clique) and len(nodes) > 3 and residuals_mirror.max() <= tol:
            mirrored = True
        del nodes[worst]
    return None, mirrored


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
