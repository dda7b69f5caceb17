"""PolSpikeNet: parameter count, shapes, supp. Eq. (19), softmax weights, ablations, gradients."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from polinfra.errors import ConfigError, ShapeError
from reconstruct.net.network import AngleAttention, NetConfig, PolSpikeNet, count_parameters, init_weights

PAPER_PARAMS = 0.51e6  # supp. Sec. 10: "about 0.51M parameters"


def _window(B=2, N=7, H=16, W=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    I = 0.1 + 0.3 * torch.rand(B, N, H, W, generator=g)
    phi = (torch.arange(N) - N // 2).float() * math.radians(31.5) + torch.rand(B, 1, generator=g)
    return I, phi


def test_parameter_count_matches_paper():
    n = count_parameters(PolSpikeNet(NetConfig(arch="v1")))
    print(f"PolSpikeNet v1 trainable parameters: {n:,} (paper: about 0.51 M)")
    assert abs(n - PAPER_PARAMS) <= 0.10 * PAPER_PARAMS


def test_v2_flops_per_frame_within_issue_budget():
    """<= 25 GFLOP per 400x250 frame (counted), >= 10x fewer than v1 (measured on a 64x64 window, FLOPs scale with area)."""
    from torch.utils.flop_counter import FlopCounterMode

    I, phi = _window(B=1, H=64, W=64)
    flops = {}
    for arch in ("v1", "v2"):
        m = PolSpikeNet(NetConfig(arch=arch, use_rir=False)).eval()
        fc = FlopCounterMode(display=False)
        with torch.inference_mode(), fc:
            m(I, phi)
        flops[arch] = fc.get_total_flops() * (252 * 400) / (64 * 64)
    assert flops["v2"] <= 25e9
    assert flops["v1"] >= 10 * flops["v2"]


def test_v2_cached_features_give_the_same_output():
    """Per-observation features computed once (as a stream does) reproduce the plain forward exactly."""
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(0)).eval()
    I, phi = _window(B=2, H=16, W=24)
    B, N, H, W = I.shape
    with torch.no_grad():
        ref = m(I, phi)
        from reconstruct.net.network import window_scale

        s = window_scale(I).reshape(B, 1).expand(B, N).reshape(-1)
        f, g = m.encode_obs(I.reshape(B * N, H, W), s)
        # frames encoded one at a time (a cache filled frame by frame) give the same features
        f1 = torch.cat([m.encode_obs(I.reshape(B * N, H, W)[i : i + 1], s[i : i + 1])[0] for i in range(B * N)])
        out = m(I, phi, feats=(f1, g))
    torch.testing.assert_close(f1, f, atol=1e-5, rtol=1e-4)  # batched vs one-at-a-time convolutions: float rounding only
    torch.testing.assert_close(out.T, ref.T, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(out.weights, ref.weights, atol=1e-5, rtol=1e-4)
    with pytest.raises(ConfigError, match="RIR off"):  # RIR warps the frames: cached features would be wrong
        PolSpikeNet(NetConfig(use_rir=True))(I, phi, feats=(f, g))


def test_v2_brightness_scaling_by_two_is_exact():
    """The v2 scale is the window mean rounded to a power of two: doubling I leaves zeta and w unchanged and doubles T, R."""
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(2)).eval()
    I, phi = _window(B=1, H=16, W=16)
    with torch.no_grad():
        a, b = m(I.double().float(), phi), m(2 * I, phi)
    torch.testing.assert_close(b.zeta_hat, a.zeta_hat, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(b.weights, a.weights, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(b.T_base, 2 * a.T_base, atol=1e-5, rtol=1e-4)


def test_v2_zeta_parameters_are_smooth_upsampled_maps():
    """(a0, ac, as) are a bilinear upsampling of a 1/4-resolution map, whatever the input (here noise):
    piecewise linear between the low-resolution sample centres (full-resolution x = 1.5 + 4 j), so
    the second difference along x vanishes at every pixel whose neighbours share a segment.
    """
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(3)).eval()
    I, phi = _window(B=1, H=32, W=32, seed=5)
    with torch.no_grad():
        _, _, a = m.param(I, phi)
    d2 = (a[..., 2:] - 2 * a[..., 1:-1] + a[..., :-2]).abs()  # centred at x = 1..30
    same_segment = [i for i in range(30) if (i + 1) % 4 in (0, 3)]  # x-1, x, x+1 between two sample centres
    other = [i for i in range(2, 30) if i not in same_segment]
    assert d2[..., same_segment].max() < 1e-5 * (1 + a.abs().max())
    assert d2[..., other].max() > 1e-4  # the map does vary (the test can fail)


def test_forward_shapes_and_zeta_weights():
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(0))
    I, phi = _window()
    out = m(I, phi)
    assert out.T.shape == (2, 16, 16) and out.R.shape == (2, 16, 16)
    assert out.zeta_hat.shape == I.shape and out.weights.shape == I.shape
    assert torch.all((out.zeta_hat > 0) & (out.zeta_hat < 1))
    torch.testing.assert_close(out.weights.sum(1), torch.ones(2, 16, 16), atol=1e-5, rtol=0)  # softmax over the window
    for t in (out.T, out.R, out.conf, out.res):
        assert torch.isfinite(t).all()


def test_zeta_follows_supp_eq19():
    """zeta_k = sigmoid(a0 + ac cos 2phi_k + as sin 2phi_k): logit(zeta) is a harmonic of 2phi."""
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(1))
    I, phi = _window(seed=3)
    zeta, _, _ = m.param(I, phi)
    logit = torch.log(zeta / (1 - zeta))
    c, s = torch.cos(2 * phi)[..., None, None], torch.sin(2 * phi)[..., None, None]
    A = torch.stack([torch.ones_like(c), c, s], -1).expand(*logit.shape, 3).permute(0, 2, 3, 1, 4)  # (B,H,W,N,3)
    y = logit.permute(0, 2, 3, 1)[..., None]
    coef = torch.linalg.lstsq(A.double(), y.double()).solution
    torch.testing.assert_close((A.double() @ coef)[..., 0], y[..., 0].double(), atol=1e-4, rtol=0)


def test_untrained_refinement_returns_solver_output_nearly():
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(0))
    out = m(*_window())
    assert (out.T - out.T_base).abs().max() < 0.05


def test_teacher_forcing_alpha_one_uses_gt_zeta():
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(0))
    I, phi = _window()
    z = torch.full_like(I, 0.2)
    out = m(I, phi, zeta_gt=z, alpha=1.0)
    torch.testing.assert_close(out.zeta_used, z)
    half = m(I, phi, zeta_gt=z, alpha=0.5)
    torch.testing.assert_close(half.zeta_used, 0.5 * z + 0.5 * half.zeta_hat)
    with pytest.raises(ShapeError):
        m(I, phi, alpha=0.5)


@pytest.mark.parametrize("arch", ["v1", "v2"])
@pytest.mark.parametrize("switch", ["use_rir", "use_attention", "use_conf"])
def test_ablation_switches_run(switch, arch):
    base = NetConfig(arch=arch, use_rir=False)
    cfg = dataclasses.replace(base, **{switch: not getattr(base, switch)})
    m = init_weights(PolSpikeNet(cfg), torch.Generator().manual_seed(0))
    out = m(*_window(B=1))
    assert torch.isfinite(out.T).all()
    if switch == "use_attention":
        assert m.param.att is None and count_parameters(m) < count_parameters(PolSpikeNet(base))
    if switch == "use_conf":
        assert m.solver_cfg.lambda_low == m.solver_cfg.lambda_high


def test_attention_is_equivariant_to_observation_order():
    """Softmax over the N observations: permuting them (with their angles) permutes the output."""
    att = AngleAttention(8, 2)
    init_weights(att, torch.Generator().manual_seed(0))
    f = torch.randn(1, 5, 8, 3, 3, generator=torch.Generator().manual_seed(1))
    phi = torch.rand(1, 5, generator=torch.Generator().manual_seed(2))
    p = torch.tensor([3, 0, 4, 1, 2])
    torch.testing.assert_close(att(f, phi)[:, p], att(f[:, p], phi[:, p]), atol=1e-5, rtol=1e-5)


def test_gradients_reach_both_branches():
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(0))
    I, phi = _window(B=1)
    out = m(I, phi)
    (out.T.mean() + out.R.mean()).backward()
    assert m.param.enc[0].conv.weight.grad.abs().sum() > 0
    assert m.refine.e1[0].conv.weight.grad.abs().sum() > 0


def test_bad_shapes_raise():
    m = PolSpikeNet(NetConfig(use_rir=False))
    I, phi = _window()
    with pytest.raises(ShapeError):
        m(I[:, :5], phi[:, :5])
    with pytest.raises(ShapeError):
        m(I[..., :15, :], phi)


def test_bf16_autocast_stays_close_to_float32():
    """Optional bf16 autocast (CPU here; the same code path as CUDA): finite, solver in float32, close to float32."""
    m = init_weights(PolSpikeNet(NetConfig(use_rir=False)), torch.Generator().manual_seed(0)).eval()
    I, phi = _window(B=1, H=16, W=16)
    with torch.no_grad():
        ref = m(I, phi)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = m(I, phi)
    assert out.zeta_hat.dtype == torch.float32 and out.T_base.dtype == torch.float32
    assert torch.isfinite(out.T).all()
    assert (out.T.float() - ref.T).abs().max() < 0.05
    assert (out.zeta_hat - ref.zeta_hat).abs().max() < 0.02
