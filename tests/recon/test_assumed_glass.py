"""Training for the self-calibration's glass errors: items carry the window's zeta under an assumed glass
(window.assumed_n), the forced step feeds it to the solver while the losses keep the true zeta.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError, ShapeError
from polphysics.fresnel import pane_coefficients
from reconstruct.net.onthefly import ASSUMED_MODELS, WindowConfig, flip_item, item_from_stream
from reconstruct.net.train import TrainConfig, assumed_glass_feed

CFG = WindowConfig(crop=12, n_obs=5, window_steps=9)


def _stream(theta, n, model, seed=0):
    rng = np.random.default_rng(seed)
    S, steps = CFG.crop, 400
    phi = rng.uniform(0, np.pi) + 2 * np.pi * 30.0 * (np.arange(steps) + 0.5) / 20000.0
    co = pane_coefficients(theta, n, model=model)
    maps = {"theta": theta, "R_perp": co["R_perp"], "R_par": co["R_par"], "phi_perp": 0.4 + 0.3 * theta}
    spikes = (rng.random((steps, S, S)) < 0.3).astype(np.uint8)
    T, R = rng.random((S, S)), rng.random((S, S))
    return spikes, 40 + np.arange(CFG.n_obs) * 60, phi, phi + 0.01, (T, R), maps


def _theta():
    yy, xx = np.mgrid[0 : CFG.crop, 0 : CFG.crop] / CFG.crop
    return np.deg2rad(35.0 + 30.0 * xx + 5.0 * yy)


@pytest.mark.parametrize("model", ASSUMED_MODELS)
def test_assumed_zeta_of_the_true_glass_is_the_true_zeta(model):
    """Oracle: where the assumed glass is the pane's own (n 1.5, same model), zeta_a_<model> is the item's zeta
    (paper Eq. (2) from the same coefficients); under the other model it is not, and a thin slab reflects more.
    """
    it = item_from_stream(*_stream(_theta(), 1.5, model), 1.0, dataclasses.replace(CFG, assumed_n=1.5))
    torch.testing.assert_close(it[f"zeta_a_{model}"], it["zeta"], rtol=0, atol=1e-6)
    other = next(m for m in ASSUMED_MODELS if m != model)
    assert float((it[f"zeta_a_{other}"] - it["zeta"]).abs().max()) > 0.01
    assert float(it["zeta_a_thin_slab"].mean()) > float(it["zeta_a_single"].mean())


def test_a_denser_glass_reads_as_a_smaller_zeta_and_flips_carry_it():
    """A pane of n 1.72 assumed to be 1.5: the assumed zeta is smaller (the scale error of --zeta self on test_001);
    mirrored items move the assumed zetas with their pixels, like zeta.
    """
    it = item_from_stream(*_stream(_theta(), 1.72, "single", seed=2), 1.0, dataclasses.replace(CFG, assumed_n=1.5))
    ratio = float(it["zeta_a_single"].mean() / it["zeta"].mean())
    assert 0.5 < ratio < 0.8
    f = flip_item(it, 5)
    torch.testing.assert_close(f["zeta_a_single"], it["zeta_a_single"].flip(-1).transpose(-1, -2), rtol=0, atol=0)
    with pytest.raises(ConfigError, match="theta"):
        args = list(_stream(_theta(), 1.5, "single"))
        args[5] = {k: v for k, v in args[5].items() if k != "theta"}
        item_from_stream(*args, 1.0, dataclasses.replace(CFG, assumed_n=1.5))


def _batch(B=4):
    g = torch.Generator().manual_seed(0)
    z = 0.05 + 0.02 * torch.rand(B, 5, 6, 6, generator=g)
    return {"zeta_a_single": 0.6 * z, "zeta_a_thin_slab": 1.1 * z}, z


def test_feed_picks_the_closer_model_when_right_and_the_other_when_not():
    b, z = _batch()
    scale = torch.full((4,), 1.3)
    cfg = TrainConfig(assumed_prob=1.0, assumed_right=1.0)
    feed, s = assumed_glass_feed(b, z, scale, cfg, torch.Generator().manual_seed(1))
    torch.testing.assert_close(feed, b["zeta_a_thin_slab"])  # 1.1x is closer to the truth than 0.6x
    assert torch.all(s == 1.0)
    feed, _ = assumed_glass_feed(b, z, scale, dataclasses.replace(cfg, assumed_right=0.0), torch.Generator().manual_seed(1))
    torch.testing.assert_close(feed, b["zeta_a_single"])
    feed, s = assumed_glass_feed(b, z, scale, dataclasses.replace(cfg, assumed_prob=0.0), torch.Generator().manual_seed(1))
    torch.testing.assert_close(feed, z)
    assert torch.all(s == 1.3)
    with pytest.raises(ConfigError, match="assumed_n"):
        assumed_glass_feed({}, z, scale, cfg, torch.Generator())


def test_network_feeds_zeta_feed_and_keeps_zeta_gt_for_the_losses():
    from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights

    net = init_weights(PolSpikeNet(NetConfig(arch="v2", use_rir=False, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), n_obs=5)), torch.Generator().manual_seed(0)).eval()
    g = torch.Generator().manual_seed(3)
    I = 0.1 + 0.3 * torch.rand(2, 5, 8, 8, generator=g)
    phi = (torch.arange(5) * math.radians(31.5)).repeat(2, 1)
    zg = 0.1 + 0.2 * torch.rand(I.shape, generator=g)
    with torch.no_grad():
        a = net(I, phi, zeta_gt=zg, alpha=1.0)
        b = net(I, phi, zeta_gt=zg, alpha=1.0, zeta_feed=zg)
        torch.testing.assert_close(a.T, b.T, rtol=0, atol=0)
        c = net(I, phi, zeta_gt=zg, alpha=1.0, zeta_feed=0.5 * zg)
    torch.testing.assert_close(c.zeta_used, 0.5 * zg)
    assert c.zeta_gt is zg and float((c.T - a.T).abs().max()) > 1e-4
    with pytest.raises(ShapeError, match="zeta_feed"):
        net(I, phi, zeta_gt=zg[:, :, :4], alpha=1.0, zeta_feed=zg)
