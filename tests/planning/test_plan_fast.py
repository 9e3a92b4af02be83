"""The Monte Carlo's fast triangulation: the ML estimator linearised about the biased true image
points (crossfield.precision.linearised_triangulation) against the full kernel and the plugin."""

from __future__ import annotations

import numpy as np
import pytest

from crossfield.planning.routes import camera_model, simulate_sessions
from crossfield.planning.station import station_from_scenario
from crossfield.plugins.triangulate_epipolar import EpipolarTriangulator
from crossfield.precision import linearised_triangulation, triangulate_batch
from crossfield.types import CentroidSet, StereoCentroids


@pytest.fixture(scope="module")
def table3():
    station = station_from_scenario("table3", bias_model="eccentricity")
    return station, camera_model(station)


def test_linear_triangulation_matches_the_full_kernel(table3):
    """Centroid noise of 0.05 px (15x the simulator's): the linearised estimator's error against
    undistortion + linear triangulation + Gauss-Newton is below 1e-3 of the noise's effect on the
    points and below 5e-4 mm; it is second order: at 0.005 px it is 100x smaller."""
    station, model = table3
    uv0 = model.uv + model.bias_uv
    sigma = np.full_like(uv0, 0.05)
    linear = linearised_triangulation(station.calibration, uv0, sigma)
    unit = np.random.default_rng(4).standard_normal((400,) + uv0.shape)
    for noise_px, max_mm in ((0.05, 5e-4), (0.005, 5e-6)):
        noise = noise_px * unit
        X_full = triangulate_batch(station.calibration, uv0 + noise, sigma, iterations=20)
        X_lin = linear(noise)
        effect = np.sqrt(np.mean((X_full - linear.X0) ** 2))
        assert effect > noise_px * 0.05  # the noise moves the points (~2 mm per px in depth)
        assert np.sqrt(np.mean((X_lin - X_full) ** 2)) < 1e-3 * effect
        assert np.max(np.abs(X_lin - X_full)) < max_mm
    # The expansion point itself is the full kernel's triangulation of uv0.
    np.testing.assert_allclose(linear.X0, triangulate_batch(station.calibration, uv0, sigma, iterations=20),
                               atol=1e-9)


def test_linear_triangulation_matches_the_epipolar_plugin(table3):
    """The same noisy centroids through the epipolar plugin (matching, undistortion, Gauss-Newton with
    the centroids' sigmas as weights): the same points to 1e-5 mm."""
    station, model = table3
    uv0 = model.uv + model.bias_uv
    sigma = np.full_like(uv0, 0.02)
    linear = linearised_triangulation(station.calibration, uv0, sigma)
    tri = EpipolarTriangulator()
    rng = np.random.default_rng(5)
    n = len(uv0)
    for k in range(3):
        noise = 0.02 * rng.standard_normal(uv0.shape)
        uv = uv0 + noise
        ones = np.ones(n)
        pair = StereoCentroids(k, CentroidSet("upper", k, uv[:, :2], sigma[:, :2], ones, ones, ones),
                               CentroidSet("lower", k, uv[:, 2:], sigma[:, 2:], ones, ones, ones))
        points = tri.triangulate(pair, station.calibration)
        assert len(points.xyz) == n
        order = np.argsort(points.upper_index)
        X_plugin = np.asarray(points.xyz)[order]
        assert np.max(np.abs(X_plugin - linear(noise)[np.asarray(points.upper_index)[order]])) < 1e-5


def test_monte_carlo_linear_and_full_triangulation_agree(table3):
    """The same random draws through both triangulations: the same session errors (all ten lengths)."""
    station, model = table3
    fast = simulate_sessions(station, 60, np.random.default_rng(6), model, triangulation="linear")
    full = simulate_sessions(station, 60, np.random.default_rng(6), model, triangulation="full")
    assert np.std(full) > 1e-3
    np.testing.assert_allclose(fast, full, atol=1e-6)
    with pytest.raises(ValueError, match="linear or full"):
        simulate_sessions(station, 2, np.random.default_rng(0), model, triangulation="dlt")
