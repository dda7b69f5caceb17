"""The data-consistency floor (reconstruct/physics/consistency.py and the network's use of it).

Oracles: the closed-form synthetic windows (reconstruct/stream/synthetic.py) with their true zeta and layers; the
physics-only RWPS on the same windows; the excess residual recomputed here from paper Eq. (1) by a plain numpy sum.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
import torch

from reconstruct.evaluate.metrics import psnr
from reconstruct.physics.consistency import FloorConfig, consistency_floor, observation_noise
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, solve
from reconstruct.stream.synthetic import SyntheticConfig, make_group


@functools.lru_cache(maxsize=None)
def _window(noise: str, exposure: float, seed: int = 0):
    g = make_group(SyntheticConfig(width=96, height=64, n_frames=9, exposure=exposure, noise=noise, motion_px_per_frame=0.0, seed=seed), 0)
    I, Z = torch.tensor(g.I[1:8]), torch.tensor(g.gt_zeta[1:8])
    ph = solve("rwps", Z, I, None, PHYSICS_SOLVER_CONFIG)
    return g, I, Z, ph.T.clamp_min(0.0), ph.R.clamp_min(0.0)


@pytest.mark.parametrize("noise, exposure", [("poisson", 1.0), ("integrate_fire", 3.0)])
def test_truth_passes_the_floor_unchanged(noise, exposure):
    """The true layers are within the observations' noise: the floor keeps them on >= 95 % of the pixels."""
    g, I, Z, Tp, Rp = _window(noise, exposure)
    Tg, Rg = torch.tensor(g.T[4]).float(), torch.tensor(g.R[4]).float()
    f = consistency_floor(Tg, Rg, Tp, Rp, Z, I)
    assert float((f.keep == 1).float().mean()) >= 0.95
    assert psnr(f.T.numpy(), g.T[4]) > psnr(Tp.numpy(), g.T[4]) + 10.0  # the truth, not the physics


@pytest.mark.parametrize("noise, exposure", [("poisson", 1.0), ("integrate_fire", 3.0)])
def test_garbage_candidate_gives_the_physics(noise, exposure):
    """A candidate that is noise of amplitude 3 (layers lie in [0, 1]) is floored to the physics: T and R PSNR within
    1 dB of the physics', and every pixel's distance from the physics in the metric of the data (the rms change of its
    7 predicted observations) below 0.1 of the light 2 I: the stated tolerance.
    """
    g, I, Z, Tp, Rp = _window(noise, exposure)
    gen = torch.Generator().manual_seed(1)
    Tn = Tp + 3.0 * torch.randn(Tp.shape, generator=gen)
    Rn = Rp + 3.0 * torch.randn(Rp.shape, generator=gen)
    f = consistency_floor(Tn, Rn, Tp, Rp, Z, I)
    for est, ref, gt in ((f.T, Tp, g.T[4]), (f.R, Rp, g.R[4])):
        assert psnr(est.numpy(), gt) >= psnr(ref.numpy(), gt) - 1.0
    assert psnr(Tn.numpy(), g.T[4]) < psnr(Tp.numpy(), g.T[4]) - 10.0  # the candidate alone is far worse
    z, dT, dR = Z.numpy().astype(np.float64), (f.T - Tp).numpy(), (f.R - Rp).numpy()
    move = np.sqrt(np.mean((z * dR + (1 - z) * dT) ** 2, axis=0))  # paper Eq. (1): change of the predicted b_k
    assert np.quantile(move, 0.99) < 0.1 * float(2 * I.mean())


def test_excess_is_the_residual_difference():
    """consistency_floor's excess (pool 1) is RSS(candidate) - RSS(physics) over sigma^2, recomputed in numpy."""
    g, I, Z, Tp, Rp = _window("poisson", 1.0)
    gen = torch.Generator().manual_seed(2)
    Tn, Rn = Tp + 0.1 * torch.randn(Tp.shape, generator=gen), Rp + 0.1 * torch.randn(Rp.shape, generator=gen)
    f = consistency_floor(Tn, Rn, Tp, Rp, Z, I, FloorConfig(pool=1))
    b, z = 2 * I.double().numpy(), Z.double().numpy()

    def rss(T, R):
        return ((b - z * R.double().numpy() - (1 - z) * T.double().numpy()) ** 2).sum(0)

    want = (rss(Tn, Rn) - rss(Tp, Rp)) / f.sigma2.double().numpy()
    np.testing.assert_allclose(f.excess.double().numpy(), want, rtol=1e-3, atol=1e-3)


def test_noise_estimate_matches_poisson():
    """observation_noise on Poisson windows of a flat scene recovers var(b) = 4 I / (exposure * 13) within 15 %."""
    rng = np.random.default_rng(3)
    N, H, W, e, L = 7, 48, 48, 2.0, 13
    z = torch.tensor(np.linspace(0.05, 0.3, N)[:, None, None] * np.ones((N, H, W)))
    I_true = 0.5 * (z * 0.4 + (1 - z) * 0.6)
    I = torch.tensor(rng.poisson(I_true.numpy() * e * L) / (e * L))
    s2 = observation_noise(z, I, pool=9)
    want = float((4 * I_true / (e * L)).mean())
    assert abs(float(s2.mean()) / want - 1) < 0.15


def test_network_with_garbage_refinement_gives_the_physics():
    """A PolSpikeNet whose refinement outputs garbage (its last layers scaled up 1e3) returns, with the floor on (the
    default at inference), T and R within 1 dB of the physics-only RWPS on the same zeta; with the floor off it does not.
    """
    from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights

    g, I, Z, Tp, Rp = _window("integrate_fire", 3.0)
    net = init_weights(PolSpikeNet(NetConfig(arch="v2", lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False)), torch.Generator().manual_seed(0))
    with torch.no_grad():
        for dec in (net.refine.dec_t, net.refine.dec_r):
            dec.out.weight.normal_(0.0, 10.0, generator=torch.Generator().manual_seed(4))
            dec.out.bias.fill_(0.7)
    net.eval()
    with torch.inference_mode():
        on = net(I[None], torch.tensor(g.phi_nominal[1:8])[None].float(), zeta_gt=Z[None], alpha=1.0)
        net_off = PolSpikeNet(dataclasses.replace(net.cfg, floor=False))
        net_off.load_state_dict(net.state_dict())
        off = net_off.eval()(I[None], torch.tensor(g.phi_nominal[1:8])[None].float(), zeta_gt=Z[None], alpha=1.0)
    for key, ref, gt in (("T", Tp, g.T[4]), ("R", Rp, g.R[4])):
        p_phys = psnr(ref.numpy(), gt)
        assert psnr(getattr(on, key)[0].numpy(), gt) >= p_phys - 1.0
    assert psnr(off.T[0].numpy(), g.T[4]) < psnr(Tp.numpy(), g.T[4]) - 5.0
    assert on.floor_keep is not None and float(on.floor_keep.mean()) < 0.2
