"""Zhang stereo calibration of the upper/lower pair from views of a planar board.

The paper calibrates the pair with Zhang's method before measuring (its
Formula (4): R_c, T_c between the cameras). Steps:

1. detection in every image (:mod:`crossfield.calibration.detect`);
   views seen mirrored are refused (a reflected image cannot come from a
   pinhole camera looking at the printed side);
2. every ``holdout_every``-th pair is held out of the solution and used
   afterwards to measure the epipolar error on data the solver never saw;
3. per camera, ``cv2.calibrateCameraExtended`` (Zhang 2000 + Levenberg-
   Marquardt on all that camera's views, partial ChArUco views included);
   the view with the largest RMS error is dropped while it exceeds
   ``outlier_factor`` x the median of the views' RMS errors, one at a time
   (relative to the others, no absolute floor: the rule is the same for
   0.03 px and 0.3 px corners; good views on the model renderer reach 4x
   the median, a board moved between the exposures 100x);
4. stereo, ``cv2.stereoCalibrateExtended`` on the points both cameras saw
   (intrinsics refined from step 3), with the same rejection of views;
5. the covariance of the camera and rig parameters
   (:mod:`crossfield.calibration.covariance`), their standard deviations,
   and the 3-D uncertainty they predict over the working volume;
6. (``joint``, the default) the joint bundle adjustment over every corner
   of both cameras with the board's bow, the jackknife over views beside
   the Jacobian's covariance (the stated std is the larger), and the
   residual maps (:mod:`crossfield.calibration.refine`); the 3-D
   uncertainty and the held-out check are then those of the refined rig.

Distortion model: ``plumb_bob`` (k1 k2 p1 p2 k3, the default) or
``rational`` (k1 .. k6). Pixels: (0, 0) is the centre of the top-left pixel.
Lengths in mm, as the board's; ``p_lower = R p_upper + T``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from crossfield.calibration.boards import Board
from crossfield.calibration.covariance import (
    StereoObservations,
    camera_param_names,
    covariance_from_jacobian,
    stereo_jacobian,
    triangulation_sensitivity,
)
from crossfield.calibration.crossval import CrossValidation
from crossfield.calibration.detect import BoardDetection, BoardDetector
from crossfield.calibration.refine import refine
from crossfield.calibration.residuals import ResidualMap
from crossfield.errors import CrossfieldError
from crossfield.progress import bar
from crossfield.types import CAMERAS, CameraIntrinsics, StereoCalibration

DISTORTION_MODELS: dict[str, tuple[int, int]] = {
    "plumb_bob": (0, 5),
    "rational": (cv2.CALIB_RATIONAL_MODEL, 8),
}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)


class CalibrationError(CrossfieldError):
    """The views cannot give a trustworthy calibration (too few, mirrored, degenerate)."""


@dataclass(frozen=True)
class CalibrationSettings:
    """Solver settings (``[calibration]`` in the config, ``docs/calibration.md``).

    distortion: "plumb_bob" or "rational". min_views: fewest views a camera
    (and the stereo step) may be left with. min_points: fewest points a
    view must have (per camera; common points for stereo). outlier_factor:
    a view is dropped while its RMS error (px) exceeds ``outlier_factor``
    x the median of the views' RMS errors. holdout_every:
    every n-th pair (n-1, 2n-1, ...) is held out for the epipolar check (0 = none).
    joint: step 6 (the joint refinement); estimate_warp: the board's bow in
    it; jackknife: the leave-one-view-out covariance in it; cross_validate:
    also calibrate two halves of the views and compare them (``crossfield.calibration.crossval``).
    """

    distortion: str = "plumb_bob"
    min_views: int = 6
    min_points: int = 8
    outlier_factor: float = 5.0
    holdout_every: int = 8
    joint: bool = True
    estimate_warp: bool = True
    jackknife: bool = True
    cross_validate: bool = False

    def __post_init__(self) -> None:
        if self.distortion not in DISTORTION_MODELS:
            raise CalibrationError(
                f"distortion model {self.distortion!r} unknown; choose one of {', '.join(DISTORTION_MODELS)}"
            )
        if self.min_views < 3:
            raise CalibrationError(
                f"min_views must be >= 3 (Zhang's method needs 3 planes), got {self.min_views}"
            )


@dataclass(frozen=True)
class DroppedView:
    """A view left out of the solution: ``stage`` is detect / mirrored / upper / lower / stereo."""

    view: int
    name: str
    stage: str
    reason: str


@dataclass(frozen=True)
class CameraSolution:
    """One camera's own calibration (step 3): K (3, 3) px, D (n,), RMS px,
    std of (fx fy cx cy D) from calibrateCameraExtended, per-view RMS (view index -> px)."""

    K: np.ndarray
    D: np.ndarray
    rms_px: float
    std: np.ndarray
    per_view_px: Mapping[int, float]
    n_points: int


@dataclass(frozen=True)
class CalibrationResult:
    """A stereo calibration with everything needed to judge it (report, YAML std keys).

    covariance: (p, p) of the camera + rig parameters named by ``param_names``
    (px, unitless distortion, rad, mm). per_view_stereo_px: view -> (upper,
    lower) RMS. holdout_epipolar_px: view -> (rms, max) distance of the lower
    points to their epipolar lines (px). uncertainty_points / uncertainty_sigma_mm:
    (N, 3) upper-frame points of the working volume and their predicted 1-sigma
    (N, 3) x y z from the calibration alone (mm). std_jacobian, std_jackknife:
    (p,) the two standard deviations behind ``std`` (the larger; jackknife
    NaN if not run); warp_mm, warp_std_mm: (2,) the board's bow (NaN if not
    estimated); residual_maps: camera -> ``ResidualMap``; cross_validation:
    a ``CrossValidation`` or None; outlier_corners: corners the joint
    refinement's mrcal-style rejection left out.
    """

    calibration: StereoCalibration
    board: Board
    settings: CalibrationSettings
    view_names: tuple[str, ...]
    cameras: Mapping[str, CameraSolution]
    rms_stereo_px: float
    per_view_stereo_px: Mapping[int, tuple[float, float]]
    dropped: tuple[DroppedView, ...]
    held_out: tuple[int, ...]
    param_names: tuple[str, ...]
    params: np.ndarray
    covariance: np.ndarray
    sigma_px: float
    holdout_epipolar_px: Mapping[int, tuple[float, float]]
    detections: tuple[Mapping[str, BoardDetection | None], ...]
    uncertainty_points: np.ndarray
    uncertainty_sigma_mm: np.ndarray
    used_stereo: tuple[int, ...] = field(default=())
    std_jacobian: np.ndarray | None = None
    std_jackknife: np.ndarray | None = None
    warp_mm: np.ndarray | None = None
    warp_std_mm: np.ndarray | None = None
    residual_maps: Mapping[str, ResidualMap] = field(default_factory=dict)
    cross_validation: CrossValidation | None = None
    outlier_corners: int = 0

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    def std_by_name(self) -> dict[str, float]:
        return dict(zip(self.param_names, map(float, self.std)))

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.calibration.t_lower_upper))

    @property
    def baseline_std_mm(self) -> float:
        """1-sigma of |T| (mm), first order: u^T Sigma_T u with u = T / |T|."""
        T = np.asarray(self.calibration.t_lower_upper)
        u = T / np.linalg.norm(T)
        cov_T = self.covariance[-3:, -3:]
        return float(np.sqrt(u @ cov_T @ u))


# ---- detection -------------------------------------------------------------------------------------


def detect_views(
    images: Sequence[Mapping[str, np.ndarray]], board: Board, bit_depth: int, *, min_points: int = 8
) -> list[dict[str, BoardDetection | None]]:
    """Detect the board in every (upper, lower) image; None where not found."""
    detector = BoardDetector(board, min_points=min_points)
    return [
        {cam: detector.detect(view[cam], bit_depth) for cam in CAMERAS}
        for view in bar(images, desc="calibrate: detecting the board", unit="pair")
    ]


def check_mirrored(
    detections: Sequence[Mapping[str, BoardDetection | None]],
    images: Sequence[Mapping[str, np.ndarray]] | None,
    board: Board,
    bit_depth: int,
    min_views: int,
) -> None:
    """Refuse a camera whose views show the board reflected (raises :class:`CalibrationError`).

    Points whose board-to-image map reverses orientation
    (:meth:`BoardDetection.orientation`) are reflected. ArUco markers are
    chiral and are not found in a flipped image at all, so when a camera has
    too few ChArUco views the failed images are tried flipped. (A plain
    chessboard is its own mirror image: a flipped chessboard view cannot be
    told from a real one, and shows only as an inconsistent stereo solution.)
    """
    for cam in CAMERAS:
        found = [d for view in detections if (d := view[cam]) is not None]
        mirrored = sum(d.orientation() < 0 for d in found)
        if found and mirrored > len(found) / 2:
            raise CalibrationError(
                f"the {cam} camera's images are mirrored: the board appears reflected in {mirrored} of "
                f"{len(found)} views (a reversed read-out, ReverseX/ReverseY, or a mirror in the path); "
                f"calibrate with unflipped images"
            )
        if board.type == "charuco" and len(found) < min_views and images is not None:
            detector = BoardDetector(board)
            failed = [k for k, view in enumerate(detections) if view[cam] is None][:8]
            flipped = sum(
                detector.detect(np.ascontiguousarray(images[k][cam][:, ::-1]), bit_depth) is not None
                for k in failed
            )
            if failed and flipped > len(failed) / 2:
                raise CalibrationError(
                    f"the {cam} camera's images are mirrored: the ChArUco board is found in {flipped} of "
                    f"{len(failed)} undetected views only after flipping them left-right (a reversed "
                    f"read-out, ReverseX/ReverseY); calibrate with unflipped images"
                )


# ---- solving ---------------------------------------------------------------------------------------


def _f32(a: np.ndarray, cols: int) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).reshape(-1, 1, cols)


def _drop_worst(
    errors: Mapping[int, float], settings: CalibrationSettings
) -> tuple[int, float, float] | None:
    """The view to drop (index, error px, limit px) or None (module docstring, step 3)."""
    values = np.array(list(errors.values()))
    limit = settings.outlier_factor * float(np.median(values))
    worst = max(errors, key=errors.get)
    if errors[worst] > limit:
        return worst, errors[worst], limit
    return None


def _too_few(
    what: str, have: int, settings: CalibrationSettings, dropped: Sequence[DroppedView]
) -> CalibrationError:
    lost = f"; dropped: {'; '.join(f'{d.name} ({d.stage}: {d.reason})' for d in dropped)}" if dropped else ""
    return CalibrationError(
        f"too few views for {what}: {have} usable, at least {settings.min_views} needed "
        f"(show the board in more positions and tilts){lost}"
    )


def calibrate_camera(
    camera: str,
    views: Mapping[int, BoardDetection],
    image_size: tuple[int, int],
    settings: CalibrationSettings,
    names: Sequence[str],
    dropped: list[DroppedView],
) -> CameraSolution:
    """Step 3 for one camera: Zhang + LM on its views, dropping outlier views one at a time."""
    flag, n_dist = DISTORTION_MODELS[settings.distortion]
    active = {k: d for k, d in views.items() if len(d) >= settings.min_points}
    for k in sorted(set(views) - set(active)):
        dropped.append(
            DroppedView(k, names[k], camera, f"only {len(views[k])} points (< {settings.min_points})")
        )
    while True:
        if len(active) < settings.min_views:
            raise _too_few(f"the {camera} camera", len(active), settings, dropped)
        keys = sorted(active)
        try:
            rms, K, D, _, _, std_in, _, per_view = cv2.calibrateCameraExtended(
                [_f32(active[k].object_points, 3) for k in keys],
                [_f32(active[k].image_points, 2) for k in keys],
                image_size,
                None,
                None,
                flags=flag,
                criteria=_CRITERIA,
            )
        except cv2.error as exc:
            raise CalibrationError(f"the {camera} camera: OpenCV calibrateCamera failed: {exc.err}") from None
        errors = dict(zip(keys, map(float, per_view.ravel())))
        worst = _drop_worst(errors, settings)
        if worst is None:
            break
        k, err, limit = worst
        dropped.append(
            DroppedView(k, names[k], camera, f"RMS reprojection error {err:.3f} px > limit {limit:.3f} px")
        )
        del active[k]
    std = np.asarray(std_in).ravel()[: 4 + n_dist]
    return CameraSolution(
        np.asarray(K, float),
        np.asarray(D, float).ravel()[:n_dist],
        float(rms),
        std,
        errors,
        int(sum(len(active[k]) for k in keys)),
    )


def _common(a: BoardDetection, b: BoardDetection) -> tuple[BoardDetection, BoardDetection]:
    ids = np.intersect1d(a.ids, b.ids)
    return a.subset(ids), b.subset(ids)


def _epipolar_errors(
    upper: BoardDetection, lower: BoardDetection, calibration: StereoCalibration
) -> np.ndarray:
    """Distances (px) of the lower points to the epipolar lines of their upper partners (undistorted pixels).

    F = K2^-T [T]x R K1^-1 (Hartley & Zisserman 9.6); d = |x2^T F x1| / |(F x1)_{1,2}|.
    """
    u, lo = _common(upper, lower)
    K1, D1 = calibration.upper.camera_matrix, calibration.upper.dist_coeffs
    K2, D2 = calibration.lower.camera_matrix, calibration.lower.dist_coeffs
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    x1 = cv2.undistortPoints(u.image_points.reshape(-1, 1, 2), K1, D1, P=K1, criteria=crit).reshape(-1, 2)
    x2 = cv2.undistortPoints(lo.image_points.reshape(-1, 1, 2), K2, D2, P=K2, criteria=crit).reshape(-1, 2)
    T = np.asarray(calibration.t_lower_upper)
    Tx = np.array([[0, -T[2], T[1]], [T[2], 0, -T[0]], [-T[1], T[0], 0]])
    F = np.linalg.inv(K2).T @ Tx @ np.asarray(calibration.R_lower_upper) @ np.linalg.inv(K1)
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    lines = h1 @ F.T
    return np.abs(np.sum(h2 * lines, axis=1)) / np.hypot(lines[:, 0], lines[:, 1])


def working_volume_points(
    calibration: StereoCalibration,
    depths_mm: Sequence[float] = (350.0, 400.0, 450.0),
    grid: int = 5,
    margin: float = 0.1,
) -> np.ndarray:
    """(N, 3) upper-frame points (mm) seen by both cameras: a grid x grid lattice at each depth."""
    out = []
    K1 = np.asarray(calibration.upper.camera_matrix)
    w, h = calibration.upper.image_size
    for z in depths_mm:
        for fu in np.linspace(margin, 1 - margin, grid):
            for fv in np.linspace(margin, 1 - margin, grid):
                X = np.linalg.inv(K1) @ np.array([fu * (w - 1), fv * (h - 1), 1.0]) * z
                Xl = np.asarray(calibration.R_lower_upper) @ X + np.asarray(calibration.t_lower_upper)
                uv, _ = cv2.projectPoints(
                    Xl[None],
                    np.zeros(3),
                    np.zeros(3),
                    np.asarray(calibration.lower.camera_matrix),
                    np.asarray(calibration.lower.dist_coeffs),
                )
                wl, hl = calibration.lower.image_size
                if 0 <= uv[0, 0, 0] < wl and 0 <= uv[0, 0, 1] < hl:
                    out.append(X)
    return np.array(out).reshape(-1, 3)


def solve_stereo(
    detections: Sequence[Mapping[str, BoardDetection | None]],
    image_sizes: Mapping[str, tuple[int, int]],
    board: Board,
    settings: CalibrationSettings = CalibrationSettings(),
    *,
    names: Sequence[str] | None = None,
    source: str = "crossfield calibrate",
) -> CalibrationResult:
    """Steps 2-5 of the module docstring on detected views; raises :class:`CalibrationError`."""
    # the steps on a terminal (crossfield.progress): each camera, the stereo pair, the joint refinement
    with bar(desc="calibrate: solving", total=3 + bool(settings.joint), unit="step") as steps:
        return _solve_stereo(detections, image_sizes, board, settings, names=names, source=source, steps=steps)


def _solve_stereo(
    detections: Sequence[Mapping[str, BoardDetection | None]],
    image_sizes: Mapping[str, tuple[int, int]],
    board: Board,
    settings: CalibrationSettings,
    *,
    names: Sequence[str] | None,
    source: str,
    steps: Any,
) -> CalibrationResult:
    n = len(detections)
    names = [f"view {k}" for k in range(n)] if names is None else list(names)
    dropped: list[DroppedView] = []
    flag, n_dist = DISTORTION_MODELS[settings.distortion]
    held_out = tuple(
        k
        for k in range(n)
        if settings.holdout_every and k % settings.holdout_every == settings.holdout_every - 1
    )
    usable: dict[str, dict[int, BoardDetection]] = {cam: {} for cam in CAMERAS}
    for k, view in enumerate(detections):
        for cam in CAMERAS:
            d = view[cam]
            if d is None:
                dropped.append(DroppedView(k, names[k], "detect", f"board not found in the {cam} image"))
            elif d.orientation() < 0:
                dropped.append(
                    DroppedView(k, names[k], "mirrored", f"the board appears reflected in the {cam} image")
                )
            elif k not in held_out:
                usable[cam][k] = d
    cameras = {}
    for cam in CAMERAS:
        cameras[cam] = calibrate_camera(cam, usable[cam], image_sizes[cam], settings, names, dropped)
        steps.update()
    # Step 4: stereo on the common points of the views both cameras kept.
    pairs: dict[int, tuple[BoardDetection, BoardDetection]] = {}
    for k in sorted(set(cameras["upper"].per_view_px) & set(cameras["lower"].per_view_px)):
        a, b = _common(usable["upper"][k], usable["lower"][k])
        if len(a) < settings.min_points:
            dropped.append(
                DroppedView(
                    k,
                    names[k],
                    "stereo",
                    f"only {len(a)} points seen by both cameras (< {settings.min_points})",
                )
            )
        else:
            pairs[k] = (a, b)
    K1, D1 = cameras["upper"].K, cameras["upper"].D
    K2, D2 = cameras["lower"].K, cameras["lower"].D
    while True:
        if len(pairs) < settings.min_views:
            raise _too_few("the stereo pair (views both cameras saw)", len(pairs), settings, dropped)
        keys = sorted(pairs)
        try:
            rms, K1s, D1s, K2s, D2s, R, T, _, _, rvecs, tvecs, per_view = cv2.stereoCalibrateExtended(
                [_f32(pairs[k][0].object_points, 3) for k in keys],
                [_f32(pairs[k][0].image_points, 2) for k in keys],
                [_f32(pairs[k][1].image_points, 2) for k in keys],
                K1.copy(),
                D1.copy(),
                K2.copy(),
                D2.copy(),
                image_sizes["upper"],
                None,
                None,
                flags=cv2.CALIB_USE_INTRINSIC_GUESS | flag,
                criteria=_CRITERIA,
            )
        except cv2.error as exc:
            raise CalibrationError(f"OpenCV stereoCalibrate failed: {exc.err}") from None
        per_view = np.asarray(per_view).reshape(-1, 2)
        errors = {k: float(np.sqrt(np.mean(per_view[i] ** 2))) for i, k in enumerate(keys)}
        worst = _drop_worst(errors, settings)
        if worst is None:
            break
        k, err, limit = worst
        dropped.append(
            DroppedView(
                k,
                names[k],
                "stereo",
                f"stereo RMS reprojection error {err:.3f} px > limit "
                f"{limit:.3f} px (the board moved between the exposures, or unpaired images?)",
            )
        )
        del pairs[k]
    R = np.asarray(R, float)
    T = np.asarray(T, float).ravel()
    if np.linalg.det(R) < 0:  # pragma: no cover - stereoCalibrate returns a rotation
        raise CalibrationError("the stereo solution is a reflection (det R = -1): are the images mirrored?")
    K1s, K2s = np.asarray(K1s, float), np.asarray(K2s, float)
    D1s, D2s = np.asarray(D1s, float).ravel()[:n_dist], np.asarray(D2s, float).ravel()[:n_dist]
    calibration = StereoCalibration(
        CameraIntrinsics(K1s, D1s, image_sizes["upper"]),
        CameraIntrinsics(K2s, D2s, image_sizes["lower"]),
        R,
        T,
        source=source,
    )
    steps.update()
    # Step 5: covariance at the solution (the board poses marginalised).
    obs = StereoObservations(
        tuple(pairs[k][0].object_points for k in keys),
        tuple(pairs[k][0].image_points for k in keys),
        tuple(pairs[k][1].image_points for k in keys),
    )
    rvec = cv2.Rodrigues(R)[0].ravel()
    res, J = stereo_jacobian(
        obs, K1s, D1s, K2s, D2s, rvec, T, [np.ravel(r) for r in rvecs], [np.ravel(t) for t in tvecs]
    )
    try:
        cov_full, sigma = covariance_from_jacobian(res, J)
    except ValueError as exc:
        raise CalibrationError(
            f"no uncertainty for this calibration: {exc}; add views with other tilts"
        ) from None
    p_cam = 2 * (4 + n_dist) + 6
    cov = cov_full[:p_cam, :p_cam]
    params = np.concatenate(
        [K1s[[0, 1, 0, 1], [0, 1, 2, 2]], D1s, K2s[[0, 1, 0, 1], [0, 1, 2, 2]], D2s, rvec, T]
    )
    extra: dict[str, object] = {"std_jacobian": np.sqrt(np.diag(cov))}
    if settings.joint:
        # Step 6: every corner of both cameras in the stereo views, the bow, the jackknife.
        refined = refine(
            {k: (usable["upper"][k], usable["lower"][k]) for k in keys},
            params,
            calibration,
            board.object_points(),
            estimate_warp=settings.estimate_warp,
            jackknife_views=settings.jackknife,
        )
        calibration, params, cov, sigma = refined.calibration, refined.params, refined.covariance, refined.sigma_px
        steps.update()
        K1s, D1s = np.asarray(calibration.upper.camera_matrix), np.asarray(calibration.upper.dist_coeffs)
        K2s, D2s = np.asarray(calibration.lower.camera_matrix), np.asarray(calibration.lower.dist_coeffs)
        rvec, T = params[-6:-3], params[-3:]
        extra = {
            "std_jacobian": refined.std_jacobian,
            "std_jackknife": refined.std_jackknife,
            "warp_mm": refined.warp_mm,
            "warp_std_mm": refined.warp_std_mm,
            "residual_maps": refined.residual_maps,
            "outlier_corners": refined.outlier_corners,
        }
    holdout = {}
    for k in held_out:
        a, b = detections[k]["upper"], detections[k]["lower"]
        if a is not None and b is not None and a.orientation() > 0 and b.orientation() > 0:
            common = np.intersect1d(a.ids, b.ids)
            if len(common) >= 4:
                d = _epipolar_errors(a, b, calibration)
                holdout[k] = (float(np.sqrt(np.mean(d**2))), float(d.max()))
    points = working_volume_points(calibration)
    G, _ = triangulation_sensitivity(points, K1s, D1s, K2s, D2s, rvec, T)
    cov_X = np.einsum("nip,pq,njq->nij", G, cov, G)
    sigma_X = np.sqrt(np.einsum("nii->ni", cov_X))
    return CalibrationResult(
        calibration=calibration,
        board=board,
        settings=settings,
        view_names=tuple(names),
        cameras=cameras,
        rms_stereo_px=float(rms),
        per_view_stereo_px={k: tuple(map(float, per_view[i])) for i, k in enumerate(keys)},
        dropped=tuple(sorted(dropped, key=lambda d: (d.view, d.stage))),
        held_out=held_out,
        param_names=camera_param_names(n_dist),
        params=params,
        covariance=cov,
        sigma_px=sigma,
        holdout_epipolar_px=holdout,
        detections=tuple(dict(v) for v in detections),
        uncertainty_points=points,
        uncertainty_sigma_mm=sigma_X,
        used_stereo=tuple(keys),
        **extra,
    )


def calibrate_images(
    images: Sequence[Mapping[str, np.ndarray]],
    board: Board,
    bit_depth: int,
    settings: CalibrationSettings = CalibrationSettings(),
    *,
    names: Sequence[str] | None = None,
    source: str = "crossfield calibrate",
) -> CalibrationResult:
    """Detect, check and solve: the whole calibration from (upper, lower) image pairs."""
    if not images:
        raise CalibrationError("no image pairs to calibrate from")
    detections = detect_views(images, board, bit_depth, min_points=min(settings.min_points, 6))
    check_mirrored(detections, images, board, bit_depth, settings.min_views)
    sizes = {cam: (images[0][cam].shape[1], images[0][cam].shape[0]) for cam in CAMERAS}
    result = solve_stereo(detections, sizes, board, settings, names=names, source=source)
    return cross_validated(result) if settings.cross_validate else result


def cross_validated(result: CalibrationResult) -> CalibrationResult:
    """``result`` with its cross-validation: the stereo views split into two interleaved halves,
    each solved as the whole was (same settings, no hold-out), compared (``crossval.compare``)."""
    from dataclasses import replace

    from crossfield.calibration.crossval import compare, split_views

    halves = split_views(tuple(result.used_stereo))
    sizes = {cam: result.calibration.camera(cam).image_size for cam in CAMERAS}
    settings = replace(result.settings, holdout_every=0, cross_validate=False)
    solved = []
    for half in halves:
        dets = [result.detections[k] if k in half else {c: None for c in CAMERAS} for k in range(len(result.detections))]
        try:
            solved.append(solve_stereo(dets, sizes, result.board, settings, names=result.view_names))
        except CalibrationError as exc:
            raise CalibrationError(f"cross-validation: a half of {len(half)} views cannot be solved: {exc}") from None
    a, b = solved
    cv = compare(a.calibration, a.covariance, b.calibration, b.covariance, halves=halves)
    return replace(result, cross_validation=cv)


def settings_from_dict(data: Mapping[str, object], source: str = "<calibration>") -> CalibrationSettings:
    """:class:`CalibrationSettings` from a ``[calibration]`` table; errors name ``source`` and the key."""
    fields = CalibrationSettings.__dataclass_fields__
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise CalibrationError(
            f"{source}: [calibration] unknown key {unknown[0]!r} (keys: {', '.join(fields)})"
        )
    values = {}
    for key, value in data.items():
        default = fields[key].default
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise CalibrationError(f"{source}: [calibration] {key} must be true or false, got {value!r}")
            values[key] = value
            continue
        if isinstance(default, str) != isinstance(value, str) or isinstance(value, bool):
            raise CalibrationError(
                f"{source}: [calibration] {key} must be a {type(default).__name__}, got {value!r}"
            )
        if isinstance(default, int) and not isinstance(default, bool) and not isinstance(value, int):
            raise CalibrationError(f"{source}: [calibration] {key} must be an integer, got {value!r}")
        values[key] = float(value) if isinstance(default, float) else value
    try:
        return CalibrationSettings(**values)
    except CalibrationError as exc:
        raise CalibrationError(f"{source}: [calibration] {exc}") from None
