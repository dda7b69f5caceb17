"""Harmonic fit, supp. Eq. (1)-(2): closed-form oracles."""

from __future__ import annotations

import numpy as np
import torch

from polphysics.stokes import dop as stokes_dop
from polphysics.stokes import polarizer_intensity
from reconstruct.physics.harmonic_fit import aolp, dop, harmonic_eval, harmonic_fit


def test_noise_free_fit_recovers_stokes(np_rng):
    H, W, N = 5, 6, 7
    s0 = np_rng.uniform(0.5, 1.0, (H, W))
    lin = np_rng.uniform(0, 0.9, (H, W)) * s0
    ang = np_rng.uniform(0, np.pi, (H, W))
    s1, s2 = lin * np.cos(2 * ang), lin * np.sin(2 * ang)
    phi = np.deg2rad(31.5) * np.arange(N)
    I = np.stack([polarizer_intensity(s0, s1, s2, p) for p in phi])  # I = 1/2 (S0 + S1 cos 2phi + S2 sin 2phi)
    a0, ac, as_ = harmonic_fit(torch.from_numpy(I), torch.from_numpy(phi))
    assert np.allclose(a0.numpy(), s0 / 2, atol=1e-10)
    assert np.allclose(ac.numpy(), s1 / 2, atol=1e-10)
    assert np.allclose(as_.numpy(), s2 / 2, atol=1e-10)
    assert np.allclose(dop(a0, ac, as_, eps=0.0).numpy(), stokes_dop(s0, s1, s2), atol=1e-9)
    a = aolp(ac, as_).numpy()
    assert np.allclose(np.cos(2 * a), np.cos(2 * ang), atol=1e-9) and np.allclose(np.sin(2 * a), np.sin(2 * ang), atol=1e-9)
    back = harmonic_eval(a0, ac, as_, torch.from_numpy(phi)).numpy()
    assert np.allclose(back, I, atol=1e-10)


def test_weights_and_per_pixel_angles_batched_equal_looped(np_rng):
    B, N, H, W = 3, 7, 4, 5
    I = torch.from_numpy(np_rng.uniform(0, 1, (B, N, H, W)))
    phi = torch.from_numpy(np_rng.uniform(0, np.pi, (B, N, H, W)))
    w = torch.from_numpy(np_rng.uniform(0, 1, (B, N, H, W)))
    full = harmonic_fit(I, phi, w)
    for b in range(B):
        one = harmonic_fit(I[b], phi[b], w[b])
        for x, y in zip(full, one):
            assert torch.allclose(x[b], y, atol=1e-12)


def test_degenerate_windows_stay_finite():
    I = torch.ones(7, 3, 3)
    same = torch.zeros(7)
    out = harmonic_fit(I, same) + harmonic_fit(I, same, torch.zeros_like(I))
    assert all(torch.isfinite(x).all() for x in out)
    assert torch.isfinite(dop(*harmonic_fit(torch.zeros(7, 2, 2), torch.arange(7.0)))).all()


def test_gradcheck():
    g = torch.Generator().manual_seed(7)
    I = torch.rand(5, 2, 3, dtype=torch.float64, generator=g).requires_grad_(True)
    phi = torch.rand(5, dtype=torch.float64, generator=g).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, p: dop(*harmonic_fit(a, p)), (I, phi))
