"""The one exception hierarchy of polspike.

Every error a user can cause raises a subclass of :class:`PolspikeError` whose
message is one line that says what was wrong, the value seen and what to change.
The library raises; only the CLI turns these into exit code 2.  Each class also
inherits the matching builtin so code that catches ``ValueError`` keeps working.
"""

from __future__ import annotations

__all__ = [
    "PolspikeError",
    "ConfigError",
    "SceneError",
    "ShapeError",
    "DataFormatError",
    "BackendUnavailableError",
    "CheckpointError",
    "OutputError",
    "PolspikeWarning",
]


class PolspikeError(Exception):
    """Base class of every error polspike raises on bad input or environment."""


class ConfigError(PolspikeError, ValueError):
    """A configuration file or value is malformed, unknown or out of range."""


class SceneError(ConfigError):
    """A scene is well-formed but physically or geometrically unusable."""


class ShapeError(PolspikeError, ValueError):
    """An array has the wrong shape.

    Attributes:
        actual_shape: the shape seen.
        expected_shape: a description of the shape wanted, e.g. ``"(T, H, W)"``.
    """

    def __init__(self, message: str, actual_shape: tuple | None = None, expected_shape: object = None):
        super().__init__(message)
        self.actual_shape = actual_shape
        self.expected_shape = expected_shape


class DataFormatError(PolspikeError, ValueError):
    """A data file is malformed (e.g. a .dat size that is not a whole number of frames)."""


class BackendUnavailableError(PolspikeError, RuntimeError):
    """A requested compute backend (Mitsuba variant, CUDA, LLVM) is not available."""


class CheckpointError(PolspikeError, ValueError):
    """A model checkpoint is missing, corrupt or incompatible."""


class OutputError(PolspikeError, OSError):
    """An output location cannot be written (permissions, full disk)."""


class PolspikeWarning(UserWarning):
    """Physically suspicious but allowed (e.g. a simulated ISI CV far above real cameras)."""
