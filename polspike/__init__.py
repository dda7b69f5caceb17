"""polspike: shared foundation (errors, config loading, polarization physics, I/O).

The CLI lives in :mod:`polspike.cli`; it is the only module that imports every stage.
"""

from polspike.errors import (
    BackendUnavailableError,
    CheckpointError,
    ConfigError,
    DataFormatError,
    OutputError,
    PolspikeError,
    PolspikeWarning,
    SceneError,
    ShapeError,
)

__version__ = "0.1.0"

__all__ = [
    "BackendUnavailableError",
    "CheckpointError",
    "ConfigError",
    "DataFormatError",
    "OutputError",
    "PolspikeError",
    "PolspikeWarning",
    "SceneError",
    "ShapeError",
    "__version__",
]
