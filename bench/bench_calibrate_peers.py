"""crossfield's stereo calibration against its peers, on the same detections, with known truth.

Peers (issue 28):

* **crossfield**: ``solve_stereo`` (per-camera Zhang + LM with its view
  rejection, stereo LM, the Jacobian and jackknife standard deviations);
* **OpenCV**: a plain script: ``cv2.calibrateCameraExtended`` per camera on
  every view, then ``cv2.stereoCalibrateExtended`` (``CALIB_USE_INTRINSIC_GUESS``)
  on the common points; stated std: calibrateCameraExtended's intrinsics
  only (OpenCV states none for R, T);
* **mrcal** (``LENSMODEL_OPENCV5``, or 8 with ``--distortion rational``):
  ``mrcal.optimize`` through its Python API in a subprocess under Debian's
  ``/usr/bin/python3`` (``bench/mrcal_peer.py``; ``apt-get install -y
  python3-mrcal mrcal``), seeded with the OpenCV script's solution, fed every
  corner of every view; its outlier rejection, regularisation and board
  warp (``calobject_warp``) on, as ``mrcal-calibrate-cameras`` runs it;
  stated std from its Jacobian.

Every tool gets the same corners: crossfield's detector on the simulator's
rendered board views (``crossfield.simulator.board_views``, a new pose
layout and noise per seed). Errors against the rendered truth: focal lengths
(relative, RMS over fx fy of both cameras), principal points (px, RMS of the
four), the rig rotation (the angle of R_est R_true^T, arcsec) and
translation (|T_est - T_true|, mm); the stated std against the actual
error: the share of |error| / std < 2 over fx fy cx cy of both cameras and
the six rig parameters (95 % expected); the solve time (s).

    .venv/bin/python bench/bench_calibrate_peers.py --seeds 10 --pairs 16 30
    .venv/bin/python bench/bench_calibrate_peers.py --seeds 10 --mismatch --cache /tmp/peers

``--mismatch`` renders with :class:`ViewMismatch` (thin-prism lens terms,
astigmatic PSF, a bowed board, per-view bow) instead of the estimator's own
model. ``--cache DIR`` keeps the detections (``.npz``) so that a second run
skips the rendering. Times are medians of one run on a shared machine: read
them as ratios.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from crossfield.calibration.detect import BoardDetection
from crossfield.calibration.solve import CalibrationError, CalibrationSettings, detect_views, solve_stereo
from crossfield.simulator.board_views import (
    ViewMismatch,
    default_board,
    render_calibration_views,
    station_calibration,
    true_image_points,
)
from crossfield.types import CAMERAS

MRCAL_PYTHON = "/usr/bin/python3"
MISMATCH = ViewMismatch(
    thin_prism=(3e-4, 0.0, -2e-4, 0.0),
    psf_sigma_px=(1.2, 0.8),
    board_warp_mm=(0.2, -0.1),
    bow_per_view_mm=0.05,
)
_CRIT = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
PARAMS = [f"{c}.{p}" for c in CAMERAS for p in ("fx", "fy", "cx", "cy")] + [
    f"rig.{p}" for p in ("rx", "ry", "rz", "Tx", "Ty", "Tz")
]


# ---- the views ------------------------------------------------------------------------------------


def session_detections(
    seed: int, n_views: int, mismatch: bool, supersample: int, cache: Path | None
) -> tuple[list[dict[str, BoardDetection | None]], float, tuple[int, int], dict]:
    """Detections of one simulated session (rendered or cached), their corner RMS error vs truth (px)."""
    board = default_board()
    key = f"peers_v3_s{seed}_n{n_views}_m{int(mismatch)}_x{supersample}.npz"
    truth = station_calibration()
    size = truth.upper.image_size
    if cache is not None and not (cache / key).exists():
        # the first n views of a longer cached session are the n-view session (same poses, same noise draws)
        for longer in sorted(cache.glob(f"peers_v3_s{seed}_n*_m{int(mismatch)}_x{supersample}.npz")):
            if int(longer.name.split("_n")[1].split("_")[0]) > n_views:
                key = longer.name
                break
    if cache is not None and (cache / key).exists():
        with np.load(cache / key, allow_pickle=False) as z:
            dets = []
            for k in range(n_views):
                view = {}
                for cam in CAMERAS:
                    ids = z[f"{k}_{cam}_ids"]
                    view[cam] = (
                        BoardDetection(ids, z[f"{k}_{cam}_uv"], board.object_points()[ids])
                        if len(ids)
                        else None
                    )
                dets.append(view)
            return dets, float(z["corner_rms_px"]), size, json.loads(str(z["truth"]))
    views = render_calibration_views(
        n_views=n_views,
        seed=seed,
        layout_seed=1000 + seed,
        supersample=supersample,
        mismatch=MISMATCH if mismatch else None,
    )
    dets = detect_views(views.images, board, views.bit_depth, min_points=6)
    errors = [
        d.image_points - true_image_points(views, k, cam)[d.ids]
        for k, view in enumerate(dets)
        for cam, d in view.items()
        if d is not None
    ]
    corner_rms = float(np.sqrt(np.mean(np.concatenate(errors) ** 2) * 2))
    cal = views.calibration
    truth_d = {
        "K1": np.asarray(cal.upper.camera_matrix).tolist(),
        "K2": np.asarray(cal.lower.camera_matrix).tolist(),
        "R": np.asarray(cal.R_lower_upper).tolist(),
        "T": np.asarray(cal.t_lower_upper).tolist(),
    }
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        arrays = {"corner_rms_px": corner_rms, "truth": json.dumps(truth_d)}
        for k, view in enumerate(dets):
            for cam, d in view.items():
                arrays[f"{k}_{cam}_ids"] = d.ids if d is not None else np.zeros(0, np.int64)
                arrays[f"{k}_{cam}_uv"] = d.image_points if d is not None else np.zeros((0, 2))
        np.savez(cache / key, **arrays)
    return dets, corner_rms, size, truth_d


# ---- the peers ------------------------------------------------------------------------------------


def _f32(a, cols):
    return np.ascontiguousarray(a, np.float32).reshape(-1, 1, cols)


def opencv_script(dets, size, flags: int) -> dict:
    """The plain OpenCV script: per-camera calibrateCamera on every view, then stereoCalibrate."""
    t0 = time.perf_counter()
    cams = {}
    for cam in CAMERAS:
        views = [d[cam] for d in dets if d[cam] is not None and len(d[cam]) >= 8]
        _, K, D, _, _, std, _, _ = cv2.calibrateCameraExtended(
            [_f32(v.object_points, 3) for v in views],
            [_f32(v.image_points, 2) for v in views],
            size,
            None,
            None,
            flags=flags,
            criteria=_CRIT,
        )
        cams[cam] = (K, D, np.ravel(std)[:4])
    obj, up, lo = [], [], []
    for d in dets:
        a, b = d["upper"], d["lower"]
        if a is None or b is None:
            continue
        ids = np.intersect1d(a.ids, b.ids)
        if len(ids) >= 8:
            a, b = a.subset(ids), b.subset(ids)
            obj.append(_f32(a.object_points, 3))
            up.append(_f32(a.image_points, 2))
            lo.append(_f32(b.image_points, 2))
    rms, K1, D1, K2, D2, R, T, _, _, rvecs, tvecs, _ = cv2.stereoCalibrateExtended(
        obj,
        up,
        lo,
        cams["upper"][0].copy(),
        cams["upper"][1].copy(),
        cams["lower"][0].copy(),
        cams["lower"][1].copy(),
        size,
        None,
        None,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags,
        criteria=_CRIT,
    )
    elapsed = time.perf_counter() - t0
    std = np.concatenate([cams["upper"][2], cams["lower"][2], np.full(6, np.nan)])
    return {
        "K1": K1,
        "K2": K2,
        "D1": np.ravel(D1),
        "D2": np.ravel(D2),
        "R": R,
        "T": np.ravel(T),
        "std": std,
        "solve_s": elapsed,
        "rvecs": [np.ravel(r) for r in rvecs],
        "tvecs": [np.ravel(t) for t in tvecs],
        "stereo_views": [
            k
            for k, d in enumerate(dets)
            if d["upper"] is not None
            and d["lower"] is not None
            and len(np.intersect1d(d["upper"].ids, d["lower"].ids)) >= 8
        ],
        "rms_px": float(rms),
    }


def crossfield_solve(dets, size, distortion: str) -> dict:
    settings = CalibrationSettings(distortion=distortion, holdout_every=0)
    t0 = time.perf_counter()
    res = solve_stereo(dets, {c: size for c in CAMERAS}, default_board(), settings)
    elapsed = time.perf_counter() - t0
    cal = res.calibration
    by = res.std_by_name()
    jac = dict(zip(res.param_names, map(float, res.std_jacobian)))
    return {
        "K1": np.asarray(cal.upper.camera_matrix),
        "K2": np.asarray(cal.lower.camera_matrix),
        "R": np.asarray(cal.R_lower_upper),
        "T": np.asarray(cal.t_lower_upper),
        "std": np.array([by[p] for p in PARAMS]),
        "std_jacobian": np.array([jac[p] for p in PARAMS]),
        "warp_mm": None if res.warp_mm is None else np.asarray(res.warp_mm).tolist(),
        "solve_s": elapsed,
        "dropped": sum(d.stage in ("upper", "lower", "stereo") for d in res.dropped),
        "masked": res.outlier_corners,
    }


def mrcal_problem(dets, ocv: dict, n_dist: int) -> dict[str, np.ndarray]:
    """The mrcal problem: every corner of the OpenCV script's stereo views, seeded by its solution."""
    board = default_board()
    cols, rows = board.pattern_size
    first = board.object_points()[0]
    obs, idx = [], []
    for i, k in enumerate(ocv["stereo_views"]):
        for c, cam in enumerate(CAMERAS):
            d = dets[k][cam]
            grid = np.zeros((rows, cols, 3))
            grid[..., 2] = -1.0  # not detected: mrcal's outlier marker
            if d is not None:
                r, col = np.divmod(d.ids, cols)
                grid[r, col, :2] = d.image_points
                grid[r, col, 2] = 1.0
            obs.append(grid)
            idx.append((i, c, c - 1))
    frames = []
    for rv, tv in zip(ocv["rvecs"], ocv["tvecs"]):
        R, _ = cv2.Rodrigues(rv)
        frames.append(np.concatenate([rv, tv + R @ first]))  # mrcal's board origin: corner 0
    intr = [
        np.concatenate([K[[0, 1, 0, 1], [0, 1, 2, 2]], np.ravel(D)[:n_dist]])
        for K, D in ((ocv["K1"], ocv["D1"]), (ocv["K2"], ocv["D2"]))
    ]
    rvec, _ = cv2.Rodrigues(ocv["R"])
    return {
        "obs": np.array(obs),
        "idx": np.array(idx, np.int32),
        "intrinsics": np.array(intr),
        "extrinsics": np.concatenate([rvec.ravel(), ocv["T"]])[None],
        "frames": np.array(frames),
    }


def run_mrcal(problems: list[dict], size, lensmodel: str, flags: tuple[str, ...] = ("--warp",)) -> list[dict]:
    """Solve all problems in one mrcal subprocess (npz in, JSON out; never pickle);
    flags: ``mrcal_peer.py``'s (``--warp``, ``--no-regularization``, ``--no-outliers``)."""
    with tempfile.TemporaryDirectory() as tmp:
        arrays = {f"p{i}_{k}": v for i, p in enumerate(problems) for k, v in p.items()}
        arrays.update(
            n_problems=len(problems),
            spacing_mm=default_board().square_mm,
            imagersizes=np.array([size, size]),
            lensmodel=lensmodel,
        )
        np.savez(Path(tmp) / "problems.npz", **arrays)
        out = Path(tmp) / "results.json"
        here = Path(__file__).resolve().parent
        proc = subprocess.run(
            [MRCAL_PYTHON, str(here / "mrcal_peer.py"), str(Path(tmp) / "problems.npz"), str(out), *flags],
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            raise SystemExit(f"mrcal peer failed: {proc.stderr.strip().splitlines()[-1:]}")
        results = json.loads(out.read_text())["results"]
    solved = []
    for r in results:
        i1, i2 = np.array(r["intrinsics"])
        K1 = np.array([[i1[0], 0, i1[2]], [0, i1[1], i1[3]], [0, 0, 1]])
        K2 = np.array([[i2[0], 0, i2[2]], [0, i2[1], i2[3]], [0, 0, 1]])
        ext = np.array(r["extrinsics"])
        s1, s2 = (np.array(s)[:4] for s in r["std_intrinsics"])
        solved.append(
            {
                "K1": K1,
                "K2": K2,
                "R": cv2.Rodrigues(ext[:3])[0],
                "T": ext[3:],
                "std": np.concatenate([s1, s2, r["std_extrinsics"]]),
                "solve_s": r["solve_s"],
                "masked": r["masked_corners"],
                "cost_board_px2": r["cost_board_px2"],
                "warp_mm": r["calobject_warp"],
            }
        )
    return solved


# ---- errors ---------------------------------------------------------------------------------------


def errors(sol: dict, truth: dict) -> dict:
    """Errors of one solution against the truth, and |error| / stated std per parameter."""
    K1t, K2t = np.array(truth["K1"]), np.array(truth["K2"])
    Rt, Tt = np.array(truth["R"]), np.array(truth["T"])
    f = [(sol[K][i, i] - Kt[i, i]) / Kt[i, i] for K, Kt in (("K1", K1t), ("K2", K2t)) for i in (0, 1)]
    c = [sol[K][i, 2] - Kt[i, 2] for K, Kt in (("K1", K1t), ("K2", K2t)) for i in (0, 1)]
    dR = sol["R"] @ Rt.T
    angle = float(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    r_err = cv2.Rodrigues(sol["R"])[0].ravel() - cv2.Rodrigues(Rt)[0].ravel()
    actual = np.concatenate(
        [
            [sol["K1"][0, 0] - K1t[0, 0], sol["K1"][1, 1] - K1t[1, 1], c[0], c[1]],
            [sol["K2"][0, 0] - K2t[0, 0], sol["K2"][1, 1] - K2t[1, 1], c[2], c[3]],
            r_err,
            sol["T"] - Tt,
        ]
    )
    z = np.abs(actual) / sol["std"]
    extra = {"z_jacobian": (np.abs(actual) / sol["std_jacobian"]).tolist()} if "std_jacobian" in sol else {}
    return {
        **extra,
        "f_rel": float(np.sqrt(np.mean(np.square(f)))),
        "c_px": float(np.sqrt(np.mean(np.square(c)))),
        "rot_arcsec": float(np.degrees(angle) * 3600),
        "T_mm": float(np.linalg.norm(sol["T"] - Tt)),
        "z": z.tolist(),
        "solve_s": sol["solve_s"],
    }


def table(rows: list[dict], pairs: list[int]) -> str:
    """The markdown table of medians over the seeds."""
    out = [
        (
            '| pairs | tool | f rel. error | c error px | rotation error " | T error mm '
            "| within 2 stated std | solve s | views dropped |"
        ),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for n in pairs:
        for tool in ("crossfield", "opencv", "mrcal"):
            sel = [r for r in rows if r["pairs"] == n and r["tool"] == tool]
            if not sel:
                continue
            med = lambda key, sel=sel: float(np.median([r[key] for r in sel]))
            z = np.array([v for r in sel for v in r["z"]], float)
            z = z[np.isfinite(z)]
            cover = f"{np.mean(z < 2) * 100:.0f} % of {len(z)}" if len(z) else "n/a"
            if tool == "crossfield":
                zj = np.array([v for r in sel for v in r["z_jacobian"]], float)
                cover += f" (Jacobian alone {np.mean(zj < 2) * 100:.0f} %)"
            drop = f"{np.mean([r.get('dropped', 0) for r in sel]):.1f}" if tool == "crossfield" else "-"
            out.append(
                f"| {n} | {tool} | {med('f_rel'):.2e} | {med('c_px'):.3f} | {med('rot_arcsec'):.1f} | "
                f"{med('T_mm'):.4f} | {cover} | {med('solve_s'):.3f} | {drop} |"
            )
    return "\n".join(out)


def verdict(rows: list[dict], pairs: list[int]) -> list[str]:
    """The issue's criterion: crossfield's medians <= 1.1 x the better peer's (rotation, T, f)."""
    lines = []
    for n in pairs:
        for key in ("rot_arcsec", "T_mm", "f_rel"):
            med = {
                tool: float(np.median([r[key] for r in rows if r["pairs"] == n and r["tool"] == tool]))
                for tool in ("crossfield", "opencv", "mrcal")
            }
            best = min(med["opencv"], med["mrcal"])
            ratio = med["crossfield"] / best
            lines.append(
                f"{n} pairs {key}: crossfield / better peer = {ratio:.2f} ({'ok' if ratio <= 1.1 else 'WORSE'})"
            )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="sessions (seed 1..N: layout and noise)")
    ap.add_argument("--pairs", type=int, nargs="+", default=[16, 30], help="view pairs per calibration")
    ap.add_argument("--mismatch", action="store_true", help="render with ViewMismatch (not the model)")
    ap.add_argument("--distortion", choices=("plumb_bob", "rational"), default="plumb_bob")
    ap.add_argument("--supersample", type=int, default=3, help="renderer sub-samples per pixel side")
    ap.add_argument("--cache", type=Path, default=None, help="directory keeping the detections (.npz)")
    ap.add_argument("--json", type=Path, default=None, help="write the per-run rows here")
    args = ap.parse_args(argv)
    n_max = max(args.pairs)
    flags, n_dist, lensmodel = (
        (0, 5, "LENSMODEL_OPENCV5")
        if args.distortion == "plumb_bob"
        else (cv2.CALIB_RATIONAL_MODEL, 8, "LENSMODEL_OPENCV8")
    )
    rows, problems, pending = [], [], []
    corner = []
    for seed in range(1, args.seeds + 1):
        t0 = time.perf_counter()
        dets_all, corner_rms, size, truth = session_detections(
            seed, n_max, args.mismatch, args.supersample, args.cache
        )
        corner.append(corner_rms)
        for n in args.pairs:
            dets = dets_all[:n]
            try:
                cf = crossfield_solve(dets, size, args.distortion)
                rows.append(
                    {
                        "seed": seed,
                        "pairs": n,
                        "tool": "crossfield",
                        "dropped": cf["dropped"],
                        "masked": cf["masked"],
                        **errors(cf, truth),
                    }
                )
            except CalibrationError as exc:
                print(f"seed {seed} pairs {n}: crossfield failed: {exc}", file=sys.stderr)
            ocv = opencv_script(dets, size, flags)
            rows.append({"seed": seed, "pairs": n, "tool": "opencv", **errors(ocv, truth)})
            problems.append(mrcal_problem(dets, ocv, n_dist))
            pending.append((seed, n, truth))
        print(
            f"seed {seed}: corner RMS {corner_rms:.4f} px ({time.perf_counter() - t0:.1f} s)", file=sys.stderr
        )
    for (seed, n, truth), sol in zip(pending, run_mrcal(problems, size, lensmodel)):
        rows.append(
            {"seed": seed, "pairs": n, "tool": "mrcal", "masked": sol["masked"], **errors(sol, truth)}
        )
    print(
        f"{args.seeds} seeds, {'ViewMismatch' if args.mismatch else 'model'} renderer, {args.distortion}; "
        f"corner RMS error vs truth (detections all tools share): median {np.median(corner):.4f} px"
    )
    print(table(rows, args.pairs))
    print("\n".join(verdict(rows, args.pairs)))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
