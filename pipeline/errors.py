"""Exceptions with messages that name the file, line, key or message at fault."""

__all__ = [
    "ConfigError",
    "CorrespondenceError",
    "CrossfieldError",
    "MeasurementError",
    "PluginError",
    "RecordingError",
    "ReferenceImportError",
    "RegistrationError",
]


class CrossfieldError(Exception):
    """Base class: an error the user can act on (shown without a traceback)."""


class ConfigError(CrossfieldError):
    """A config or plan file is malformed; the message names file and key."""


class PluginError(CrossfieldError):
    """Unknown or duplicate implementation name, or a bad plugin."""


class RegistrationError(CrossfieldError):
    """The registration cannot be trusted (reflection, too few points...)."""


class CorrespondenceError(CrossfieldError):
    """Camera points could not be matched to the CMM control points."""


class ReferenceImportError(CrossfieldError):
    """The CMM data could not be read at all."""


class RecordingError(CrossfieldError):
    """A recording is unreadable, not crossfield's, or damaged."""


class MeasurementError(CrossfieldError):
    """A characteristic cannot be evaluated (e.g. a reference line the probes do not determine)."""
