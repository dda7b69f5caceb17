"""The solvers' shortcuts give the floats of the plain computation: the box mean those of ``avg_pool2d`` with
``count_include_pad=False`` (and a brute-force mean), the RWPS solve with its window sums shared between the noise pass
and the final solve those of the same steps each computing its own sums.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, _box, lambda_from_conf, poisson_reliability, pooled_difference_prior, solve, solve_weighted_ridge


def _pooled(x: torch.Tensor, k: int) -> torch.Tensor:
    """Rows then columns through avg_pool2d (padding k // 2, padding not counted, cropped to the map)."""
    shp = x.shape
    y = x.reshape(-1, 1, *shp[-2:])
    y = F.avg_pool2d(y, (k, 1), stride=1, padding=(k // 2, 0), count_include_pad=False)[..., : shp[-2], :]
    y = F.avg_pool2d(y, (1, k), stride=1, padding=(0, k // 2), count_include_pad=False)[..., : shp[-1]]
    return y.reshape(shp)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("shape", "k"), [((2, 60, 90), 31), ((3, 2, 17, 9), 5), ((1, 40, 33), 31), ((2, 7, 8), 4), ((5, 3, 2), 5)])
def test_box_is_avg_pool_bit_for_bit(shape, k, dtype):
    g = torch.Generator().manual_seed(7)
    x = torch.randn(*shape, generator=g, dtype=dtype) * 10.0 ** torch.randint(-6, 7, shape, generator=g).to(dtype)  # magnitudes 1e-6..1e6: rounding shows
    assert torch.equal(_box(x, k), _pooled(x, k))


def test_box_is_the_mean_of_the_clipped_window():
    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, 9, 11, generator=g, dtype=torch.float64)
    k, h = 5, 2
    want = torch.empty_like(x)
    for i in range(9):
        for j in range(11):
            want[0, i, j] = x[0, max(i - h, 0) : i - h + k, max(j - h, 0) : j - h + k].mean()
    assert torch.allclose(_box(x, k), want, rtol=1e-13, atol=0)


def test_box_gradient_matches_avg_pool():
    g = torch.Generator().manual_seed(5)
    x = torch.rand(2, 12, 14, generator=g, dtype=torch.float64, requires_grad=True)
    wgt = torch.rand(2, 12, 14, generator=g, dtype=torch.float64)
    (ga,) = torch.autograd.grad((_box(x, 5) * wgt).sum(), x)
    (gb,) = torch.autograd.grad((_pooled(x, 5) * wgt).sum(), x)
    assert torch.allclose(ga, gb, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("given_w", [False, True])
def test_rwps_with_shared_sums_is_the_unshared_steps_bit_for_bit(given_w):
    g = torch.Generator().manual_seed(11)
    zeta = 0.4 * torch.rand(2, 7, 30, 41, generator=g)
    I = torch.rand(2, 7, 30, 41, generator=g)
    w = torch.rand(2, 7, 30, 41, generator=g) if given_w else None
    c = PHYSICS_SOLVER_CONFIG
    got = solve("rwps", zeta, I, w, c)
    b = 2.0 * I
    w0 = w.clamp(0.0, 1.0) if given_w else poisson_reliability(zeta, I, first_lambda=c.lambda_high)
    D0, q = pooled_difference_prior(zeta, b, w0, c.prior_pool, c.prior_kappa, c.noise_pool)  # its own sums
    lam = lambda_from_conf(q / (q + c.snr_kappa), c.lambda_low, c.lambda_high)
    R, T = solve_weighted_ridge(zeta, b, w0, lam, "equal", D0)  # its own sums
    assert torch.equal(got.R, R) and torch.equal(got.T, T) and torch.equal(got.lam, lam)
