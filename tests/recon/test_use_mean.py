"""A network that also sees the long spike mean (net.use_mean): its input in training items, in
evaluation and in the streaming reconstructor equals the raw-spike mean of the store; widening a trained
network's refinement for it starts from exactly the same outputs.
"""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError, ShapeError
from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights
from reconstruct.net.train import _widened
from tests.recon.test_windows import make_group

SMALL = NetConfig(arch="v2", feat_ch=8, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False, floor=False)  # the forward before the data-consistency floor (tests/recon/test_consistency_floor.py)


def _window(seed=0, B=2, H=16, W=16):
    g = torch.Generator().manual_seed(seed)
    I = torch.rand(B, 7, H, W, generator=g) * 0.5
    phi = torch.arange(7, dtype=torch.float32)[None].repeat(B, 1) * 0.55
    return I, phi, 0.5 * I.mean(1) + 0.01 * torch.rand(B, H, W, generator=g)


def test_widened_network_starts_as_the_given_one_and_needs_the_mean():
    torch.manual_seed(0)
    base = init_weights(PolSpikeNet(SMALL), torch.Generator().manual_seed(1)).eval()
    for p in base.refine.parameters():  # non-zero decoders, so the refinement's input matters
        torch.nn.init.normal_(p, 0, 0.05)
    wide = PolSpikeNet(dataclasses.replace(SMALL, use_mean=True)).eval()
    wide.load_state_dict(_widened(base.state_dict(), wide.state_dict()))
    I, phi, Im = _window()
    with torch.no_grad():
        a, b = base(I, phi), wide(I, phi, I_mean=Im)
    torch.testing.assert_close(a.T, b.T, rtol=0, atol=1e-6)
    torch.testing.assert_close(a.R, b.R, rtol=0, atol=1e-6)
    w = wide.refine.e1[0]
    k = next(v for n, v in wide.state_dict().items() if n.startswith("refine.e1.0") and v.dim() == 4)
    assert k.shape[1] == 8 and float(k[:, 6:].abs().max()) == 0.0  # the two new inputs start at zero weight
    with torch.no_grad():  # once the new weights move, the mean changes the output
        for n, v in wide.named_parameters():
            if n.startswith("refine.e1.0") and v.dim() == 4:
                v[:, 6:] = 0.1
        c = wide(I, phi, I_mean=Im)
        d = wide(I, phi, I_mean=Im * 2)
    assert float((c.T - d.T).abs().max()) > 1e-4
    with pytest.raises(ShapeError, match="I_mean"):
        wide(I, phi)
    assert w is not None


def test_onthefly_item_mean_is_the_raw_spike_mean():
    from reconstruct.net.onthefly import WindowConfig, item_from_stream

    rng = np.random.default_rng(0)
    spikes = (rng.random((900, 8, 8)) < 0.2).astype(np.uint8)
    cfg = WindowConfig(crop=8, mean_steps=350)
    ck = 300 + np.arange(7) * 58
    phi = np.linspace(0, 5, 900)
    maps = {"R_perp": np.full((8, 8), 0.1), "R_par": np.full((8, 8), 0.01), "phi_perp": np.zeros((8, 8))}
    it = item_from_stream(spikes, ck, phi, phi, (np.zeros((8, 8)),) * 2, maps, 0.7, cfg)
    c = ck[3]
    np.testing.assert_allclose(it["I_mean"].numpy(), spikes[c - 175 : c + 176].sum(0) / (351 * 0.7), rtol=1e-6)
    assert "I_mean" not in item_from_stream(spikes, ck, phi, phi, (np.zeros((8, 8)),) * 2, maps, 0.7, WindowConfig(crop=8))


class _Recorder(torch.nn.Module):
    """Stands in for a use_mean network: records the I_mean it is given, returns T = 2 I_mean."""

    def __init__(self):
        super().__init__()
        self.cfg = types.SimpleNamespace(n_obs=7, inputs=frozenset({"I_mean"}))
        self.seen: list[np.ndarray] = []

    def forward(self, I, phi, I_mean=None, **kw):
        self.seen.append(I_mean.numpy().copy())
        z = torch.zeros_like(I_mean)
        return types.SimpleNamespace(T=2 * I_mean, R=z, T_base=z, R_base=z)


@pytest.mark.parametrize("chunk", [37, 2000])
def test_stream_gives_the_network_the_store_spike_mean(tmp_path, chunk):
    from reconstruct.stream.groups import spike_mean_frames
    from reconstruct.stream.sources import group_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream
    from spike_sim.aggregate import AggregateConfig, frame_centres
    from spike_sim.store import open_group

    make_group(tmp_path / "g", seed=3, duration=0.04)
    rec = _Recorder()
    src = group_source(tmp_path / "g", chunk_steps=chunk)
    s = reconstruct_stream(src, rec, tmp_path / "out", ReconstructConfig(video=False, chunk_steps=chunk, batch=2, tile=0, cache=False))
    got = np.concatenate(rec.seen)
    assert got.shape[0] == s["frames"] >= 3
    with open_group(tmp_path / "g") as g:
        c, _ = frame_centres(g.phi_nominal_rad, AggregateConfig())
        ref = spike_mean_frames(g, c[3 : 3 + got.shape[0]], 350, src.exposure)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)


def test_a_mean_network_refuses_groups_without_spikes():
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups
    from reconstruct.stream.synthetic import SyntheticConfig
    from reconstruct.stream.synthetic import make_group as synth

    g = dataclasses.replace(synth(SyntheticConfig(width=16, height=16, n_groups=1, n_frames=9), 0), I_mean=None)  # e.g. an in-memory group
    rec = _Recorder()
    import reconstruct.evaluate.harness as ev

    orig = ev.load_network
    ev.load_network = lambda cfg: (rec, {"label": "full"})
    try:
        with pytest.raises(ConfigError, match="long spike mean"):
            evaluate_groups([g], EvalConfig(methods="full", rir=False, max_frames=1))
    finally:
        ev.load_network = orig


def test_synthetic_groups_carry_the_half_turn_mean():
    """The closed-form synthetic set gives a use_mean network its input: noise-free and static, 2 I_mean =
    T + zbar (R - T) with zbar = (R_perp + R_par) / 2 (paper Eq. (1)-(2) averaged over a half turn).
    """
    from reconstruct.stream.synthetic import SyntheticConfig
    from reconstruct.stream.synthetic import make_group as synth

    g = synth(SyntheticConfig(width=24, height=16, n_groups=1, n_frames=9, noise="none", motion_px_per_frame=0.0), 0)
    zbar = 0.5 * (g.maps.R_perp + g.maps.R_par)
    np.testing.assert_allclose(2 * g.I_mean[4], g.T[4] + zbar * (g.R[4] - g.T[4]), atol=1e-5)
    gn = synth(SyntheticConfig(width=24, height=16, n_groups=1, n_frames=9, motion_px_per_frame=0.0), 0)  # Poisson: 350 steps
    assert float(np.abs(gn.I_mean[4] - g.I_mean[4]).mean()) < float(np.abs(gn.I[4] - g.I[4]).mean()) / 3


def test_zbar_of_is_the_half_turn_mean_not_the_window_mean():
    """Closed form: zeta = a + b cos 2phi + c sin 2phi (paper Eq. (2)); over the N = 7, 0.65 ms windows (~84 deg of
    2 phi) the plain mean is off by up to the modulation depth, the first-harmonic level is a; it equals the mean
    over a whole turn, and a still polarizer (all angles equal) gives the plain mean.
    """
    from reconstruct.physics.span import zbar_of

    rng = np.random.default_rng(3)
    a, b, c = rng.uniform(0.05, 0.3, (3, 5)), rng.uniform(-0.1, 0.1, (3, 5)), rng.uniform(-0.1, 0.1, (3, 5))
    phi = 0.4 + np.radians(7.02) * (np.arange(7) - 3)
    z = a + b * np.cos(2 * phi)[:, None, None] + c * np.sin(2 * phi)[:, None, None]
    assert float(np.abs(z.mean(0) - a).max()) > 0.05  # the window mean is far off
    np.testing.assert_allclose(zbar_of(z, phi), a, atol=5e-5)
    turn = np.linspace(0, np.pi, 64, endpoint=False)
    zt = a + b * np.cos(2 * turn)[:, None, None] + c * np.sin(2 * turn)[:, None, None]
    np.testing.assert_allclose(zbar_of(z, phi), zt.mean(0), atol=5e-5)
    np.testing.assert_allclose(zbar_of(z, np.full(7, 0.4)), z.mean(0), atol=1e-12)
    zb = zbar_of(torch.tensor(z[None], dtype=torch.float32), torch.tensor(phi[None]))  # batched torch
    assert zb.dtype == torch.float32 and zb.shape == (1, 3, 5)
    np.testing.assert_allclose(zb[0].numpy(), a, atol=1e-4)


def test_anchored_base_network_starts_as_the_anchored_solver():
    """Base = anchored with zero decoder outputs returns exactly anchor_to_mean of its own solver output (with the
    first-harmonic zbar); the forced zeta scale reaches the solver but not the returned ground truth.
    """
    from reconstruct.physics.span import anchor_to_mean, zbar_of

    cfg = dataclasses.replace(SMALL, use_mean=True, base="anchored", anchor_zbar="harmonic")
    net = init_weights(PolSpikeNet(cfg), torch.Generator().manual_seed(1)).eval()
    with torch.no_grad():
        for d in (net.refine.dec_t, net.refine.dec_r):
            d.out.weight.zero_()
            d.out.bias.zero_()
    I, phi, Im = _window()
    with torch.no_grad():
        o = net(I, phi, I_mean=Im)
    Ta, Ra = anchor_to_mean(o.T_base, o.R_base, Im, zbar_of(o.zeta_used, phi))
    torch.testing.assert_close(o.T, Ta, rtol=0, atol=1e-6)
    torch.testing.assert_close(o.R, Ra, rtol=0, atol=1e-6)
    zg = torch.full_like(o.zeta_hat, 0.2)
    with torch.no_grad():
        f = net(I, phi, zeta_gt=zg, alpha=1.0, I_mean=Im, zeta_scale=torch.tensor([1.0, 1.5]))
    torch.testing.assert_close(f.zeta_used[0], zg[0])
    torch.testing.assert_close(f.zeta_used[1], zg[1] * 1.5)
    assert f.zeta_gt is zg
    zv = 0.1 + 0.2 * torch.rand(o.zeta_hat.shape, generator=torch.Generator().manual_seed(3))  # a modulating zeta
    with torch.no_grad():
        f = net(I, phi, zeta_gt=zv, alpha=1.0, I_mean=Im, zeta_scale=torch.tensor([1.0, 1.5]), zeta_shape=torch.tensor([0.5, 1.2]))
    m = zv.mean(1, keepdim=True)  # the shape factor scales the modulation about the window mean, then the scale applies
    torch.testing.assert_close(f.zeta_used[0], (m + 0.5 * (zv - m))[0])
    torch.testing.assert_close(f.zeta_used[1], (1.5 * (m + 1.2 * (zv - m)))[1].clamp(0, 1))
    assert f.zeta_gt is zv
    with pytest.raises(ConfigError, match="base = anchored needs use_mean"):  # a configuration problem, found when the config is made
        dataclasses.replace(SMALL, base="anchored")


def test_r_level_takes_rs_level_from_the_base_and_its_structure_from_the_refinement():
    """r_level_px > 0: R = R_ref + G_s * (R_base - R_ref). A refinement that only shifts R's level (Delta_r = c) is
    undone exactly (R = the anchored base), while without it R = base + c; T is untouched. gaussian_blur equals
    scipy's mirrored Gaussian filter (truncated at 3 sigma).
    """
    from scipy.ndimage import gaussian_filter

    from reconstruct.physics.span import anchor_to_mean, gaussian_blur, zbar_of

    x = torch.rand(2, 40, 50, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    ref = np.stack([gaussian_filter(a, 3.0, mode="mirror", truncate=3.0) for a in x.numpy()])
    np.testing.assert_allclose(gaussian_blur(x, 3.0).numpy(), ref, atol=1e-12)
    outs = {}
    for s in (0.0, 8.0):
        cfg = dataclasses.replace(SMALL, use_mean=True, base="anchored", anchor_zbar="harmonic", r_level_px=s)
        net = init_weights(PolSpikeNet(cfg), torch.Generator().manual_seed(1)).eval()
        with torch.no_grad():
            net.refine.dec_r.out.weight.zero_()
            net.refine.dec_r.out.bias.fill_(0.05)  # Delta_r = 0.05 everywhere: a pure level shift
        I, phi, Im = _window()
        with torch.no_grad():
            outs[s] = net(I, phi, I_mean=Im)
    o0, o8 = outs[0.0], outs[8.0]
    Ta, Ra = anchor_to_mean(o0.T_base, o0.R_base, Im, zbar_of(o0.zeta_used, phi))
    torch.testing.assert_close(o0.R, Ra + 0.05, rtol=0, atol=1e-5)
    torch.testing.assert_close(o8.R, Ra, rtol=0, atol=1e-5)
    torch.testing.assert_close(o8.T, o0.T, rtol=0, atol=0)
