"""mrcal as a benchmark peer: solve stereo calibration problems given as an .npz, write JSON.

Runs under Debian's ``/usr/bin/python3`` (``apt-get install -y python3-mrcal mrcal``),
not the project's venv: mrcal is a peer of ``bench/bench_calibrate_peers.py``,
never a dependency of crossfield. No pickle: the problems come in an
``.npz`` loaded with ``allow_pickle=False``, the results go out as JSON.

Input (``problems.npz``), for each problem i = 0 .. n-1 (keys prefixed ``p{i}_``):

* ``obs``: (Nobs, H, W, 3) float64 board observations (u, v, weight) px;
  weight -1 marks a corner not detected (mrcal's outlier convention);
* ``idx``: (Nobs, 3) int32 (frame, camera intrinsics, camera extrinsics),
  extrinsics -1 for the reference (upper) camera; sorted by frame;
* ``intrinsics``: (2, 4 + nd) seed fx fy cx cy + OpenCV distortion;
* ``extrinsics``: (1, 6) seed rt_lower_upper (rotation vector rad, t mm);
* ``frames``: (Nframes, 6) seed rt_upper_board (mrcal's board frame:
  corner (0, 0) at the origin);

and once: ``spacing_mm``, ``imagersizes`` (2, 2) int, ``lensmodel`` (str),
``n_problems``.

Output JSON: per problem the solved intrinsics (2, 4 + nd), extrinsics (6,),
their standard deviations from mrcal's own Jacobian (sigma^2 (J^T J)^-1 with
sigma^2 from the board residuals, the regularisation rows excluded, mrcal's
"observed pixel uncertainty" estimated as Hartley & Zisserman 5.2.3),
calobject_warp (2,), the RMS reprojection error (px), the number of outlier
corners and the solve time (s, ``mrcal.optimize`` calls only).

Usage: /usr/bin/python3 bench/mrcal_peer.py problems.npz results.json [--warp]
[--no-regularization] [--no-outliers] (the last two switch off mrcal's
regularisation and its outlier rejection, for comparing the bare solve).
"""

from __future__ import annotations

import json
import sys
import time

import mrcal
import numpy as np


def _covariance(inputs: dict) -> tuple[np.ndarray, float, float]:
    """Covariance of the unpacked state, sigma^2 (J^T J)^-1 over the board measurement rows;
    sigma (px) and the board rows' cost sum r^2 (px^2; outliers have r = 0)."""
    _, x, J, _ = mrcal.optimizer_callback(**inputs, no_factorization=True)
    J = J.toarray()
    n_board = mrcal.num_measurements_boards(**inputs)
    i0 = mrcal.measurement_index_boards(0, **inputs)
    rows = slice(i0, i0 + n_board)
    xb, Jb = x[rows], J[rows]
    used = np.any(Jb != 0, axis=1)
    m, p = int(used.sum()), J.shape[1]
    sigma2 = float(xb[used] @ xb[used]) / max(m - p, 1)
    cov_packed = sigma2 * np.linalg.pinv(Jb[used].T @ Jb[used])
    # unpack_state scales each state element (in place): p = s * p_packed, so cov = S cov_packed S.
    scale = np.ones(p)
    mrcal.unpack_state(scale, **inputs)
    return cov_packed * np.outer(scale, scale), float(np.sqrt(sigma2)), float(xb @ xb)


def solve(
    data: np.lib.npyio.NpzFile, i: int, warp: bool, regularization: bool = True, outliers: bool = True
) -> dict:
    """One stereo problem: mrcal.optimize as mrcal-calibrate-cameras runs it (core first, then all)."""
    get = lambda key: np.ascontiguousarray(data[f"p{i}_{key}"])
    inputs = dict(
        intrinsics=get("intrinsics").astype(float),
        extrinsics_rt_fromref=get("extrinsics").astype(float),
        frames_rt_toref=get("frames").astype(float),
        points=None,
        observations_board=get("obs").astype(float),
        indices_frame_camintrinsics_camextrinsics=get("idx").astype(np.int32),
        observations_point=None,
        indices_point_camintrinsics_camextrinsics=None,
        lensmodel=str(data["lensmodel"]),
        imagersizes=np.ascontiguousarray(data["imagersizes"], dtype=np.int32),
        calobject_warp=np.zeros(2),
        calibration_object_spacing=float(data["spacing_mm"]),
        do_optimize_intrinsics_core=True,
        do_optimize_intrinsics_distortions=True,
        do_optimize_extrinsics=True,
        do_optimize_frames=True,
        do_optimize_calobject_warp=False,
        do_apply_outlier_rejection=outliers,
        do_apply_regularization=regularization,
    )
    t0 = time.perf_counter()
    # mrcal-calibrate-cameras solves in stages: the core and poses without distortion first.
    mrcal.optimize(**{**inputs, "do_optimize_intrinsics_distortions": False})
    inputs["do_optimize_calobject_warp"] = warp
    stats = mrcal.optimize(**inputs)
    elapsed = time.perf_counter() - t0
    cov, sigma, cost = _covariance(inputs)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    ni = inputs["intrinsics"].shape[1]
    std_intr = [std[(s := mrcal.state_index_intrinsics(c, **inputs)) : s + ni].tolist() for c in range(2)]
    s = mrcal.state_index_extrinsics(0, **inputs)
    outliers = int(np.sum(inputs["observations_board"][..., 2] <= 0))
    return {
        "intrinsics": inputs["intrinsics"].tolist(),
        "extrinsics": inputs["extrinsics_rt_fromref"][0].tolist(),
        "std_intrinsics": std_intr,
        "std_extrinsics": std[s : s + 6].tolist(),
        "calobject_warp": inputs["calobject_warp"].tolist(),
        "rms_px": float(stats["rms_reproj_error__pixels"]),
        "sigma_px": sigma,
        "cost_board_px2": cost,
        "masked_corners": outliers,
        "solve_s": elapsed,
    }


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(
            "usage: mrcal_peer.py problems.npz results.json [--warp] [--no-regularization] [--no-outliers]",
            file=sys.stderr,
        )
        return 2
    warp = "--warp" in argv[2:]
    regularization = "--no-regularization" not in argv[2:]
    outliers = "--no-outliers" not in argv[2:]
    with np.load(argv[0], allow_pickle=False) as data:
        results = [solve(data, i, warp, regularization, outliers) for i in range(int(data["n_problems"]))]
    with open(argv[1], "w") as f:
        json.dump({"mrcal_version": getattr(mrcal, "__version__", "2.x"), "results": results}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
