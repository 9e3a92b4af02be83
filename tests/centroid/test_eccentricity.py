"""Perspective eccentricity of circle centres, against the simulator's exact rendering.

The simulator renders each target by casting every sub-sample through the lens
onto the target plane (pipeline/simulator/render.py), so the blob centre it
reports is the true centroid of the perspective, distorted image of the circle.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crossfield.imaging import eccentricity as ecc
from crossfield.chain.registry import implementations, make_plugin_manager
from crossfield.simulator.render import render_disc
from crossfield.simulator.scenarios import build_scene
from crossfield.types import StereoCentroids


def views_of(calibration):
    return (
        ecc.View(calibration.upper.camera_matrix, calibration.upper.dist_coeffs, np.eye(3), np.zeros(3)),
        ecc.View(calibration.lower.camera_matrix, calibration.lower.dist_coeffs,
                 calibration.R_lower_upper, calibration.t_lower_upper),
    )


def test_ellipse_centre_point_is_the_pole_of_the_line_at_infinity():
    """X_e against the centre of the analytic image conic C' = H^-T C H^-1 (H&Z 2.2.3)."""
    rng = np.random.default_rng(4)
    C = np.column_stack([rng.uniform(-60, 60, 20), rng.uniform(-40, 40, 20), rng.uniform(300, 450, 20)])
    n = Rotation.from_rotvec(rng.uniform(-0.8, 0.8, (20, 3))).apply(-C / np.linalg.norm(C, axis=1, keepdims=True))
    r = rng.uniform(1.0, 5.0, 20)
    Xe = ecc.ellipse_centre_point(C, n, r)
    for k in range(20):
        e1 = np.cross(n[k], [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        H = np.column_stack([e1, np.cross(n[k], e1), C[k]])
        G = np.linalg.inv(H)
        Q = G.T @ np.diag([1.0, 1.0, -r[k] ** 2]) @ G
        centre = -np.linalg.solve(Q[:2, :2], Q[:2, 2])
        np.testing.assert_allclose(Xe[k, :2] / Xe[k, 2], centre, atol=1e-12)


@pytest.fixture(scope="module")
def scene():
    return build_scene("camera-limited")


@pytest.mark.parametrize("tilt_deg", [0.0, 60.0])  # the ends of the range (each case renders 8 discs)
def test_blob_centre_offsets_match_the_exact_rendering(tilt_deg, scene):
    """Strong tilts (up to 60 deg), large targets, the camera-limited scene's distorted lenses."""
    cal = scene.calibration
    views = views_of(cal)
    rng = np.random.default_rng(int(tilt_deg) + 1)
    C = np.column_stack([rng.uniform(-70, 70, 4), rng.uniform(-30, 60, 4), rng.uniform(360, 400, 4)])
    sight = -C / np.linalg.norm(C, axis=1, keepdims=True)
    axes = np.cross(sight, rng.normal(size=(4, 3)))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    n = Rotation.from_rotvec(np.radians(tilt_deg) * axes).apply(sight)
    r = np.full(4, 2.5)
    predicted = ecc.centre_offsets(C, n, r, views)
    for k, view in enumerate(views):
        intr = cal.upper if k == 0 else cal.lower
        Cv = C @ view.R.T + view.t
        truth = np.array([render_disc(c, nv, 2.5, intr).centroid_uv for c, nv in zip(Cv, n @ view.R.T)])
        offset = truth - ecc.project(view, Cv)
        if tilt_deg:
            assert np.abs(offset).max() > 0.02  # the effect is real ...
        np.testing.assert_allclose(predicted[:, 2 * k : 2 * k + 2], offset, atol=2e-5)  # ... and modelled


@pytest.fixture(scope="module")
def camera_limited_points(scene):
    pm = make_plugin_manager()
    centroid = implementations(pm, "centroid")["modelfit"].create({})
    out = {}
    for flag in (False, True):
        triangulate = implementations(pm, "triangulate")["epipolar"].create({"eccentricity": flag})
        errors, chi2 = [], []
        for k in range(4):
            frame = scene.render_pair(k, np.random.default_rng([21, k]))
            points = triangulate.triangulate(
                StereoCentroids(k, centroid.extract(frame.upper, "upper", k), centroid.extract(frame.lower, "lower", k)),
                scene.calibration,
            )
            truth = np.array([t.centre_camera for t in scene.targets])
            index = np.linalg.norm(points.xyz[:, None] - truth[None], axis=2).argmin(axis=1)
            assert len(points) == len(truth) and len(set(index.tolist())) == len(truth)
            e = points.xyz - truth[index]
            errors.append(e[np.argsort(index)])
            chi2.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(points.cov_xyz), e))
        out[flag] = np.array(errors), np.concatenate(chi2)
    return out


def test_eccentricity_bias_gone_on_the_camera_limited_scene(camera_limited_points):
    """Tilts of 10-25 deg: uncorrected, the points are biased by several sigma; corrected, not."""
    raw, raw_chi2 = camera_limited_points[False]
    fixed, fixed_chi2 = camera_limited_points[True]
    # per-target bias (mean over frames) against the per-frame scatter
    raw_bias = np.sqrt(np.mean(raw.mean(axis=0) ** 2))
    fixed_bias = np.sqrt(np.mean(fixed.mean(axis=0) ** 2))
    assert fixed_bias < 0.5 * raw_bias, (raw_bias, fixed_bias)
    # lateral error shrinks to the noise; the stated covariance covers (chi-square, 3 dof)
    assert np.sqrt(np.mean(fixed[..., :2] ** 2)) < 0.5 * np.sqrt(np.mean(raw[..., :2] ** 2))
    assert np.mean(raw_chi2) / 3 > 5.0
    assert 0.5 < np.mean(fixed_chi2) / 3 < 1.6, np.mean(fixed_chi2) / 3


def test_circle_normals_and_radii_recovered(scene):
    centroid = implementations(make_plugin_manager(), "centroid")["modelfit"].create({})
    frame = scene.render_pair(0, np.random.default_rng(5))
    views = views_of(scene.calibration)
    ellipses, covs = [], []
    for camera in ("upper", "lower"):
        result = centroid.extract(frame.image(camera), camera, 0)
        truth = np.array([scene.true_blob_centres(camera)[t.id] for t in scene.targets])
        index = np.linalg.norm(result.uv[:, None] - truth[None], axis=2).argmin(axis=0)
        ellipses.append(result.ellipse[index])
        covs.append(result.ellipse_cov[index])
    C = np.array([t.centre_camera for t in scene.targets])
    fit = ecc.fit_circles(C, views, tuple(ellipses), tuple(covs))
    n_true = np.array([t.normal_camera for t in scene.targets])
    angle = np.degrees(np.arccos(np.clip(np.sum(fit.normal * n_true, axis=1), -1, 1)))
    assert angle.max() < 0.5
    np.testing.assert_allclose(fit.radius_mm, 1.5, atol=0.02)
