"""triangulate "epipolar": epipolar matching, linear triangulation, reprojection-error refinement.

Method (``docs/triangulation.md``):

1. Undistort both centroid sets (``cv2.undistortPoints``, tight iteration criteria).
2. Match under the epipolar constraint ``q_lower^T F q_upper = 0`` with
   ``F = K_lower^-T [t]x R K_upper^-1`` (Hartley & Zisserman 9.2, 9.6). A pair
   is a *candidate* when the lower point lies within a threshold (pixels) of
   the upper point's epipolar line and the pair triangulates to a depth inside
   the working range [z_min_mm, z_max_mm] (and in front of the lower camera).
   A pair is accepted only when each of its two centroids has exactly one
   candidate; every other centroid is rejected with a reason (no match,
   ambiguous). Nothing is guessed.
3. Triangulate each accepted pair by the linear method (H&Z 12.2, inhomogeneous form)
   in normalised coordinates, then refine by Gauss-Newton on the weighted
   reprojection error in both (distorted) images, i.e. the maximum-likelihood
   point for Gaussian centroid errors (H&Z 12.3, with OpenCV's lens model).
4. Propagate the centroid uncertainties to first order:
   ``cov(X) = (J^T W J)^-1`` with ``J`` the 4x3 Jacobian of the two
   projections and ``W = diag(1 / sigma_uv^2)`` (H&Z 5.2.2, backward
   propagation of covariance for an ML estimate).
5. When both centroid sets carry their fitted edge conics (``ellipse``, e.g.
   centroid "modelfit") and ``eccentricity`` is on: fit each target's 3-D
   circle to its two conics, take the perspective eccentricity (the offset of
   the blob centre from the image of the circle centre) off both centroids,
   re-triangulate (twice, as the offset depends on the point), and add the
   offsets' covariance, propagated through the triangulation
   ``G = (J^T W J)^-1 J^T W``, to cov(X) (:mod:`crossfield.imaging.eccentricity`).

The camera model, the undistortion, the epipolar distances, the linear
triangulation, the Gauss-Newton refinement and the covariance are the core's
(:mod:`crossfield.camera.stereo_model`, compiled kernels).

Units: pixels in the images (OpenCV convention), mm in the upper camera frame.
"""

from __future__ import annotations

import math

import numpy as np

from crossfield.plugin_api import (
    CameraPoints,
    StereoCalibration,
    StereoCentroids,
    StereoGeometry,
    View,
    centre_offsets,
    centroid_sigmas,
    epipolar_candidates,
    fit_circles,
    hookimpl,
    offset_covariance,
    paired_observations,
    point_covariance,
    refine_points,
    stereo_geometry,
    undistort,
    unique_matches,
)


def _names(camera: str, indices) -> str:
    return ", ".join(f"{camera}[{int(k)}]" for k in indices)


# --------------------------------------------------------------------------------------------------
# The implementation
# --------------------------------------------------------------------------------------------------


class EpipolarTriangulator:
    """Epipolar matching with ambiguity rejection, DLT + Gauss-Newton triangulation.

    Options (pixels / mm):

    max_epipolar_px: fixed limit on the lower point's distance to the upper
        point's epipolar line (undistorted lower image, px); 0 = derive it per
        pair as ``epipolar_k * sqrt(sigma_line^2 + calibration_px^2)``, where
        sigma_line is the standard deviation of that distance propagated from
        both centroids' sigma_uv.
    epipolar_k: coverage factor of the derived limit.
    calibration_px: standard uncertainty (px) of the epipolar geometry itself
        (calibration error), added to the derived limit.
    z_min_mm, z_max_mm: working range of depth (upper camera z, mm); pairs
        that triangulate outside it are not candidates.
    refine: Gauss-Newton refinement of the reprojection error (else linear only).
    max_iterations: Gauss-Newton iteration limit.
    default_sigma_px: used where a centroid carries no valid sigma_uv.
    eccentricity: correct the perspective eccentricity of circular targets
        where the centroids carry fitted conics (step 5); no effect otherwise.
    """

    def __init__(
        self,
        *,
        max_epipolar_px: float = 0.0,
        epipolar_k: float = 5.0,
        calibration_px: float = 0.1,
        z_min_mm: float = 100.0,
        z_max_mm: float = 2000.0,
        refine: bool = True,
        max_iterations: int = 10,
        default_sigma_px: float = 0.05,
        eccentricity: bool = True,
    ):
        def number(name: str, value, minimum: float = 0.0, strict: bool = False) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
                raise ValueError(f"option {name!r} must be a number, got {value!r}")
            if value < minimum or (strict and value == minimum):
                relation = ">" if strict else ">="
                raise ValueError(f"option {name!r} must be {relation} {minimum}, got {value!r}")
            return float(value)

        self.max_epipolar_px = number("max_epipolar_px", max_epipolar_px)
        self.epipolar_k = number("epipolar_k", epipolar_k, strict=True)
        self.calibration_px = number("calibration_px", calibration_px)
        self.z_min_mm = number("z_min_mm", z_min_mm)
        self.z_max_mm = number("z_max_mm", z_max_mm)
        if not self.z_max_mm > self.z_min_mm:
            raise ValueError(f"option 'z_max_mm' ({z_max_mm}) must be greater than 'z_min_mm' ({z_min_mm})")
        if not isinstance(refine, bool):
            raise ValueError(f"option 'refine' must be true or false, got {refine!r}")
        self.refine = refine
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
            raise ValueError(f"option 'max_iterations' must be an integer >= 1, got {max_iterations!r}")
        self.max_iterations = max_iterations
        self.default_sigma_px = number("default_sigma_px", default_sigma_px, strict=True)
        if not isinstance(eccentricity, bool):
            raise ValueError(f"option 'eccentricity' must be true or false, got {eccentricity!r}")
        self.eccentricity = eccentricity
        self._cached_calibration: StereoCalibration | None = None
        self._cached_geometry: StereoGeometry | None = None
        self._cached_views: tuple[View, View] | None = None

    def _geometry(self, calibration: StereoCalibration) -> StereoGeometry:
        # Cache keyed on the calibration object's identity (holding a reference, so the id cannot be reused).
        if calibration is not self._cached_calibration:
            self._cached_geometry = stereo_geometry(calibration)
            self._cached_calibration = calibration
            self._cached_views = None
        return self._cached_geometry

    def _views(self, geometry: StereoGeometry) -> tuple[View, View]:
        """The eccentricity module's (upper, lower) :class:`View` of the cached geometry, made once
        per calibration (the same objects every frame: the module caches its lens arrays by identity)."""
        if self._cached_views is None:
            self._cached_views = tuple(View(c.K, c.dist, c.R, c.t) for c in (geometry.upper, geometry.lower))
        return self._cached_views

    def triangulate(self, centroids: StereoCentroids, calibration: StereoCalibration) -> CameraPoints:
        """Match and triangulate one stereo pair's centroids.

        Returns points in the upper camera frame (mm) with sigma_xyz (mm),
        reprojection residual (px) and the indices into both CentroidSets;
        every centroid not triangulated is listed in ``rejected`` with its reason.
        """
        geometry = self._geometry(calibration)
        upper, lower = centroids.upper, centroids.lower
        sigma_u = centroid_sigmas(upper.sigma_uv, self.default_sigma_px)
        sigma_l = centroid_sigmas(lower.sigma_uv, self.default_sigma_px)
        xn_u = undistort(upper.uv, geometry.upper)
        xn_l = undistort(lower.uv, geometry.lower)

        # Epipolar distances on undistorted pixels (H&Z 9.2), each pair's limit from both centroids'
        # sigmas (Sampson, H&Z 4.2.6), and working-range pruning: the pairs on the line are
        # triangulated and kept when in range. All (N, M); X_pairs (N, M, 3) mm, nan off the line.
        distance, limit, X_pairs, candidate = epipolar_candidates(
            xn_u, xn_l, sigma_u, sigma_l, geometry, max_epipolar_px=self.max_epipolar_px,
            epipolar_k=self.epipolar_k, calibration_px=self.calibration_px,
            z_min_mm=self.z_min_mm, z_max_mm=self.z_max_mm,
        )
        # Accepted: the pairs whose two centroids have exactly one candidate each (sorted by upper index).
        n_upper, n_lower, ai, aj = unique_matches(candidate)
        rejected = self._reasons(candidate, n_upper, n_lower, distance, limit, X_pairs[:, :, 2], len(ai))

        # Initial points from the linear triangulation already done for the candidates; the
        # observations [u_upper, v_upper, u_lower, v_lower] (K, 4) px and their weights 1 / sigma^2.
        X, uv_obs, weights = paired_observations(ai, aj, upper.uv, lower.uv, sigma_u, sigma_l, X_pairs)
        X, residual, J, information = self._refine(X, uv_obs, weights, geometry)
        offset_cov = None
        if self.eccentricity and len(X) and upper.ellipse is not None and lower.ellipse is not None:
            X, residual, J, information, offset_cov = self._eccentricity(
                X, uv_obs, weights, geometry, calibration, upper, lower, ai, aj
            )

        # First-order propagation: cov(X) = (J^T W J)^-1 (ML estimate, H&Z 5.2.2), plus the
        # eccentricity offsets' own uncertainty G C G^T, G = (J^T W J)^-1 J^T W (3 x 4).
        if information is None:
            information = np.matmul(np.swapaxes(J, 1, 2) * weights[:, None, :], J)
        covariance, sigma_xyz = point_covariance(information, J, weights, offset_cov)
        squared = residual * residual
        residual_px = np.sqrt(0.5 * squared.sum(axis=1))
        chi2 = (weights * squared).sum(axis=1)  # 4 coordinates - 3 unknowns: 1 dof (H&Z 4.2.6)
        return CameraPoints(
            sequence=centroids.sequence,
            xyz=X,
            sigma_xyz=sigma_xyz,
            upper_index=ai,
            lower_index=aj,
            residual_px=residual_px,
            rejected=tuple(rejected),
            method="epipolar",
            cov_xyz=covariance,
            chi2=chi2,
        )

    # ---- eccentricity ----------------------------------------------------------------------------

    def _eccentricity(self, X, uv_obs, weights, geometry, calibration, upper, lower, ai, aj):
        """Step 5: fit the circles, take the eccentricity off the centroids, re-triangulate.

        Returns X, residual, J, information as :meth:`_refine` does, and the (K, 4, 4) px^2
        covariance of the offsets taken off [u_upper, v_upper, u_lower, v_lower].
        """
        views = self._views(geometry)
        ellipses = (upper.ellipse[ai], lower.ellipse[aj])
        covs = (
            upper.ellipse_cov[ai] if upper.ellipse_cov is not None else None,
            lower.ellipse_cov[aj] if lower.ellipse_cov is not None else None,
        )
        try:
            circles = fit_circles(X, views, ellipses, covs)
        except np.linalg.LinAlgError:  # degenerate conics (not from a disc fit): leave the points as they are
            return (*self._refine(X, uv_obs, weights, geometry), None)
        result = (X,)
        for _ in range(2):  # the offsets depend (weakly) on the point: one update suffices
            offsets = centre_offsets(result[0], circles.normal, circles.radius_mm, views)
            bad = ~np.isfinite(offsets).all(axis=1)
            offsets[bad] = 0.0  # a circle that could not be fitted: no correction for that target
            result = self._refine(X, uv_obs - offsets, weights, geometry)
        offset_cov = offset_covariance(result[0], circles, views)
        offset_cov[bad | ~np.isfinite(offset_cov).all(axis=(1, 2))] = 0.0
        return (*result, offset_cov)

    # ---- refinement ----------------------------------------------------------------------------

    def _refine(self, X: np.ndarray, uv_obs: np.ndarray, weights: np.ndarray, geometry: StereoGeometry):
        """Gauss-Newton with this triangulator's options (:func:`~crossfield.camera.stereo_model.refine_points`)."""
        return refine_points(X, uv_obs, weights, geometry, max_iterations=self.max_iterations, refine=self.refine)

    # ---- reasons -------------------------------------------------------------------------------

    def _reasons(self, candidate, n_upper, n_lower, distance, limit, z_upper, n_accepted: int) -> list[str]:
        n, m = candidate.shape
        if n == m == n_accepted:
            return []  # a one-to-one match: every centroid accepted
        z_range = f"{self.z_min_mm:g}..{self.z_max_mm:g} mm"
        out_of_range: dict[tuple[str, int], tuple[int, float]] = {}
        pi, pj = np.nonzero((distance <= limit) & ~candidate)  # on the line, out of range (row-major)
        for i, j, z in zip(pi.tolist(), pj.tolist(), z_upper[pi, pj].tolist()):
            out_of_range.setdefault(("upper", i), (j, z))
            out_of_range.setdefault(("lower", j), (i, z))
        reasons: list[str] = []
        for camera, other, count, other_count, table in (
            ("upper", "lower", n_upper, n_lower, candidate),
            ("lower", "upper", n_lower, n_upper, candidate.T),
        ):
            accepted = (count == 1) & (table @ (other_count == 1))
            for k in np.nonzero(~accepted)[0]:
                partners = np.nonzero(table[k])[0]
                if count[k] == 1:
                    (p,) = partners
                    rivals = np.nonzero(table[:, p])[0]
                    rivals = rivals[rivals != k]
                    reasons.append(
                        f"{camera}[{k}]: ambiguous (its candidate {other}[{p}] is also a candidate of "
                        f"{_names(camera, rivals)})"
                    )
                elif count[k] >= 2:
                    reasons.append(
                        f"{camera}[{k}]: ambiguous ({count[k]} candidates: {_names(other, partners)})"
                    )
                elif (camera, k) in out_of_range:
                    p, z = out_of_range[(camera, k)]
                    reasons.append(
                        f"{camera}[{k}]: no match ({other}[{p}] is on its epipolar line but triangulates to "
                        f"z = {z:.1f} mm, outside {z_range})"
                    )
                elif (m if camera == "upper" else n) == 0:
                    reasons.append(f"{camera}[{k}]: no match (no {other} centroids)")
                else:
                    d = distance[k] if camera == "upper" else distance[:, k]
                    lim = limit[k] if camera == "upper" else limit[:, k]
                    nearest = int(np.argmin(d))
                    reasons.append(
                        f"{camera}[{k}]: no match (nearest: {other}[{nearest}] at {d[nearest]:.2f} px from "
                        f"the epipolar line, limit {lim[nearest]:.2f} px)"
                    )
        return reasons


@hookimpl
def register_triangulates(register) -> None:
    register(
        "epipolar",
        EpipolarTriangulator,
        "Epipolar matching (ambiguities rejected), linear + Gauss-Newton triangulation, first-order sigma",
    )
