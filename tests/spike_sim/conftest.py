"""Fixtures for spike_sim tests: small sensors and in-memory keyframes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from polphysics.polarizer import PolarizerConfig
from spike_sim.config import DEFAULT
from spike_sim.simulate import keyframes_from_arrays


@pytest.fixture
def small_cfg():
    """The default noise model on a 24 x 16 sensor."""
    return dataclasses.replace(DEFAULT, width=24, height=16)


def make_keyframes(H=16, W=24, K=6, duration=0.03, seed=0, pol=None):
    """Random glass-like Stokes keyframes with GT layers and maps."""
    rng = np.random.default_rng(seed)
    times = np.linspace(0.0, duration, K) + 0.00013  # not on step boundaries: straddling steps
    T = rng.random((K, H, W)).astype(np.float32) * 0.8
    R = rng.random((K, H, W)).astype(np.float32) * 0.5
    phi_perp = np.full((H, W), 0.4, np.float32) + np.linspace(0, 0.3, W, dtype=np.float32)[None]
    Rp, Rs = np.full((H, W), 0.15, np.float32), np.full((H, W), 0.03, np.float32)
    lin = R * (Rp - Rs) / 2 + T * ((1 - Rp) - (1 - Rs)) / 2
    S0 = R * (Rp + Rs) / 2 + T * (2 - Rp - Rs) / 2
    st = np.stack([S0, lin * np.cos(2 * phi_perp), lin * np.sin(2 * phi_perp)], 1)
    maps = {"phi_perp": phi_perp, "R_perp": Rp, "R_par": Rs, "T_perp": 1 - Rp, "T_par": 1 - Rs, "theta": np.ones((H, W), np.float32)}
    return keyframes_from_arrays(times, st, (T, R), maps, polarizer=pol or PolarizerConfig(phase_deg=5.0, jitter_deg=0.1))


@pytest.fixture
def keyframes():
    """Six 24 x 16 keyframes over 30 ms."""
    return make_keyframes()


@pytest.fixture
def keyframe_factory():
    """make_keyframes(H, W, K, duration, seed, pol)."""
    return make_keyframes
