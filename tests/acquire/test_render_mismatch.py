"""The model-mismatch renderer against analytic cases and reference implementations.

Lens: OpenCV's ``projectPoints`` with 12 coefficients. PSF and pixel: the
image conic of a disc (Hartley & Zisserman 2.2.3) gives its exact area and area
centroid; the pixel integral of a Gaussian is a product of erf differences.
Sensor: the EMVA 1288 linear model's mean and variance in electrons.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.special import ndtr

from crossfield.simulator.render_mismatch import (
    PSF,
    MismatchSensor,
    TrueLens,
    apply_sensor,
    conic_of_disc,
    fit_plumb_bob,
    fixed_pattern,
    render_disc_electrons,
)

SIZE = (1626, 1236)
LENS = TrueLens(3636.0, 3636.0 * 1.0008, 812.0, 617.0, (-0.12, 0.2, -0.05, 0.01, 0.02, 0.0), (3e-4, -2e-4),
                (1e-3, -5e-4, 8e-4, 2e-4), SIZE)
PINHOLE = TrueLens(3636.0, 3636.0, 812.0, 617.0, (0.0,) * 6, (0.0, 0.0), (0.0,) * 4, SIZE)


def _conic_area_centre(C: np.ndarray) -> tuple[float, np.ndarray]:
    A, b = C[:2, :2], C[:2, 2]
    centre = -np.linalg.solve(A, b)
    area = np.pi * (b @ np.linalg.solve(A, b) - C[2, 2]) / np.sqrt(np.linalg.det(A))
    return float(area), centre


def _moments(origin, image) -> tuple[float, np.ndarray]:
    u0, v0 = origin
    vv, uu = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    total = float(image.sum())
    return total, np.array([(image * uu).sum() / total + u0, (image * vv).sum() / total + v0])


def test_lens_matches_opencv_full_model_and_inverts():
    P = np.random.default_rng(0).uniform([-80, -20, 380], [80, 70, 420], (50, 3))
    uv = LENS.project(P)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), LENS.camera_matrix(), LENS.opencv_coeffs())
    assert np.abs(uv - ref[:, 0]).max() < 1e-9
    x, y = LENS.rays(uv[:, 0], uv[:, 1])
    assert np.abs(x - P[:, 0] / P[:, 2]).max() < 1e-12 and np.abs(y - P[:, 1] / P[:, 2]).max() < 1e-12


def test_plumb_bob_fit_is_exact_for_a_plumb_bob_lens_and_leaves_the_prism():
    plumb = TrueLens(3636.0, 3636.0, 812.0, 617.0, (-0.12, 0.2, -0.05, 0, 0, 0), (3e-4, -2e-4), (0,) * 4, SIZE)
    np.testing.assert_allclose(fit_plumb_bob(plumb), [-0.12, 0.2, 3e-4, -2e-4, -0.05], atol=1e-9)
    coeffs = fit_plumb_bob(LENS)
    P = np.random.default_rng(1).uniform([-80, -20, 380], [80, 70, 420], (200, 3))
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), LENS.camera_matrix(), coeffs)
    residual = np.linalg.norm(LENS.project(P) - ref[:, 0], axis=1)
    assert 0.01 < residual.max() < 2.0  # the model error the estimator is left with (px)


@pytest.mark.parametrize("psf", [PSF(0.6, 0.7, 1.0), PSF(0.5, 1.2, 0.5), PSF(0.8, 0.0, 0.7)])
def test_tilted_disc_energy_and_centroid_are_the_exact_conic_ones(psf):
    # no distortion: the disc's image is the conic C' = H^-T C H^-1, its area and centre exact;
    # an even PSF and a centred aperture move neither; the sum is fill_factor x area
    centre = np.array([12.0, -7.0, 400.0])
    normal = np.array([0.35, -0.2, -1.0])
    origin, image = render_disc_electrons(centre, normal, 2.5, PINHOLE, psf, oversample=6)
    area, conic_centre = _conic_area_centre(conic_of_disc(centre, normal, 2.5, PINHOLE.camera_matrix()))
    total, centroid = _moments(origin, image)
    assert total / psf.fill_factor == pytest.approx(area, rel=1e-4)
    assert np.abs(centroid - conic_centre).max() < 1e-3  # px
    # the conic centre is not the projection of the disc's centre (perspective eccentricity)
    assert np.linalg.norm(conic_centre - PINHOLE.project(centre[None])[0]) > 0.01


def test_pixel_integral_of_a_gaussian_psf():
    # a frontal disc of radius 1 px centred on a pixel: pixel (i, j) holds the integral over the
    # disc of k(u - j) k(v - i), k(x) = Phi((x + a/2) / s) - Phi((x - a/2) / s) (Gaussian times the
    # aperture of side a = sqrt(fill factor)); the reference by Gauss-Legendre quadrature in polar
    # coordinates (64 x 64 nodes)
    sigma, ff, r_px = 0.7, 0.64, 1.0
    z = 400.0
    centre = np.array([0.0, 0.0, z])  # projects to (cx, cy) = (812, 617), a pixel centre
    origin, image = render_disc_electrons(centre, np.array([0, 0, -1.0]), r_px * z / PINHOLE.fx, PINHOLE,
                                          PSF(sigma, 0.0, ff), oversample=8)
    a = np.sqrt(ff)
    x, w = np.polynomial.legendre.leggauss(64)
    rho, w_rho = 0.5 * r_px * (x + 1), 0.5 * r_px * w
    phi, w_phi = np.pi * (x + 1), np.pi * w
    du = (rho[:, None] * np.cos(phi)[None, :]).ravel()
    dv = (rho[:, None] * np.sin(phi)[None, :]).ravel()
    weight = (w_rho[:, None] * rho[:, None] * w_phi[None, :]).ravel()

    def k(d):
        return ndtr((d + a / 2) / sigma) - ndtr((d - a / 2) / sigma)

    d = np.arange(-3, 4)
    reference = np.array([[np.sum(weight * k(du - dj) * k(dv - di)) for dj in d] for di in d])
    i0, j0 = 617 - origin[1], 812 - origin[0]
    window = image[i0 - 3 : i0 + 4, j0 - 3 : j0 + 4]
    assert reference.sum() == pytest.approx(ff * np.pi * r_px**2, rel=1e-3)
    np.testing.assert_allclose(window, reference, atol=2e-3 * reference.max())


def test_distorted_disc_centroid_is_its_exact_image_centroid():
    # through the full lens, the reference is the area centroid of the rim projected exactly
    # (Green's theorem on 4096 rim points)
    centre, normal, r = np.array([-60.0, 40.0, 390.0]), np.array([-0.2, 0.3, -1.0]), 2.5
    origin, image = render_disc_electrons(centre, normal, r, LENS, PSF(0.6, 0.7, 0.6), oversample=6)
    n = normal / np.linalg.norm(normal)
    e1 = np.cross([0, 0, 1.0], n)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    phi = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    uv = LENS.project(centre + r * (np.outer(np.cos(phi), e1) + np.outer(np.sin(phi), e2)))
    u, v = uv[:, 0], uv[:, 1]
    un, vn = np.roll(u, -1), np.roll(v, -1)
    cross = u * vn - un * v
    A = 0.5 * cross.sum()
    exact = np.array([((u + un) * cross).sum(), ((v + vn) * cross).sum()]) / (6 * A)
    total, centroid = _moments(origin, image)
    assert total / 0.6 == pytest.approx(abs(A), rel=2e-4)
    assert np.abs(centroid - exact).max() < 1e-3


def test_sensor_noise_in_electrons_follows_emva_1288():
    s = MismatchSensor()
    rng = np.random.default_rng(3)
    shape = (400, 500)
    mu_e = np.full(shape, 4000.0)
    flat_gain, flat_dark = np.ones(shape), np.full(shape, s.dark_e)
    a = apply_sensor(mu_e, flat_gain, flat_dark, s, rng).astype(float)
    b = apply_sensor(mu_e, flat_gain, flat_dark, s, rng).astype(float)
    K = s.gain_dn_per_e
    assert a.mean() == pytest.approx(K * (4000 + s.dark_e) + s.offset_dn, abs=0.05)
    # temporal variance from the difference of two frames (EMVA 1288 eq. (30)): K^2 (mu_e + mu_d + sigma_d^2) + 1/12
    expected = K * K * (4000 + s.dark_e + s.read_noise_e**2) + 1 / 12
    assert np.var(a - b) / 2 == pytest.approx(expected, rel=0.02)
    # the fixed pattern: PRNU scales the signal, DSNU the dark signal (spatial std over many frames' mean)
    gain, dark = fixed_pattern(shape, s, rng)
    assert np.std(gain) == pytest.approx(s.prnu, rel=0.02)
    assert np.std(dark) == pytest.approx(s.dsnu_e, rel=0.02)
    c = apply_sensor(mu_e, gain, dark, s, rng).astype(float)
    spatial = np.var(c) - expected  # temporal part taken off
    assert spatial == pytest.approx(K * K * ((4000 * s.prnu) ** 2 + s.dsnu_e**2), rel=0.1)
    # saturation: the full well, then the 12-bit ADC
    full = apply_sensor(np.full((10, 10), 3e4), flat_gain[:10, :10], flat_dark[:10, :10], s, rng)
    assert abs(full.astype(float).mean() - (K * s.full_well_e + s.offset_dn)) < 2
    hot = MismatchSensor(gain_dn_per_e=1.0, full_well_e=1e5)
    assert apply_sensor(np.full((4, 4), 5e4), np.ones((4, 4)), np.zeros((4, 4)), hot, rng).max() == 4095


def test_mismatch_scene_gives_the_estimator_a_plumb_bob_and_draws_each_session():
    from crossfield.simulator.optics import project
    from crossfield.simulator.scenarios import build_scene

    scene = build_scene("mismatch-camera")
    assert len(scene.calibration.upper.dist_coeffs) == 5
    P = np.array([t.centre_camera for t in scene.targets])
    model_error = np.linalg.norm(scene.lenses["upper"].project(P) - project(P, scene.calibration.upper), axis=1)
    assert 1e-4 < model_error.max() < 0.05  # px: a good calibration, not the truth
    a, b, a2 = scene.for_session(1), scene.for_session(2), scene.for_session(1)
    assert np.abs(a.R_lower_upper_true - b.R_lower_upper_true).max() > 1e-8  # a toe-in error of ~1e-6 rad
    np.testing.assert_array_equal(a.R_lower_upper_true, a2.R_lower_upper_true)
    tilt = [np.degrees(np.arccos(np.clip(s.normal_camera @ t.normal_camera, -1, 1)))
            for s, t in zip(a.targets, scene.targets)]
    assert 0.1 < np.sqrt(np.mean(np.square(tilt))) < 5.0
    np.testing.assert_array_equal(a.ground_truth.points_global["P1"], scene.ground_truth.points_global["P1"])


def test_simulator_source_selects_the_renderer_and_the_station():
    from crossfield.plugins.acquire_simulator import SimulatorSource
    from crossfield.simulator.scene_mismatch import MismatchScene

    source = SimulatorSource(scenario="station", frames=1, seed=3, render="mismatch")
    assert isinstance(source.scene, MismatchScene) and source.scene.session_seed == 3
    assert source.describe()["render"] == "mismatch"
    one = SimulatorSource(scenario="mismatch-camera", frames=1, seed=3, station_seed=9)
    assert one.scene.session_seed == 9
    frame = next(one.frames())
    assert frame.upper.dtype == np.uint16 and frame.upper.max() <= 4095
    assert not isinstance(SimulatorSource(scenario="station", frames=1).scene, MismatchScene)
    with pytest.raises(ValueError, match="renderer"):
        SimulatorSource(scenario="station", render="raytraced")
