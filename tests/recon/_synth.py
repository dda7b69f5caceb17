"""Closed-form synthetic windows for reconstruct tests (no spike_sim, no generator)."""

from __future__ import annotations

import numpy as np


def periodic_texture(rng: np.random.Generator, H: int, W: int, shift=(0.0, 0.0), nwaves: int = 40, fmax: float = 0.15) -> np.ndarray:
    """Sum of random cosines with whole cycles per image: exactly shiftable by any sub-pixel amount.

    Returns tex(y - dy, x - dx), zero mean, roughly unit standard deviation.
    """
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.zeros((H, W))
    ky = rng.integers(-int(fmax * H), int(fmax * H) + 1, nwaves)
    kx = rng.integers(-int(fmax * W), int(fmax * W) + 1, nwaves)
    ph = rng.uniform(0, 2 * np.pi, nwaves)
    amp = rng.uniform(0.5, 1.0, nwaves)
    for i in range(nwaves):
        out += amp[i] * np.cos(2 * np.pi * (ky[i] * (y - shift[0]) / H + kx[i] * (x - shift[1]) / W) + ph[i])
    return out / np.sqrt(0.5 * np.sum(amp**2))
