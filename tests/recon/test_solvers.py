"""Physics solvers, supp. Eq. (3)-(15): exact recovery, singular cases, gradients, batching."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from reconstruct.physics.solvers import SOLVERS, SolverConfig, confidence, lambda_from_conf, solve, solve_weighted_ridge


def _window(rng, B=2, N=7, H=4, W=5, noise=0.0):
    R = rng.uniform(0.1, 1.0, (B, 1, H, W))
    T = rng.uniform(0.1, 1.0, (B, 1, H, W))
    phi = np.deg2rad(31.5) * np.arange(N)[None, :, None, None]
    phi_perp = rng.uniform(0, np.pi, (B, 1, H, W))
    zeta = 0.25 * np.cos(phi - phi_perp) ** 2 + 0.02 * np.sin(phi - phi_perp) ** 2  # paper Eq. (2)
    I = 0.5 * (zeta * R + (1 - zeta) * T) + noise * rng.standard_normal((B, N, H, W))  # paper Eq. (1)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    return t(zeta), t(I), t(R[:, 0]), t(T[:, 0])


@pytest.mark.parametrize("method", ["ls", "irls"])
def test_noise_free_recovery(np_rng, method):
    zeta, I, R, T = _window(np_rng)
    out = solve(method, zeta, I)
    assert torch.allclose(out.R, R, atol=1e-7) and torch.allclose(out.T, T, atol=1e-8)


def test_ridge_and_rwps_reduce_to_ls_and_irls_at_zero_lambda(np_rng):
    zeta, I, R, T = _window(np_rng, noise=0.02)
    cfg = SolverConfig(ridge_lambda=0.0, lambda_low=0.0, lambda_high=0.0)
    assert torch.allclose(solve("ridge", zeta, I, config=cfg).T, solve("ls", zeta, I).T, atol=1e-12)
    ones = torch.ones_like(I)
    assert torch.allclose(solve("rwps", zeta, I, weights=ones, config=cfg).T, solve("irls", zeta, I).T, atol=1e-12)


def test_conf_is_normalised_and_scale_invariant(np_rng):
    zeta, _, _, _ = _window(np_rng)
    c = confidence(zeta)
    assert (c >= 0).all() and (c <= 1).all()
    assert torch.allclose(c, confidence(zeta, torch.full_like(zeta, 0.1)), atol=1e-12)
    half = torch.tensor([0.0, 1.0] * 3, dtype=torch.float64)[:, None, None]
    assert torch.allclose(confidence(half), torch.ones(1, 1, dtype=torch.float64))  # det maximal -> Conf = 1
    assert torch.allclose(confidence(torch.full((7, 1, 1), 0.1, dtype=torch.float64)), torch.zeros(1, 1, dtype=torch.float64))
    lam = lambda_from_conf(c, 1e-4, 1e-1)
    assert (lam >= 1e-4 - 1e-15).all() and (lam <= 1e-1 + 1e-15).all()


@pytest.mark.parametrize("method", SOLVERS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_singular_systems_no_nan(method, dtype):
    I = torch.rand(7, 3, 3, dtype=dtype, generator=torch.Generator().manual_seed(8))
    cases = [
        torch.full((7, 3, 3), 0.1, dtype=dtype),  # all zeta equal: rank 1
        torch.zeros(7, 3, 3, dtype=dtype),  # zeta = 0: R unobservable
        torch.ones(7, 3, 3, dtype=dtype),  # zeta = 1: T unobservable
    ]
    for z in cases:
        out = solve(method, z, I, weights=torch.ones_like(I))
        assert torch.isfinite(out.R).all() and torch.isfinite(out.T).all() and torch.isfinite(out.conf).all()
        # the observable combination zeta R + (1 - zeta) T is a location estimate of b = 2 I:
        # the mean for ls/ridge, a Huber M-estimate (inside the data range) for irls/rwps
        fit = (z * out.R + (1 - z) * out.T)[0]
        b = 2 * I
        if method in ("ls", "ridge"):
            assert torch.allclose(fit, b.mean(0), rtol=0.05, atol=1e-3)
        else:
            assert (fit >= b.min(0).values * 0.95 - 1e-3).all() and (fit <= b.max(0).values + 1e-3).all()
    zero_w = solve("rwps", cases[0], I, weights=torch.zeros_like(I))
    assert torch.isfinite(zero_w.R).all() and torch.isfinite(zero_w.T).all()
    R, T = solve_weighted_ridge(cases[0], 2 * I, torch.zeros_like(I), 0.0)
    assert torch.equal(R, torch.zeros_like(R)) and torch.equal(T, torch.zeros_like(T))


@pytest.mark.parametrize("method", SOLVERS)
def test_gradcheck(np_rng, method):
    zeta, I, _, _ = _window(np_rng, B=1, N=5, H=2, W=2, noise=0.01)
    zeta.requires_grad_(True)
    I.requires_grad_(True)
    w = torch.from_numpy(np_rng.uniform(0.2, 1.0, tuple(I.shape))).requires_grad_(True)

    def f(z, i, ww):
        out = solve(method, z, i, weights=ww)
        return out.R, out.T, out.conf

    assert torch.autograd.gradcheck(f, (zeta, I, w), atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("method", SOLVERS)
def test_batched_equals_looped(np_rng, method):
    zeta, I, _, _ = _window(np_rng, B=3, noise=0.02)
    full = solve(method, zeta, I)
    for b in range(3):
        one = solve(method, zeta[b], I[b])
        assert torch.allclose(full.T[b], one.T, atol=1e-12) and torch.allclose(full.R[b], one.R, atol=1e-12)
        assert torch.allclose(full.conf[b], one.conf, atol=1e-12)


def test_irls_downweights_an_outlier(np_rng):
    zeta, I, R, T = _window(np_rng, B=1)
    I_bad = I.clone()
    I_bad[:, 2] += 0.5
    ls = solve("ls", zeta, I_bad)
    irls = solve("irls", zeta, I_bad)
    assert (irls.T - T).abs().mean() < 0.5 * (ls.T - T).abs().mean()
    assert irls.weights[:, 2].mean() < 0.5 * irls.weights[:, [0, 1, 3, 4, 5, 6]].mean()


def test_noise_ordering_rwps_beats_ls(np_rng):
    # spike-like noise: ~13 spikes per frame gives ~28 % relative noise (the paper's default window)
    zeta, I, R, T = _window(np_rng, B=4, H=16, W=16, noise=0.08)
    ones = torch.ones_like(I)  # the noise here is Gaussian with constant variance: uniform reliability
    err = {m: float(((solve(m, zeta, I, weights=ones).T - T) ** 2).mean()) for m in SOLVERS}
    assert err["rwps"] < err["ls"] and err["ridge"] < err["ls"]


def test_unknown_method_lists_choices():
    from polinfra.errors import ConfigError

    with pytest.raises(ConfigError, match="rwps"):
        solve("svd", torch.zeros(3, 1, 1), torch.zeros(3, 1, 1))
    _ = SolverConfig()


def test_gradcheck_rwps_default_reliability_and_conf_lambda(np_rng):
    # the whole RWPS chain: Poisson reliability -> Conf (supp. Eq. (12)-(15)) -> lambda (supp. Eq. (8)) -> 2x2 solve (supp. Eq. (9)) -> IRLS
    zeta, I, _, _ = _window(np_rng, B=1, N=7, H=2, W=3, noise=0.01)
    zeta.requires_grad_(True)
    I.requires_grad_(True)

    def f(z, i):
        out = solve("rwps", z, i)
        return out.R, out.T, out.conf, out.lam

    assert torch.autograd.gradcheck(f, (zeta, I), atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("method", SOLVERS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_singular_systems_have_finite_gradients(method, dtype):
    """Backward through rank-1 (all zeta equal) and all-zero-weight systems gives no NaN / inf."""
    g = torch.Generator().manual_seed(3)
    for z0, w0 in ((torch.full((7, 2, 2), 0.1), torch.ones(7, 2, 2)), (torch.full((7, 2, 2), 0.1), torch.zeros(7, 2, 2)), (torch.zeros(7, 2, 2), torch.ones(7, 2, 2))):
        z = z0.to(dtype).requires_grad_(True)
        w = w0.to(dtype).requires_grad_(True)
        I = torch.rand(7, 2, 2, dtype=dtype, generator=g).requires_grad_(True)
        out = solve(method, z, I, weights=w)
        (out.R.sum() + out.T.sum() + out.conf.sum()).backward()
        for t in (z.grad, I.grad, w.grad if method == "rwps" else torch.zeros(1)):
            assert t is not None and torch.isfinite(t).all(), f"{method} {dtype}: non-finite gradient"
