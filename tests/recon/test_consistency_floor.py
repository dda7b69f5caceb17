"""The data-consistency floor (reconstruct/physics/consistency.py and the network's use of it).

Oracles: the closed-form synthetic windows (reconstruct/stream/synthetic.py) with their true zeta and layers; the
physics-only RWPS on the same windows; the excess residual recomputed here from paper Eq. (1) by a plain numpy sum.
"""

from __future__ import annotations

import dataclasses
import functools
import math

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
    from reconstruct.net.network import PolSpikeNet

    g, I, Z, Tp, Rp = _window("integrate_fire", 3.0)
    net = _garbage_net()
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


# ---- the best-physics anchor (reconstruct/physics/anchor.py) and the floor at it ----

def _closed_form(sigma: float, sigma_span: float, seed: int = 0, size: int = 48):
    """N = 7 windows of paper Eq. (1)-(2) with Gaussian noise of sd ``sigma`` on b = 2 I, zeta modulated by the
    polarizer (31.5 deg apart), smooth random layers, and the span mean 2 I_mean = (1 - zbar) T + zbar R (zbar the
    polarizer-cycle mean of zeta) with noise of sd ``sigma_span``.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size

    def field():
        k = rng.uniform(1.0, 4.0, (3, 2))
        p = rng.uniform(0, 2 * np.pi, 3)
        return sum(np.sin(2 * np.pi * (k[i, 0] * xx + k[i, 1] * yy) + p[i]) for i in range(3))

    T = 0.55 + 0.12 * field()
    R = 0.4 + 0.1 * field()
    z0 = 0.15 + 0.03 * xx
    amp = 0.1 + 0.02 * yy
    phi = np.deg2rad(31.5 * np.arange(7) + 10.0)
    Z = z0 + amp * np.cos(2 * phi)[:, None, None]
    b = (1 - Z) * T + Z * R + sigma * rng.standard_normal(Z.shape)
    m = (1 - z0) * T + z0 * R + sigma_span * rng.standard_normal(T.shape)
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    return t(T), t(R), t(Z), t(b / 2), t(m / 2), t(z0)


def _p(x, ref):
    return psnr(x.numpy(), ref.numpy(), float(ref.max()))


def test_anchor_is_the_mean_where_the_windows_are_noise_limited():
    """Noise of sd 0.5 on each window (the layers' own contrast is ~0.1): the modulation is not resolvable, and the
    anchor is the span mean read as T, 2 I_mean / (1 - zbar) (Wiener weight on the least-squares reflection ~0, the span
    level's share ~1): within 0.5 dB of it, and > 10 dB above least squares.
    """
    from reconstruct.physics.anchor import physics_anchor

    T, R, Z, I, Im, z0 = _closed_form(0.5, 0.002)
    a = physics_anchor(Z, I, Im, z0)
    mean_like = 2 * Im / (1 - z0)
    assert float(a.w.median()) < 0.05 and float(a.span_weight.median()) > 0.9
    assert _p(a.T, T) >= _p(mean_like, T) - 0.5
    assert _p(a.T, T) >= _p(a.T_ls, T) + 10.0


def test_anchor_is_the_physics_where_the_modulation_is_resolved():
    """Noise of sd 0.002: the reflection is resolved (Wiener weight ~1) and the anchor's T is within 0.5 dB of least
    squares' or better, > 5 dB above the mean read as T (which keeps the reflection zbar R / (1 - zbar)).
    """
    from reconstruct.physics.anchor import physics_anchor

    T, R, Z, I, Im, z0 = _closed_form(0.002, 0.0005)
    a = physics_anchor(Z, I, Im, z0)
    assert float(a.w.median()) > 0.9
    assert _p(a.T, T) >= _p(a.T_ls, T) - 0.5
    assert _p(a.T, T) >= _p(2 * Im / (1 - z0), T) + 5.0
    assert _p(a.R, R) >= _p(a.R_ls, R) - 0.5


def test_anchor_leaves_a_smeared_span():
    """The span mean taken from layers shifted by 6 px (a pan over the span): the anchor's level comes from the
    windows where the smear shows, and its T is within 1 dB of least squares' or better, far above the smeared span's.
    """
    from reconstruct.physics.anchor import physics_anchor

    T, R, Z, I, Im, z0 = _closed_form(0.01, 0.001)
    Ims = 0.5 * ((1 - z0) * torch.roll(T, 6, -1) + z0 * torch.roll(R, 6, -1))
    a = physics_anchor(Z, I, Ims, z0)
    assert _p(a.T, T) >= _p(a.T_ls, T) - 1.0
    assert _p(a.T, T) >= _p((a.T_ls * 0 + 2 * Ims - z0 * a.R_ls) / (1 - z0), T) + 3.0


@pytest.mark.parametrize("sigma", [0.5, 0.002])
def test_garbage_candidate_gives_the_best_physics(sigma):
    """anchored_floor on a candidate that is noise of amplitude 3 (layers in [0, 1]) ends at the anchor: T and R PSNR
    within 0.5 dB of the anchor's where the modulation is resolved; where the windows are noise-limited, within 2.5 dB
    (the floor lets T move as far as the reflection the windows cannot exclude: a rms of sqrt(2 P_T_max)), and
    above the candidate's (> 13 dB).
    """
    from reconstruct.physics.anchor import anchored_floor

    T, R, Z, I, Im, z0 = _closed_form(sigma, sigma / 250)
    gen = torch.Generator().manual_seed(5)
    Tn = T + 3.0 * torch.randn(T.shape, generator=gen, dtype=T.dtype)
    Rn = R + 3.0 * torch.randn(R.shape, generator=gen, dtype=T.dtype)
    f = anchored_floor(Tn, Rn, Z, I, Im, z0)
    tol = 0.5 if sigma < 0.01 else 2.5
    assert _p(f.T, T) >= _p(f.anchor.T, T) - tol
    assert _p(f.R, R) >= _p(f.anchor.R, R) - tol
    assert _p(f.T, T) > _p(Tn, T) + 13.0


def test_truth_passes_the_anchored_floor():
    """The true layers pass the anchored floor unchanged on >= 95 % of the pixels (noise-limited and resolved)."""
    from reconstruct.physics.anchor import anchored_floor

    for sigma in (0.5, 0.002):
        T, R, Z, I, Im, z0 = _closed_form(sigma, sigma / 250)
        f = anchored_floor(T, R, Z, I, Im, z0)
        assert float((f.keep_T == 1).double().mean()) >= 0.95, sigma


def test_network_with_garbage_refinement_gives_the_best_physics():
    """floor_anchor = "best" with its layer checks: a PolSpikeNet whose refinement outputs garbage returns T and R
    within 1 dB of the best-physics anchor's PSNR on the same windows and zeta (reconstruct.physics.anchor.physics_anchor).
    """
    from reconstruct.physics.anchor import physics_anchor

    g, I, Z, Tp, Rp = _window("integrate_fire", 3.0)
    net = _garbage_net(floor_anchor="best", floor_layers=True)
    with torch.inference_mode():
        on = net(I[None], torch.tensor(g.phi_nominal[1:8])[None].float(), zeta_gt=Z[None], alpha=1.0)
    a = physics_anchor(Z.double(), I.double())
    for key, ref, gt in (("T", a.T, g.T[4]), ("R", a.R, g.R[4])):
        assert psnr(getattr(on, key)[0].numpy(), gt) >= psnr(ref.float().numpy(), gt) - 1.0
    assert float(on.floor_keep.mean()) < 0.2


def _garbage_net(**cfg):
    """A small v2 network whose decoders output garbage (weights of sd 10, bias 0.7), in eval mode."""
    from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights

    net = init_weights(PolSpikeNet(NetConfig(arch="v2", lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False, **cfg)), torch.Generator().manual_seed(0))
    with torch.no_grad():
        for dec in (net.refine.dec_t, net.refine.dec_r):
            dec.out.weight.normal_(0.0, 10.0, generator=torch.Generator().manual_seed(4))
            dec.out.bias.fill_(0.7)
    return net.eval()


def test_count_quantum_variance_is_the_noise_of_counts_under_one_spike():
    """An integrate-and-fire count over L steps at m thresholds per window (m < 1), from a residue spread uniformly over
    one threshold, is 1 with probability m, else 0: its error about m has variance m (1 - m) spike^2.  Simulated here
    pixel by pixel; count_quantum_variance gives it in units of b = 2 I (one spike = 2 / (L exposure)), and 0 from one
    spike per window up (the residual shows that noise).
    """
    from reconstruct.physics.consistency import count_quantum_variance

    rng = np.random.default_rng(11)
    L, e = 13, 0.4
    for m in (0.05, 0.3, 0.6):
        level = m / (L * e)  # radiance giving m thresholds per window
        count = np.floor(rng.uniform(0.0, 1.0, 100_000) + m)
        b_err = 2.0 * (count - m) / (L * e)
        assert float(np.var(b_err)) == pytest.approx(count_quantum_variance(level, e, L), rel=0.03)
        assert float(count_quantum_variance(torch.tensor([level]), e, L)[0]) == pytest.approx(count_quantum_variance(level, e, L))
    assert count_quantum_variance(1.5 / (L * e), e, L) == 0.0


def test_the_count_quantum_keeps_a_sub_spike_move_in_the_dark():
    """Dark windows (every count 0, but for a few single spikes) are fitted exactly by the physics: the pools' residual
    is 0 and, without a floor on the noise, any move is 'inconsistent' and pulled back.  A move of a tenth of one
    spike cannot be judged by 13-step windows at a light of 0.1 spike per window (what the long span's mean says):
    with the noise of such counts as the floor it is kept; where the windows are bright (12 spikes each) the floor is 0
    and nothing changes.
    """
    from reconstruct.physics.consistency import count_quantum_variance

    rng = np.random.default_rng(12)
    N, H, W, L, e = 7, 32, 64, 13, 0.4
    z = torch.tensor(np.linspace(0.05, 0.35, N)[:, None, None] * np.ones((N, H, W)))
    counts = np.zeros((N, H, W))
    counts[:, :, :32] = (rng.uniform(size=(N, H, 32)) < 0.02)  # dark half: a spike in 2 % of the windows
    counts[:, :, 32:] = rng.poisson(12.0, size=(N, H, 32))  # bright half
    I = torch.tensor(counts / (L * e))
    level = torch.where(torch.arange(W) < 32, 0.1, 12.0).expand(H, W) / (L * e)  # the span's mean: 0.1 and 12 spikes per window
    ph = solve("rwps", z.float(), I.float(), None, PHYSICS_SOLVER_CONFIG)
    Tp, Rp = ph.T.clamp_min(0.0), ph.R.clamp_min(0.0)
    tenth = 0.1 * 2.0 / (L * e)  # a tenth of one spike, in the layers' units (b = 2 I)
    Tn, Rn = Tp + tenth, Rp + tenth
    f0 = consistency_floor(Tn, Rn, Tp, Rp, z.float(), I.float())
    f1 = consistency_floor(Tn, Rn, Tp, Rp, z.float(), I.float(), noise_floor=count_quantum_variance(level, e, L))
    dark = (slice(None), slice(2, 28))
    assert float((f0.keep[dark] < 0.5).float().mean()) > 0.05 and float(f0.keep[dark].min()) < 0.01  # without the floor: pools with no spike pulled back
    assert float(f1.keep[dark].min()) == 1.0  # kept with it
    torch.testing.assert_close(f1.keep[:, 32:], f0.keep[:, 32:])  # the bright half: no floor, the same check


def _layer_case():
    """Noise-limited closed-form windows and a candidate off the truth by noise of sd 0.3: the layer checks bind."""
    T, R, Z, I, Im, z0 = _closed_form(0.5, 0.002)
    gen = torch.Generator().manual_seed(11)
    return T + 0.3 * torch.randn(T.shape, generator=gen, dtype=T.dtype), R + 0.3 * torch.randn(R.shape, generator=gen, dtype=T.dtype), Z, I, Im, z0


def test_layer_checks_count_from_one_spike_per_window():
    """anchored_floor's layer checks count in full where the windows expect >= layer_counts spikes (the result is
    the ungated one, bit for bit), not at all where they expect none (the data check alone: ``layers = False``), and
    in between the kept fraction only rises as the expected count falls.
    """
    from reconstruct.physics.anchor import AnchorFloorConfig, anchored_floor

    Tn, Rn, Z, I, Im, z0 = _layer_case()
    full = anchored_floor(Tn, Rn, Z, I, Im, z0)
    data = anchored_floor(Tn, Rn, Z, I, Im, z0, cfg=AnchorFloorConfig(layers=False))
    assert float((full.keep_T < data.keep_T - 1e-6).double().mean()) > 0.05  # the layer checks bind somewhere
    ones = torch.ones_like(Tn)
    assert torch.equal(anchored_floor(Tn, Rn, Z, I, Im, z0, counts=1.5 * ones).T, full.T)
    assert torch.equal(anchored_floor(Tn, Rn, Z, I, Im, z0, counts=0.0 * ones).T, data.T)
    keeps = [anchored_floor(Tn, Rn, Z, I, Im, z0, counts=c * ones).keep_T for c in (1.0, 0.7, 0.4, 0.1)]
    for hi, lo in zip(keeps, keeps[1:]):
        assert bool((lo >= hi - 1e-12).all())
    assert bool((keeps[-1] > keeps[0] + 1e-6).any())


def test_anchor_floor_is_the_data_check_falling_back_to_the_best_physics():
    """floor_anchor = "best" (floor_layers off) on an external zeta is anchored_floor's data check against the RWPS's
    residual with the best physics as fallback: the network's output equals it, recomputed here from the unfloored
    network; and a garbage refinement ends within 1 dB of the anchor's PSNR on T and R.
    """
    from reconstruct.physics.anchor import AnchorFloorConfig, anchored_floor, physics_anchor

    g, I, Z, Tp, Rp = _window("integrate_fire", 3.0)
    net = _garbage_net(floor_anchor="best")
    assert not net.cfg.floor_layers
    phi = torch.tensor(g.phi_nominal[1:8])[None].float()
    with torch.inference_mode():
        on = net(I[None], phi, zeta_gt=Z[None], alpha=1.0)
        net.cfg = dataclasses.replace(net.cfg, floor=False)
        off = net(I[None], phi, zeta_gt=Z[None], alpha=1.0)
    f = anchored_floor(off.T, off.R, Z[None], I[None], cfg=AnchorFloorConfig(layers=False), reference=(Tp[None], Rp[None]))  # the default: the stream's own spread, none set here
    assert torch.allclose(on.T, f.T, atol=1e-5) and torch.allclose(on.R, f.R, atol=1e-5)
    a = physics_anchor(Z.double(), I.double())
    for key, ref, gt in (("T", a.T, g.T[4]), ("R", a.R, g.R[4])):
        assert psnr(getattr(on, key)[0].numpy(), gt) >= psnr(ref.float().numpy(), gt) - 1.0


def test_truth_behind_a_pixel_gain_spread_passes_with_the_gain_allowance():
    """Closed-form windows whose every pixel has a photo-gain error g (sd 6 %, fixed pattern: all 7 observations scaled
    alike) and little noise: least squares absorbs g, so the true layers miss the data by g^2 sum_k b_k^2 and the floor
    pulls them toward the physics on most pixels.  With ``gain_spread`` the move along the physics within two spreads
    is not counted: the truth passes on >= 90 % (a pixel beyond three spreads fails its 5 x 5 neighbours with it), while a candidate off the truth by noise of sd 0.05 is still pulled
    back on most pixels.
    """
    T, R, Z, I, Im, z0 = _closed_form(0.002, 0.0005)
    g = 1.0 + 0.06 * torch.randn(T.shape, generator=torch.Generator().manual_seed(3), dtype=T.dtype)
    Ig = I * g
    ls = solve("ls", Z, Ig, None, PHYSICS_SOLVER_CONFIG)
    bare = consistency_floor(T, R, ls.T, ls.R, Z, Ig)
    held = consistency_floor(T, R, ls.T, ls.R, Z, Ig, gain_spread=0.06)
    assert float((bare.keep == 1).double().mean()) < 0.5
    assert float((held.keep == 1).double().mean()) >= 0.9
    gen = torch.Generator().manual_seed(4)
    off = consistency_floor(T + 0.05 * torch.randn(T.shape, generator=gen, dtype=T.dtype), R, ls.T, ls.R, Z, Ig, gain_spread=0.06)
    assert float((off.keep == 1).double().mean()) < 0.5


def test_error_blend_is_the_minimum_variance_combination():
    """Two unbiased estimates with independent Gaussian errors, the anchor's of stated power P_a = 0.04 and the
    reference's of power P_r (unstated): the blend's mean square error is within 15 % of P_a P_r / (P_a + P_r) (the
    minimum-variance combination), below both inputs', and at P_r = 0 the blend is the reference.
    """
    from reconstruct.physics.anchor import error_blend

    rng = np.random.default_rng(3)
    x = torch.tensor(rng.uniform(0.2, 0.8, (128, 128)))
    Pa = 0.04
    xa = x + Pa**0.5 * torch.tensor(rng.standard_normal(x.shape))
    for Pr in (0.01, 0.04, 0.16):
        xr = x + Pr**0.5 * torch.tensor(rng.standard_normal(x.shape))
        e = float(((error_blend(xa, xr, torch.full_like(x, Pa), 9) - x) ** 2).mean())
        best = Pa * Pr / (Pa + Pr)
        assert abs(e - best) < 0.15 * best, (Pr, e, best)
        assert e < min(Pa, Pr)
    assert float(((error_blend(xa, x, torch.full_like(x, Pa), 9) - x) ** 2).mean()) < 0.05 * Pa


def test_anchor_pools_a_smooth_strong_reflection_the_windows_barely_modulate():
    """A strong smooth reflection (R 1.2 +- 0.1, T 0.25 +- 0.1) under a pane that barely modulates (zeta 0.15 +- 0.01)
    with noise sd 0.01: the reflection's texture is not resolvable, so shrinking R toward 0 (``r_pool`` 0) leaves the
    whole reflection in T, while shrinking it toward its 5 x 5 neighbourhood (the default) removes it: T > 10 dB better.
    """
    from reconstruct.physics.anchor import physics_anchor

    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:48, 0:48] / 48
    T = 0.25 + 0.1 * np.sin(2 * np.pi * (2 * xx + yy))
    R = 1.2 + 0.1 * np.cos(2 * np.pi * (xx - 2 * yy))
    phi = np.deg2rad(31.5 * np.arange(7) + 10.0)
    Z = 0.15 + 0.01 * np.cos(2 * phi)[:, None, None] + 0 * xx
    b = (1 - Z) * T + Z * R + 0.01 * rng.standard_normal(Z.shape)
    Zt, It, Tt = torch.tensor(Z), torch.tensor(b / 2), torch.tensor(T)
    pooled, zero = physics_anchor(Zt, It, r_pool=5), physics_anchor(Zt, It, r_pool=0)
    assert _p(pooled.T, Tt) >= _p(zero.T, Tt) + 10.0
    assert _p(pooled.T, Tt) >= _p(pooled.T_ls, Tt)


def test_pixel_gain_spread_adds_the_fixed_pattern_in_quadrature():
    """A stored configuration's count spread: gain, comparator offset and capacitance in quadrature; 0 without the
    fixed pattern (the ideal preset).
    """
    from spike_sim.config import DEFAULT, IDEAL, pixel_gain_spread

    d = dataclasses.asdict(DEFAULT)
    assert pixel_gain_spread(d) == pytest.approx(float(np.sqrt(0.0577**2 + 0.0455**2 + 0.00294**2)))
    assert pixel_gain_spread(dataclasses.asdict(IDEAL)) == 0.0


def test_the_floor_allows_the_streams_own_gain_spread():
    """A candidate that is the physics rescaled pixel by pixel by a pattern of sd 5 % (what a pixel gain error does,
    which the fit absorbs): on bright windows the floor (``floor_gain_spread = -1``: the stream's own) pulls it back to
    the physics when the stream has no gain spread, and keeps it when the reader set the stream's spread to 5.8 %;
    a smooth 10 % rescaling is pulled back either way; ``-1`` is the default, and ``floor_gain_spread = 0`` ignores
    the stream's.
    """
    from reconstruct.net.checkpoint import set_stream_gain_spread

    g, I, Z, Tp, Rp = _window("poisson", 200.0)
    net = _garbage_net(floor_anchor="rwps")  # the default: -1
    pattern = 1.0 + 0.05 * torch.randn(Tp.shape, generator=torch.Generator().manual_seed(5)).clamp(-2.0, 2.0)
    T, R = pattern * Tp, pattern * Rp
    keep = {}
    for label, spread in (("none", 0.0), ("sensor", 0.058)):
        set_stream_gain_spread(net, spread)
        keep[label] = float(net.data_floor(T[None], R[None], Z[None], I[None], 200.0)[2].mean())
        keep[label + " smooth"] = float(net.data_floor(1.1 * Tp[None], 1.1 * Rp[None], Z[None], I[None], 200.0)[2].mean())
    assert keep["none"] < 0.5 < 0.95 < keep["sensor"], keep
    assert keep["sensor smooth"] < 0.5, keep  # a smooth 10 % rescaling is no fixed pattern: pulled back all the same
    pinned = _garbage_net(floor_anchor="rwps", floor_gain_spread=0.0)
    set_stream_gain_spread(pinned, 0.058)
    assert float(pinned.data_floor(T[None], R[None], Z[None], I[None], 200.0)[2].mean()) == pytest.approx(keep["none"])


def test_a_candidate_that_is_no_number_gives_the_fallback_there_and_nothing_else_moves():
    """NaN / inf pixels of a candidate (a network that overflowed) are the floor's fallback there, kept 0, and no NaN
    spreads through the floor's pools: with the truth elsewhere, the other pixels are as without the bad ones.
    Both floors: the data check on the RWPS and the anchored floor with the blend.
    """
    from reconstruct.physics.anchor import anchored_floor

    g, I, Z, Tp, Rp = _window("poisson", 1.0)
    Tg, Rg = torch.tensor(g.T[4]).float(), torch.tensor(g.R[4]).float()
    bad = torch.zeros_like(Tg, dtype=torch.bool)
    bad[10:13, 20:24] = True
    bad[40, 70] = True
    Tn, Rn = Tg.masked_fill(bad, float("nan")), Rg.clone()
    Rn[5, 5], bad[5, 5] = float("inf"), True
    far = ~torch.nn.functional.max_pool2d(bad[None, None].float(), 11, 1, 5)[0, 0].bool()  # beyond two pools of 5
    f, f0 = consistency_floor(Tn, Rn, Tp, Rp, Z, I), consistency_floor(Tg, Rg, Tp, Rp, Z, I)
    assert torch.isfinite(f.T).all() and torch.isfinite(f.R).all()
    assert torch.equal(f.T[bad], Tp[bad]) and torch.equal(f.R[bad], Rp[bad]) and float(f.keep[bad].max()) == 0.0
    assert torch.equal(f.T[far], f0.T[far]) and torch.equal(f.R[far], f0.R[far])
    a, a0 = anchored_floor(Tn, Rn, Z, I, reference=(Tp, Rp), fallback="blend"), anchored_floor(Tg, Rg, Z, I, reference=(Tp, Rp), fallback="blend")
    assert torch.isfinite(a.T).all() and torch.isfinite(a.R).all() and float(a.keep_T[bad].max()) == 0.0
    assert torch.allclose(a.T[far], a0.T[far]) and torch.allclose(a.R[far], a0.R[far])


def test_the_fallback_never_takes_least_squares_below_zero():
    """Where zeta is near 1, T hardly reaches the windows and least squares runs away (the anchor's T far below 0 on
    the pixels that see almost only the reflection); the blend floor's fallback is >= 0 there, and any pixel the data
    check pulls lies between the candidate and that fallback.
    """
    from reconstruct.physics.anchor import anchored_floor, physics_anchor

    g = np.random.default_rng(8)
    H, W, N = 24, 30, 7
    phi = torch.tensor((np.arange(N) - 3) * math.radians(31.5))
    zbar = torch.full((H, W), 0.985, dtype=torch.float64)
    zeta = (zbar + 0.012 * torch.cos(2 * phi)[:, None, None]).clamp(0, 1)
    T, R = torch.full((H, W), 0.5, dtype=torch.float64), torch.full((H, W), 0.6, dtype=torch.float64)
    I = 0.5 * (zeta * R + (1 - zeta) * T) + torch.from_numpy(g.normal(0.0, 0.02, (N, H, W)))
    a = physics_anchor(zeta, I)
    assert float(a.T.min()) < -1.0  # the runaway this guards against
    bad_T, bad_R = torch.full((H, W), 5.0, dtype=torch.float64), torch.zeros((H, W), dtype=torch.float64)  # fails the data check
    f = anchored_floor(bad_T, bad_R, zeta, I, reference=(T.clamp_min(0.0) * 0.9, R * 0.9), fallback="blend")
    assert float(f.T.min()) >= 0.0 and float(f.R.min()) >= 0.0
    assert float((f.keep_T < 1).double().mean()) > 0.5


def test_noise_estimate_is_the_least_squares_residual_per_pixel():
    """observation_noise (pool 1) is numpy lstsq's residual of b = zeta R + (1 - zeta) T over N - 2 dof per pixel, and
    where zeta does not modulate the residual about the window mean over N - 1.
    """
    rng = np.random.default_rng(8)
    N, H, W = 7, 5, 6
    z = rng.uniform(0.02, 0.6, (N, H, W))
    z[:, 0, :] = 0.3  # a pane that does not modulate on the first row
    I = rng.uniform(0.0, 1.0, (N, H, W))
    got = observation_noise(torch.tensor(z), torch.tensor(I), pool=1).numpy()
    b = 2 * I
    for y in range(H):
        for x in range(W):
            if y == 0:
                want = ((b[:, y, x] - b[:, y, x].mean()) ** 2).sum() / (N - 1)
            else:
                A = np.stack([z[:, y, x], 1 - z[:, y, x]], 1)
                rss = np.linalg.lstsq(A, b[:, y, x], rcond=None)[1][0]
                want = rss / (N - 2)
            assert got[y, x] == pytest.approx(want, rel=1e-9, abs=1e-12), (y, x)


@pytest.mark.parametrize("white", [0, 5])
def test_excess_less_a_gain_error_is_the_residual_difference_of_the_move_less_its_part_along_the_reference(white):
    """move_excess with a gain spread: RSS(x_ref + d') - RSS(x_ref) in numpy, d' = d - alpha' x_ref, alpha the data
    metric's projection of d on x_ref: clipped to 3 spreads, or (``white_pool`` 5) its part less its 5 x 5 box mean m,
    scaled to at most twice the spread's variance in the box and clipped to 3 spreads, plus m clipped to 3 spreads / 5
    (box mean over the pixels inside).
    """
    from reconstruct.physics.consistency import move_excess

    rng = np.random.default_rng(9)
    N, H, W, gs = 7, 12, 13, 0.02
    z, I = rng.uniform(0.02, 0.6, (N, H, W)), rng.uniform(0.0, 1.0, (N, H, W))
    Tr, Rr = rng.uniform(0.1, 1.0, (H, W)), rng.uniform(0.0, 1.0, (H, W))
    T, R = Tr * (1 + rng.uniform(-0.1, 0.1, (H, W))), Rr * (1 + rng.uniform(-0.1, 0.1, (H, W)))
    b = 2 * I

    def A(T_, R_):
        return z * R_ + (1 - z) * T_

    u, Ad = A(Tr, Rr), A(T - Tr, R - Rr)
    alpha = (Ad * u).sum(0) / (u * u).sum(0)
    if white:

        def box(a):
            return np.array([[a[max(0, y - 2) : y + 3, max(0, x - 2) : x + 3].mean() for x in range(W)] for y in range(H)])

        m = box(alpha)
        part = (alpha - m) * np.sqrt(np.minimum(1.0, 2 * gs**2 / box((alpha - m) ** 2)))  # at most twice a pattern's power per box
        a2 = np.clip(part, -3 * gs, 3 * gs) + np.clip(m, -3 * gs / white, 3 * gs / white)
    else:
        part = alpha
        a2 = np.clip(alpha, -3 * gs, 3 * gs)
    T2, R2 = T - a2 * Tr, R - a2 * Rr
    want = ((b - A(T2, R2)) ** 2).sum(0) - ((b - A(Tr, Rr)) ** 2).sum(0)
    got = move_excess(*(torch.tensor(v) for v in (T, R, Tr, Rr, z, I)), gain_spread=gs, white_pool=white).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert np.any(np.abs(part) >= 3 * gs) and np.any(np.abs(part) < 3 * gs)  # both branches of the clip are met


def test_where_zeta_leaves_t_unobserved_the_candidates_t_stands():
    """Where zeta ~ 1 (a grazing view's corner: 1 - zeta = 1e-4), the windows see T through 1 - zeta only, so T's least
    squares is noise far beyond the light and any fallback's T with it.  A candidate with the true T and a wrong R
    there fails the data check (its R moves the observations), yet where the anchor states its T error beyond
    BLIND_T times the light, the candidate's T must stand, not the fallback's, while R is floored as before; where zeta
    is small the rule changes nothing (T's kept fraction is the joint check's, as R's).
    """
    from reconstruct.physics.anchor import BLIND_T, anchored_floor
    from reconstruct.physics.consistency import box_mean

    T, R, Z, I, Im, z0 = _closed_form(0.02, 0.02 / 250, seed=3)
    corner = torch.zeros_like(T, dtype=torch.bool)
    corner[:, 32:] = True
    Zc = torch.where(corner, 0.9999 + 0.00002 * (Z - z0[None]) / 0.1, Z)
    zbar = torch.where(corner, torch.full_like(z0, 0.9999), z0)
    gen = np.random.default_rng(4)
    b = (1 - Zc) * T + Zc * R + 0.02 * torch.tensor(gen.standard_normal(Zc.shape))
    m = (1 - zbar) * T + zbar * R + 0.02 / 250 * torch.tensor(gen.standard_normal(T.shape))
    Rn = torch.where(corner, R + 0.3, R)  # a wrong R where T is unobserved: the data check fails there
    f = anchored_floor(T, Rn, Zc, b / 2, m / 2, zbar)
    blind = box_mean(f.anchor.P_T, 5) > BLIND_T**2 * box_mean(b.mean(0) ** 2, 5)
    assert float(blind[corner].double().mean()) > 0.3 and not bool(blind[:, :28].any())  # 45 % of the corner here
    assert torch.equal(f.T[blind], T[blind])
    assert float((f.T[blind] - f.anchor.T[blind]).abs().max()) > 5.0  # the fallback was far off there
    assert float(f.keep_R[corner & blind].max()) < 0.5  # R was pulled: the check did fail there
    plain = ~corner
    plain[:, 28:] = False
    assert torch.equal(f.keep_T[plain], f.keep_R[plain])
