"""The two prediction routes of ``crossfield plan`` (``docs/planning.md``).

Both predict, for each characteristic, the standard uncertainty of the
*session* result: the mean over ``frames`` stereo pairs, as the pipeline
reports it (``docs/report.md``). The camera noise is new in every frame and
averages out; the CMM probing (control points, reference elements) is done once
per session and does not. So ``u_session^2 = u_cmm^2 + u_camera,frame^2 / frames``.

* :func:`analytic`: the Cramér-Rao bound of each camera point
  (:mod:`crossfield.precision`, centroid bound times the station's
  ``centroid_efficiency``), Fitzpatrick, West & Maurer's isotropic TRE model for
  the registration (FLE^2 = the mean trace of the control points' camera
  covariance, and 3 sigma_cmm^2 for the CMM), the reference-line fit's linear
  covariance, first-order propagation to each characteristic.
* :func:`monte_carlo`: sessions simulated through the pipeline's kernels,
  batched: biased true centroids plus Gaussian noise of the same sigma, the
  ``epipolar`` triangulation (:func:`crossfield.precision.triangulate_batch`)
  linearised about the biased true centroids
  (:func:`crossfield.precision.linearised_triangulation`, exact to second order),
  the CMM control points plus N(0, sigma_cmm^2 I), the weighted Kabsch fit
  (:func:`crossfield.rigid.kabsch`, the runner's weights
  ``1 / (tr Sigma_cam / 3 + sigma_cmm^2)``), the characteristic evaluated per
  frame and averaged per session. Reference points get CMM noise; reference
  lines are drawn from their fit's linear covariance (the cylinder fit itself
  is not batched).

Both routes also carry the fixed bias of every centroid (:func:`centroid_bias`):
rendered (:mod:`crossfield.planning.image_bias`: the simulator's renderer and the
session's centroid implementation; eccentricity, pixelisation and the centroid's
own bias) or the perspective eccentricity alone
(:func:`crossfield.imaging.eccentricity.centre_offsets`), the same in every frame
and session, so a fixed bias of each session result (``bias_mm``); the analytic
route propagates it linearly, the Monte Carlo adds it to the true image
positions. ``u_mm`` is the RMS session error ``sqrt(u_random^2 + bias^2)``.

Lengths mm, angles rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from crossfield.chain.weights import registration_weights
from crossfield.geometry import fit_cylinder_axis, fit_line, point_line_distance
from crossfield.imaging.eccentricity import centre_offsets, stereo_views
from crossfield.planning.image_bias import rendered_bias
from crossfield.planning.station import Characteristic, ReferenceLine, Station
from crossfield.precision.chain import centroid_sigmas, image_radius_px
from crossfield.precision.registration import (
    fitzpatrick_covariance,
    fitzpatrick_tre,
    point_jacobian,
    registration_covariance,
)
from crossfield.precision.stereo import (
    camera_point_covariance,
    linearised_triangulation,
    project_stereo,
    triangulate_batch,
)
from crossfield.progress import bar
from crossfield.rigid import kabsch
from crossfield.simulator.render import SensorModel


@dataclass(frozen=True)
class CameraModel:
    """The camera side of a station: true points X (M, 3) mm (targets then controls, upper
    frame), their true image positions uv (M, 4) px, centroid sigmas (M, 4) px and
    camera-point covariances (M, 3, 3) mm^2."""

    X: np.ndarray
    uv: np.ndarray
    sigma_uv: np.ndarray
    cov: np.ndarray
    crb_sigma_uv: np.ndarray
    bias_uv: np.ndarray  # (M, 4) px: perspective eccentricity of the blob centres (zeros when off)
    J: np.ndarray  # (M, 4, 3) px/mm


def camera_model(station: Station) -> CameraModel:
    """The camera side (:class:`CameraModel`): each point's centroid bound from its own image radius
    and signal (``Station.point_signals``, DN), times the station's centroid efficiency."""
    X = station.camera_xyz
    radius_px = image_radius_px(station.calibration, X, station.camera_normals, np.full(len(X), station.radius_mm))
    crb = centroid_sigmas(radius_px, station.blur_sigma_px, station.point_signals, station.background_dn,
                          station.noise)
    sigma = crb * station.centroid_efficiency
    uv, J = project_stereo(station.calibration, X)
    return CameraModel(X, uv, sigma, camera_point_covariance(J, sigma), crb, centroid_bias(station, uv), J)


def runner_weights(station: Station, model: CameraModel) -> np.ndarray:
    """(C,) the runner's registration weights of the controls, ``1 / (tr Sigma_cam / 3 + sigma^2)``
    (docs/registration.md), sigma the CMM sigma the reference plugin states
    (``Station.weight_cmm_sigma_mm``; unset: the arm's ``cmm_sigma_mm``)."""
    T = len(station.target_ids)
    stated = station.cmm_sigma_mm if station.weight_cmm_sigma_mm is None else station.weight_cmm_sigma_mm
    C = len(model.cov) - T
    return registration_weights(np.trace(model.cov[T:], axis1=1, axis2=2) / 3, np.full(C, stated))


def centroid_bias(station: Station, uv: np.ndarray, noise: str = "antithetic") -> np.ndarray:
    """(M, 4) px: the fixed bias of every centroid (targets then controls) from the projected
    true centre uv (M, 4) px, by the station's ``bias_model``: ``rendered``
    (:func:`crossfield.planning.image_bias.rendered_bias`: eccentricity, pixelisation and the
    centroid's own bias; a point whose blob the centroid does not find keeps the eccentricity
    model) or ``eccentricity`` (:func:`crossfield.imaging.eccentricity.centre_offsets` alone);
    zeros when ``perspective_bias`` is off. noise: the rendered image's (``rendered_bias``)."""
    X = station.camera_xyz
    if not station.perspective_bias:
        return np.zeros_like(uv)
    ecc = centre_offsets(X, station.camera_normals, np.full(len(X), station.radius_mm),
                         stereo_views(station.calibration))
    if station.bias_model == "eccentricity":
        return ecc
    sensor = SensorModel(station.noise.gain_dn_per_e, station.noise.read_noise_dn, 12, station.blur_sigma_px)
    rendered = rendered_bias(station.calibration, X, station.camera_normals, station.radius_mm,
                             station.point_signals, sensor, station.background_dn, uv,
                             background_seed=station.background_seed, centroid=station.centroid,
                             noise=noise).bias_uv
    return np.where(np.isnan(rendered), ecc, rendered)


@lru_cache(maxsize=64)
def _unit_line_fit(key: bytes, shape: tuple[int, int], fit: str):
    probes = np.frombuffer(key).reshape(shape)
    return fit_cylinder_axis(probes, sigma_mm=1.0) if fit == "cylinder" else fit_line(probes, sigma_mm=1.0)


def line_fit(line: ReferenceLine, sigma_mm: float):
    """The reference line's fit to its exact probes, its covariance for CMM sigma ``sigma_mm``."""
    import dataclasses

    unit = _unit_line_fit(np.ascontiguousarray(line.probes).tobytes(), line.probes.shape, line.fit)
    return dataclasses.replace(unit, covariance=unit.covariance * sigma_mm**2, sigma_mm=sigma_mm)


def true_value(station: Station, c: Characteristic) -> float:
    """The characteristic's true value (mm) from the station geometry."""
    points = _true_points(station)
    if c.kind == "point_point":
        return float(np.linalg.norm(points[c.a] - points[c.b]))
    if c.kind == "point_line":
        line = next(line for line in station.reference_lines if line.id == c.b)
        return float(line.axis.distance(points[c.a]))
    return float(points[c.a][2])


def _true_points(station: Station) -> dict[str, np.ndarray]:
    Xg = station.to_global(station.camera_xyz)
    ids = station.target_ids + station.control_ids
    points = {i: Xg[k] for k, i in enumerate(ids)}
    points.update(station.reference_points)
    return points


# ---------------------------------------------------------------------------------------------
# Analytic route
# ---------------------------------------------------------------------------------------------


def analytic(station: Station, model: CameraModel | None = None) -> dict[str, Any]:
    """Analytic prediction (module docstring): per characteristic the session u (mm) and its parts,
    and the Fitzpatrick TRE at the targets and over the measuring volume.

    Each entry also gives ``u_linear_mm``: the same first-order propagation with the
    registration's exact linear covariance for anisotropic errors and the runner's weights
    (:func:`crossfield.precision.registration_covariance`) instead of Fitzpatrick's isotropic
    model; the difference between the two is the cost of the isotropy assumption.
    """
    model = model or camera_model(station)
    T = len(station.target_ids)
    R = np.asarray(station.R_global_camera)
    Xg = station.to_global(model.X)
    G = Xg[T:]
    s2 = station.cmm_sigma_mm**2
    fle_cam = float(np.sqrt(np.mean(np.trace(model.cov[T:], axis1=1, axis2=2))))
    fle_cmm = float(np.sqrt(3.0) * station.cmm_sigma_mm)
    C_cam, g_bar = fitzpatrick_covariance(G, fle_cam)
    C_cmm, _ = fitzpatrick_covariance(G, fle_cmm)
    S_cam = R @ model.cov[T:] @ R.T
    w = runner_weights(station, model)
    L_cam, g_w = registration_covariance(G, S_cam, w)
    L_cmm, _ = registration_covariance(G, np.broadcast_to(s2 * np.eye(3), S_cam.shape), w)
    fits = {line.id: line_fit(line, station.cmm_sigma_mm) for line in station.reference_lines}
    bias_global = _bias_global(model, R, Xg, T, w, g_w)
    out = []
    for c in station.characteristics:
        v_cam, v_cmm, line_var = _variances(station, c, Xg, model.cov, R, C_cam, C_cmm, g_bar, fits)
        l_cam, l_cmm, _ = _variances(station, c, Xg, model.cov, R, L_cam, L_cmm, g_w, fits)
        bias = _characteristic_bias(station, c, Xg, bias_global, fits)
        u_random = float(np.sqrt(v_cmm + v_cam / station.frames))
        u = float(np.sqrt(u_random**2 + bias**2))
        out.append({
            "name": c.name,
            "u_mm": u,
            "U_mm": station.coverage_factor * u,
            "u_random_mm": u_random,
            "bias_mm": bias,
            "u_frame_mm": float(np.sqrt(v_cmm + v_cam)),
            "u_camera_frame_mm": float(np.sqrt(v_cam)),
            "u_cmm_mm": float(np.sqrt(v_cmm)),
            "u_reference_line_mm": float(np.sqrt(line_var)),
            "u_linear_mm": float(np.sqrt(l_cmm + l_cam / station.frames + bias**2)),
        })
    tre_t = _tre(G, fle_cam, fle_cmm, Xg[:T], station.frames)
    return {
        "characteristics": out,
        "fle_camera_mm": fle_cam,
        "fle_cmm_mm": fle_cmm,
        "tre_targets_mm": {tid: float(v) for tid, v in zip(station.target_ids, tre_t)},
        "tre_field": tre_field(station, G, fle_cam, fle_cmm),
    }


def _bias_global(model: CameraModel, R: np.ndarray, Xg: np.ndarray, T: int, w: np.ndarray,
                 g_w: np.ndarray) -> np.ndarray:
    """(T, 3) mm: the targets' global-frame bias from the blob-centre bias ``model.bias_uv``,
    propagated linearly: ML triangulation ``dX = (J^T W J)^-1 J^T W duv``, then the weighted
    Kabsch fit's response to the controls' bias ``dxi = -A^-1 sum_k w_k J_k^T R dX_k``
    (``A = sum_k w_k J_k^T J_k``), and ``b_t = R dX_t + J(p_t) dxi``."""
    W = 1.0 / model.sigma_uv**2
    JtW = np.swapaxes(model.J, 1, 2) * W[:, None, :]
    dX = np.linalg.solve(JtW @ model.J, (JtW @ model.bias_uv[:, :, None]))[:, :, 0]  # (M, 3) camera frame
    wn = w / w.sum()
    Jc = point_jacobian(Xg[T:], g_w)
    A = np.einsum("n,nai,naj->ij", wn, Jc, Jc)
    rhs = np.einsum("n,nai,na->i", wn, Jc, dX[T:] @ R.T)
    dxi = -np.linalg.solve(A, rhs)
    return dX[:T] @ R.T + point_jacobian(Xg[:T], g_w) @ dxi


def _characteristic_bias(station: Station, c: Characteristic, Xg, bias_global, fits) -> float:
    """First-order bias (mm) of characteristic c from the targets' global bias (CMM points: none)."""
    index = {tid: k for k, tid in enumerate(station.target_ids)}
    points = _true_points(station)

    def b(eid: str) -> np.ndarray:
        return bias_global[index[eid]] if eid in index else np.zeros(3)

    a = points[c.a]
    if c.kind == "point_point":
        g = (a - points[c.b]) / np.linalg.norm(a - points[c.b])
        return float(g @ (b(c.a) - b(c.b)))
    if c.kind == "point_line":
        _, _, g = point_line_distance(a, fits[c.b])
        return float(g @ b(c.a))
    return float(b(c.a)[2])


def _variances(station, c, Xg, cam_cov, R, C_cam, C_cmm, g_bar, fits) -> tuple[float, float, float]:
    """(camera part per frame, CMM part, of it the reference line) variances (mm^2) of c."""
    index = {tid: k for k, tid in enumerate(station.target_ids)}
    s2 = station.cmm_sigma_mm**2

    def element(eid: str):
        """xyz (3,), own camera covariance, own CMM covariance (3, 3), registration Jacobian (3, 6)."""
        if eid in index:
            k = index[eid]
            return Xg[k], R @ cam_cov[k] @ R.T, np.zeros((3, 3)), point_jacobian(Xg[k], g_bar)
        xyz = _true_points(station)[eid]  # a control or reference point: a CMM point
        return xyz, np.zeros((3, 3)), s2 * np.eye(3), np.zeros((3, 6))

    a, ca_cam, ca_cmm, Ja = element(c.a)
    line_var = 0.0
    if c.kind == "point_point":
        b, cb_cam, cb_cmm, Jb = element(c.b)
        g = (a - b) / np.linalg.norm(a - b)
        J = Ja - Jb  # the shared registration: propagate the difference
        v_cam = g @ (ca_cam + cb_cam + J @ C_cam @ J.T) @ g
        v_cmm = g @ (ca_cmm + cb_cmm + J @ C_cmm @ J.T) @ g
    else:
        if c.kind == "point_line":
            _, sigma_line, g = point_line_distance(a, fits[c.b])
            line_var = sigma_line**2
        else:
            g = np.array([0.0, 0.0, 1.0])
        v_cam = g @ (ca_cam + Ja @ C_cam @ Ja.T) @ g
        v_cmm = g @ (ca_cmm + Ja @ C_cmm @ Ja.T) @ g + line_var
    return max(float(v_cam), 0.0), max(float(v_cmm), 0.0), float(line_var)  # round-off of a zero part


def _tre(G: np.ndarray, fle_cam: float, fle_cmm: float, points: np.ndarray, frames: int) -> np.ndarray:
    """Session TRE (mm): the CMM part whole, the camera part averaged over the frames."""
    return np.sqrt(fitzpatrick_tre(G, fle_cmm, points) ** 2 + fitzpatrick_tre(G, fle_cam, points) ** 2 / frames)


def tre_field(station: Station, G: np.ndarray, fle_cam: float, fle_cmm: float, n: tuple[int, int] = (13, 9)):
    """Session TRE (mm) on a grid over the measuring volume: the plane z = working distance
    (upper frame) spanning twice the control box laterally. Returns x, y (mm, camera frame) and tre (ny, nx)."""
    centre, half = station.control_box
    xs = np.linspace(centre[0] - 2 * half[0], centre[0] + 2 * half[0], n[0])
    ys = np.linspace(centre[1] - 2 * max(half[1], 1.0), centre[1] + 2 * max(half[1], 1.0), n[1])
    Xc = np.array([[x, y, centre[2]] for y in ys for x in xs])
    tre = _tre(G, fle_cam, fle_cmm, station.to_global(Xc), station.frames).reshape(len(ys), len(xs))
    return {"x_mm": xs.tolist(), "y_mm": ys.tolist(), "z_mm": float(centre[2]), "tre_mm": tre.tolist()}


# ---------------------------------------------------------------------------------------------
# Monte Carlo route
# ---------------------------------------------------------------------------------------------


def simulate_sessions(
    station: Station, sessions: int, rng: np.random.Generator, model: CameraModel | None = None,
    chunk: int | None = None, triangulation: str = "linear",
) -> np.ndarray:
    """Session errors (sessions, K) mm of the K characteristics, through the batched kernels.

    triangulation: ``"linear"`` (default) triangulates every trial by the ML estimator
    linearised about the biased true image points
    (:func:`crossfield.precision.linearised_triangulation`: the full kernel once, then a
    (3 x 4) product per point and trial; second-order error, ~1e-4 of the noise's effect);
    ``"full"`` runs :func:`crossfield.precision.triangulate_batch` (undistortion, linear
    triangulation, Gauss-Newton) on every trial. chunk: sessions per batch (None: ~40 000
    registrations per batch).
    """
    if triangulation not in ("linear", "full"):
        raise ValueError(f"triangulation must be linear or full, got {triangulation!r}")
    model = model or camera_model(station)
    T, F = len(station.target_ids), station.frames
    C = len(station.control_ids)
    sigma = station.cmm_sigma_mm
    w = runner_weights(station, model)
    truth = np.array([true_value(station, c) for c in station.characteristics])
    index = {tid: k for k, tid in enumerate(station.target_ids)}
    cmm_ids = list(station.control_ids) + list(station.reference_points)
    cmm_true = np.array([_true_points(station)[i] for i in cmm_ids]).reshape(-1, 3)
    cmm_index = {i: k for k, i in enumerate(cmm_ids)}
    fits = {line.id: line_fit(line, sigma) for line in station.reference_lines}
    out = np.zeros((sessions, len(truth)))
    chunk = chunk or max(1, 40000 // F)
    # The centroids are biased off the projected target centres by the fixed bias model.bias_uv
    # (the same in every frame and session); the noise is new in every frame.
    uv_biased = model.uv + model.bias_uv
    linear = linearised_triangulation(station.calibration, uv_biased, model.sigma_uv) \
        if triangulation == "linear" else None
    for start in range(0, sessions, chunk):
        B = min(chunk, sessions - start)
        noise = model.sigma_uv * rng.standard_normal((B, F) + model.uv.shape)
        if linear is not None:
            X = linear(noise)  # (B, F, M, 3)
        else:
            X = triangulate_batch(station.calibration, uv_biased + noise, model.sigma_uv)
        cmm = cmm_true + sigma * rng.standard_normal((B,) + cmm_true.shape)  # (B, P, 3), once per session
        Q = np.broadcast_to(cmm[:, None, :C], (B, F, C, 3))
        R, t, _, _ = kabsch(X[:, :, T:], Q, w)
        P = X[:, :, :T] @ np.swapaxes(R, -1, -2) + t[:, :, None, :]  # (B, F, T, 3) global: R x + t
        lines = {}
        for lid, fit in fits.items():
            delta = rng.multivariate_normal(np.zeros(4), fit.covariance, size=B, method="cholesky") \
                if sigma > 0 else np.zeros((B, 4))
            e1, e2 = fit.basis
            c0 = fit.line.point + delta[:, :1] * e1 + delta[:, 1:2] * e2
            d = fit.line.direction + delta[:, 2:3] * e1 + delta[:, 3:4] * e2
            lines[lid] = (c0, d / np.linalg.norm(d, axis=1, keepdims=True))

        def point(eid: str) -> np.ndarray:  # (B, F, 3)
            if eid in index:
                return P[:, :, index[eid]]
            return np.broadcast_to(cmm[:, None, cmm_index[eid]], (B, F, 3))

        for k, c in enumerate(station.characteristics):
            a = point(c.a)
            if c.kind == "point_point":
                value = np.linalg.norm(a - point(c.b), axis=-1)
            elif c.kind == "point_line":
                c0, d = lines[c.b]
                v = a - c0[:, None, :]
                n = v - np.sum(v * d[:, None, :], axis=-1, keepdims=True) * d[:, None, :]
                value = np.linalg.norm(n, axis=-1)
            else:
                value = a[..., 2]
            out[start : start + B, k] = value.mean(axis=1) - truth[k]
    return out


def monte_carlo(
    station: Station, sessions: int = 2000, seed: int = 0, model: CameraModel | None = None
) -> dict[str, Any]:
    """Monte Carlo prediction: per characteristic the RMS session error (= u, mm) over ``sessions``
    simulated sessions, its sampling uncertainty, the bias and the spread."""
    if sessions < 2:
        raise ValueError(f"the Monte Carlo route needs at least 2 sessions, got {sessions}")
    errors = simulate_sessions(station, sessions, np.random.default_rng(seed), model)
    rms = np.sqrt(np.mean(errors**2, axis=0))
    out = []
    for k, c in enumerate(station.characteristics):
        out.append({
            "name": c.name,
            "u_mm": float(rms[k]),
            "U_mm": float(station.coverage_factor * rms[k]),
            "u_sampling_mm": float(rms[k] / np.sqrt(2 * sessions)),
            "bias_mm": float(errors[:, k].mean()),
            "std_mm": float(errors[:, k].std(ddof=1)),
        })
    return {"characteristics": out, "sessions": sessions, "seed": seed}


def predict(
    station: Station, *, sessions: int = 2000, seed: int = 0, route: str = "both"
) -> dict[str, Any]:
    """Both routes side by side, as ``crossfield plan --json`` prints it.

    ``predicted_u_mm`` is the Monte Carlo value when that route runs (it goes through the
    pipeline's kernels and weights), else the analytic one.
    """
    if route not in ("both", "analytic", "monte-carlo"):
        raise ValueError(f"route must be both, analytic or monte-carlo, got {route!r}")
    with bar(desc="plan: rendered centroid bias", total=1 + (route != "monte-carlo") + (route != "analytic"),
             unit="step") as steps:
        model = camera_model(station)
        steps.update()
        steps.set_description_str("plan: analytic route")
        an = analytic(station, model) if route != "monte-carlo" else None
        steps.update(route != "monte-carlo")
        steps.set_description_str(f"plan: Monte Carlo route ({sessions} sessions)")
        mc = monte_carlo(station, sessions, seed, model) if route != "analytic" else None
    chars = []
    for k, c in enumerate(station.characteristics):
        entry: dict[str, Any] = {"name": c.name, "kind": c.kind, "a": c.a, "b": c.b,
                                 "true_mm": true_value(station, c)}
        if an is not None:
            entry["analytic"] = an["characteristics"][k]
        if mc is not None:
            entry["monte_carlo"] = mc["characteristics"][k]
        best = (mc or an)["characteristics"][k]
        entry["predicted_u_mm"] = best["u_mm"]
        entry["predicted_U_mm"] = best["U_mm"]
        chars.append(entry)
    doc: dict[str, Any] = {
        "station": station.summary(),
        "coverage_factor": station.coverage_factor,
        "route": "monte-carlo" if mc is not None else "analytic",
        "characteristics": chars,
        "centroid_crb_px": float(np.mean(model.crb_sigma_uv)),
        "centroid_sigma_px": float(np.mean(model.sigma_uv)),
        "bias_model": station.bias_model if station.perspective_bias else "none",
        "centroid_bias_rms_px": float(np.sqrt(np.mean(model.bias_uv**2))),
        "camera_sigma_mm": np.sqrt(np.mean(np.diagonal(model.cov, axis1=1, axis2=2), axis=0)).tolist(),
    }
    if an is not None:
        doc.update({k: an[k] for k in ("fle_camera_mm", "fle_cmm_mm", "tre_targets_mm", "tre_field")})
    if mc is not None:
        doc["monte_carlo_sessions"] = sessions
    return doc
