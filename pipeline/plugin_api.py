"""The public API for plugins: the one module a crossfield plugin imports.

Every name here is part of crossfield's plugin surface (docs/plugins.md, "The public
API", lists each with the module it lives in): the hook markers and the typed
``Register``, the stage protocols and the optional capabilities, the frozen stage data
types, the measurement plan, the session summary, the exceptions, and the shared
kernels the built-in plugins are made of (blob detection, the disc model, the rigid
fit, the covariance kernel, reference-element fits, CMM line formats and point files,
the report document and figures). The built-in plugins import nothing else from the
core (tests/structure/test_structure.py checks it), so what they can do a third-party
plugin can do with the same names.

Usage::

    from crossfield.plugin_api import CentroidSet, hookimpl

    @hookimpl
    def register_centroids(register):
        register("mine", MyCentroids, "my sub-pixel step")
"""

from crossfield.blas_order import dot, matmul, matmul_at, matmul_bt, quadratic, vecmat
from crossfield.camera.calibration_io import read_stereo_calibration
from crossfield.camera.pair_files import pattern_regex
from crossfield.camera.pairing import (
    ArrivalPairer,
    BlockCounter,
    GrabbedFrame,
    IncidentLog,
    LogCallable,
    pair_skew_ns,
)
from crossfield.camera.stereo_model import (
    StereoGeometry,
    centroid_sigmas,
    epipolar_candidates,
    linear_triangulation,
    paired_observations,
    point_covariance,
    refine_points,
    stereo_geometry,
    undistort,
    unique_matches,
)
from crossfield.cmm.controls import control_problems
from crossfield.cmm.formats import FORMATS, UNITS, LineFormat
from crossfield.cmm.plausible import DEFAULT_VOLUME_MM, check_volume
from crossfield.cmm.point_files import (
    LENGTH_UNITS,
    FilePoint,
    PointFileReference,
    approach_direction,
    by_name,
    by_probing_order,
    check_units,
    finite,
    in_volume,
    parse_float,
    quoted,
    resolve_units,
    text_lines,
    unit_name,
)
from crossfield.cmm.protocol import (
    READ_BYTES,
    Decoder,
    LineDecoder,
    LinkLost,
    ProbeRecord,
    Rejection,
    SerialTransport,
    Transport,
)
from crossfield.covariance import camera_covariance, registration_jacobian, skew
from crossfield.errors import (
    ConfigError,
    CorrespondenceError,
    CrossfieldError,
    MeasurementError,
    PluginError,
    RecordingError,
    ReferenceImportError,
    RegistrationError,
)
from crossfield.geometry import AxisFit, fit_reference_element, point_line_distance
from crossfield.hookspecs import Factory, Register, hookimpl
from crossfield.imaging.blobs import (
    Background,
    Blob,
    BlobDetector,
    BlobStack,
    DetectorOptions,
    sort_order,
    sort_rejected,
)
from crossfield.imaging.centroids import BlobCentroids, SubPixel
from crossfield.imaging.disc_model import PSF_ORDERS, edge_profile, fit_discs, shape_from_moments
from crossfield.imaging.eccentricity import View, centre_offsets, fit_circles, offset_covariance
from crossfield.plan import CharacteristicSpec, MeasurementPlan
from crossfield.report.document import REPORT_JSON, TEMPLATE_DIR, document_of, dumps
from crossfield.report.figures import deviation_chart, residual_chart, thumbnail_chart, trend_chart
from crossfield.report.header import session_header
from crossfield.report.pages import render_page
from crossfield.report.thumbnails import KIND_CONTROL, KIND_TARGET
from crossfield.report.vocabulary import (
    DASH,
    common_coverage_factor,
    decision_class,
    decision_text,
    expanded_cell,
    expanded_heading,
    fixed,
    rule_text,
    tolerance_text,
)
from crossfield.rigid import (
    REFLECTION_RATIO,
    check_ratio,
    check_reflection,
    kabsch,
    point_set_size,
    residual_rms,
    rigid_fit,
    validate_pairs,
    weighted_rms,
)
from crossfield.session import CharacteristicSummary, FrameResult, SessionInfo, SessionSummary
from crossfield.simulator.arm import SimulatedArm
from crossfield.simulator.scenarios import SCENARIOS, build_scene
from crossfield.stages import (
    STAGES,
    AcceptsCovariance,
    Acquisition,
    BytesSink,
    CentroidExtractor,
    DecodesLinkEvents,
    LinkEvent,
    ListsReportFiles,
    LogCallback,
    Measurer,
    RecordedAcquisition,
    ReferenceSource,
    Registrar,
    Reporter,
    ReportsIncidents,
    SerialChunk,
    ServesSimulatedArm,
    Triangulator,
    implements,
)
from crossfield.tables import report_text
from crossfield.types import (
    CAMERAS,
    DEFAULT_SCALE_U,
    CameraPoints,
    CentroidSet,
    CharacteristicResult,
    GroundTruth,
    Measurement,
    ProbedPoint,
    ReferenceData,
    Registration,
    RegistrationConsistency,
    RejectedBlob,
    RigidFit,
    StereoCalibration,
    StereoCentroids,
    StereoFrame,
)
from crossfield.uncertainty.budget import combined, merge
from crossfield.uncertainty.dof import excess_dof
from crossfield.uncertainty.eccentricity import eccentricity_sigma_mm, off_axis_rad

__all__ = [
    "AcceptsCovariance",
    "Acquisition",
    "ArrivalPairer",
    "AxisFit",
    "Background",
    "Blob",
    "BlobCentroids",
    "BlobDetector",
    "BlobStack",
    "BlockCounter",
    "BytesSink",
    "CAMERAS",
    "CameraPoints",
    "CentroidExtractor",
    "CentroidSet",
    "CharacteristicResult",
    "CharacteristicSpec",
    "CharacteristicSummary",
    "ConfigError",
    "CorrespondenceError",
    "CrossfieldError",
    "DASH",
    "DEFAULT_SCALE_U",
    "DEFAULT_VOLUME_MM",
    "Decoder",
    "DecodesLinkEvents",
    "DetectorOptions",
    "FORMATS",
    "Factory",
    "FilePoint",
    "FrameResult",
    "GrabbedFrame",
    "GroundTruth",
    "IncidentLog",
    "KIND_CONTROL",
    "KIND_TARGET",
    "LENGTH_UNITS",
    "LineDecoder",
    "LineFormat",
    "LinkEvent",
    "LinkLost",
    "ListsReportFiles",
    "LogCallable",
    "LogCallback",
    "Measurement",
    "MeasurementError",
    "MeasurementPlan",
    "Measurer",
    "PSF_ORDERS",
    "PluginError",
    "PointFileReference",
    "ProbeRecord",
    "ProbedPoint",
    "READ_BYTES",
    "REFLECTION_RATIO",
    "REPORT_JSON",
    "RecordedAcquisition",
    "RecordingError",
    "ReferenceData",
    "ReferenceImportError",
    "ReferenceSource",
    "Register",
    "Registrar",
    "Registration",
    "RegistrationConsistency",
    "RegistrationError",
    "RejectedBlob",
    "Rejection",
    "Reporter",
    "ReportsIncidents",
    "RigidFit",
    "SCENARIOS",
    "STAGES",
    "SerialChunk",
    "SerialTransport",
    "ServesSimulatedArm",
    "SessionInfo",
    "SessionSummary",
    "SimulatedArm",
    "StereoCalibration",
    "StereoCentroids",
    "StereoFrame",
    "StereoGeometry",
    "SubPixel",
    "TEMPLATE_DIR",
    "Transport",
    "Triangulator",
    "UNITS",
    "View",
    "approach_direction",
    "build_scene",
    "by_name",
    "by_probing_order",
    "camera_covariance",
    "centre_offsets",
    "centroid_sigmas",
    "check_ratio",
    "check_reflection",
    "check_units",
    "check_volume",
    "combined",
    "common_coverage_factor",
    "control_problems",
    "decision_class",
    "decision_text",
    "deviation_chart",
    "document_of",
    "dot",
    "dumps",
    "eccentricity_sigma_mm",
    "edge_profile",
    "epipolar_candidates",
    "excess_dof",
    "expanded_cell",
    "expanded_heading",
    "finite",
    "fit_circles",
    "fit_discs",
    "fit_reference_element",
    "fixed",
    "hookimpl",
    "implements",
    "in_volume",
    "kabsch",
    "linear_triangulation",
    "matmul",
    "matmul_at",
    "matmul_bt",
    "merge",
    "off_axis_rad",
    "offset_covariance",
    "pair_skew_ns",
    "paired_observations",
    "parse_float",
    "pattern_regex",
    "point_covariance",
    "point_line_distance",
    "point_set_size",
    "quadratic",
    "quoted",
    "read_stereo_calibration",
    "refine_points",
    "registration_jacobian",
    "render_page",
    "report_text",
    "residual_chart",
    "residual_rms",
    "resolve_units",
    "rigid_fit",
    "rule_text",
    "session_header",
    "shape_from_moments",
    "skew",
    "sort_order",
    "sort_rejected",
    "stereo_geometry",
    "text_lines",
    "thumbnail_chart",
    "tolerance_text",
    "trend_chart",
    "undistort",
    "unique_matches",
    "unit_name",
    "validate_pairs",
    "vecmat",
    "weighted_rms",
]
