"""One exception family: every message says what was wrong and how to fix it."""


class NeuralsurfError(Exception):
    """Base class of every error neuralsurf raises on purpose."""


class InputError(NeuralsurfError, ValueError):
    """Data handed to neuralsurf is malformed (shape, dtype, NaN, empty, units)."""


class FileFormatError(InputError):
    """A file is missing, unreadable or has an extension neuralsurf cannot handle."""


class DownloadError(NeuralsurfError, OSError):
    """A data set could not be downloaded, or what arrived does not match its checksum."""


class ConfigError(NeuralsurfError, ValueError):
    """A configuration value is unknown or out of range."""


class DeviceError(NeuralsurfError, RuntimeError):
    """The requested compute device is not available."""


class MissingDependencyError(NeuralsurfError, ImportError):
    """An optional dependency is needed; the message names the extra to install."""


class ExtractionError(NeuralsurfError, RuntimeError):
    """A field has no zero level set inside the extraction box."""


class CheckpointError(NeuralsurfError):
    """A checkpoint cannot be read, does not match, or holds something other than neuralsurf's plain data."""
