"""One registration from every frame of a session, for a static station, and a test that it was.

Assumption (stated in ``docs/registration.md``, "Session estimate"): the
camera rig and the part do not move relative to each other during the
session, and the controls were probed once (one CMM point per control for
the whole session). Then every frame measures the *same* camera-frame
control points, with independent image noise, and the maximum-likelihood
pose from all frames at once is the ML fit of the information-weighted
means

    p_bar_i = (sum_f C_fi^-1)^-1 sum_f C_fi^-1 p_fi,   cov(p_bar_i) = (sum_f C_fi^-1)^-1

(the camera model is linear in each frame's point, so these means are
sufficient statistics; the CMM errors are shared by all frames and enter
once, through the fit's control sigmas). The per-frame poses' average is
not this: it counts the CMM noise F times as independent.

Moved station: if the station is static, the frames' points scatter about
their means only by their stated covariances, so

    chi2 = sum_i sum_f (p_fi - p_bar_i)^T C_fi^-1 (p_fi - p_bar_i) ~ chi-square(3 sum_i (F_i - 1))

and a p-value below ``alpha`` (default 1e-3) says the camera-frame points
moved between frames (the rig or the part was knocked, a thermal drift):
then the joint estimate is not valid and the result says so. Accumulated
frame by frame: chi2 = sum_f p^T C^-1 p - p_bar^T (sum_f C^-1) p_bar, so
memory does not grow with the session.

Caveat: errors common to all frames (calibration, the eccentricity model)
do not average out; the joint covariance states only the independent part.
Units: mm; camera points in the upper camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_distribution

from crossfield.chain.weights import fit_registration
from crossfield.types import CameraPoints, Registration, RigidFit

#: default significance level of the motion test
ALPHA = 1e-3


@dataclass(frozen=True)
class SessionPose:
    """The session's joint T_global_camera and the static-station test.

    fit: the ML fit (covariance (6, 6), chi2) to the frames' mean control points.
    control_ids: the controls used, in the order of fit.residuals.
    frames: frames that contributed. motion_chi2 / motion_dof / motion_p: the
    test statistic, its degrees of freedom and p-value. moved: motion_p < alpha.
    camera_xyz, camera_cov: (M, 3) mm, (M, 3, 3) mm^2 the mean control points.
    """

    fit: RigidFit
    control_ids: tuple[str, ...]
    frames: int
    motion_chi2: float
    motion_dof: int
    motion_p: float
    moved: bool
    camera_xyz: np.ndarray
    camera_cov: np.ndarray

    def message(self) -> str:
        """One line for the log."""
        verdict = (
            "the station MOVED during the session (joint pose not valid)" if self.moved else "consistent with a static station"
        )
        return (
            f"session pose from {self.frames} frames jointly ({len(self.control_ids)} controls, {self.fit.method}): "
            f"motion test chi2 = {self.motion_chi2:.1f} for {self.motion_dof} dof, p = {self.motion_p:.3g}: {verdict}"
        )


class SessionPoseAccumulator:
    """Adds each frame's matched control points; :meth:`result` gives the :class:`SessionPose`."""

    def __init__(self) -> None:
        self._info: dict[str, np.ndarray] = {}  # id -> sum C^-1 (3, 3)
        self._vector: dict[str, np.ndarray] = {}  # id -> sum C^-1 p (3,)
        self._quadratic: dict[str, float] = {}  # id -> sum p^T C^-1 p
        self._count: dict[str, int] = {}
        self.frames = 0

    def add(self, points: CameraPoints | None, registration: Registration | None) -> None:
        """One frame's camera points and the correspondence its registration used (skipped if None)."""
        if points is None or registration is None:
            return
        index = registration.correspondence.camera_index
        xyz = points.xyz[index]
        cov = points.cov_xyz[index] if points.cov_xyz is not None else np.stack(
            [np.diag(s**2) for s in points.sigma_xyz[index]]
        ).reshape(-1, 3, 3)
        info = np.linalg.inv(cov)
        for cid, p, W in zip(registration.correspondence.control_ids, xyz, info):
            Wp = W @ p
            if cid in self._info:
                self._info[cid] += W
                self._vector[cid] += Wp
                self._quadratic[cid] += float(p @ Wp)
                self._count[cid] += 1
            else:
                self._info[cid], self._vector[cid] = W.copy(), Wp
                self._quadratic[cid], self._count[cid] = float(p @ Wp), 1
        self.frames += 1

    def result(self, control_xyz: dict[str, np.ndarray], control_sigma: dict[str, float], registrar,
               alpha: float = ALPHA) -> SessionPose | None:
        """The joint pose from the controls seen so far (None with fewer than 3).

        control_xyz / control_sigma: id -> global CMM point (3,) mm and its sigma (mm).
        registrar: a register implementation; given the mean points' covariances
        if it accepts them, with the Formula (5) weights (:func:`crossfield.chain.weights.fit_registration`).
        """
        ids = tuple(cid for cid in self._info if cid in control_xyz)
        if len(ids) < 3:
            return None
        cov = np.array([np.linalg.inv(self._info[c]) for c in ids])
        mean = np.einsum("nij,nj->ni", cov, np.array([self._vector[c] for c in ids]))
        chi2 = float(sum(self._quadratic[c] - mean[k] @ self._vector[c] for k, c in enumerate(ids)))
        dof = 3 * sum(self._count[c] - 1 for c in ids)
        p_value = float(chi2_distribution.sf(chi2, dof)) if dof > 0 else 1.0
        Q = np.array([control_xyz[c] for c in ids])
        sigma = np.array([control_sigma[c] for c in ids])
        fit = fit_registration(registrar, mean, Q, np.trace(cov, axis1=1, axis2=2) / 3, sigma, cov)
        return SessionPose(fit, ids, self.frames, chi2, dof, p_value, bool(dof > 0 and p_value < alpha), mean, cov)
