"""Cramér-Rao bounds of the measuring chain (``docs/precision.md``).

* :func:`centroid_crb`, :func:`edge_limited_bound`: a target centroid (px);
* :func:`camera_point_covariance`, :func:`project_stereo`: a triangulated camera point (mm);
* :func:`registration_crb`, :func:`registration_covariance`, :func:`fitzpatrick_tre`,
  :func:`fitzpatrick_covariance`: the rigid registration (6 x 6, rad and mm);
* :func:`chain_bound`: all of them for a station's points, and the target points in the global frame;
* :func:`triangulate_batch`: the batched triangulation kernel of the Monte Carlo routes, and
  :func:`linearised_triangulation`: that estimator linearised about one set of image points.

The perspective bias of a circle's blob centre is :mod:`crossfield.imaging.eccentricity`'s.
"""

from crossfield.precision.centroid import CentroidBound, NoiseModel, centroid_crb, edge_limited_bound
from crossfield.precision.chain import ChainBound, centroid_sigmas, chain_bound, image_radius_px
from crossfield.precision.registration import (
    fitzpatrick_covariance,
    fitzpatrick_tre,
    global_point_covariance,
    point_jacobian,
    registration_covariance,
    registration_crb,
)
from crossfield.precision.stereo import (
    LinearTriangulation,
    camera_point_covariance,
    linearised_triangulation,
    project_stereo,
    triangulate_batch,
)

__all__ = [
    "CentroidBound", "ChainBound", "LinearTriangulation", "NoiseModel", "camera_point_covariance",
    "centroid_crb", "centroid_sigmas", "chain_bound", "edge_limited_bound", "fitzpatrick_covariance",
    "fitzpatrick_tre", "global_point_covariance", "image_radius_px", "linearised_triangulation",
    "point_jacobian", "project_stereo", "registration_covariance", "registration_crb", "triangulate_batch",
]
