"""generator: radiance behind a glass pane as Stokes images over time (analytic, Mitsuba maps and full tiers).

Second floor: imports :mod:`polinfra` and :mod:`polphysics` only. Scene TOML -> render
directory (Stokes keyframes, ground-truth layers, zeta maps); see generator/README.md if present.
"""
