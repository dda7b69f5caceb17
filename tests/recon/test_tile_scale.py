"""Tiles of one frame share the frame's brightness scale (v2), so tiles cannot disagree at their seams."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights, window_scale
from reconstruct.stream.window_inputs import WindowInputs
from reconstruct.video.tiling import run_model_on_windows


class _Recorder(torch.nn.Module):
    """Wraps a network and records the scale each call receives (None = the network's own)."""

    def __init__(self, net):
        super().__init__()
        self.net, self.cfg, self.seen = net, net.cfg, []

    @property
    def pad_multiple(self):
        return self.net.pad_multiple

    def forward(self, I, phi, scale=None):
        self.seen.append(None if scale is None else scale.clone())
        return self.net(I, phi, scale=scale)


def _frame(H=64, W=128, seed=0):
    rng = np.random.default_rng(seed)
    I = rng.uniform(0.5, 1.0, (1, 7, H, W)).astype(np.float32)
    I[..., : W // 2] *= 0.08  # the left tile's own mean rounds to 1/16, the right one's to 1/2
    I[..., W // 2 :] *= 0.6
    return I, np.linspace(0.0, np.pi, 7, dtype=np.float32)[None]


def test_every_tile_gets_the_whole_frames_scale():
    net = init_weights(PolSpikeNet(NetConfig(arch="v2", use_rir=False)), torch.Generator().manual_seed(1)).eval()
    rec = _Recorder(net)
    I, phi = _frame()
    run_model_on_windows(rec, WindowInputs(I, phi), tile=64, margin=16, max_batch=1)
    whole = float(window_scale(torch.as_tensor(I)).reshape(()))
    own = [float(window_scale(torch.as_tensor(I[..., :64])).reshape(())), float(window_scale(torch.as_tensor(I[..., 64:])).reshape(()))]
    assert own[0] != own[1]  # the case that made seams: each tile's own power of two differs
    assert len(rec.seen) == 2 and all(s is not None for s in rec.seen)
    assert [float(s.reshape(())) for s in rec.seen] == [whole, whole]


def test_explicit_scale_equal_to_the_default_changes_nothing():
    net = init_weights(PolSpikeNet(NetConfig(arch="v2", use_rir=False)), torch.Generator().manual_seed(2)).eval()
    I, phi = _frame(32, 32)
    x, p = torch.as_tensor(I), torch.as_tensor(phi)
    with torch.inference_mode():
        a = net(x, p)
        b = net(x, p, scale=window_scale(x).reshape(1))
        c = net(x, p, scale=4.0 * window_scale(x).reshape(1))
    assert torch.equal(a.T, b.T) and torch.equal(a.R, b.R)
    assert not torch.allclose(a.T, c.T)  # the scale really reaches the parameter branch


def test_v1_refuses_a_scale():
    from polinfra.errors import ConfigError

    net = PolSpikeNet(NetConfig(arch="v1", use_rir=False)).eval()
    I, phi = _frame(32, 32)
    with pytest.raises(ConfigError, match="v2 option"):
        net(torch.as_tensor(I), torch.as_tensor(phi), scale=torch.ones(1))


def test_tiles_keep_the_r_level_blur_inside_their_margin():
    """A model whose R is a Gaussian blur of its input (as r_level_px blurs R - R_base) gives, tiled, the whole frame's R
    away from the frame's border: run_model_on_windows widens the tiles' margin to the blur's 3-sigma radius.
    """
    import types

    import numpy as np

    from reconstruct.physics.span import gaussian_blur
    from reconstruct.video.tiling import run_model_on_windows

    sigma = 8.0

    class Blur:
        cfg = NetConfig(n_obs=3, r_level_px=sigma, arch="v1")
        pad_multiple = 4

        def __call__(self, I, phi, **kw):
            T = I[:, 0]
            return types.SimpleNamespace(T=T, R=gaussian_blur(T, sigma), T_base=T, R_base=T)

    rng = np.random.default_rng(0)
    I = rng.random((1, 3, 96, 120)).astype(np.float32)
    phi = np.zeros((1, 3), np.float32)
    whole = run_model_on_windows(Blur(), WindowInputs(I, phi), tile=0)["R"][0]
    tiled = run_model_on_windows(Blur(), WindowInputs(I, phi), tile=32, margin=4)["R"][0]
    r = 24  # near the frame's border the tiles see replicated, the whole frame reflected pixels
    np.testing.assert_allclose(tiled[r:-r, r:-r], whole[r:-r, r:-r], atol=1e-5)
