"""The pooled RWPS prior (``rwps_prior = "pooled"``): R - T pulled toward a conditioning-weighted,
box-pooled estimate of itself instead of toward 0.  Oracles: closed-form windows (paper Eq. (1)-(2))
with a known difference field, and the near-singular limit where the answer must be the window mean.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, pooled_difference_prior, solve

from .test_rwps_adaptive import _psnr, _regime_windows


def _windows(zeta_k, R, T):
    """Noise-free windows: zeta_k (N,) the same at every pixel, layers (H, W)."""
    z = torch.tensor(zeta_k, dtype=torch.float64)[:, None, None].expand(len(zeta_k), *R.shape)
    R_, T_ = (torch.from_numpy(a)[None] for a in (R, T))
    return z, 0.5 * (z * R_ + (1 - z) * T_)  # paper Eq. (1)


def test_pooled_mean_of_a_linear_difference_is_the_difference_shrunk_by_box_conditioning():
    """Uniform conditioning: every pixel weighs the same, so in the interior D0 is the plain box mean
    of R - T; a linear ramp's box mean is the ramp itself; then the conditioning factor d / (d + kappa0).
    """
    H, W = 24, 40
    x = np.linspace(0.0, 1.0, W)[None, :].repeat(H, 0)
    T = 0.3 + 0.4 * x
    R = 0.1 + 0.0 * x  # R - T = -0.2 - 0.4 x: linear
    zk = 0.3 + 0.25 * np.cos(2 * np.deg2rad(31.5) * np.arange(7))
    zeta, I = _windows(zk, R, T)
    pool, k0 = 9, 0.003
    D0, _ = pooled_difference_prior(zeta, 2 * I, torch.ones_like(I), pool=pool, kappa0=k0)
    d = 4 * np.var(zk)  # 4 Var_w(zeta) with uniform weights, the same in every box
    inner = (slice(pool // 2, H - pool // 2), slice(pool // 2, W - pool // 2))
    np.testing.assert_allclose(D0.numpy()[inner], (R - T)[inner] * d / (d + k0), atol=1e-9)


def test_near_singular_window_returns_the_window_mean():
    """All zeta equal: the data fix only zeta R + (1 - zeta) T; the box is singular, D0 -> 0, and the
    pooled prior gives R = T = the window mean 2 <I> (TFP), whatever the data's R - T.
    """
    rng = np.random.default_rng(3)
    R, T = rng.uniform(0.05, 0.3, (16, 16)), rng.uniform(0.3, 0.9, (16, 16))
    zeta, I = _windows([0.08] * 7, R, T)
    D0, q = pooled_difference_prior(zeta, 2 * I, torch.ones_like(I))
    assert D0.abs().max() < 1e-6
    cfg = dataclasses.replace(PHYSICS_SOLVER_CONFIG, rwps_prior="pooled")
    out = solve("rwps", zeta[None], I[None], config=cfg)
    np.testing.assert_allclose(out.T[0].numpy(), 2 * I.mean(0).numpy(), atol=1e-6)


def test_the_equal_prior_fails_where_the_reflection_is_weak_and_the_pooled_prior_does_not():
    """The regime behind the stress table's "reflection weak" failure: R = T / 10, strong modulation.
    Pulling R - T toward 0 loses clearly to LS; the pooled prior follows LS.
    """
    zeta, I, T = _regime_windows("weak_reflection_glancing")
    ls = _psnr("ls", zeta, I, T, PHYSICS_SOLVER_CONFIG)
    ridge = _psnr("ridge", zeta, I, T, PHYSICS_SOLVER_CONFIG)
    equal = _psnr("rwps", zeta, I, T, dataclasses.replace(PHYSICS_SOLVER_CONFIG, rwps_prior="equal"))
    pooled = _psnr("rwps", zeta, I, T, dataclasses.replace(PHYSICS_SOLVER_CONFIG, rwps_prior="pooled"))
    assert equal < max(ls, ridge) - 1.0, (equal, ls, ridge)
    assert pooled >= max(ls, ridge) - 0.3, (pooled, ls, ridge)


def test_pooled_conf_rises_with_light():
    """Q = s_D^2 / v_D: the same scene, brighter (more spikes) -> the difference is better measured."""
    qs = []
    for regime in ("weak_reflection_glancing_dim", "weak_reflection_glancing"):
        zeta, I, _ = _regime_windows(regime)
        qs.append(float(pooled_difference_prior(zeta, 2 * I, torch.ones_like(I))[1].median()))
    assert qs[1] > 5 * qs[0], qs
