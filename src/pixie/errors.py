"""Exceptions with messages that name the problem and the input that caused it."""


class PixieError(Exception):
    """Base class of every error pixie raises on purpose."""


class MeshError(PixieError):
    """The mesh is missing, unreadable, empty, degenerate or in implausible units."""


class CameraError(PixieError):
    """Intrinsics or a pose are invalid (zero focal length, principal point off the image, non-rigid)."""


class ImageError(PixieError):
    """An image is missing, unreadable, of the wrong shape, or a crop of it is empty."""


class ReferenceSetError(PixieError):
    """A reference set is missing, corrupt, of another format version, or built from another mesh."""


class WeightsError(PixieError):
    """Matcher weights could not be found or loaded; the message lists where pixie looked."""


class DatasetError(PixieError):
    """A dataset folder or a results file does not follow the BOP format."""


class ConfigError(PixieError):
    """A configuration key or value is unknown or invalid."""


class OutputError(PixieError):
    """An output path cannot be used: it is a folder, not a regular file, not writable, or already exists."""


class UsageError(PixieError):
    """A command-line argument is malformed (not a number, wrong count, out of range)."""


class EstimateError(DatasetError, ValueError):
    """A pose estimate given to the evaluation is not a pose: R not a rotation, NaN/inf values (also a ValueError)."""
