"""The fixed image-position bias of every target, rendered (``docs/planning.md``).

A session's centroids are not unbiased estimates of the projected target
centres: the image of a tilted circle is an ellipse whose centre is off the
projection of the circle's centre (perspective eccentricity), the pixel grid
and the blur shape the blob, and the centroid implementation (window,
threshold, local background over a vignetted background) adds its own offset.
All of these are fixed for a given layout: the same in every frame and session.

:func:`rendered_bias` measures them the way a session would meet them: each
camera's image of the station is rendered once with the simulator's own
renderer (:func:`crossfield.simulator.render.render_disc`,
:func:`~crossfield.simulator.render.compose_clean_image`: exact perspective
coverage, Gaussian blur, the background), and the session's centroid
implementation (a registered ``centroid`` plugin, ``weighted`` by default) is
run on it. The bias of target k in camera c is ``centroid - projection of the
true centre`` (px), which contains the eccentricity, the pixelisation and the
centroid's own bias. A centroid that delivers edge conics (``modelfit``) lets the
session's triangulation remove the eccentricity; its bias is then taken less the
eccentricity model's offset at the true circle (what the correction takes off).

The image the centroid sees is *noise-free to first order*: the mean of the
centroids found in ``clean + n`` and ``clean - n`` (an antithetic pair, n the
sensor's photon and read noise, :class:`~crossfield.simulator.render.SensorModel`),
so the detector meets the noise level it meets in a session (its threshold is
``threshold_sigma`` noise sigmas above the background) while the noise itself
cancels in the centroid to first order. On the ``station`` scenario this pair
reproduces the mean centroid over 80 noisy frames (40 other antithetic pairs) to
0.00005 px RMS, against a bias of 0.02 px (``bench/bench_plan_validation.py
--efficiency`` prints the check).

Pixels: (0, 0) is the centre of the top-left pixel; lengths mm; points in the
upper camera frame.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from crossfield.imaging.eccentricity import centre_offsets, stereo_views
from crossfield.simulator.render import SensorModel, background_image, compose_clean_image, render_disc
from crossfield.types import StereoCalibration

__all__ = ["RenderedBias", "antithetic_pair", "centroid_implementation", "rendered_bias"]

#: A found centroid is the point's when it is within this many px of the projected centre.
MATCH_RADIUS_PX = 3.0


@dataclass(frozen=True)
class RenderedBias:
    """bias_uv: (M, 4) px ``[u_upper, v_upper, u_lower, v_lower]`` of (centroid - projected centre);
    found: (M, 2) bool, the point's blob was found by the centroid in (upper, lower) (where it was
    not, its bias is NaN); centroid: the implementation's name."""

    bias_uv: np.ndarray
    found: np.ndarray
    centroid: str


def _images(calibration: StereoCalibration, X: np.ndarray, normals: np.ndarray, radius_mm: float, signals: np.ndarray,
            sensor: SensorModel, background_dn: float, background_seed: int | None):
    """The clean (float32 DN) image of each camera: the simulator's scene composition."""
    R = np.asarray(calibration.R_lower_upper, dtype=np.float64)
    t = np.asarray(calibration.t_lower_upper, dtype=np.float64)
    out = {}
    for cam in ("upper", "lower"):
        intr = calibration.camera(cam)
        Xc, nc = (X, normals) if cam == "upper" else (X @ R.T + t, normals @ R.T)
        discs = []
        for k in range(len(X)):
            disc = render_disc(Xc[k], nc[k], radius_mm, intr, sensor.blur_sigma_px)  # the simulator's rendering
            if disc is not None:
                discs.append((disc, float(signals[k])))
        w, h = intr.image_size
        if background_seed is None:
            background = np.full((h, w), background_dn, np.float32)
        else:  # the simulator's vignetted background, drawn as Scene.clean_images draws it
            background = background_image((w, h), background_dn,
                                          np.random.default_rng(background_seed + (cam == "lower")))
        out[cam] = compose_clean_image((w, h), discs, background)
    return out


def antithetic_pair(clean: np.ndarray, sensor: SensorModel, rng: np.random.Generator):
    """``clean +- n``, n the sensor's noise (photon + read, EMVA 1288 linear model, as
    :func:`crossfield.simulator.render.add_noise`), clipped and quantised to uint16 DN."""
    sigma = np.sqrt(clean * np.float32(sensor.gain_dn_per_e) + np.float32(sensor.read_noise_dn**2))
    n = rng.standard_normal(clean.shape, dtype=np.float32) * sigma
    return tuple(np.rint(np.clip(clean + s * n, 0, sensor.max_dn)).astype(np.uint16) for s in (1, -1))


@lru_cache(maxsize=1)
def _plugin_manager():
    from crossfield.chain.registry import make_plugin_manager

    return make_plugin_manager()


def centroid_implementation(name: str):
    """The registered ``centroid`` implementation ``name`` (a PluginError listing the names if none)."""
    from crossfield.chain.registry import get_implementation

    return get_implementation(_plugin_manager(), "centroid", name)


def _match(found_uv: np.ndarray, expected_uv: np.ndarray) -> np.ndarray:
    """(M, 2) the found centroid nearest each expected position, NaN if none within MATCH_RADIUS_PX."""
    out = np.full(expected_uv.shape, np.nan)
    if len(found_uv) == 0:
        return out
    d = np.linalg.norm(expected_uv[:, None, :] - found_uv[None, :, :], axis=-1)
    k = np.argmin(d, axis=1)
    ok = d[np.arange(len(expected_uv)), k] <= MATCH_RADIUS_PX
    out[ok] = found_uv[k[ok]]
    return out


_CACHE: dict[str, RenderedBias] = {}
_IMAGES: dict[str, dict[str, np.ndarray]] = {}


def rendered_bias(
    calibration: StereoCalibration,
    X: np.ndarray,
    normals: np.ndarray,
    radius_mm: float,
    signals_dn: np.ndarray,
    sensor: SensorModel,
    background_dn: float,
    uv_true: np.ndarray,
    *,
    background_seed: int | None = None,
    centroid: str = "weighted",
    centroid_options: dict | None = None,
    seed: int = 0,
    noise: str = "antithetic",
) -> RenderedBias:
    """The fixed centroid bias (module docstring) of points X (M, 3) mm (upper frame) with unit
    normals (M, 3), discs of radius_mm, signals_dn (M,) DN above the background.

    uv_true: (M, 4) px the projections of the true centres (``precision.project_stereo``).
    background_seed: None for a flat background of background_dn, else the simulator's
    vignetted background drawn with that seed (``Scene.background_seed``).
    centroid: the registered centroid implementation the session runs, with its options.
    noise: ``"antithetic"`` (default: the mean over the pair ``clean +- n``, what the centroid
    gives on average in a session) or ``"none"`` (the clean image itself, rounded to DN: what
    the centroid gives on a noise-free image, whose detector threshold is lower; on the
    ``station`` scenario the two differ by 0.0002 px RMS).
    Results are cached on all inputs (a sweep re-renders only the layouts it changes).
    """
    if noise not in ("antithetic", "none"):
        raise ValueError(f"noise must be antithetic or none, got {noise!r}")
    X = np.ascontiguousarray(X, dtype=np.float64)
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    signals = np.ascontiguousarray(np.broadcast_to(np.asarray(signals_dn, dtype=np.float64), (len(X),)))
    h = hashlib.sha256()
    for a in (X, normals, signals,
              np.asarray(calibration.upper.camera_matrix), np.asarray(calibration.upper.dist_coeffs),
              np.asarray(calibration.lower.camera_matrix), np.asarray(calibration.lower.dist_coeffs),
              np.asarray(calibration.R_lower_upper), np.asarray(calibration.t_lower_upper)):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    h.update(repr((radius_mm, sensor, background_dn, background_seed,
                   calibration.upper.image_size, calibration.lower.image_size)).encode())
    image_key = h.hexdigest()
    h.update(np.ascontiguousarray(uv_true, dtype=np.float64).tobytes())
    h.update(repr((centroid, sorted((centroid_options or {}).items()), seed, noise)).encode())
    key = h.hexdigest()
    if key in _CACHE:
        return _CACHE[key]
    centroider = centroid_implementation(centroid).create(dict(centroid_options or {}), "<plan>")
    if image_key not in _IMAGES:
        if len(_IMAGES) >= 4:  # two full frames of float32 each: keep a few layouts
            _IMAGES.pop(next(iter(_IMAGES)))
        _IMAGES[image_key] = _images(calibration, X, normals, radius_mm, signals, sensor, background_dn,
                                     background_seed)
    images = _IMAGES[image_key]
    rng = np.random.default_rng(seed)
    uv_true = np.asarray(uv_true, dtype=np.float64)
    bias = np.full(uv_true.shape, np.nan)
    with_conics = []
    for j, cam in enumerate(("upper", "lower")):
        expected = uv_true[:, 2 * j : 2 * j + 2]
        pair = antithetic_pair(images[cam], sensor, rng) if noise == "antithetic" else \
            (np.rint(np.clip(images[cam], 0, sensor.max_dn)).astype(np.uint16),)
        results = [centroider.extract(img, cam, 0) for img in pair]
        found = [_match(np.asarray(r.uv, dtype=np.float64), expected) for r in results]
        bias[:, 2 * j : 2 * j + 2] = np.mean(found, axis=0) - expected
        with_conics += [r.ellipse is not None for r in results]
    if all(with_conics):
        # centroids with edge conics: the session's triangulation takes the eccentricity off
        # (``epipolar``, step 5); what stays is the centroid's bias beyond it, to first order
        # the found centre minus the model's offset at the true circles
        bias -= centre_offsets(X, normals, np.full(len(X), float(radius_mm)), stereo_views(calibration))
    result = RenderedBias(bias, ~np.isnan(bias[:, ::2]), centroid)
    if len(_CACHE) > 256:
        _CACHE.clear()
    _CACHE[key] = result
    return result
