"""The floor's allowance for a sensor's fixed pattern as the windows show it (``--gain-spread estimate``).

Oracles: a known per-pixel gain pattern drawn on closed-form windows (paper Eq. (1)) with integrate-and-fire counting,
the numpy residuals of the move less its white part along the reference, and the two kinds of error the estimate must
tell apart: a pattern that is independent from pixel to pixel and a candidate's rescaling that is smooth.
"""

from __future__ import annotations

import math

import pytest
import torch

from reconstruct.physics.consistency import box_mean, consistency_floor, estimate_gain_spread, observation_noise
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, solve


def _scene(H: int = 64, W: int = 64, N: int = 7):
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H, dtype=torch.float64), torch.linspace(0, 1, W, dtype=torch.float64), indexing="ij")
    T = 0.5 + 0.3 * torch.sin(6 * xx) * torch.cos(4 * yy)
    R = 0.3 + 0.2 * torch.cos(5 * xx + 2 * yy)
    phi = torch.arange(N, dtype=torch.float64) * math.radians(31.5)
    Z = (0.3 + 0.25 * torch.cos(2 * phi)).reshape(N, 1, 1).expand(N, H, W).clone()
    return T, R, Z


def _windows(spread: float, exposure: float, seed: int):
    """13-step integrate-and-fire windows (a residue uniform over one threshold) of pixels whose gain is 1 + spread x
    N(0, 1), fixed over the 7 windows; the RWPS on them (layers >= 0) and sigma^2 as the floor measures it.
    """
    gen = torch.Generator().manual_seed(seed)
    T, R, Z = _scene()
    gain = 1.0 + spread * torch.randn(T.shape, generator=gen, dtype=T.dtype)
    lam = 13.0 * exposure * 0.5 * (Z * R + (1 - Z) * T) * gain
    I = torch.floor(lam + torch.rand(lam.shape, generator=gen, dtype=T.dtype)) / (13.0 * exposure)
    ph = solve("rwps", Z[None], I[None], None, PHYSICS_SOLVER_CONFIG)
    return T, R, Z, I, ph.T[0].clamp_min(0.0), ph.R[0].clamp_min(0.0), observation_noise(Z, I)


@pytest.mark.parametrize("spread", [0.03, 0.0735])
@pytest.mark.parametrize("exposure", [1.0, 5.0])
def test_the_estimate_recovers_a_known_fixed_pattern(spread, exposure):
    """With 2.7 and 13.6 spikes per window, the spread estimated between the truth and the RWPS is the drawn one
    within 15 %; without a pattern it is below 0.01.
    """
    T, R, Z, I, Tp, Rp, s2 = _windows(spread, exposure, seed=1)
    est = float(estimate_gain_spread(T, R, Tp, Rp, Z, I, s2))
    assert est == pytest.approx(spread, rel=0.15)
    T, R, Z, I, Tp, Rp, s2 = _windows(0.0, exposure, seed=2)
    assert float(estimate_gain_spread(T, R, Tp, Rp, Z, I, s2)) < 0.01


def test_the_estimate_is_zero_where_the_windows_count_under_one_spike():
    """0.5 spikes per window: the windows' noise hides any pattern, too few pixels qualify, and the estimate is 0."""
    T, R, Z, I, Tp, Rp, s2 = _windows(0.0735, 0.2, seed=3)
    assert float(estimate_gain_spread(T, R, Tp, Rp, Z, I, s2)) == 0.0


def test_one_estimate_per_image_of_a_batch():
    """A batch of a patterned and a clean image gives each its own spread, shaped (B, 1, 1)."""
    a, b = _windows(0.0735, 5.0, seed=4), _windows(0.0, 5.0, seed=5)
    T, R, Z, I, Tp, Rp, s2 = (torch.stack([x, y]) for x, y in zip(a, b))
    est = estimate_gain_spread(T, R, Tp, Rp, Z, I, s2)
    assert est.shape == (2, 1, 1)
    assert float(est[0]) == pytest.approx(0.0735, rel=0.15) and float(est[1]) < 0.01


def test_the_estimated_allowance_passes_the_truth_and_still_catches_a_smooth_rescaling():
    """Bright windows (13.6 spikes each) behind a 7.35 % pattern: without an allowance the floor pulls the truth toward
    the physics on every pixel; with the estimated one the truth passes on >= 75 % (78 % measured: the pattern's
    5 x 5 mean, a fifth of it, is still counted, and at 13.6 spikes per window it can exceed the windows' noise).  A candidate 10 % too bright over
    the whole view (a smooth error along the physics, which a known spread of 5.8 % would let through) and one off by
    noise of sd 0.05 are still pulled back on most pixels.
    """
    T, R, Z, I, Tp, Rp, _ = _windows(0.0735, 5.0, seed=6)
    assert float((consistency_floor(T, R, Tp, Rp, Z, I).keep == 1).double().mean()) < 0.5
    assert float((consistency_floor(T, R, Tp, Rp, Z, I, gain_spread=None).keep == 1).double().mean()) >= 0.75
    T9, R9, Z9, I9, Tp9, Rp9, _ = _windows(0.0, 5.0, seed=7)
    bright = consistency_floor(1.1 * Tp9, 1.1 * Rp9, Tp9, Rp9, Z9, I9, gain_spread=None)
    assert float((bright.keep == 1).double().mean()) < 0.5
    assert float((consistency_floor(1.1 * Tp9, 1.1 * Rp9, Tp9, Rp9, Z9, I9, gain_spread=0.058).keep == 1).double().mean()) < 0.5
    gen = torch.Generator().manual_seed(8)
    noisy = T + 0.1 * torch.randn(T.shape, generator=gen, dtype=T.dtype)
    assert float((consistency_floor(noisy, R, Tp, Rp, Z, I, gain_spread=None).keep == 1).double().mean()) < 0.5
    assert float((consistency_floor(noisy, R, Tp, Rp, Z, I, gain_spread=0.0735).keep == 1).double().mean()) < 0.05
    # its limit: a white error is what a pattern looks like, so the estimate reads one of sd 0.05 (10 % of T) as a
    # 12 % pattern and frees most of it (the known spread frees 59 % of the pixels, no allowance none)
    gen = torch.Generator().manual_seed(8)
    faint = T + 0.05 * torch.randn(T.shape, generator=gen, dtype=T.dtype)
    assert float(estimate_gain_spread(faint, R, Tp, Rp, Z, I, observation_noise(Z, I))) > 0.1


def test_box_mean_of_a_white_pattern_is_a_fifth_of_it():
    """The premise of the white part: the 5 x 5 box mean of an independent pattern has a fifth of its sd."""
    x = torch.randn(256, 256, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert float(box_mean(x, 5)[4:-4, 4:-4].std()) == pytest.approx(0.2, rel=0.05)


def test_a_constant_added_to_the_layers_is_no_pattern():
    """T + 0.05 and R - 0.05 behind a 7.35 % pattern, bright windows: the move's rescaling alpha follows the scene's
    texture, so part of it is white, but far beyond a pattern's power in a box; with the stream's known spread the
    floor still keeps under half of the move on average and no pixel whole.
    """
    T, R, Z, I, Tp, Rp, _ = _windows(0.0735, 5.0, seed=6)
    f = consistency_floor(T + 0.05, R - 0.05, Tp, Rp, Z, I, gain_spread=0.0735)
    assert float(f.keep.mean()) < 0.5 and float((f.keep == 1).double().mean()) == 0.0
