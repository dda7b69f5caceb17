"""polinfra: project infrastructure at the bottom floor: errors, typed TOML config, atomic/EXR I/O, progress, plots.

Imports nothing else of the project (a test reads the imports with ast). Modules:
:mod:`.errors` (the one exception hierarchy; the CLI maps it to exit 2),
:mod:`.config` (strict typed dataclass loading of TOML/dicts), :mod:`.atomic`
(temp-file-and-rename writers), :mod:`.exr` (multi-channel float EXR),
:mod:`.progress` (a rich progress bar behind a plain callback), :mod:`.plotting`
(atomic PNG saving, labelled image grids).
"""
