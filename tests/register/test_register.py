"""Registration implementations: exact recovery, reflections, noise vs scipy, agreement.

Every "register" implementation offered by the built-in plugins runs the same
conformance tests (parametrised over implementations(pm, "register")).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.errors import ConfigError, RegistrationError
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.stages import Registrar

PM = make_plugin_manager()
REGISTRARS = implementations(PM, "register")
NAMES = sorted(REGISTRARS)

#: The rotation printed in the paper's Table 1 (4 decimals): det = -1, a reflection.
PAPER_TABLE1 = np.array(
    [[-0.9472, -0.1538, -0.2810], [-0.2734, 0.8451, 0.4592], [-0.1669, -0.5118, 0.8426]]
)


def make(name: str, **options) -> Registrar:
    return REGISTRARS[name].create(options)


def random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform(-1000, 1000, 3)


def control_layout(rng: np.random.Generator, n: int = 8) -> np.ndarray:
    """n non-coplanar points in a camera view, mm (like the paper's control targets)."""
    return np.column_stack([rng.uniform(-80, 80, n), rng.uniform(-20, 70, n), rng.uniform(382, 418, n)])


def test_builtin_implementations_present():
    assert {"svd", "umeyama", "horn"} <= set(NAMES)
    for name in NAMES:
        assert isinstance(make(name), Registrar)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", range(5))
def test_recovers_known_transform_exactly(name, seed):
    rng = np.random.default_rng(seed)
    R, t = random_pose(rng)
    camera = control_layout(rng)
    global_ = camera @ R.T + t
    fit = make(name).fit(camera, global_)
    assert np.abs(fit.R - R).max() < 1e-12
    assert np.abs(fit.t - t).max() < 1e-9  # |t| ~ 1000 mm
    assert np.linalg.det(fit.R) == pytest.approx(1.0, abs=1e-12)
    assert fit.scale == 1.0
    assert fit.rms_mm < 1e-9
    assert fit.residuals.shape == (8, 3)
    # The documented orientation: global ~ R @ camera + t.
    np.testing.assert_allclose(fit.apply(camera), global_, atol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_residuals_and_rms_are_as_documented(name):
    rng = np.random.default_rng(11)
    R, t = random_pose(rng)
    camera = control_layout(rng, 10)
    global_ = camera @ R.T + t + rng.normal(0, 0.05, (10, 3))
    fit = make(name).fit(camera, global_)
    np.testing.assert_allclose(fit.residuals, camera @ fit.R.T + fit.t - global_, atol=1e-12)
    assert fit.rms_mm == pytest.approx(np.sqrt(np.mean(np.sum(fit.residuals**2, axis=1))), rel=1e-12)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("noise_mm", [0.0, 0.05])
def test_mirror_image_is_an_error(name, noise_mm):
    rng = np.random.default_rng(3)
    R, t = random_pose(rng)
    camera = control_layout(rng)
    mirrored = camera * np.array([-1.0, 1.0, 1.0])  # x -> -x: a left-handed camera frame
    global_ = mirrored @ R.T + t + rng.normal(0, noise_mm, camera.shape)
    with pytest.raises(RegistrationError, match="reflection"):
        make(name).fit(camera, global_)


@pytest.mark.parametrize("name", NAMES)
def test_paper_table1_matrix_is_a_reflection(name):
    """The paper's Table 1 'rotation' has det = -1: data related by it must be refused."""
    assert np.linalg.det(PAPER_TABLE1) == pytest.approx(-1.0, abs=2e-3)
    U, _, Vt = np.linalg.svd(PAPER_TABLE1)
    M = U @ Vt  # nearest orthogonal matrix, still det = -1
    rng = np.random.default_rng(4)
    camera = control_layout(rng)
    global_ = camera @ M.T + np.array([-93.4623, 44.8897, -312.5442])  # Table 2 translation
    with pytest.raises(RegistrationError, match="det = -1"):
        make(name).fit(camera, global_)


@pytest.mark.parametrize("name", NAMES)
def test_coplanar_points_with_noise_are_not_called_mirrored(name):
    """Planar sets fit a rotation as well as a reflection; det(V U^T) = -1 happens by chance
    and must not raise: the proper rotation is returned, close to the truth."""
    rng = np.random.default_rng(5)
    flips = 0
    for _ in range(200):
        R, t = random_pose(rng)
        camera = np.column_stack([rng.uniform(-50, 50, 8), rng.uniform(-50, 50, 8), np.zeros(8)])
        global_ = camera @ R.T + t + rng.normal(0, 0.02, (8, 3))
        camera_noisy = camera + rng.normal(0, 0.02, (8, 3))
        H = (camera_noisy - camera_noisy.mean(0)).T @ (global_ - global_.mean(0))
        U, _, Vt = np.linalg.svd(H)
        flips += np.linalg.det(Vt.T @ U.T) < 0
        fit = make(name).fit(camera_noisy, global_)
        assert np.linalg.det(fit.R) == pytest.approx(1.0)
        # A wrongly flipped fit would be off by ~pi.
        assert Rotation.from_matrix(fit.R @ R.T).magnitude() < 5e-3
    assert flips > 20  # the test does exercise the determinant correction


@pytest.mark.parametrize("name", NAMES)
def test_noisy_fit_matches_scipy_align_vectors(name):
    """Independent reference: scipy's Rotation.align_vectors (Kabsch/Markley) on centred sets."""
    rng = np.random.default_rng(7)
    R, t = random_pose(rng)
    camera = control_layout(rng, 12)
    global_ = camera @ R.T + t + rng.normal(0, 0.1, (12, 3))
    fit = make(name).fit(camera, global_)
    reference, _ = Rotation.align_vectors(global_ - global_.mean(0), camera - camera.mean(0))
    np.testing.assert_allclose(fit.R, reference.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(fit.t, global_.mean(0) - reference.as_matrix() @ camera.mean(0), atol=1e-8)


@pytest.mark.parametrize("name", NAMES)
def test_weighted_fit_matches_scipy_and_ignores_zero_weights(name):
    rng = np.random.default_rng(8)
    R, t = random_pose(rng)
    camera = control_layout(rng, 10)
    global_ = camera @ R.T + t + rng.normal(0, 0.05, (10, 3))
    weights = rng.uniform(0.2, 5.0, 10)
    fit = make(name).fit(camera, global_, weights)
    w = weights / weights.sum()
    reference, _ = Rotation.align_vectors(global_ - w @ global_, camera - w @ camera, weights=weights)
    np.testing.assert_allclose(fit.R, reference.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(fit.t, w @ global_ - reference.as_matrix() @ (w @ camera), atol=1e-8)

    # A gross outlier with weight 0 has no influence.
    exact = camera @ R.T + t
    exact[3, 0] += 25.0
    weights = np.ones(10)
    weights[3] = 0.0
    fit = make(name).fit(camera, exact, weights)
    assert np.abs(fit.R - R).max() < 1e-12
    assert np.linalg.norm(fit.residuals[3]) == pytest.approx(25.0, abs=1e-9)


def test_implementations_agree_on_noisy_data():
    rng = np.random.default_rng(9)
    for _ in range(20):
        R, t = random_pose(rng)
        camera = control_layout(rng, int(rng.integers(4, 12)))
        global_ = camera @ R.T + t + rng.normal(0, 0.05, camera.shape)
        weights = rng.uniform(0.5, 2.0, len(camera))
        fits = [make(name).fit(camera, global_, weights) for name in NAMES]
        for fit in fits[1:]:
            assert np.abs(fit.R - fits[0].R).max() < 1e-10
            assert np.abs(fit.t - fits[0].t).max() < 1e-8
            assert fit.rms_mm == pytest.approx(fits[0].rms_mm, rel=1e-8)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(
    "camera, message",
    [
        (np.array([[0.0, 0, 0], [10, 0, 0]]), "at least 3"),
        (np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0], [35, 0, 0]]), "collinear"),
        (np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0]]), "collinear"),
    ],
)
def test_degenerate_input_is_an_error(name, camera, message):
    with pytest.raises(RegistrationError, match=message):
        make(name).fit(camera, camera + 5.0)


@pytest.mark.parametrize("name", NAMES)
def test_bad_input_is_an_error(name):
    rng = np.random.default_rng(10)
    camera = control_layout(rng, 5)
    registrar = make(name)
    with pytest.raises(RegistrationError, match=r"\(N, 3\)"):
        registrar.fit(camera, camera[:4])
    bad = camera.copy()
    bad[2, 1] = np.nan
    with pytest.raises(RegistrationError, match="non-finite"):
        registrar.fit(bad, camera)
    with pytest.raises(RegistrationError, match="non-negative"):
        registrar.fit(camera, camera, -np.ones(5))
    with pytest.raises(RegistrationError, match="at least 3"):
        registrar.fit(camera, camera, np.array([1.0, 1.0, 0.0, 0.0, 0.0]))


@pytest.mark.parametrize("name", NAMES)
def test_reflection_ratio_option_is_validated(name):
    with pytest.raises(ConfigError, match="reflection_ratio"):
        REGISTRARS[name].create({"reflection_ratio": 0.5})


def test_umeyama_estimates_scale_only_when_asked():
    rng = np.random.default_rng(12)
    R, t = random_pose(rng)
    camera = control_layout(rng)
    global_ = 1.002 * camera @ R.T + t
    fit = make("umeyama", with_scale=True).fit(camera, global_)
    assert fit.scale == pytest.approx(1.002, abs=1e-12)
    assert np.abs(fit.R - R).max() < 1e-12
    np.testing.assert_allclose(fit.apply(camera), global_, atol=1e-9)
    rigid = make("umeyama").fit(camera, global_)
    assert rigid.scale == 1.0
    assert rigid.rms_mm > 0.1  # 0.2 % of ~400 mm cannot be absorbed by a rigid motion
    with pytest.raises(ConfigError, match="with_scale"):
        REGISTRARS["umeyama"].create({"with_scale": "yes"})


# --------------------------------------------------------------------------
# The shared kernel crossfield.rigid.kabsch: batched, two solvers, one decision
# --------------------------------------------------------------------------

from crossfield import rigid  # noqa: E402


def batch_of_scenes(rng: np.random.Generator, n: int, points: int = 8, kind: str = "noisy"):
    """n registrations (n, points, 3) camera/global mm of one kind, with their true rotations."""
    R = Rotation.random(n, random_state=rng).as_matrix()
    P = np.stack([control_layout(rng, points) for _ in range(n)])
    if kind == "coplanar":
        P[..., 2] = 400.0
    Pm = P * np.array([1.0, 1.0, -1.0]) if kind == "mirrored" else P
    Q = np.einsum("bij,bnj->bni", R, Pm) + rng.uniform(-1000, 1000, (n, 1, 3))
    if kind != "exact":
        P = P + rng.normal(0, 0.02, P.shape)
        Q = Q + rng.normal(0, 0.02, Q.shape)
    return P, Q, R


def mirror_decisions(P, Q, w, fits):
    """Per registration: would check_reflection refuse it (rms_proper > 5 rms_mirror)?"""
    R, t, Rm, tm = fits
    w = w / w.sum(axis=-1, keepdims=True)

    def weighted_rms(residuals):
        return np.sqrt(np.einsum("bn,bn->b", w, np.sum(residuals**2, axis=-1)))

    rms = weighted_rms(np.einsum("bij,bnj->bni", R, P) + t[:, None] - Q)
    rms_m = weighted_rms(np.einsum("bij,bnj->bni", Rm, P) + tm[:, None] - Q)
    floor = 1e-9 * np.maximum(1.0, weighted_rms(P - np.einsum("bn,bni->bi", w, P)[:, None]))
    return (rms > rigid.REFLECTION_RATIO * rms_m) & (rms > floor)


@pytest.mark.parametrize("kind", ["noisy", "exact", "coplanar", "mirrored"])
def test_closed_form_and_svd_routes_agree(kind):
    """The quaternion (closed-form) route gives the SVD route's R, R_mirror to 1e-12
    and the same proper / mirror decision, on 3000 registrations at once."""
    rng = np.random.default_rng({"noisy": 1, "exact": 2, "coplanar": 3, "mirrored": 4}[kind])
    P, Q, R_true = batch_of_scenes(rng, 3000, kind=kind)
    w = rng.uniform(0.2, 5.0, P.shape[:2])
    fast = rigid.kabsch(P, Q, w, method="quaternion")
    svd = rigid.kabsch(P, Q, w, method="svd")
    for a, b in zip(fast, svd):
        assert a.shape == b.shape
    np.testing.assert_allclose(fast[0], svd[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast[2], svd[2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast[1], svd[1], rtol=0, atol=1e-12 * 2000)  # |t| ~ 1000 mm
    np.testing.assert_allclose(fast[3], svd[3], rtol=0, atol=1e-12 * 2000)
    np.testing.assert_allclose(np.linalg.det(fast[0]), 1.0, atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(fast[2]), -1.0, atol=1e-13)
    decided = mirror_decisions(P, Q, w, fast)
    np.testing.assert_array_equal(decided, mirror_decisions(P, Q, w, svd))
    assert decided.all() if kind == "mirrored" else not decided.any()
    if kind == "exact":
        np.testing.assert_allclose(fast[0], R_true, atol=1e-12)
    if kind == "mirrored":  # the data are a reflection of R_true: the improper fit recovers it
        np.testing.assert_allclose(fast[2], R_true * np.array([1.0, 1.0, -1.0]), atol=1e-2)  # 0.02 mm noise


def test_batched_kabsch_matches_scipy_align_vectors():
    rng = np.random.default_rng(11)
    P, Q, _ = batch_of_scenes(rng, 200, points=10)
    w = rng.uniform(0.2, 5.0, P.shape[:2])
    R, t, _, _ = rigid.kabsch(P, Q, w)
    for k in range(len(P)):
        wk = w[k] / w[k].sum()
        reference, _ = Rotation.align_vectors(Q[k] - wk @ Q[k], P[k] - wk @ P[k], weights=w[k])
        np.testing.assert_allclose(R[k], reference.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(t[k], wk @ Q[k] - reference.as_matrix() @ (wk @ P[k]), atol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_batched_kabsch_matches_each_plugin_one_at_a_time(name):
    rng = np.random.default_rng(12)
    P, Q, _ = batch_of_scenes(rng, 100)
    w = rng.uniform(0.2, 5.0, P.shape[:2])
    R, t, _, _ = rigid.kabsch(P, Q, w)
    registrar = make(name)
    for k in range(len(P)):
        fit = registrar.fit(P[k], Q[k], w[k])
        np.testing.assert_allclose(fit.R, R[k], atol=1e-12)
        np.testing.assert_allclose(fit.t, t[k], atol=1e-9)


@pytest.fixture(params=["svd", "quaternion-eigh", "quaternion-closed-form"])
def route(request, monkeypatch):
    """A rotation route of rigid.kabsch; single registrations normally take np.linalg.eigh
    of Horn's matrix, "quaternion-closed-form" forces the closed form on them."""
    if request.param == "quaternion-closed-form":
        monkeypatch.setattr(rigid, "_CLOSED_FORM_MIN", 1)
    return request.param.split("-")[0]


def test_auto_method_picks_the_closed_form_for_batches(monkeypatch):
    used = []
    for name in ("_svd_rotations", "_quaternion_block"):
        original = getattr(rigid, name)
        monkeypatch.setattr(rigid, name, lambda H, f=original, n=name: (used.append((n, len(H))), f(H))[1])
    H = np.random.default_rng(0).normal(size=(100, 3, 3))
    rigid.best_rotations(H[:5])
    rigid.best_rotations(H)
    assert used == [("_svd_rotations", 5), ("_quaternion_block", 100)]


@pytest.mark.parametrize(
    "R_true",
    [
        np.eye(3),
        np.diag([1.0, -1.0, -1.0]),  # half turns: the quaternion's w is 0
        np.diag([-1.0, -1.0, 1.0]),
        Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix(),
        Rotation.from_rotvec(np.pi * np.array([1.0, 1.0, 1.0]) / np.sqrt(3)).as_matrix(),
        Rotation.from_rotvec([1e-9, 0.0, 0.0]).as_matrix(),
    ],
    ids=["identity", "half-turn-x", "half-turn-z", "quarter-z", "half-turn-diagonal", "tiny"],
)
def test_kabsch_analytic_cases(R_true, route):
    """Exact data from a known rotation: a 3-D layout, a coplanar one (both the rotation
    and its mirror fit exactly) and the mirror image of the layout."""
    rng = np.random.default_rng(13)
    P = control_layout(rng, 6)
    t_true = np.array([250.0, -40.0, 900.0])
    method = route
    R, t, R_m, _ = rigid.kabsch(P, P @ R_true.T + t_true, method=method)
    np.testing.assert_allclose(R, R_true, atol=1e-13)
    np.testing.assert_allclose(t, t_true, atol=1e-10)
    flat = P.copy()
    flat[:, 2] = 0.0  # coplanar in z = 0: the mirror in z is an exact improper fit
    R, _, R_m, t_m = rigid.kabsch(flat, flat @ R_true.T + t_true, method=method)
    np.testing.assert_allclose(R, R_true, atol=1e-13)
    np.testing.assert_allclose(R_m, R_true @ np.diag([1.0, 1.0, -1.0]), atol=1e-13)
    np.testing.assert_allclose(t_m, t_true, atol=1e-10)
    mirror = R_true @ np.diag([1.0, -1.0, 1.0])
    _, _, R_m, t_m = rigid.kabsch(P, P @ mirror.T + t_true, method=method)
    np.testing.assert_allclose(R_m, mirror, atol=1e-13)
    np.testing.assert_allclose(t_m, t_true, atol=1e-10)


def test_kabsch_degenerate_sets_still_give_best_fits(monkeypatch):
    """Collinear or coincident points (which validate_pairs refuses): the rotation is not
    unique, but both routes return orthogonal matrices with the same, optimal residual
    (the closed form hands these repeated eigenvalues to np.linalg.eigh)."""
    eigh_calls = []
    eigh = np.linalg.eigh
    monkeypatch.setattr(np.linalg, "eigh", lambda A: (eigh_calls.append(A.shape), eigh(A))[1])
    monkeypatch.setattr(rigid, "_CLOSED_FORM_MIN", 1)  # the closed form, even for one registration
    rng = np.random.default_rng(14)
    line = np.outer(np.linspace(-50, 50, 5), [0.6, 0.0, 0.8]) + [10.0, 20.0, 400.0]
    R_true = Rotation.random(random_state=rng).as_matrix()
    cases = [(line, line @ R_true.T + 5.0), (np.ones((4, 3)), np.ones((4, 3)) * 7.0)]
    for P, Q in cases:
        results = [rigid.kabsch(P, Q, method=m) for m in rigid.KABSCH_METHODS]
        for R, t, R_m, t_m in results:
            for M, sign in ((R, 1.0), (R_m, -1.0)):
                np.testing.assert_allclose(M @ M.T, np.eye(3), atol=1e-12)
                assert np.linalg.det(M) == pytest.approx(sign, abs=1e-12)
            assert rigid.residual_rms(P @ R.T + t - Q) < 1e-10
    assert eigh_calls == [(2, 4, 4)] * 2  # proper and mirror, for each of the two cases


def test_kabsch_shapes_and_leading_batch_dimensions():
    rng = np.random.default_rng(15)
    P, Q, _ = batch_of_scenes(rng, 12)
    P, Q = P.reshape(3, 4, 8, 3), Q.reshape(3, 4, 8, 3)
    R, t, R_m, t_m = rigid.kabsch(P, Q, np.ones(8))
    assert R.shape == R_m.shape == (3, 4, 3, 3) and t.shape == t_m.shape == (3, 4, 3)
    single = rigid.kabsch(P[1, 2], Q[1, 2])
    np.testing.assert_allclose(single[0], R[1, 2], atol=1e-15)
    with pytest.raises(ValueError, match="unknown Kabsch method 'lu': expected auto, svd, quaternion"):
        rigid.kabsch(P, Q, method="lu")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        rigid.best_rotations(np.eye(4))


@pytest.mark.parametrize("method", rigid.KABSCH_METHODS)
def test_project_to_rotation_is_the_nearest_rotation(method):
    """Against the SVD formula U diag(1, 1, det(U V^T)) V^T, batched, including matrices
    whose nearest orthogonal matrix is a reflection (negative determinant)."""
    rng = np.random.default_rng(16)
    M = Rotation.random(500, random_state=rng).as_matrix() + rng.normal(0, 0.3, (500, 3, 3))
    M[:100] *= -1.0  # det < 0
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(M), 3))
    D[:, 2] = d
    expected = (U * D[:, None, :]) @ Vt
    got = rigid.project_to_rotation(M, method=method)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=1e-13)
    others = Rotation.random(2000, random_state=rng).as_matrix()
    for k in (0, 1, 200, 201):  # nearer than any of 2000 random rotations
        assert np.linalg.norm(got[k] - M[k]) < np.linalg.norm(others - M[k], axis=(1, 2)).min()


def test_rotation_angle_against_scipy_and_tiny_angles():
    rng = np.random.default_rng(17)
    for angle in (1e-10, 1e-6, 0.3, 2.0, np.pi - 1e-6):
        axis = rng.normal(size=3)
        R_a = Rotation.random(random_state=rng).as_matrix()
        R_b = R_a @ Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
        assert rigid.rotation_angle(R_a, R_b) == pytest.approx(angle, rel=1e-6, abs=1e-15)
        assert rigid.rotation_angle(R_a, R_b) == pytest.approx(
            Rotation.from_matrix(R_a.T @ R_b).magnitude(), rel=1e-6, abs=1e-15
        )
    assert rigid.chord_to_angle(0.0) == 0.0
    assert rigid.chord_to_angle(2 * np.sqrt(2)) == pytest.approx(np.pi)
