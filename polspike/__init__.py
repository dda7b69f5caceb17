"""polspike: the application on the top floor: the CLI, its commands, the dataset pipeline, benches, the demo.

Layers, bottom to top (pinned by tests/test_import_graph.py):
:mod:`polinfra` and :mod:`polphysics` (foundation) -> :mod:`generator`, :mod:`spike_sim`
-> :mod:`reconstruct` -> :mod:`polspike` (may import every stage). The errors are
re-exported here for users of the application.
"""

from polinfra.errors import (
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
