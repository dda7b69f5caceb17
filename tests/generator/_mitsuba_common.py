"""Helpers shared by the Mitsuba tests: skip logic and small scenes (80x50 pixels)."""

from __future__ import annotations

import os

import pytest

from polinfra.config import to_dict


def require_mitsuba(backend: str = "llvm"):
    """Set a working polarized mono variant and return mitsuba.

    Skips only when the ``mitsuba`` package itself is not importable (not
    installed).  A broken install, a missing libLLVM 19 or an unavailable
    backend variant is an environment fault: outside CI it skips with the
    reason, but when the ``CI`` environment variable is set (``.ci/run`` runs
    with ``CI=true``) it fails the test, so CI cannot go green with the Mitsuba
    tests silently skipped.
    """
    import importlib.util

    if importlib.util.find_spec("mitsuba") is None:
        pytest.skip("mitsuba is not installed")
    from generator.mitsuba_backend import load_mitsuba, resolve_backend
    from polinfra.errors import BackendUnavailableError

    try:
        resolve_backend(backend)
        return load_mitsuba()
    except BackendUnavailableError as exc:  # installed, but the import or the variant does not work
        msg = f"mitsuba is installed but its {backend} backend is unavailable: {exc}"
        if os.environ.get("CI"):
            pytest.fail(f"{msg} (CI is set: a missing backend is a failure, not a skip)")
        pytest.skip(msg)


def small_scene(name: str = "brewster", width: int = 80, height: int = 50, **pane):
    """A default scene shrunk to width x height, with pane fields overridden."""
    from generator.scene import load_scene, scene_from_dict

    d = to_dict(load_scene(name))
    d["camera"].update(width=width, height=height)
    d["pane"].update(pane)
    return scene_from_dict(d)


def uniform_layers(scene, t_level: float = 0.6, r_level: float = 1.0):
    """The same scene with spatially uniform, static T and R layers (no geometry sensitivity)."""
    from generator.scene import scene_from_dict

    d = to_dict(scene)
    d["layers"]["transmission"] = {"source": "procedural:gradient", "brightness": 0.0, "offset": t_level, "distance_m": 4.0}
    d["layers"]["reflection"] = {"source": "procedural:gradient", "brightness": 0.0, "offset": r_level, "distance_m": 2.0}
    return scene_from_dict(d)
