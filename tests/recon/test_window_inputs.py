"""What a network reads beside its windows: one record (WindowInputs) checked against the configuration's inputs, and
the configuration's feature combinations checked when it is made (ConfigError), never at the forward pass.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError, ShapeError
from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights
from reconstruct.stream.window_inputs import EXTRA_INPUTS, WindowInputs

SMALL = NetConfig(arch="v2", lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False, floor=False)
CONFIGS = {
    "plain": SMALL,
    "mean": dataclasses.replace(SMALL, use_mean=True),
    "harm": dataclasses.replace(SMALL, use_mean=True, use_harm=True),
    "wide": dataclasses.replace(SMALL, use_mean=True, use_wide=True),
    "span": dataclasses.replace(SMALL, use_mean=True, span_level=True),
}
"""Each feature that adds an input, on its own (the documented reader of each input: NetConfig's help strings)."""
READS = {"plain": set(), "mean": {"I_mean"}, "harm": {"I_mean", "I_harm"}, "wide": {"I_mean", "I_wide"}, "span": {"I_mean", "I_harm", "exposure", "span_steps"}}


def _full(B=2, N=7, H=16, W=16, seed=0) -> WindowInputs:
    g = torch.Generator().manual_seed(seed)
    I = 0.05 + 0.4 * torch.rand(B, N, H, W, generator=g)
    phi = ((torch.arange(N) - N // 2) * 0.55)[None].repeat(B, 1)
    return WindowInputs(I, phi, I_mean=0.5 * I.mean(1), I_harm=0.01 * torch.rand(B, 2, H, W, generator=g), I_wide=I.clone(), exposure=2.0, span_steps=350)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_a_network_reads_exactly_its_configurations_inputs(name):
    cfg = CONFIGS[name]
    assert cfg.inputs == READS[name]
    net = init_weights(PolSpikeNet(cfg), torch.Generator().manual_seed(1)).eval()
    x = _full().only(cfg.inputs)
    Z = torch.full_like(x.I, 0.2)
    with torch.no_grad():
        out = net(x.I, x.phi, zeta_gt=Z, alpha=1.0, **x.extras())  # exactly what it reads: runs
    assert torch.isfinite(out.T).all()
    for k in cfg.inputs:  # each input it reads, left out: a one-line ShapeError naming it
        with pytest.raises(ShapeError, match=f"missing: {k}$") as e:
            net(x.I, x.phi, zeta_gt=Z, alpha=1.0, **dataclasses.replace(x, **{k: None}).extras())
        assert "\n" not in str(e.value)
    for k in set(EXTRA_INPUTS) - cfg.inputs:  # an input it does not read: refused, by name
        with pytest.raises(ShapeError, match=f"does not read {k} "):
            net(x.I, x.phi, **{**x.extras(), k: getattr(_full(), k)})


def test_window_inputs_check_names_the_missing_input_and_the_wrong_shape():
    cfg = CONFIGS["span"]
    x = _full().only(cfg.inputs)
    assert x.check(cfg) is x
    with pytest.raises(ShapeError, match=r"missing: exposure, span_steps$"):
        dataclasses.replace(x, exposure=None, span_steps=None).check(cfg)
    with pytest.raises(ShapeError, match=r"I_harm must be \(2, 2, 16, 16\)"):
        dataclasses.replace(x, I_harm=x.I_harm[:, :1]).check(cfg)
    with pytest.raises(ShapeError, match=r"I_mean must be \(2, 16, 16\)"):
        dataclasses.replace(x, I_mean=x.I_mean[:1]).check(cfg)
    with pytest.raises(ShapeError, match=r"exposure must be a number or \(2,\)"):
        dataclasses.replace(x, exposure=torch.ones(3)).check(cfg)
    with pytest.raises(ShapeError, match=r"I must be \(B, 7, H, W\)"):
        dataclasses.replace(x, I=x.I[:, :5]).check(cfg)


def test_batches_and_rows_keep_the_inputs_of_each_window():
    rng = np.random.default_rng(2)
    wins = [WindowInputs(rng.random((7, 4, 4)), rng.random(7), I_mean=rng.random((4, 4)), I_harm=rng.random((2, 4, 4))) for _ in range(3)]
    b = WindowInputs.batch(wins, exposure=1.5, span_steps=350)
    assert b.I.shape == (3, 7, 4, 4) and b.I_mean.shape == (3, 4, 4) and b.I_wide is None and b.exposure == 1.5
    r = b.rows(1, 3)
    np.testing.assert_array_equal(r.I_harm[0], wins[1].I_harm)
    np.testing.assert_array_equal(r.phi[1], wins[2].phi)
    assert r.span_steps == 350


@pytest.mark.parametrize("bad, message", [
    (dict(use_harm=True), "use_harm needs use_mean"),
    (dict(base="anchored", span_level=True), "base = anchored, span_level need use_mean"),
    (dict(t_level_px=2.0), "t_level_px needs use_mean"),
    (dict(r_level_from="wide"), "r_level_from = wide needs use_mean"),
    (dict(lr_ch=9, heads=2), "lr_ch = 9 must be a multiple of heads = 2"),
])
def test_inconsistent_network_configs_are_refused_when_made(bad, message):
    with pytest.raises(ConfigError, match=message):
        dataclasses.replace(SMALL, **bad)


def test_cli_train_with_an_inconsistent_network_config_exits_2(tmp_path, polspike_cli):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('epochs = 1\n\n[net]\narch = "v2"\nuse_wide = true\n')
    r = polspike_cli("train", cfg, "--out", tmp_path / "run", timeout=300)
    polspike_cli.one_line_exit_2(r, "use_wide needs use_mean = true")
