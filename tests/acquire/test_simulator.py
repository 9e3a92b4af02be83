"""The simulator is the oracle: check it against analytic results and OpenCV."""

import cv2
import numpy as np
import pytest

from crossfield.simulator.optics import pixel_rays, project
from crossfield.simulator.render import SensorModel, add_noise, render_disc
from crossfield.simulator.scenarios import TABLE3_ACTUAL_MM, build_scene, station_calibration
from crossfield.types import CameraIntrinsics


def pinhole(dist=(0, 0, 0, 0, 0)):
    K = np.array([[3636.4, 0, 812.5], [0, 3636.4, 617.5], [0, 0, 1]])
    return CameraIntrinsics(K, np.array(dist, float), (1626, 1236))


def test_projection_matches_opencv():
    intr = station_calibration().upper
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-80, 80, 50), rng.uniform(-60, 60, 50), rng.uniform(350, 450, 50)])
    ours = project(P, intr)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), intr.camera_matrix, intr.dist_coeffs)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-9)


def test_pixel_rays_invert_projection():
    intr = station_calibration().lower
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-90, 90, 50), rng.uniform(-70, 70, 50), np.full(50, 400.0)])
    uv = project(P, intr)
    x, y = pixel_rays(uv[:, 0], uv[:, 1], intr)
    np.testing.assert_allclose(np.column_stack([x, y]), P[:, :2] / 400.0, atol=1e-12)


def ellipse_centre_of_projected_circle(K, centre, normal, radius):
    """Analytic image of a circle: conic C' = H^-T C H^-1 (Hartley & Zisserman 2.2.3)."""
    n = normal / np.linalg.norm(normal)
    e1 = np.cross(n, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    H = K @ np.column_stack([e1, e2, centre])
    C = np.diag([1.0, 1.0, -radius**2])
    Hinv = np.linalg.inv(H)
    Ci = Hinv.T @ C @ Hinv
    return np.linalg.solve(Ci[:2, :2], -Ci[:2, 2])


def test_fronto_parallel_disc_is_a_circle_at_the_projected_centre():
    intr = pinhole()
    centre = np.array([3.1, -2.7, 400.0])
    disc = render_disc(centre, np.array([0, 0, -1.0]), 2.5, intr)
    np.testing.assert_allclose(disc.centroid_uv, project(centre[None], intr)[0], atol=1e-9)
    area_px = np.pi * (2.5 * 3636.4 / 400.0) ** 2
    # the PSF and the pixel keep the signal: the image sums to the blob's area
    assert disc.image.sum() == pytest.approx(area_px, rel=1e-9)


def test_disc_image_is_the_psf_and_pixel_integral_over_the_disc():
    """Pixel values against scipy's 2-D quadrature of k(u - j) k(v - i) over the circle,
    k = Gaussian PSF (x) unit pixel: an edge pixel, its outer neighbour, a diagonal edge
    pixel and the centre."""
    from scipy.integrate import dblquad
    from scipy.special import ndtr

    intr = pinhole()
    centre = np.array([3.1, -2.7, 400.0])
    c = project(centre[None], intr)[0]
    r = 2.5 * intr.camera_matrix[0, 0] / 400.0
    sigma = 0.9
    disc = render_disc(centre, np.array([0, 0, -1.0]), 2.5, intr, blur_sigma_px=sigma)
    u0, v0 = disc.origin

    def k(x):
        return ndtr((x + 0.5) / sigma) - ndtr((x - 0.5) / sigma)

    def half(u):
        return np.sqrt(max(r * r - (u - c[0]) ** 2, 0.0))

    for j, i in ((round(c[0] + r), round(c[1])), (round(c[0] + r) + 1, round(c[1])),
                 (round(c[0] + 0.7 * r), round(c[1] - 0.7 * r)), (round(c[0]), round(c[1]))):
        ref, _ = dblquad(lambda v, u: k(u - j) * k(v - i), c[0] - r, c[0] + r,
                         lambda u: c[1] - half(u), lambda u: c[1] + half(u), epsabs=1e-11, epsrel=1e-10)
        assert disc.image[i - v0, j - u0] == pytest.approx(ref, abs=1e-9)
    with pytest.raises(ValueError, match="blur_sigma_px"):
        render_disc(centre, np.array([0, 0, -1.0]), 2.5, intr, blur_sigma_px=0.0)


def test_disc_gradient_is_the_derivative_of_a_shift():
    """DiscImage.gradient against central differences of the rendering of a shifted disc
    (fronto-parallel pinhole: moving the centre by dX mm shifts the image by f dX / Z px)."""
    intr = pinhole()
    centre = np.array([3.1, -2.7, 400.0])
    f = intr.camera_matrix[0, 0]
    disc = render_disc(centre, np.array([0, 0, -1.0]), 2.5, intr)
    h = 1e-3  # px
    for axis in (0, 1):
        step = np.zeros(3)
        step[axis] = h * 400.0 / f
        plus = render_disc(centre + step, np.array([0, 0, -1.0]), 2.5, intr)
        minus = render_disc(centre - step, np.array([0, 0, -1.0]), 2.5, intr)
        assert plus.origin == minus.origin == disc.origin
        numeric = (plus.image - minus.image) / (2 * h)
        np.testing.assert_allclose(disc.gradient[axis], numeric, atol=2e-4 * np.abs(numeric).max())


def test_tilted_disc_centre_is_the_ellipse_centre_not_the_projected_centre():
    intr = pinhole()
    centre = np.array([60.0, 40.0, 380.0])
    normal = np.array([0.5, -0.3, -1.0])
    disc = render_disc(centre, normal, 2.5, intr)
    ellipse_centre = ellipse_centre_of_projected_circle(intr.camera_matrix, centre, normal, 2.5)
    projected_centre = project(centre[None], intr)[0]
    np.testing.assert_allclose(disc.centroid_uv, ellipse_centre, atol=1e-9)
    # The perspective bias is real and larger than the rendering error.
    assert np.linalg.norm(ellipse_centre - projected_centre) > 0.01


def test_noise_model_matches_emva_linear_model():
    sensor = SensorModel()
    clean = np.full((400, 400), 1000.0, dtype=np.float32)
    image = add_noise(clean, sensor, np.random.default_rng(3))
    assert image.dtype == np.uint16
    expected = np.sqrt(sensor.gain_dn_per_e * 1000 + sensor.read_noise_dn**2 + 1 / 12)
    assert image.std() == pytest.approx(expected, rel=0.02)
    assert image.mean() == pytest.approx(1000, abs=0.1)


def test_table3_truth_is_the_papers_actual_sizes():
    scene = build_scene("table3")
    truth = scene.ground_truth
    axis = truth.lines_global["L3"]
    for k, actual in enumerate(TABLE3_ACTUAL_MM):
        assert axis.distance(truth.points_global[f"P{k + 1}"]) == pytest.approx(actual, abs=1e-9)
    assert np.linalg.det(truth.R_global_camera) == pytest.approx(1.0)
    # Every target is seen by both cameras; the references are out of view.
    for camera in ("upper", "lower"):
        assert len(scene.true_blob_centres(camera)) == 18
    R1_camera = truth.camera_points(["R1"])[0]
    uv = project(R1_camera[None], scene.calibration.upper)[0]
    assert not (0 <= uv[0] < 1626 and 0 <= uv[1] < 1236)


def test_frames_and_probes_are_deterministic_and_noisy_as_stated():
    scene = build_scene("station", arm_sigma_mm=0.02)
    a = scene.render_pair(0, np.random.default_rng(5))
    b = scene.render_pair(0, np.random.default_rng(5))
    assert np.array_equal(a.upper, b.upper) and np.array_equal(a.lower, b.lower)
    assert a.upper.shape == (1236, 1626) and a.upper.max() <= 4095
    errors = []
    for seed in range(40):
        for p in scene.arm_probes(np.random.default_rng(seed)):
            if p.label in scene.ground_truth.points_global:
                errors.append(p.xyz - scene.ground_truth.points_global[p.label])
    assert np.std(errors) == pytest.approx(0.02, rel=0.1)
    labels = [p.label for p in scene.arm_probes(np.random.default_rng(0))]
    assert labels == scene.plan.probing_order()
