"""The compiled correspondence kernels against the NumPy formulation they replaced.

``reference_match`` below is ``crossfield.chain.correspondence.match_control_points``
as it was before its steps 1-4 were compiled (numba): the same association graph,
pruning, greedy clique, fast path, Bron-Kerbosch and Kabsch verification in NumPy.
The two must give the same correspondence (or the same CorrespondenceError, message
and all) on random scenes: shuffled points, strays, noise, missing controls, 3
controls, coplanar, collinear, symmetric (rectangle) and mirrored layouts, tolerances
from 0.2 to 1 mm. The output is discrete: equality is asserted.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.chain import correspondence
from crossfield.chain.correspondence import match_control_points
from crossfield.errors import CorrespondenceError
from crossfield.rigid import kabsch
from crossfield.types import Correspondence

# ---- the reference: the NumPy formulation (verbatim but for the name) ---------------------

#: Default agreement of camera and CMM distances (mm); see the module docstring.
DEFAULT_TOLERANCE_MM = 0.5

#: Bron-Kerbosch gives up beyond this many maximal cliques (pathological input).
MAX_CLIQUES = 20000


def reference_match(
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


# ---- the comparison -------------------------------------------------------------------------

IDS = [f"C{k + 1}" for k in range(8)]


def outcome(match, *args, **kwargs):
    """The correspondence as plain tuples, or the error's type and message."""
    try:
        c = match(*args, **kwargs)
    except CorrespondenceError as exc:
        return "error", str(exc)
    return tuple(c.camera_index.tolist()), c.control_ids, c.unmatched_camera, c.unmatched_control


def random_scene(rng, kind):
    """(camera (N, 3), control (M, 3), ids, tolerance) of one of the edge-case kinds."""
    m = int(rng.integers(3, 9))
    G0 = np.column_stack([rng.uniform(-80, 80, m), rng.uniform(-20, 70, m), rng.uniform(382, 418, m)])
    if kind == "coplanar":
        G0[:, 2] = 400.0
    elif kind == "rectangle":  # symmetric layout: ambiguous
        G0 = np.array([[0, 0, 400], [50, 0, 400], [0, 30, 400], [50, 30, 400.0]])
    elif kind == "collinear":
        G0 = np.outer(np.linspace(-60, 60, m), [0.6, 0.0, 0.8]) + [0, 0, 400]
    elif kind == "three":
        G0 = G0[:3]
    m = len(G0)
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.uniform(-800, 800, 3)
    camera = G0.copy()
    if kind == "mirror":
        camera[:, 0] *= -1.0
    visible = rng.uniform(size=m) > (0.2 if kind == "missing" else 0.0)
    extra = int(rng.integers(0, 15))
    strays = np.column_stack([rng.uniform(-80, 80, extra), rng.uniform(-20, 70, extra), rng.uniform(380, 420, extra)])
    noise = 0.3 if kind == "noisy" else 0.05
    points = np.vstack([camera[visible], strays])
    points = points + rng.normal(0, noise, points.shape)
    return points[rng.permutation(len(points))], G0 @ R.T + t, IDS[:m], float(rng.choice([0.2, 0.5, 1.0]))


KINDS = ["plain", "coplanar", "rectangle", "collinear", "three", "mirror", "missing", "noisy"]


@pytest.mark.parametrize("kind", KINDS)
def test_the_compiled_match_equals_the_numpy_formulation(kind):
    rng = np.random.default_rng(KINDS.index(kind))
    errors = 0
    for _ in range(150):
        camera, control, ids, tol = random_scene(rng, kind)
        expected = outcome(reference_match, camera, control, ids, tolerance_mm=tol)
        assert outcome(match_control_points, camera, control, ids, tolerance_mm=tol) == expected
        errors += expected[0] == "error"
    if kind in ("rectangle", "collinear", "mirror"):
        assert errors > 0  # the edge case is exercised: the same error is raised


def test_the_kernels_equal_their_numpy_steps():
    """Steps 1-4 one by one: compatibility table, pruning, greedy clique, fast path, fits."""
    rng = np.random.default_rng(11)
    for _ in range(100):
        camera, control, _, tol = random_scene(rng, "plain")
        n, m = len(camera), len(control)
        Dc = np.linalg.norm(camera[:, None, :] - camera[None, :, :], axis=2)
        Dg = np.linalg.norm(control[:, None, :] - control[None, :, :], axis=2)
        table = np.abs(Dc[:, None, None, :] - Dg[None, :, :, None]) <= tol
        table &= ~np.eye(n, dtype=bool)[:, None, None, :]
        table &= ~np.eye(m, dtype=bool)[None, :, :, None]
        alive = table.any(axis=3).sum(axis=2) >= 2
        compatible, alive_new = correspondence._compatibility(camera, control, tol)
        assert np.array_equal(compatible, table) and np.array_equal(alive_new, alive)
        if not alive.any():
            continue
        greedy = _greedy_clique(table, alive)
        assert tuple(correspondence._greedy_clique(table, alive).tolist()) == greedy
        for need in (2, 3, 5):
            assert np.array_equal(correspondence._prune(table, alive, need), _prune(table, alive, need))
            pruned = _prune(table, alive, need)
            assert correspondence._fast_path(table, pruned) == _fast_path(table, pruned)
        for minimum in (3, 4):
            assert correspondence._verified_subset(greedy, camera, control, tol, minimum, m) == _verified_subset(
                greedy, camera, control, tol, minimum, m
            )


def test_the_compiled_fit_residuals_match_kabsch():
    """The verification fit's residuals against crossfield.rigid.kabsch (to rounding, 1e-9 mm)."""
    rng = np.random.default_rng(5)
    for n in (3, 4, 8, 12):
        P = rng.uniform(-80, 80, (n, 3)) + [0, 0, 400]
        R = Rotation.random(random_state=rng).as_matrix()
        for mirror in (False, True):
            Q = (P * ([-1.0, 1.0, 1.0] if mirror else 1.0)) @ R.T + 300 + rng.normal(0, 0.05, P.shape)
            proper, improper = correspondence._kabsch_residuals(P, Q)
            ref_proper, ref_improper = _kabsch_residuals(P, Q)
            np.testing.assert_allclose(proper, ref_proper, rtol=0, atol=1e-9)
            np.testing.assert_allclose(improper, ref_improper, rtol=0, atol=1e-9)
