"""Shared fixtures: seeded rng, the shared data folder, a tiny scene."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def np_rng() -> np.random.Generator:
    """A seeded numpy Generator (never the global RNG)."""
    return np.random.default_rng(12345)


@pytest.fixture
def shared_data() -> Path:
    """../shared/data, or skip with the reason when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def tiny_scene():
    """A 41 x 25 pixel brewster-like scene (odd sizes: the centre pixel is on the axis)."""
    from generator.scene import load_scene
    import dataclasses

    s = load_scene("brewster")
    cam = dataclasses.replace(s.camera, width=41, height=25)
    return dataclasses.replace(s, camera=cam, render=dataclasses.replace(s.render, duration_s=0.02, fps=100.0))
