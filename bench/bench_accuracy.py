"""Accuracy ablation and the plain-OpenCV baseline pipeline, against simulator truth and the CRB.

Run: ``.venv/bin/python bench/bench_accuracy.py [--scenario camera-limited] [--sessions N] [--frames F]``

For each session (fresh image and arm noise, ``--frames`` stereo pairs) every
configuration below processes the *same* images and CMM probes:

* ``opencv``: a plain OpenCV pipeline: threshold (crossfield's background
  estimate) -> ``cv2.findContours`` -> intensity moments (``cv2.moments``,
  background subtracted) inside each filled contour; correspondences handed
  to it from the truth; ``cv2.undistortPoints`` + ``cv2.triangulatePoints``;
  unweighted Kabsch (:func:`crossfield.rigid.kabsch`); target points averaged
  over the session's frames.
* ``weighted``: the defaults before issue 11 (centroid "weighted", triangulate
  "epipolar", register "svd" with the runner's weights, measure "plan").
* ``+modelfit``: centroid "modelfit" (its default, optical, PSF order: the
  simulator's), eccentricity correction off.
* ``+eccentricity``: the same with the eccentricity correction.
* ``+ml``: and register "ml" (full covariances).
* ``default``: crossfield's built-in defaults (:data:`crossfield.config.DEFAULT_PLUGINS`,
  default options): today the same stages as ``+ml``.
* ``+session``: and the joint session pose (all frames, static station,
  :mod:`crossfield.chain.session_pose`) with the frames' mean camera points.

Figures: centroid RMS / CRB (the CRB from the Fisher information of the
simulator's own rendering: its exact translation derivatives),
camera-point RMS error (camera frame), target-point RMS error (global frame,
per session), its ratio to the CRB of the chain (centroid CRB -> ML
triangulation -> ML registration with the arm sigma -> target point, for the
session's frames), length RMS error of the plan's characteristics, and the
fraction of length errors within 2u (the measure stage's u).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from crossfield.imaging.blobs import estimate_background  # noqa: E402
from crossfield.camera.stereo_model import project_pair, stereo_geometry  # noqa: E402
from crossfield.config import DEFAULT_PLUGINS  # noqa: E402
from crossfield.covariance import skew  # noqa: E402
from crossfield.chain.registry import implementations, make_plugin_manager  # noqa: E402
from crossfield.rigid import kabsch  # noqa: E402
from crossfield.chain.runner import register_frame  # noqa: E402
from crossfield.chain.session_pose import SessionPoseAccumulator  # noqa: E402
from crossfield.simulator.scenarios import build_scene  # noqa: E402
from crossfield.types import CAMERAS, ProbedPoint, ReferenceData, StereoCentroids  # noqa: E402

CONFIGS = ("opencv", "weighted", "+modelfit", "+eccentricity", "+ml", "default", "+session")
#: configuration -> its (centroid, triangulate, register) stages (keys of main's ``stages``)
SETUP = {
    "weighted": ("weighted", "tri_plain", "svd"),
    "+modelfit": ("modelfit", "tri_plain", "svd"),
    "+eccentricity": ("modelfit", "tri_ecc", "svd"),
    "+ml": ("modelfit", "tri_ecc", "ml"),
    "default": ("default_centroid", "default_triangulate", "default_register"),
    "+session": ("modelfit", "tri_ecc", "ml"),
}


# ------------------------------------------------------------------ CRB of the chain


def centroid_fisher(scene, camera: str) -> dict[str, np.ndarray]:
    """Target id -> (2, 2) Fisher information (px^-2) of its blob centre in ``camera``:
    the translation derivatives of the simulator's own rendering (exact PSF and pixel
    integration, ``DiscImage.gradient``), amplitude and background as nuisance parameters."""
    clean = scene.clean_images[camera]
    sensor = scene.sensor
    out = {}
    for t in scene.targets:
        disc = scene._discs[camera].get(t.id)
        if disc is None:
            continue
        u0, v0 = disc.origin
        h, w = disc.image.shape
        derivs = [t.signal_dn * disc.gradient[0], t.signal_dn * disc.gradient[1], disc.image, np.ones((h, w))]
        mu = clean[v0 : v0 + h, u0 : u0 + w].astype(np.float64)
        var = mu * sensor.gain_dn_per_e + sensor.read_noise_dn**2 + 1.0 / 12.0
        D = np.stack([d.ravel() for d in derivs])
        F = (D / var.ravel()) @ D.T
        out[t.id] = np.linalg.inv(np.linalg.inv(F)[:2, :2])
    return out


def chain_crb(scene, fisher, frames: int, cmm_sigma: float) -> dict[str, np.ndarray]:
    """Target id -> (3, 3) CRB (mm^2) of its global point from ``frames`` frames (static station)."""
    geometry = stereo_geometry(scene.calibration)
    ids = [t.id for t in scene.targets]
    X = np.array([t.centre_camera for t in scene.targets])
    _, J = project_pair(geometry, X)  # (N, 4, 3)
    cam_cov = {}
    for k, tid in enumerate(ids):
        L = np.zeros((4, 4))
        L[:2, :2] = fisher["upper"][tid]
        L[2:, 2:] = fisher["lower"][tid]
        cam_cov[tid] = np.linalg.inv(J[k].T @ L @ J[k]) / frames
    Rg, tg = scene.R_global_camera, scene.t_global_camera
    H = np.zeros((6, 6))
    for tid in scene.plan.control_ids:
        g = Rg @ X[ids.index(tid)] + tg
        Jp = np.hstack([-skew(g), np.eye(3)])
        S = Rg @ cam_cov[tid] @ Rg.T + cmm_sigma**2 * np.eye(3)
        H += Jp.T @ np.linalg.solve(S, Jp)
    P = np.linalg.inv(H)
    out = {}
    for target in scene.plan.targets:
        g = Rg @ X[ids.index(target.id)] + tg
        G = np.hstack([-skew(g), np.eye(3)])
        out[target.id] = Rg @ cam_cov[target.id] @ Rg.T + G @ P @ G.T
    return out


# ------------------------------------------------------------------ the plain OpenCV pipeline


def opencv_centroids(image: np.ndarray) -> np.ndarray:
    """threshold -> findContours -> background-subtracted intensity moments in each filled contour."""
    bg = estimate_background(image, 8.0)
    mask = (image > bg.threshold_dn).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out = []
    for contour in contours:
        x, y, w, h = cv2.boundingRect(contour)
        if w * h < 30:
            continue
        filled = np.zeros((h, w), np.uint8)
        cv2.drawContours(filled, [contour], -1, 1, thickness=-1, offset=(-x, -y))
        roi = (image[y : y + h, x : x + w].astype(np.float32) - np.float32(bg.level_dn)) * filled
        m = cv2.moments(roi)
        if m["m00"] > 0:
            out.append((x + m["m10"] / m["m00"], y + m["m01"] / m["m00"]))
    return np.array(out).reshape(-1, 2)


def handed(uv: np.ndarray, truth: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Correspondences handed over: target id -> its centroid (nearest within 2 px)."""
    out = {}
    for tid, t in truth.items():
        d = np.linalg.norm(uv - t, axis=1) if len(uv) else np.zeros(0)
        if len(d) and d.min() < 2.0:
            out[tid] = uv[d.argmin()]
    return out


def opencv_triangulate(scene, up: dict, lo: dict) -> dict[str, np.ndarray]:
    cal = scene.calibration
    ids = [i for i in up if i in lo]
    a = cv2.undistortPoints(np.array([up[i] for i in ids]).reshape(-1, 1, 2), cal.upper.camera_matrix, cal.upper.dist_coeffs)
    b = cv2.undistortPoints(np.array([lo[i] for i in ids]).reshape(-1, 1, 2), cal.lower.camera_matrix, cal.lower.dist_coeffs)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([cal.R_lower_upper, cal.t_lower_upper[:, None]])
    Xh = cv2.triangulatePoints(P1, P2, a.reshape(-1, 2).T, b.reshape(-1, 2).T)
    X = (Xh[:3] / Xh[3]).T
    return dict(zip(ids, X))


# ------------------------------------------------------------------ one session


def reference_of(scene, probes, sigma):
    return ReferenceData(tuple(ProbedPoint(p.label, p.xyz, sigma) for p in probes), source="simulator")


def run_session(scene, stages, seed: int, frames: int, fisher, cmm_sigma: float):
    """Per configuration: dicts of metrics of this session."""
    rng = np.random.default_rng([seed, 1])
    probes = scene.arm_probes(np.random.default_rng([seed, 2]))
    reference = reference_of(scene, probes, cmm_sigma)
    by_label = reference.by_label()
    truth_g = scene.ground_truth.points_global
    target_ids = [t.id for t in scene.plan.targets]
    ctrl = list(scene.plan.control_ids)
    true_cam = {t.id: t.centre_camera for t in scene.targets}
    blob_truth = {cam: scene.true_blob_centres(cam) for cam in CAMERAS}
    metrics = {c: {"centroid_z2": [], "cam_err2": [], "targets": {}, "lengths": [], "covered": []} for c in CONFIGS}
    pose_acc = SessionPoseAccumulator()
    images = [scene.render_pair(k, rng) for k in range(frames)]

    def centroid_stats(name, sets):
        for cam, cs in zip(CAMERAS, sets):
            got = handed(cs, blob_truth[cam])
            for tid, uv in got.items():
                e = uv - blob_truth[cam][tid]
                metrics[name]["centroid_z2"].append((e @ fisher[cam][tid] @ e, 2))

    def cam_stats(name, xyz_by_id):
        for tid, x in xyz_by_id.items():
            metrics[name]["cam_err2"].append(np.sum((x - true_cam[tid]) ** 2))

    def add_targets(name, g_by_id):
        for tid in target_ids:
            if tid in g_by_id:
                metrics[name]["targets"].setdefault(tid, []).append(g_by_id[tid])

    # ---- opencv
    for frame in images if "opencv" in CONFIGS else ():
        cents = [opencv_centroids(frame.image(cam)) for cam in CAMERAS]
        centroid_stats("opencv", cents)
        up, lo = (handed(c, blob_truth[cam]) for c, cam in zip(cents, CAMERAS))
        X = opencv_triangulate(scene, up, lo)
        cam_stats("opencv", X)
        use = [c for c in ctrl if c in X]
        R, t, _, _ = kabsch(np.array([X[c] for c in use]), np.array([by_label[c].xyz for c in use]))
        add_targets("opencv", {tid: R @ X[tid] + t for tid in X})

    # ---- crossfield configurations (centroids shared where the configuration is the same)
    for name in [c for c in CONFIGS if c != "opencv"]:
        centroid, tri, reg = (stages[key] for key in SETUP[name])
        per_frame_points = []
        for frame in images:
            sc = StereoCentroids(frame.sequence, *(centroid.extract(frame.image(cam), cam, frame.sequence) for cam in CAMERAS))
            centroid_stats(name, [sc.upper.uv, sc.lower.uv])
            points = tri.triangulate(sc, scene.calibration)
            ids = {}
            for k, x in enumerate(points.xyz):
                d = {tid: np.linalg.norm(x - c) for tid, c in true_cam.items()}
                best = min(d, key=d.get)
                if d[best] < 0.5:
                    ids[best] = k
            cam_stats(name, {tid: points.xyz[k] for tid, k in ids.items()})
            registration = register_frame(points, reference, scene.plan, reg, 0.5)
            measurement = stages["measure"].measure(scene.plan, reference, points, registration, scene.ground_truth)
            if name != "+session":
                add_targets(name, {tid: np.array(v) for tid, v in measurement.target_points.items()})
                for c in measurement.characteristics:
                    if c.error_mm is not None:
                        metrics[name]["lengths"].append(c.error_mm)
                        metrics[name]["covered"].append(abs(c.error_mm) <= 2 * c.uncertainty_mm)
            else:
                pose_acc.add(points, registration)
                per_frame_points.append((points, ids))
        if name == "+session":
            pose = pose_acc.result({c: by_label[c].xyz for c in ctrl}, {c: cmm_sigma for c in ctrl}, stages["ml"])
            # the frames' information-weighted mean target points, mapped by the joint pose
            for tid in target_ids:
                W = np.zeros((3, 3))
                b = np.zeros(3)
                for points, ids in per_frame_points:
                    if tid in ids:
                        Wk = np.linalg.inv(points.cov_xyz[ids[tid]])
                        W += Wk
                        b += Wk @ points.xyz[ids[tid]]
                if W.any():
                    metrics[name]["targets"][tid] = [pose.fit.apply(np.linalg.solve(W, b)[None])[0]]
            metrics[name]["moved"] = pose.moved
    # session target points (mean over frames) vs truth
    for name in CONFIGS:
        errs = [np.mean(v, axis=0) - truth_g[tid] for tid, v in metrics[name]["targets"].items()]
        metrics[name]["target_err2"] = [float(e @ e) for e in errs]
    return metrics


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="camera-limited")
    parser.add_argument("--sessions", type=int, default=10)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--only", default="", help="comma-separated configurations to run (default: all)")
    args = parser.parse_args(argv)
    global CONFIGS
    if args.only:
        unknown = set(args.only.split(",")) - set(CONFIGS)
        if unknown:
            parser.error(f"unknown configuration(s) {', '.join(sorted(unknown))}; choose from {', '.join(CONFIGS)}")
        CONFIGS = tuple(c for c in CONFIGS if c in args.only.split(","))
    scene = build_scene(args.scenario)
    cmm_sigma = scene.arm_sigma_mm
    pm = make_plugin_manager()
    impl = {s: implementations(pm, s) for s in ("centroid", "triangulate", "register", "measure")}
    stages = {
        "weighted": impl["centroid"]["weighted"].create({}),
        "modelfit": impl["centroid"]["modelfit"].create({}),
        "tri_plain": impl["triangulate"]["epipolar"].create({"eccentricity": False}),
        "tri_ecc": impl["triangulate"]["epipolar"].create({}),
        "svd": impl["register"]["svd"].create({}),
        "ml": impl["register"]["ml"].create({}),
        "measure": impl["measure"]["plan"].create({}),
    }
    for stage, key in (("centroid", "default_centroid"), ("triangulate", "default_triangulate"), ("register", "default_register")):
        stages[key] = impl[stage][DEFAULT_PLUGINS[stage]].create({})
    t0 = time.perf_counter()
    fisher = {cam: centroid_fisher(scene, cam) for cam in CAMERAS}
    crb = chain_crb(scene, fisher, args.frames, cmm_sigma)
    crb_rms = float(np.sqrt(np.mean([np.trace(c) for c in crb.values()])))
    totals = {c: {"centroid": [], "cam": [], "target": [], "lengths": [], "covered": []} for c in CONFIGS}
    moved = 0
    for s in range(args.sessions):
        m = run_session(scene, stages, args.seed + s, args.frames, fisher, cmm_sigma)
        for c in CONFIGS:
            totals[c]["centroid"] += m[c]["centroid_z2"]
            totals[c]["cam"] += m[c]["cam_err2"]
            totals[c]["target"] += m[c]["target_err2"]
            totals[c]["lengths"] += m[c]["lengths"]
            totals[c]["covered"] += m[c]["covered"]
        moved += bool(m.get("+session", {}).get("moved"))
    print(
        f"scenario {args.scenario}: {args.sessions} sessions x {args.frames} frames, arm sigma {cmm_sigma} mm, "
        f"{time.perf_counter() - t0:.0f} s; target-point CRB (global, per session) {crb_rms * 1e3:.2f} um RMS"
        + (f"; session motion test false alarms: {moved}/{args.sessions}" if "+session" in CONFIGS else "")
    )
    print(f"{'configuration':15s} {'centroid RMS/CRB':>16s} {'camera pt um':>12s} {'target pt um':>12s} "
          f"{'target/CRB':>10s} {'vs opencv':>9s} {'length um':>9s} {'|e|<=2u':>8s}")
    base = np.sqrt(np.mean(totals["opencv"]["target"])) if "opencv" in CONFIGS else float("nan")
    for c in CONFIGS:
        z2 = np.array([z for z, _ in totals[c]["centroid"]])
        ratio = np.sqrt(z2.mean() / 2.0) if len(z2) else float("nan")
        cam = np.sqrt(np.mean(totals[c]["cam"])) * 1e3
        tgt = np.sqrt(np.mean(totals[c]["target"]))
        lengths = np.sqrt(np.mean(np.square(totals[c]["lengths"]))) * 1e3 if totals[c]["lengths"] else float("nan")
        cover = np.mean(totals[c]["covered"]) * 100 if totals[c]["covered"] else float("nan")
        print(f"{c:15s} {ratio:16.2f} {cam:12.2f} {tgt * 1e3:12.2f} {tgt / crb_rms:10.2f} {tgt / base:9.2f} "
              f"{lengths:9.2f} {cover:7.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
