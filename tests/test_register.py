"""Registration implementations: exact recovery, reflections, noise vs scipy, agreement.

Every "register" implementation offered by the built-in plugins runs the same
conformance tests (parametrised over implementations(pm, "register")).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.errors import ConfigError, RegistrationError
from crossfield.registry import implementations, make_plugin_manager
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
