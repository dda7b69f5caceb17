"""polphysics: the polarization physics of a glass pane and a rotating polarizer (pure numpy, no Mitsuba).

Bottom floor beside :mod:`polinfra` (the only project package it imports).

Modules: :mod:`.fresnel` (interface and pane coefficients), :mod:`.geometry`
(pinhole camera, pane plane, per-pixel theta and phi_perp), :mod:`.zeta`
(paper Eq. (1)-(2) and their Stokes form), :mod:`.stokes` (polarizer, DoP,
AoLP), :mod:`.polarizer` (the rotating polarizer phi(t) and its step integral).
"""
