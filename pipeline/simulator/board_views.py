"""Simulated calibration views: a printed board seen by the station's stereo pair.

Each pixel's value is the exact image of the printed pattern: every
sub-sample of the pixel (``supersample``^2 of them, each in its own row and
column of the pixel, :func:`sample_offsets`) is cast back through the lens
(distortion inverted, the fixed-point iteration of
:func:`crossfield.simulator.optics.pixel_rays`, run by ``cv2.undistortPoints``)
and intersected with the board plane, where the printed pattern (a raster
of ``texel_mm`` texels whose edges fall exactly on the squares' edges) is
looked up by bilinear interpolation between texel centres (a tent pre-filter
one texel wide, symmetric about every edge, so no edge moves). A nearest-texel
lookup makes each sub-sample a step, and with 16 sub-samples per pixel the
pixel's coverage is quantised along a slanted edge: the station's corners
then carry a deterministic error of 0.011-0.027 px RMS per view against a
converged (256-sample) rendering; the tent lookup brings it to 0.003-0.004 px
at 1.3x the lookup time of the nearest one (issue 28,
``tests/calibration/test_board_render.py``). The pixel's coverage is then
lit (a vignetted illumination),
blurred with the sensor's Gaussian PSF and noised (shot + read noise,
:func:`crossfield.simulator.render.add_noise`), like the target images.

Pixel -> board is a smooth map: it is evaluated exactly at pixel centres
and to first order inside the pixel (its Jacobian by central differences),
an error below 1e-4 px for the station's geometry.

The truth comes with the views: the board pose in the upper-camera frame
per view (``X_upper = R @ X_board + t``, mm), the rig's calibration and
(:func:`true_image_points`) every board point's exact pixel position.

:class:`ViewMismatch` makes the views depart from the estimator's model (a
pinhole with OpenCV's plumb_bob lens, a flat board, independent corner
errors): thin-prism lens terms no fitted model has, an astigmatic PSF, a
board bowed like mrcal's ``calobject_warp`` (fixed, and a random part per
view: corner errors correlated within a view). It stands in for an
independent renderer (issue 28) until ``render_mismatch`` lands.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from crossfield.calibration.boards import Board
from crossfield.progress import bar
from crossfield.simulator.optics import project
from crossfield.simulator.render import SensorModel, add_noise, background_image
from crossfield.simulator.scenarios import SCENARIOS, VIEW_CENTRE, station_calibration
from crossfield.types import CAMERAS, CameraIntrinsics, StereoCalibration

#: Reflectance of the surroundings and of the black print, in 1/255 of the white paper's.
BACKGROUND_LEVEL = 20
BLACK_LEVEL = 15
#: DN of white paper at the image centre.
WHITE_DN = 2900.0


@dataclass(frozen=True)
class BoardTexture:
    """The printed board as a raster: reflectance levels (rows, cols) uint8, 255 = white paper.

    origin_mm: board-frame (x, y) of texel [0, 0]'s top-left corner (mm);
    texel_mm: texel side (mm). The raster includes a white margin and one
    texel of surroundings all round (what a lookup outside the sheet gets).
    """

    levels: np.ndarray
    origin_mm: tuple[float, float]
    texel_mm: float

    def sample(self, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """Reflectance (0..1) at board-frame points (mm), nearest texel; any shape."""
        rows, cols = self.levels.shape
        c = np.clip(np.floor((bx - self.origin_mm[0]) / self.texel_mm), 0, cols - 1).astype(np.intp)
        r = np.clip(np.floor((by - self.origin_mm[1]) / self.texel_mm), 0, rows - 1).astype(np.intp)
        return self.levels[r, c] / np.float32(255)

    @property
    def corners_mm(self) -> np.ndarray:
        """(4, 2) board-frame corners of the sheet (mm)."""
        rows, cols = self.levels.shape
        x0, y0 = self.origin_mm
        x1, y1 = x0 + cols * self.texel_mm, y0 + rows * self.texel_mm
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def board_texture(board: Board, *, texel_mm: float = 0.05, margin_mm: float | None = None) -> BoardTexture:
    """Rasterise the printed pattern (black = 0 on white = 1 paper) at ``texel_mm``."""
    margin = board.square_mm if margin_mm is None else margin_mm
    if board.type == "circles":
        margin = 2 * board.spacing_mm if margin_mm is None else margin_mm
    ox, oy = board.pattern_origin_mm
    width, height = board.extent_mm
    if board.type != "circles":
        texel_mm = board.square_mm / round(board.square_mm / texel_mm)  # square edges on texel edges
    n_margin = int(round(margin / texel_mm))
    cols = int(round(width / texel_mm))
    rows = int(round(height / texel_mm))
    if board.type == "charuco":
        pattern = board.charuco_board().generateImage((cols, rows), marginSize=0, borderBits=1)
        pattern = pattern.astype(np.float32) / 255.0
    elif board.type == "chessboard":
        per = int(round(board.square_mm / texel_mm))
        r, c = np.mgrid[0:rows, 0:cols]
        pattern = (((r // per) + (c // per)) % 2 == 1).astype(np.float32)  # top-left square black
    else:
        r, c = np.mgrid[0:rows, 0:cols]
        x = ox + (c + 0.5) * texel_mm
        y = oy + (r + 0.5) * texel_mm
        pattern = np.ones((rows, cols), np.float32)
        for centre in board.object_points():
            inside = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 <= (board.diameter_mm / 2) ** 2
            pattern[inside] = 0.0
    pattern = np.where(pattern > 0.5, 255, BLACK_LEVEL).astype(np.uint8)
    sheet = np.pad(pattern, n_margin, constant_values=255)
    sheet = np.pad(sheet, 1, constant_values=BACKGROUND_LEVEL)
    origin = (ox - (n_margin + 1) * texel_mm, oy - (n_margin + 1) * texel_mm)
    return BoardTexture(np.ascontiguousarray(sheet, dtype=np.uint8), origin, float(texel_mm))


@lru_cache(maxsize=4)
def _rays_cached(key: bytes, K: tuple, D: tuple, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    # cv2.undistortPoints runs the fixed-point inversion of optics.pixel_rays in C++; 20 iterations
    # converge to machine precision for the station's lenses (contraction ~ 3 |k1| r^2 ~ 0.015).
    v, u = np.mgrid[0 : size[1], 0 : size[0]].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT, 20, 0.0)
    xy = cv2.undistortPoints(pts, np.array(K).reshape(3, 3), np.array(D), criteria=criteria).reshape(
        size[1], size[0], 2
    )
    return np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1])


def camera_rays(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised ray (x, y) of every pixel centre, each (H, W) float64 (cached)."""
    K = tuple(np.asarray(intrinsics.camera_matrix).ravel().tolist())
    D = tuple(np.asarray(intrinsics.dist_coeffs).ravel().tolist())
    return _rays_cached(repr((K, D, intrinsics.image_size)).encode(), K, D, intrinsics.image_size)


def sample_offsets(n: int) -> np.ndarray:
    """(n, 2) sub-pixel sample offsets (du, dv) in (-0.5, 0.5): a rank-1 lattice ("n rooks").

    Every sample has its own column and row (offsets (i + 1/2)/n), so an edge
    parallel to the pixel grid is resolved to 1/n px, not 1/sqrt(n) as on a
    regular grid; the generator (the integer nearest 0.38 n coprime to n,
    a Fibonacci lattice) spreads the samples evenly over the pixel.
    """
    g = max(1, int(round(0.382 * n)))
    while np.gcd(g, n) != 1:
        g += 1
    i = np.arange(n)
    return np.stack([(i + 0.5) / n - 0.5, ((i * g) % n + 0.5) / n - 0.5], axis=1)


def _integrate(texture: BoardTexture, tx: np.ndarray, ty: np.ndarray, n_samples: int) -> np.ndarray:
    """Mean reflectance over each pixel from ``n_samples`` sub-samples (:func:`sample_offsets`).

    tx, ty: (rows, cols) float64 texel coordinates of the pixel centres. The
    map pixel -> texel is smooth: a sub-sample at (du, dv) is looked up at
    ``t + du dt/du + dv dt/dv`` (first order; the Jacobian by central differences).
    Each lookup is bilinear between texel centres (module docstring: a
    nearest lookup quantises the coverage of a slanted edge).
    """
    tx_v, tx_u = (g.astype(np.float32) for g in np.gradient(tx))
    ty_v, ty_u = (g.astype(np.float32) for g in np.gradient(ty))
    tx32, ty32 = tx.astype(np.float32), ty.astype(np.float32)
    acc = np.zeros(tx.shape, np.uint16)
    for du, dv in sample_offsets(n_samples):
        mx = cv2.scaleAdd(tx_v, float(dv), cv2.scaleAdd(tx_u, float(du), tx32))
        my = cv2.scaleAdd(ty_v, float(dv), cv2.scaleAdd(ty_u, float(du), ty32))
        # uint8 out: each sample rounded to 1/255 of white (0.2 % of the contrast); a float32 lookup
        # is 1.4x slower and gives the same corners (0.003-0.004 px from a 64-sample rendering)
        acc += cv2.remap(texture.levels, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return acc.astype(np.float32) / np.float32(255 * n_samples)


def board_height_mm(
    bx: np.ndarray, by: np.ndarray, board: Board, warp_mm: tuple[float, float]
) -> np.ndarray:
    """Height (mm, along the board's z) of a bowed board at board-frame (bx, by) mm; any shape.

    mrcal's ``calobject_warp`` form: ``z = wx (1 - xn^2) + wy (1 - yn^2)`` with
    xn, yn in [-1, 1] across the corner grid (mrcal docs, "Board deformation"):
    a board bowed by wx along x and wy along y, 0 at the grid's edges.
    """
    obj = board.object_points()
    lo, hi = obj[:, :2].min(axis=0), obj[:, :2].max(axis=0)
    xn = 2 * (bx - lo[0]) / (hi[0] - lo[0]) - 1
    yn = 2 * (by - lo[1]) / (hi[1] - lo[1]) - 1
    return warp_mm[0] * (1 - xn * xn) + warp_mm[1] * (1 - yn * yn)


def render_board(
    texture: BoardTexture,
    R_camera_board: np.ndarray,
    t_camera_board: np.ndarray,
    intrinsics: CameraIntrinsics,
    sensor: SensorModel,
    rng: np.random.Generator,
    *,
    supersample: int = 4,
    illumination_seed: int = 11,
    height_mm=None,
    psf_sigma_px: tuple[float, float] | None = None,
) -> np.ndarray:
    """One noisy (H, W) uint16 image of the board at pose (R, t): ``X_camera = R X_board + t`` (mm).

    height_mm: None (a flat board) or a function (bx, by) -> z (mm) of the
    board's surface (:func:`board_height_mm`). psf_sigma_px: (sigma_u,
    sigma_v) of an astigmatic Gaussian PSF replacing the sensor's round one.
    """
    width, height = intrinsics.image_size
    R = np.asarray(R_camera_board, float)
    t = np.asarray(t_camera_board, float)
    coverage = np.full((height, width), BACKGROUND_LEVEL / 255, np.float32)
    # Region of interest: the sheet's outline, projected.
    edge = np.linspace(0.0, 1.0, 64)[:, None]
    c = texture.corners_mm
    outline = np.concatenate([c[k] + edge * (c[(k + 1) % 4] - c[k]) for k in range(4)])
    outline_cam = outline @ R[:, :2].T + t
    if np.all(outline_cam[:, 2] > 1.0):
        uv = project(outline_cam, intrinsics)
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 4, 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 4, [width - 1, height - 1])
        if u1 > u0 + 2 and v1 > v0 + 2:
            x, y = camera_rays(intrinsics)
            x = x[v0 : v1 + 1, u0 : u1 + 1]
            y = y[v0 : v1 + 1, u0 : u1 + 1]
            # The plane z_board = 0: (x, y, 1) ~ H (bx, by, 1), H = [r1 r2 t] (Zhang 2000, eq. 2).
            Hinv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
            den = Hinv[2, 0] * x + Hinv[2, 1] * y + Hinv[2, 2]
            # Texel coordinates for cv2.remap (texel i's centre at i: it covers [i - 0.5, i + 0.5)).
            tx = (
                (Hinv[0, 0] * x + Hinv[0, 1] * y + Hinv[0, 2]) / den - texture.origin_mm[0]
            ) / texture.texel_mm - 0.5
            ty = (
                (Hinv[1, 0] * x + Hinv[1, 1] * y + Hinv[1, 2]) / den - texture.origin_mm[1]
            ) / texture.texel_mm - 0.5
            if height_mm is not None:
                tx, ty = _bowed_lookup(texture, R, x, y, tx, ty, height_mm)
            coverage[v0 : v1 + 1, u0 : u1 + 1] = _integrate(texture, tx, ty, int(supersample) ** 2)
    light = background_image(intrinsics.image_size, WHITE_DN, np.random.default_rng(illumination_seed))
    su, sv = (sensor.blur_sigma_px,) * 2 if psf_sigma_px is None else psf_sigma_px
    clean = cv2.GaussianBlur(coverage * light, (0, 0), sigmaX=su, sigmaY=sv)
    return add_noise(clean, sensor, rng)


def _bowed_lookup(texture, R, x, y, tx, ty, height_mm):
    """Texel coordinates where the rays (x, y, 1) meet a bowed board instead of its plane.

    A ray meeting the plane z_board = 0 at b meets the surface z = h(b') at
    b' = b + h(b') d_xy / d_z, with d = R^T (x, y, 1) its direction in the
    board frame; solved by fixed-point iteration (3 steps: the error shrinks
    by |grad h| |d_xy / d_z| < 0.02 per step for bows under 1 mm).
    """
    dx = R[0, 0] * x + R[1, 0] * y + R[2, 0]
    dy = R[0, 1] * x + R[1, 1] * y + R[2, 1]
    dz = R[0, 2] * x + R[1, 2] * y + R[2, 2]
    bx0 = (tx + 0.5) * texture.texel_mm + texture.origin_mm[0]
    by0 = (ty + 0.5) * texture.texel_mm + texture.origin_mm[1]
    bx, by = bx0, by0
    for _ in range(3):
        h = height_mm(bx, by)
        bx, by = bx0 + h * dx / dz, by0 + h * dy / dz
    return (
        (bx - texture.origin_mm[0]) / texture.texel_mm - 0.5,
        (by - texture.origin_mm[1]) / texture.texel_mm - 0.5,
    )


# ---- the station's calibration session -----------------------------------------------------------


@dataclass(frozen=True)
class BoardPose:
    """True board pose in the upper-camera frame: X_upper = R @ X_board + t (mm).

    lower_shift: for an outlier view, the board's extra rigid motion
    (rotation vector rad, translation mm) between the upper and the lower
    exposure; None for a good view. warp_mm: the board's bow (wx, wy) in
    this view (:func:`board_height_mm`; (0, 0) flat).
    """

    R: np.ndarray
    t: np.ndarray
    lower_shift: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    warp_mm: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class ViewMismatch:
    """How the rendered views depart from the estimator's model (all zero / None: they do not).

    thin_prism: (s1, s2, s3, s4) thin-prism terms added to both lenses
    (OpenCV's 12-coefficient model; neither plumb_bob nor rational fits
    them). psf_sigma_px: (sigma_u, sigma_v) px astigmatic Gaussian PSF
    instead of the sensor's round one. board_warp_mm: (wx, wy) fixed bow of
    the board (:func:`board_height_mm`, mrcal's calobject_warp).
    bow_per_view_mm: standard deviation of a random bow (wx, wy) added per
    view (a board that flexes as it is handled): corner errors correlated
    within a view.
    """

    thin_prism: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    psf_sigma_px: tuple[float, float] | None = None
    board_warp_mm: tuple[float, float] = (0.0, 0.0)
    bow_per_view_mm: float = 0.0

    def lens(self, intrinsics: CameraIntrinsics) -> CameraIntrinsics:
        """The rendered lens: ``intrinsics`` with the thin-prism terms (12 coefficients) if any."""
        if not any(self.thin_prism):
            return intrinsics
        D = np.zeros(12)
        D[: min(8, len(intrinsics.dist_coeffs))] = np.asarray(intrinsics.dist_coeffs)[:8]
        D[8:12] = self.thin_prism
        return CameraIntrinsics(intrinsics.camera_matrix, D, intrinsics.image_size)


@dataclass(frozen=True)
class CalibrationViews:
    """A simulated calibration session: the views and the truth they were rendered from.

    images: per view a dict camera -> (H, W) uint16 image (``bit_depth`` bits).
    """

    board: Board
    calibration: StereoCalibration
    poses: tuple[BoardPose, ...]
    images: tuple[dict[str, np.ndarray], ...]
    bit_depth: int
    sensor: SensorModel = field(default_factory=SensorModel)
    mismatch: ViewMismatch = field(default_factory=ViewMismatch)


def true_image_points(views: CalibrationViews, view: int, camera: str) -> np.ndarray:
    """(n_points, 2) exact pixel positions of every board point (by id) in one rendered image.

    The board point (x, y, h(x, y)) (bow included) through the pose and the
    rendered lens (thin-prism terms included; ``cv2.projectPoints``). A point
    behind the camera is NaN. Mirrored views are not handled (their truth is
    the mirror image).
    """
    pose = views.poses[view]
    obj = views.board.object_points().copy()
    obj[:, 2] = board_height_mm(obj[:, 0], obj[:, 1], views.board, pose.warp_mm)
    X = obj @ np.asarray(pose.R).T + np.asarray(pose.t)
    if camera == "lower":
        R_u, t_u = np.asarray(pose.R), np.asarray(pose.t)
        if pose.lower_shift is not None:
            dR = Rotation.from_rotvec(pose.lower_shift[0]).as_matrix()
            R_u, t_u = dR @ R_u, dR @ t_u + np.asarray(pose.lower_shift[1])
        X = obj @ R_u.T + t_u
        X = X @ np.asarray(views.calibration.R_lower_upper).T + np.asarray(views.calibration.t_lower_upper)
    lens = views.mismatch.lens(views.calibration.camera(camera))
    uv, _ = cv2.projectPoints(
        X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), np.asarray(lens.camera_matrix), np.asarray(lens.dist_coeffs)
    )
    uv = uv.reshape(-1, 2)
    uv[X[:, 2] <= 0] = np.nan
    return uv


def default_board() -> Board:
    """The issue's example board: ChArUco 11 x 8 squares of 15 mm, 11 mm DICT_5X5_100 markers."""
    return Board()


def station_board_poses(n_views: int, board: Board, *, layout_seed: int = 2026) -> list[BoardPose]:
    """``n_views`` board poses spread over the station's shared view and depth (340..470 mm).

    Every pose is tilted 12..40 deg out of the image plane (Zhang's method
    needs non-parallel planes) and rolled up to +-30 deg; the board centre
    sweeps a 3 x 3 grid of the view so that corners reach the image edges.
    """
    rng = np.random.default_rng(layout_seed)
    width, height = board.extent_mm
    ox, oy = board.pattern_origin_mm
    centre_board = np.array([ox + width / 2, oy + height / 2, 0.0])
    poses = []
    for k in range(n_views):
        z = rng.uniform(340.0, 470.0)
        gx, gy = (k % 3) - 1, ((k // 3) % 3) - 1
        lateral = np.array([gx * 0.16 * z + rng.uniform(-8, 8), gy * 0.10 * z + rng.uniform(-6, 6)])
        centre = np.array(
            [
                VIEW_CENTRE[0] * z / VIEW_CENTRE[2] + lateral[0],
                VIEW_CENTRE[1] * z / VIEW_CENTRE[2] + lateral[1],
                z,
            ]
        )
        axis_angle = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(12.0, 40.0))
        tilt_rot = Rotation.from_rotvec(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]))
        roll = Rotation.from_rotvec([0.0, 0.0, np.radians(rng.uniform(-30.0, 30.0))])
        R = (tilt_rot * roll).as_matrix()
        poses.append(BoardPose(R, centre - R @ centre_board))
    return poses


def render_calibration_views(
    scenario: str = "station",
    *,
    n_views: int = 20,
    seed: int = 1,
    board: Board | None = None,
    outlier_views: tuple[int, ...] = (),
    mirrored: str | None = None,
    supersample: int = 4,
    layout_seed: int = 2026,
    mismatch: ViewMismatch | None = None,
) -> CalibrationViews:
    """Render a calibration session of ``scenario``'s rig (both cameras, ``n_views`` pairs).

    seed: image noise. outlier_views: views in which the board moves
    (0.6 mm, 1 mrad) between the upper and the lower exposure, as with
    cameras that are not triggered together. mirrored: a camera whose images
    are flipped left-right (a reversed read-out). Poses from
    :func:`station_board_poses`. mismatch: the ways the views depart from
    the estimator's model (:class:`ViewMismatch`; the per-view bows are
    drawn from ``seed``); ``calibration`` then holds the rendered lenses.
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; scenarios: {', '.join(SCENARIOS)}")
    if mirrored is not None and mirrored not in CAMERAS:
        raise ValueError(f"mirrored must be one of {CAMERAS}, got {mirrored!r}")
    board = default_board() if board is None else board
    mismatch = ViewMismatch() if mismatch is None else mismatch
    truth = station_calibration()
    calibration = StereoCalibration(
        mismatch.lens(truth.upper),
        mismatch.lens(truth.lower),
        truth.R_lower_upper,
        truth.t_lower_upper,
        source=truth.source,
    )
    sensor = SensorModel()
    texture = board_texture(board)
    poses = station_board_poses(n_views, board, layout_seed=layout_seed)
    bow_rng = np.random.default_rng([seed, 5])
    warps = [
        tuple(np.asarray(mismatch.board_warp_mm) + mismatch.bow_per_view_mm * bow_rng.standard_normal(2))
        for _ in poses
    ]
    poses = [
        BoardPose(
            p.R,
            p.t,
            ((0.0007, -0.0005, 0.0004), (0.45, -0.3, 0.25)) if k in outlier_views else None,
            (float(warps[k][0]), float(warps[k][1])),
        )
        for k, p in enumerate(poses)
    ]
    rng = np.random.default_rng([seed, 3])
    images = []
    R_lu, t_lu = calibration.R_lower_upper, calibration.t_lower_upper
    for pose in bar(poses, desc="simulating the board views", unit="pair"):
        height = None
        if any(pose.warp_mm):
            height = lambda bx, by, w=pose.warp_mm: board_height_mm(bx, by, board, w)
        extra = {"height_mm": height, "psf_sigma_px": mismatch.psf_sigma_px}
        R_u, t_u = pose.R, pose.t
        if pose.lower_shift is not None:
            dR = Rotation.from_rotvec(pose.lower_shift[0]).as_matrix()
            R_u, t_u = dR @ R_u, dR @ t_u + np.asarray(pose.lower_shift[1])
        view = {
            "upper": render_board(
                texture, pose.R, pose.t, calibration.upper, sensor, rng, supersample=supersample, **extra
            ),
            "lower": render_board(
                texture,
                R_lu @ R_u,
                R_lu @ t_u + t_lu,
                calibration.lower,
                sensor,
                rng,
                supersample=supersample,
                illumination_seed=12,
                **extra,
            ),
        }
        if mirrored is not None:
            view[mirrored] = np.ascontiguousarray(view[mirrored][:, ::-1])
        for image in view.values():
            image.flags.writeable = False
        images.append(view)
    return CalibrationViews(
        board, calibration, tuple(poses), tuple(images), sensor.bit_depth, sensor, mismatch
    )


@lru_cache(maxsize=2)
def _cached_views(scenario: str, n_views: int, seed: int, board: Board, outlier_views: tuple[int, ...]):
    return render_calibration_views(
        scenario, n_views=n_views, seed=seed, board=board, outlier_views=outlier_views
    )


def cached_calibration_views(
    scenario: str = "station",
    n_views: int = 20,
    seed: int = 1,
    board: Board | None = None,
    outlier_views: tuple[int, ...] = (),
) -> CalibrationViews:
    """:func:`render_calibration_views`, remembered (the images are read-only): a process that
    calibrates the same simulated session twice (the tests, the CLI in-process) renders it once."""
    return _cached_views(
        scenario, n_views, seed, default_board() if board is None else board, tuple(outlier_views)
    )
