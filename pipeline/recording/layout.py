"""The layout of a crossfield session recording: every name, defined once.

Every topic, JSON schema name, metadata record name, channel metadata key
and attachment name of ``session.mcap`` (``docs/recording.md``) is defined
here and imported everywhere else; no other module of ``crossfield`` or
``crossfield.plugins`` spells a topic (``tests/recording/test_recording.py`` walks
the sources and fails on one).

Units of the recorded data: the JSON messages carry mm, rad and px; the
Foxglove geometry messages (``foxglove.PointCloud``,
``foxglove.FrameTransforms``) carry metres (the Foxglove convention).
"""

from __future__ import annotations

from collections.abc import Sequence

from crossfield.types import CAMERAS

#: Identifies this layout; written into the ``crossfield.session`` metadata.
RECORDING_FORMAT = "crossfield-mcap/1"
#: The recording layouts this crossfield reads (replay, audit, view).
READABLE_FORMATS = ("crossfield-mcap/1",)

# ---- topics ---------------------------------------------------------------

_TOPIC_IMAGE = "/camera/{camera}/image"
_TOPIC_CALIBRATION = "/camera/{camera}/calibration"
_TOPIC_CENTROIDS = "/centroids/{camera}"
#: foxglove.ImageAnnotations of each camera: centroids and rejected blobs (crossfield.recording.foxglove_overlay).
_TOPIC_ANNOTATIONS = "/camera/{camera}/annotations"

TOPIC_TF = "/tf"
TOPIC_POINTS_CAMERA = "/points/camera"
TOPIC_POINTS_REFERENCE = "/points/reference"
TOPIC_POINTS_GLOBAL = "/points/global"
#: Suffix of the JSON twin of each point cloud topic (ids and uncertainties, mm).
JSON_TWIN = "/json"
TOPIC_POINTS_CAMERA_JSON = TOPIC_POINTS_CAMERA + JSON_TWIN
TOPIC_POINTS_REFERENCE_JSON = TOPIC_POINTS_REFERENCE + JSON_TWIN
TOPIC_POINTS_GLOBAL_JSON = TOPIC_POINTS_GLOBAL + JSON_TWIN
#: The exact bytes read from the CMM line, before any parsing.
TOPIC_CMM_RAW = "/cmm/raw"
TOPIC_REGISTRATION = "/registration"
TOPIC_MEASUREMENT = "/measurement"
TOPIC_REFERENCE = "/reference"
TOPIC_FRAMES = "/frames"
TOPIC_REPORT = "/report"
TOPIC_LOG = "/log"
#: foxglove.SceneUpdate: CMM points, reference lines, targets, characteristics (crossfield.recording.foxglove_overlay).
TOPIC_SCENE = "/scene"
#: The integrity chain's records (:mod:`crossfield.recording.integrity`).
TOPIC_INTEGRITY = "/integrity"
#: Why a session stopped taking input before its end (SIGINT, a source error): at most
#: one message, a raw input (replay reads it and stops where the live run stopped).
TOPIC_SESSION_STOP = "/session/stop"

# ---- a calibration session (crossfield calibrate --record; docs/calibration.md) ----

#: Raw board views, one per camera and view (foxglove.RawImage, lossless).
TOPIC_CALIBRATION_IMAGE = "/calibration/{camera}/image"
#: The board detections of each view (JSON).
TOPIC_CALIBRATION_DETECTIONS = "/calibration/detections"
#: The solved calibration and its report (JSON).
TOPIC_CALIBRATION_RESULT = "/calibration/result"
CALIBRATION_METADATA = "crossfield.calibration"
CALIBRATION_ATTACHMENT = "calibration.yml"
CALIBRATION_PROFILE = "crossfield-calibration"

# ---- a verification session (crossfield verify --record; docs/calibration.md) ----

#: Raw scale-bar pairs, one per camera and pair (foxglove.RawImage, lossless);
#: sequence: the pair's index over all positions.
TOPIC_VERIFICATION_IMAGE = "/verification/{camera}/image"
#: Per bar position its lengths and E (JSON, sequence: the position's index).
TOPIC_VERIFICATION_POSITION = "/verification/position"
#: The verification result (JSON, ``VerificationResult.to_dict``).
TOPIC_VERIFICATION_RESULT = "/verification/result"
VERIFICATION_METADATA = "crossfield.verification.procedure"
VERIFICATION_PROFILE = "crossfield-verification"


def image_topic(camera: str) -> str:
    """``/camera/<camera>/image`` (foxglove.RawImage)."""
    return _TOPIC_IMAGE.format(camera=camera)


def calibration_topic(camera: str) -> str:
    """``/camera/<camera>/calibration`` (foxglove.CameraCalibration)."""
    return _TOPIC_CALIBRATION.format(camera=camera)


def centroids_topic(camera: str) -> str:
    """``/centroids/<camera>`` (crossfield.CentroidSet)."""
    return _TOPIC_CENTROIDS.format(camera=camera)


def annotations_topic(camera: str) -> str:
    """``/camera/<camera>/annotations`` (foxglove.ImageAnnotations)."""
    return _TOPIC_ANNOTATIONS.format(camera=camera)


#: The raw image topics, one per camera, in :data:`crossfield.types.CAMERAS` order.
IMAGE_TOPICS = tuple(image_topic(camera) for camera in CAMERAS)
#: The centroid topics, one per camera.
CENTROID_TOPICS = tuple(centroids_topic(camera) for camera in CAMERAS)
#: topic -> camera, for the per-camera topics.
CAMERA_OF_TOPIC = {
    **{image_topic(c): c for c in CAMERAS},
    **{calibration_topic(c): c for c in CAMERAS},
    **{centroids_topic(c): c for c in CAMERAS},
    **{annotations_topic(c): c for c in CAMERAS},
}

#: Raw inputs: what a replay reads (and so does not reproduce), plus the chain.
RAW_TOPICS = frozenset({*IMAGE_TOPICS, TOPIC_CMM_RAW, TOPIC_INTEGRITY, TOPIC_SESSION_STOP})

#: Coordinate frame id of the global (CMM) frame (foxglove ``frame_id``).
FRAME_GLOBAL = "global"
#: Coordinate frame id of the camera frame (the upper camera's).
FRAME_CAMERA = "upper"

# ---- channels -------------------------------------------------------------

#: Message encoding of ``/cmm/raw`` (schema-less: the bytes as read).
RAW_ENCODING = "application/octet-stream"
#: Channel metadata key of the image topics: the sensor's bit depth.
CHANNEL_BIT_DEPTH = "bit_depth"
#: Channel metadata key of ``/cmm/raw``: the port / source the bytes came from.
CHANNEL_SOURCE = "source"
#: Channel metadata key of ``/cmm/raw``: what the channel holds; :data:`LINK_EVENTS`
#: marks the channel of the line's link events (absent: the bytes as read).
CHANNEL_CONTENT = "content"
#: ``content`` of the ``/cmm/raw`` channel that holds the line's link events
#: (UTF-8 JSON ``{"event": "down"|"up", "detail": ...}``), in file order with the bytes.
LINK_EVENTS = "link-events"

# ---- JSON schemas -----------------------------------------------------------

SCHEMA_CENTROIDS = "crossfield.CentroidSet"
SCHEMA_CAMERA_POINTS = "crossfield.CameraPoints"
SCHEMA_REFERENCE_POINTS = "crossfield.ReferencePoints"
SCHEMA_GLOBAL_POINTS = "crossfield.GlobalPoints"
SCHEMA_REGISTRATION = "crossfield.Registration"
SCHEMA_MEASUREMENT = "crossfield.Measurement"
SCHEMA_REFERENCE = "crossfield.ReferenceData"
SCHEMA_FRAME_STATUS = "crossfield.FrameStatus"
SCHEMA_REPORT = "crossfield.Report"
SCHEMA_INTEGRITY = "crossfield.Integrity"
SCHEMA_SESSION_STOP = "crossfield.SessionStop"

#: JSON schema name -> file in ``pipeline/recording/schemas``.
JSON_SCHEMAS: dict[str, str] = {
    SCHEMA_CENTROIDS: "centroids.schema.json",
    SCHEMA_CAMERA_POINTS: "camera_points.schema.json",
    SCHEMA_REFERENCE_POINTS: "reference_points.schema.json",
    SCHEMA_GLOBAL_POINTS: "global_points.schema.json",
    SCHEMA_REGISTRATION: "registration.schema.json",
    SCHEMA_MEASUREMENT: "measurement.schema.json",
    SCHEMA_REFERENCE: "reference.schema.json",
    SCHEMA_FRAME_STATUS: "frame_status.schema.json",
    SCHEMA_REPORT: "report.schema.json",
    SCHEMA_INTEGRITY: "integrity.schema.json",
    SCHEMA_SESSION_STOP: "session_stop.schema.json",
}

# ---- metadata records and attachments ------------------------------------------

META_SESSION = "crossfield.session"
META_CONFIG = "crossfield.config"
META_PLUGINS = "crossfield.plugins"
META_PACKAGES = "crossfield.packages"
META_ACQUISITION = "crossfield.acquisition"
META_MACHINE = "crossfield.machine"
META_RESULT = "crossfield.result"
#: The metadata records a replay needs (besides :data:`META_SESSION`).
REQUIRED_METADATA = (META_CONFIG, META_PLUGINS, META_PACKAGES, META_ACQUISITION)
#: Every metadata record a complete session writes, in write order.
METADATA_RECORDS = (
    META_SESSION,
    META_CONFIG,
    META_PLUGINS,
    META_PACKAGES,
    META_ACQUISITION,
    META_MACHINE,
    META_RESULT,
)
#: Key of a metadata record holding its exact JSON document.
META_JSON = "json"

ATTACHMENT_PLAN = "plan.toml"
ATTACHMENT_CALIBRATION = "calibration.yml"
ATTACHMENT_GROUND_TRUTH = "simulator_ground_truth.json"
#: The attachments a replay needs.
REQUIRED_ATTACHMENTS = (ATTACHMENT_PLAN, ATTACHMENT_CALIBRATION)


def recorded_topics(cameras: Sequence[str] = CAMERAS) -> list[str]:
    """Every topic a complete session writes (``/cmm/raw`` only if bytes were read)."""
    topics = []
    for camera in cameras:
        topics += [image_topic(camera), calibration_topic(camera), centroids_topic(camera)]
        topics += [annotations_topic(camera)]
    topics += [TOPIC_SCENE, TOPIC_TF, TOPIC_LOG, TOPIC_CMM_RAW, TOPIC_REFERENCE, TOPIC_REGISTRATION, TOPIC_MEASUREMENT]
    topics += [TOPIC_FRAMES, TOPIC_REPORT, TOPIC_INTEGRITY]
    for cloud in (TOPIC_POINTS_CAMERA, TOPIC_POINTS_REFERENCE, TOPIC_POINTS_GLOBAL):
        topics += [cloud, cloud + JSON_TWIN]
    return topics
