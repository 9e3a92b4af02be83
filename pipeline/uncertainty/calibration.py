"""The stereo calibration's parameter uncertainty, as a relative scale of camera-frame distances.

Stereo depth is ``Z = f B / disparity`` and lateral positions ``X = x Z / f``:
an error of the baseline B or of the focal length f scales the triangulated
points (to first order, about the rig). The rigid registration to the
controls cannot absorb a scale, so a camera point p moves by ``s (p - g_bar)``
(g_bar the control centroid, global frame) for a relative scale error s, with

    u(s)^2 = (u(|T|) / |T|)^2 + (u(f) / f)^2 ,

u(|T|) from the calibration file's ``std_T`` (mm, per component) and u(f)
from ``std_M1`` / ``std_M2`` (px, standard deviations of fx fy cx cy: fx
first), the keys ``crossfield calibrate`` writes (``T_std``, ``M1_std``,
``M2_std`` are read as well; the reader is
:func:`crossfield.calibration.file.read_uncertainty_keys`). Without
them the stated default :data:`DEFAULT_SCALE_U` is used. The file's content is
the one the session read at its start, which a replay and an audit take from
the recording's copy (:mod:`crossfield.recording.calibration_files`), never
from the recorded path.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from crossfield.types import DEFAULT_SCALE_U  # re-exported: the default the term falls back to

__all__ = [
    "DEFAULT_SCALE_U",
    "CalibrationCovariance",
    "CalibrationUncertainty",
    "calibration_contributions",
    "calibration_covariance",
    "calibration_uncertainty",
    "point_displacements",
    "registered_displacements",
    "sqrt_columns",
]


class CalibrationUncertainty:
    """scale_u: relative standard uncertainty of camera-frame distances; source: where it came from."""

    def __init__(self, scale_u: float, source: str) -> None:
        self.scale_u = float(scale_u)
        self.source = source

    def __repr__(self) -> str:
        return f"CalibrationUncertainty(scale_u={self.scale_u!r}, source={self.source!r})"


def calibration_uncertainty(
    source: str = "", default: float = DEFAULT_SCALE_U, files: Sequence[Any] | None = None
) -> CalibrationUncertainty:
    """The relative scale uncertainty of the calibration in ``files`` (the calibration
    files' contents, :class:`crossfield.recording.calibration_files.CalibrationFile`:
    read at a live session's start, or the recorded copies in a replay; the first file
    holding a key wins), or ``default`` when they state no standard deviations. Without
    ``files`` the files ``source`` names (paths joined by ``", "``) are read now."""
    from crossfield.calibration.file import read_uncertainty_keys  # the one reader of the std_* keys
    from crossfield.recording.calibration_files import read_calibration_files

    keys: dict[str, np.ndarray] = {}
    for f in read_calibration_files(source) if files is None else files:
        for key, value in read_uncertainty_keys(f.text).items():
            keys.setdefault(key, value)
    terms = []
    if "T_std" in keys and "T" in keys:
        T = keys["T"].reshape(-1)
        norm = float(np.linalg.norm(T))
        if norm > 0:
            # u(|T|) = |T^ . u(T)| for independent components: sqrt(sum (T_i/|T| u_i)^2)
            terms.append(float(np.sqrt(np.sum((T / norm * keys["T_std"].reshape(-1)) ** 2))) / norm)
    for m, m_std in (("M1", "M1_std"), ("M2", "M2_std")):
        if m_std in keys and m in keys:
            std = keys[m_std].reshape(-1)
            f = float(keys[m].reshape(-1)[0])
            u_f = float(std[0]) if std.size else 0.0  # fx (OpenCV's stdDeviationsIntrinsics order)
            if f > 0:
                terms.append(u_f / f / math.sqrt(2.0))  # two cameras, averaged in the disparity
    if not terms:
        return CalibrationUncertainty(default, "stated default")
    return CalibrationUncertainty(math.sqrt(sum(t * t for t in terms)), "calibration file std_* keys")


# --------------------------------------------------------------------------
# The calibration's parameters propagated into the characteristics (issue 22 item 4)
# --------------------------------------------------------------------------
#
# A calibration file that states the standard deviations of every parameter
# (``std_M1 std_D1 std_M2 std_D2 std_R std_T``, ``crossfield calibrate``; since
# issue 28 each the larger of the Jacobian's and the jackknife's over views) gives
# more than a scale: an error of the rotation between the cameras (``std_R``)
# tilts the lower camera's rays and moves every triangulated point along its line
# of sight, by about ``Z^2 d(omega) / B``; the principal points and distortion move
# points sideways. The error is one draw for the session (the same calibration in
# every frame): a systematic source, not divided by sqrt(n).
#
# Per camera point X (upper frame, mm), dX/dtheta = G (3, p) is the implicit-function
# derivative of the least-squares triangulation from fixed pixels
# (``crossfield.calibration.covariance.triangulation_sensitivity``, Hartley &
# Zisserman 5.2; the same G the calibration report's predicted 3-D sigma uses).
# The registration to the controls answers the displacement of its control points:
# with their global displacements R d_k and J_k = [-[g_k - g_bar]x, I] the
# linearised rigid fit moves by xi = -(J^T J)^-1 sum_k J_k^T R d_k (equal weights,
# as the budget's registration terms), and a point's net global displacement is
# N_j = R d_j + J_j xi (a pure scale gives N_j = s (p_j - g_bar), the scale term).
# The characteristics' response to each independent column of the covariance's
# square root (Sigma = sum_l c_l c_l^T, from its eigen-decomposition) is taken by
# central differences through the session's own measurer (GUM 5.1.3, eq. (10)
# with c_i found numerically), so every kind of characteristic is propagated as
# it is measured: ``u^2 = sum_l ((y(+N c_l) - y(-N c_l)) / 2)^2``.

#: Parameter order of the std_* keys and of ``cov_params``
#: (``crossfield.calibration.covariance.camera_param_names``).
_STD_KEYS = ("std_M1", "std_D1", "std_M2", "std_D2", "std_R", "std_T")


class CalibrationCovariance:
    """The calibration's parameter covariance (p, p) in ``camera_param_names(n_dist)`` order
    (px, unitless distortion, rad, mm); n_dist: distortion terms per camera; source: where
    the standard deviations and the correlations came from."""

    def __init__(self, covariance: np.ndarray, n_dist: int, source: str) -> None:
        self.covariance = np.asarray(covariance, dtype=np.float64)
        self.n_dist = int(n_dist)
        self.source = source

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def __repr__(self) -> str:
        return f"CalibrationCovariance(p={len(self.covariance)}, n_dist={self.n_dist}, source={self.source!r})"


def calibration_covariance(source: str, files: Sequence[Any] | None = None) -> CalibrationCovariance | None:
    """The parameter covariance the calibration files state, or None when none states
    every ``std_*`` key. ``files``: the files' contents
    (:class:`crossfield.recording.calibration_files.CalibrationFile`: read at a live
    session's start, or a replay's recorded copies, never re-read by the recorded path);
    without them the files ``source`` names (paths separated by ``", "``) are read now.

    The standard deviations are the ``std_*`` keys as written (the honest ones: the
    larger of the Jacobian's and the jackknife's); the correlations those of
    ``cov_params`` when it is there with the same parameters, else none (diagonal):
    ``Sigma = D Corr D``, D = diag(std)."""
    from crossfield.calibration.covariance import camera_param_names
    from crossfield.recording.calibration_files import read_calibration_files

    for f in read_calibration_files(source) if files is None else files:
        keys = _text_keys(f.text, _STD_KEYS)
        if len(keys) != len(_STD_KEYS) or keys["std_D1"].size != keys["std_D2"].size:
            continue
        std = np.concatenate([keys[k].reshape(-1) for k in _STD_KEYS])
        n_dist = int(keys["std_D1"].size)
        names = camera_param_names(n_dist)
        if std.size != len(names) or not np.all(np.isfinite(std)) or np.any(std < 0):
            continue
        corr = np.eye(len(std))
        how = "std_* keys, no correlations"
        cov, labels = _text_keys(f.text, ("cov_params",)).get("cov_params"), _text_string(f.text, "cov_param_names")
        if cov is not None and cov.ndim == 2 and tuple(labels.split()) == names:
            s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            ok = s > 0
            corr[np.ix_(ok, ok)] = cov[np.ix_(ok, ok)] / np.outer(s[ok], s[ok])
            how = "std_* keys, correlations of cov_params"
        return CalibrationCovariance(corr * np.outer(std, std), n_dist, f"{f.path}: {how}")
    return None


def _text_keys(text: str, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The matrices ``keys`` of a calibration file's text (OpenCV FileStorage, read from
    memory: a file's content, never a path); a text OpenCV cannot parse gives ``{}``."""
    import cv2

    found: dict[str, np.ndarray] = {}
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):
        return found
    try:
        if fs.isOpened():
            for name in keys:
                node = fs.getNode(name)
                if not node.empty() and not node.isNone():
                    value = node.mat()
                    if value is not None:
                        found[name] = np.asarray(value, dtype=np.float64)
    finally:
        fs.release()
    return found


def _text_string(text: str, key: str) -> str:
    """The string ``key`` of a calibration file's text ('' when absent or unreadable)."""
    import cv2

    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):
        return ""
    try:
        node = fs.getNode(key) if fs.isOpened() else None
        return node.string() if node is not None and not node.empty() else ""
    finally:
        fs.release()


def sqrt_columns(covariance: np.ndarray) -> np.ndarray:
    """Columns c_l (p, q) with sum_l c_l c_l^T = covariance (symmetric PSD; eigen-decomposition,
    negative rounding clipped, null directions dropped)."""
    w, V = np.linalg.eigh(0.5 * (covariance + covariance.T))
    keep = w > max(float(w.max(initial=0.0)), 0.0) * 1e-14
    return V[:, keep] * np.sqrt(w[keep])


def point_displacements(
    points_upper: np.ndarray,
    calibration,
    n_dist: int,
    columns: np.ndarray,
) -> np.ndarray:
    """(N, 3, q) mm: how each triangulated point (upper frame, (N, 3) mm) moves for a
    calibration error along each column of ``columns`` (p, q); ``calibration`` the
    :class:`crossfield.types.StereoCalibration` the points were triangulated with (its
    distortion padded or cut to ``n_dist`` terms, the file's)."""
    import cv2

    from crossfield.calibration.covariance import triangulation_sensitivity

    def dist(intr) -> np.ndarray:
        d = np.zeros(n_dist)
        given = np.asarray(intr.dist_coeffs, dtype=np.float64).reshape(-1)[:n_dist]
        d[: given.size] = given
        return d

    rvec = cv2.Rodrigues(np.asarray(calibration.R_lower_upper, dtype=np.float64))[0].reshape(3)
    G, _ = triangulation_sensitivity(
        np.asarray(points_upper, dtype=np.float64).reshape(-1, 3),
        np.asarray(calibration.upper.camera_matrix, dtype=np.float64), dist(calibration.upper),
        np.asarray(calibration.lower.camera_matrix, dtype=np.float64), dist(calibration.lower),
        rvec, np.asarray(calibration.t_lower_upper, dtype=np.float64),
    )
    return np.einsum("nip,pq->niq", G, columns)


def registered_displacements(
    points_upper: np.ndarray,
    displacements: np.ndarray,
    registration,
    reference,
) -> np.ndarray:
    """(N, 3, q) mm, global frame: the displacements (N, 3, q, camera frame) of the camera
    points ``points_upper`` (N, 3) after the registration to the controls has answered
    its control points' (comment above: N_j = R d_j + J_j xi,
    xi = -(J^T J)^-1 sum_k J_k^T R d_k, J_k = [-[g_k - g_bar]x, I], g_k the CMM controls)."""
    from crossfield.covariance import registration_jacobian

    fit = registration.fit
    R = np.asarray(fit.R) * float(fit.scale)
    moved = np.einsum("ij,njq->niq", R, displacements)
    corr = registration.correspondence
    by_label = reference.by_label()
    pairs = [(cid, int(i)) for cid, i in zip(corr.control_ids, corr.camera_index) if cid in by_label]
    if len(pairs) < 3:
        return moved
    g = np.array([by_label[cid].xyz for cid, _ in pairs], dtype=np.float64)
    g_bar = g.mean(axis=0)
    J = registration_jacobian(g, g_bar)  # (K, 3, 6)
    JtJ = np.einsum("kia,kib->ab", J, J)
    Jtd = np.einsum("kia,kiq->aq", J, moved[[i for _, i in pairs]])
    xi = -np.linalg.solve(JtJ, Jtd)  # (6, q): (dtheta rad, dt mm) per column
    J_points = registration_jacobian(fit.apply(np.asarray(points_upper, dtype=np.float64)), g_bar)
    return moved + np.einsum("nia,aq->niq", J_points, xi)


def calibration_contributions(
    plan,
    reference,
    points,
    registration,
    calibration,
    stated: CalibrationCovariance,
    measurer,
) -> dict[str, float]:
    """Characteristic name -> its calibration contribution u (mm): the covariance
    ``stated`` propagated through the triangulation (G), the registration (xi) and the
    measurement of one frame (``points`` :class:`CameraPoints`, ``registration``), by
    central differences of ``measurer.measure`` along each independent column
    (comment above). A systematic source: the same for every frame of the session."""
    columns = sqrt_columns(stated.covariance)
    xyz = np.asarray(points.xyz, dtype=np.float64)
    if columns.shape[1] == 0 or len(xyz) == 0:
        return {}
    d_camera = point_displacements(xyz, calibration, stated.n_dist, columns)
    d_global = registered_displacements(xyz, d_camera, registration, reference)
    # back to the camera frame, so that the measurer's own registration maps each point
    # to its displaced global position: p_c' = p_c + (s R)^-1 N
    fit = registration.fit
    back = np.einsum("ji,njq->niq", np.asarray(fit.R), d_global) / float(fit.scale)
    sums: dict[str, float] = {}
    for col in range(columns.shape[1]):
        values = []
        for sign in (1.0, -1.0):
            moved = dataclasses.replace(points, xyz=xyz + sign * back[:, :, col])
            m = measurer.measure(plan, reference, moved, registration, None)
            values.append({c.name: c.measured_mm for c in m.characteristics})
        for name, plus in values[0].items():
            minus = values[1].get(name)
            if minus is not None and math.isfinite(plus) and math.isfinite(minus):
                sums[name] = sums.get(name, 0.0) + (0.5 * (plus - minus)) ** 2
    return {name: math.sqrt(v) for name, v in sums.items()}


def session_propagation(plan, reference, calibration, measurer, files: Sequence[Any] | None = None):
    """The session's calibration propagation, ``frame -> {name: u (mm)}``
    (:func:`calibration_contributions` on a measured :class:`FrameResult`), with the
    covariance the calibration files state (``files``, see :func:`calibration_covariance`;
    None: those of ``calibration.source``, read now); None when they state none (the
    budget then keeps the relative scale term)."""
    stated = calibration_covariance(getattr(calibration, "source", ""), files)
    if stated is None:
        return None

    def propagate(frame) -> dict[str, float]:
        return calibration_contributions(
            plan, reference, frame.points, frame.registration, calibration, stated, measurer
        )

    propagate.source = stated.source  # type: ignore[attr-defined]
    return propagate
