"""D = R - T from every spike of the long span (net.span_level): the span's inverse-variance weights against a
Monte Carlo of the spikes, the blend against its closed form (it keeps the long mean, takes an exact span's D, leaves
pixels without weight alone), and the wiring: only on an external zeta, the stream hands the network what the store
does, tiles agree with whole frames, training items carry the span's length and exposure per image.
"""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
import torch

from polinfra.errors import ShapeError
from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights
from reconstruct.physics.span import SPAN_SATURATION, harmonic_of, long_span_separation, span_blend, span_weights
from reconstruct.physics.zeta import zeta_from_maps
from reconstruct.stream.groups import span_harmonic
from reconstruct.stream.window_inputs import WindowInputs
from tests.recon.test_long_span import _static_scene

SMALL = NetConfig(arch="v2", feat_ch=8, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False, use_mean=True, base="anchored", anchor_zbar="harmonic")
SPAN = 350
PHI_T = 0.4 + np.arange(SPAN) * 2 * math.pi * 30 / 20000  # 30 rev/s at 20 kHz: about one turn of 2 phi
WIN = 175 + (np.arange(7) - 3) * 58  # the N = 7 window centres inside the span


def _scene(H=6, W=5, seed=0):
    return _static_scene(seed=seed, H=H, W=W)  # random layers and pane maps (test_long_span's)


def _light(T, R, maps):
    """Per-step intensity (SPAN, H, W) of paper Eq. (1)-(2) for a static scene, the span's exact mean over a whole
    number of half turns, and the windows' zeta and angles.
    """
    z_t = zeta_from_maps(maps, PHI_T, dtype=torch.float64).numpy()
    I_t = 0.5 * (z_t * R + (1 - z_t) * T)
    phi_w = torch.from_numpy(PHI_T[WIN])[None]
    Zw = zeta_from_maps(maps, phi_w, dtype=torch.float64)
    return I_t, phi_w, Zw


def _design(phi):
    return np.stack([np.ones_like(phi), np.cos(2 * phi), np.sin(2 * phi)])


def test_span_weights_are_the_inverse_variance_of_the_span_difference_under_bernoulli_spikes():
    """Monte Carlo oracle: spikes drawn per step with probability I_t x exposure; the spread of the span's D over
    1500 draws matches 1 / span_weights within 15 % per pixel (the weights' closed form, not fitted).
    """
    T, R, maps = _scene()
    I_t, phi_w, Zw = _light(T, R, maps)
    e = 1.2
    rng = np.random.default_rng(5)
    X = _design(PHI_T)
    Ds = []
    means = []
    for _ in range(1500):
        s = (rng.random(I_t.shape) < I_t * e).astype(np.float64)
        h = span_harmonic(np.tensordot(X, s, axes=(1, 0)), PHI_T, e)
        Im = s.mean(0) / e
        Tl, Rl = long_span_separation(torch.from_numpy(Im)[None], torch.from_numpy(h.astype(np.float64))[None], Zw, phi_w)
        Ds.append((Rl - Tl)[0].numpy())
        means.append(Im)
    w = span_weights(torch.from_numpy(np.mean(means, 0))[None], Zw, phi_w, e, SPAN)[0].numpy()
    ratio = np.var(Ds, 0) * w
    assert np.all(np.abs(ratio - 1) < 0.15), ratio


def test_span_weights_are_zero_where_the_pixel_saturates():
    T, R, maps = _scene()
    _, phi_w, Zw = _light(T, R, maps)
    Im = torch.full((1, *T.shape), 0.2, dtype=torch.float64)
    e = 2.0
    w = span_weights(Im, Zw, phi_w, e, SPAN)
    assert bool((w > 0).all())
    peak = Im.clone()
    peak[0, 1, 2] = SPAN_SATURATION / e  # one window at the ceiling: that pixel's span is clipped
    Im2 = Im.clone()
    Im2[0, 3, 3] = 0.999 / e
    w2 = span_weights(Im2, Zw, phi_w, e, SPAN, I_peak=peak)
    assert float(w2[0, 1, 2]) == 0.0 and float(w2[0, 3, 3]) == 0.0
    keep = torch.ones_like(w2, dtype=torch.bool)
    keep[0, 1, 2] = keep[0, 3, 3] = False
    torch.testing.assert_close(w2[keep], w[keep])


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_span_blend_takes_an_exact_span_and_keeps_the_long_mean(sigma):
    """A noise-free static span gives the exact D (up to the documented floor); a separation off by a constant 0.1 in
    D is moved onto it when the span's weight is large (any sigma: the offset is smooth), and T + a D, the long
    mean's relation 2 I_mean = T + zbar D, is unchanged for any weights.
    """
    T, R, maps = _scene(H=12, W=10)
    I_t, phi_w, Zw = _light(T, R, maps)
    h = torch.from_numpy(span_harmonic(np.tensordot(_design(PHI_T), I_t, axes=(1, 0)), PHI_T).astype(np.float64))[None]
    Im = torch.from_numpy(I_t[: int(round(20000 / 60))].mean(0))[None]  # half a turn: the exact level
    Ts, Rs = long_span_separation(Im, h, Zw, phi_w)
    a = harmonic_of(Zw, phi_w)[0]
    T0 = torch.from_numpy(T)[None] - 0.05
    R0 = T0 + (Rs - Ts) + 0.1
    big = torch.full_like(T0, 1e9)
    T1, R1 = span_blend(T0, R0, Im, h, Zw, phi_w, big, sigma, 0.5)
    torch.testing.assert_close(R1 - T1, Rs - Ts, rtol=0, atol=1e-6)
    torch.testing.assert_close(T1 + a * (R1 - T1), T0 + a * (R0 - T0), rtol=0, atol=1e-12)
    w = torch.rand(T0.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 50
    T2, R2 = span_blend(T0, R0, Im, h, Zw, phi_w, w, sigma, 0.5)
    torch.testing.assert_close(T2 + a * (R2 - T2), T0 + a * (R0 - T0), rtol=0, atol=1e-12)
    assert float((R2 - R0).abs().max()) > 1e-3


def test_span_blend_gain_is_the_inverse_variance_combination_and_zero_without_weight():
    """Per pixel (sigma 0) the new D is D + lam (D_span - D), lam = tol^2 w / (tol^2 w + 1): the inverse-variance
    combination of the separation (error tol) and the span (variance 1 / w); a pixel of weight 0 is left exactly.
    """
    T, R, maps = _scene()
    I_t, phi_w, Zw = _light(T, R, maps)
    h = torch.from_numpy(span_harmonic(np.tensordot(_design(PHI_T), I_t, axes=(1, 0)), PHI_T).astype(np.float64))[None]
    Im = torch.from_numpy(I_t.mean(0))[None]
    Ts, Rs = long_span_separation(Im, h, Zw, phi_w)
    T0 = torch.from_numpy(T)[None]
    R0 = torch.from_numpy(R)[None] + 0.2
    w = torch.linspace(0, 40, T0.numel(), dtype=torch.float64).reshape(T0.shape)
    tol = 0.3
    T1, R1 = span_blend(T0, R0, Im, h, Zw, phi_w, w, 0.0, tol)
    lam = tol**2 * w / (tol**2 * w + 1)
    D0 = R0 - T0
    torch.testing.assert_close(R1 - T1, D0 + lam * ((Rs - Ts) - D0), rtol=1e-9, atol=1e-9)
    assert float(w[0, 0, 0]) == 0.0 and float(T1[0, 0, 0]) == float(T0[0, 0, 0]) and float(R1[0, 0, 0]) == float(R0[0, 0, 0])


def _net(**kw):
    n = init_weights(PolSpikeNet(dataclasses.replace(SMALL, **kw)), torch.Generator().manual_seed(0)).eval()
    with torch.no_grad():
        for pn, p in n.refine.named_parameters():
            p.copy_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(len(pn))))
    return n


def _inputs(H=24, W=24):
    T, R, maps = _scene(H, W, seed=2)
    I_t, phi_w, Zw = _light(T, R, maps)
    X = _design(PHI_T)
    h = torch.from_numpy(span_harmonic(np.tensordot(X, I_t, axes=(1, 0)), PHI_T).astype(np.float32))[None]
    I = torch.from_numpy(I_t[WIN].astype(np.float32))[None] * (1 + 0.05 * torch.randn(1, 7, H, W, generator=torch.Generator().manual_seed(4)))
    return I, phi_w.float(), torch.from_numpy(I_t.mean(0).astype(np.float32))[None], h, Zw.float()


def test_span_level_network_moves_d_on_an_external_zeta_only_and_needs_the_exposure():
    I, phi, Im, h, Z = _inputs()
    off, on = _net(), _net(span_level=True)
    kw = dict(I_mean=Im, I_harm=h, exposure=1.0, span_steps=SPAN)
    with torch.no_grad():
        a = off(I, phi, zeta_gt=Z, alpha=1.0, I_mean=Im)
        b = on(I, phi, zeta_gt=Z, alpha=1.0, **kw)
        assert float(((b.R - b.T) - (a.R - a.T)).abs().max()) > 1e-3  # moved toward the span's D
        torch.testing.assert_close(b.T_base, a.T_base)
        # the learned zeta: left as it is (the floors off: given the exposure, the floor also bounds the noise by the
        # spikes' own, which the network without the exposure cannot)
        c = _net(span_level=True, floor=False)(I, phi, **kw)
        d = _net(floor=False)(I, phi, I_mean=Im)
        torch.testing.assert_close(c.T, d.T)
        torch.testing.assert_close(c.R, d.R)
        with pytest.raises(ShapeError, match="exposure"):
            on(I, phi, zeta_gt=Z, alpha=1.0, I_mean=Im, I_harm=h)
        with pytest.raises(ShapeError, match="I_harm"):
            on(I, phi, zeta_gt=Z, alpha=1.0, I_mean=Im, exposure=1.0, span_steps=SPAN)


def test_span_level_passes_the_refinements_gradient_in_training():
    """On a forced step (external zeta, alpha = 1) the span's move is an input: T's and R's gradients still reach the
    refinement (before, the blend ran under no_grad and replaced T and R, so a forced step trained nothing of it),
    and the values are the inference path's within float32 rounding of adding the move.
    """
    I, phi, Im, h, Z = _inputs()
    kw = dict(I_mean=Im, I_harm=h, exposure=1.0, span_steps=SPAN)
    net = _net(span_level=True, floor=False).train()
    out = net(I, phi, zeta_gt=Z, alpha=1.0, **kw)
    (out.T.mean() + out.R.mean()).backward()
    for dec in (net.refine.dec_t, net.refine.dec_r):
        assert dec.out.weight.grad is not None and float(dec.out.weight.grad.abs().max()) > 0
    with torch.no_grad():
        ref = net.eval()(I, phi, zeta_gt=Z, alpha=1.0, **kw)
    torch.testing.assert_close(out.T.detach().to(ref.T.dtype), ref.T, rtol=0, atol=1e-6)
    torch.testing.assert_close(out.R.detach().to(ref.R.dtype), ref.R, rtol=0, atol=1e-6)


class _BlendOnly(torch.nn.Module):
    """A per-pixel separation followed by the span_level blend, as PolSpikeNet applies it (a stand-in: the network's
    own frame-wide statistics would hide what the tiles' margin must cover).
    """

    def __init__(self, sigma):
        super().__init__()
        self.cfg = NetConfig(arch="v1", use_mean=True, span_level=True, span_level_px=sigma)

    def forward(self, I, phi, zeta_gt=None, alpha=0.0, I_mean=None, I_harm=None, exposure=None, span_steps=None):
        T = 2 * I_mean - 0.05
        R = T + 0.1 * I.std(1)
        w = span_weights(I_mean, zeta_gt, phi, exposure, span_steps, I_peak=I.max(1).values)
        T, R = span_blend(T, R, I_mean, I_harm, zeta_gt, phi, w, self.cfg.span_level_px, 0.5)
        return types.SimpleNamespace(T=T.float(), R=R.float(), T_base=T.float(), R_base=R.float())


def test_span_level_tiles_agree_with_the_whole_frame():
    """run_model_on_windows widens the tiles' margin to the span correction's blur radius (9 px at sigma 3), so tiles
    of 16 px asked for a 1 px margin agree with the whole frame.
    """
    from reconstruct.video.tiling import run_model_on_windows

    I, phi, Im, h, Z = _inputs(H=40, W=36)
    m = _BlendOnly(3.0)
    x = WindowInputs(I.numpy(), phi.numpy(), I_mean=Im.numpy(), I_harm=h.numpy(), exposure=1.0, span_steps=SPAN)
    whole = run_model_on_windows(m, x, tile=0, zeta=Z.numpy())
    tiled = run_model_on_windows(m, x, tile=16, margin=1, zeta=Z.numpy())
    inner = (slice(None), slice(9, -9), slice(9, -9))  # the frame's own border is padded differently (replicate vs reflect)
    np.testing.assert_allclose(tiled["R"][inner], whole["R"][inner], atol=1e-6)
    np.testing.assert_allclose(tiled["T"][inner], whole["T"][inner], atol=1e-6)
    assert float(np.abs(whole["R"] - (2 * Im.numpy() - 0.05 + 0.1 * I.numpy().std(1, ddof=1))).max()) > 1e-3  # the blend acted


class _SpanRecorder(torch.nn.Module):
    """Stands in for a span_level network: records the exposure and span length it is given."""

    def __init__(self):
        super().__init__()
        self.cfg = NetConfig(arch="v1", use_mean=True, span_level=True, span_level_px=2.0)
        self.seen: list[np.ndarray] = []  # the harmonics, per call (what test_long_span._streamed concatenates)
        self.span: list[tuple] = []

    def forward(self, I, phi, I_mean=None, I_harm=None, exposure=None, span_steps=None, **kw):
        self.span.append((exposure, span_steps))
        self.seen.append(I_harm.numpy().copy())
        T = 2 * I_mean
        return types.SimpleNamespace(T=T, R=T, T_base=T, R_base=T)


def test_stream_hands_a_span_level_network_the_store_exposure_span_and_harmonic(tmp_path):
    from tests.recon.test_long_span import _streamed

    rec = _SpanRecorder()
    got, src, g = _streamed(tmp_path, 37, 3, rec)
    assert set(rec.span) == {(src.exposure, g.span_steps)}
    assert g.span_steps == SPAN and g.exposure == src.exposure
    np.testing.assert_allclose(got, g.I_harm[3 : 3 + got.shape[0]], rtol=1e-5, atol=1e-6)


def test_training_items_carry_what_a_span_level_network_reads_and_the_forced_scores_use_it():
    """Window items with the long span carry its length; evaluate_model (the training validation and
    checkpoint-scores) hands a span_level network each item's exposure and span length, and its forced R moves
    (the self-calibrated zeta's path); without the span the batch is refused with what to set.
    """
    from polinfra.errors import ConfigError
    from reconstruct.net.onthefly import OnTheFlyWindows
    from reconstruct.net.train import TINY, batch_inputs, evaluate_model
    from tests.recon.test_train import _stream_item

    wcfg = dataclasses.replace(TINY.window, mean_steps=SPAN, crop=24)
    ds = OnTheFlyWindows(lambda s_, i: _stream_item(s_, i, wcfg), length=4, seed=3)
    item = ds[0]
    assert 0 < float(item["span_steps"]) <= SPAN + 1  # an odd span centred on the frame
    nets = {k: _net(**kw) for k, kw in {"off": {}, "on": {"span_level": True}}.items()}
    sc = {k: evaluate_model(n, ds, batch_size=4, forced=True) for k, n in nets.items()}
    assert all(np.isfinite(v["psnr_R_forced"]) for v in sc.values())
    assert sc["on"]["psnr_R_forced"] != sc["off"]["psnr_R_forced"]
    assert sc["on"]["psnr_T"] == sc["off"]["psnr_T"]  # the network's own zeta: unchanged
    with pytest.raises(ConfigError, match="mean_steps"):
        batch_inputs({"I": item["I"][None], "phi": item["phi"][None], "exposure": item["exposure"][None]}, "cpu", nets["on"].cfg)


def test_span_weights_take_one_exposure_and_span_per_image():
    T, R, maps = _scene()
    _, phi_w, Zw = _light(T, R, maps)
    Im = torch.full((2, *T.shape), 0.2, dtype=torch.float64)
    Z2, P2 = Zw.expand(2, -1, -1, -1), phi_w.expand(2, -1)
    both = span_weights(Im, Z2, P2, torch.tensor([1.0, 2.0]), torch.tensor([350.0, 100.0]))
    torch.testing.assert_close(both[0], span_weights(Im[:1], Zw, phi_w, 1.0, 350)[0])
    torch.testing.assert_close(both[1], span_weights(Im[:1], Zw, phi_w, 2.0, 100)[0])


def test_t_tolerance_caps_the_gain_where_zeta_mean_is_large():
    """Per pixel (sigma 0) with tol_t: lam = min(tol^2 w / (tol^2 w + 1), tol_t^2 w / (tol_t^2 w + a^2)), a = zeta's
    half-turn mean; the cap binds where a is large (T moves by a dD), and the long mean is kept either way.
    """
    T, R, maps = _scene()
    I_t, phi_w, Zw = _light(T, R, maps)
    h = torch.from_numpy(span_harmonic(np.tensordot(_design(PHI_T), I_t, axes=(1, 0)), PHI_T).astype(np.float64))[None]
    Im = torch.from_numpy(I_t.mean(0))[None]
    Ts, Rs = long_span_separation(Im, h, Zw, phi_w)
    T0, R0 = torch.from_numpy(T)[None], torch.from_numpy(R)[None] + 0.2
    w = torch.linspace(0.5, 400, T0.numel(), dtype=torch.float64).reshape(T0.shape)
    tol, tol_t = 0.3, 0.02
    a = harmonic_of(Zw, phi_w)[0]
    T1, R1 = span_blend(T0, R0, Im, h, Zw, phi_w, w, 0.0, tol, tol_t)
    lam = torch.minimum(tol**2 * w / (tol**2 * w + 1), tol_t**2 * w / (tol_t**2 * w + a * a))
    D0 = R0 - T0
    torch.testing.assert_close(R1 - T1, D0 + lam * ((Rs - Ts) - D0), rtol=1e-9, atol=1e-9)
    assert bool((tol_t**2 * w / (tol_t**2 * w + a * a) < tol**2 * w / (tol**2 * w + 1)).any())  # the cap binds somewhere
    torch.testing.assert_close(T1 + a * (R1 - T1), T0 + a * (R0 - T0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_span_move_is_equivariant_to_the_brightness_scale(sigma):
    """The weights scale with exposure^2 and the tolerances with the pixel's light (as the network sets them): a stream
    read at another exposure (an estimated one) gives the same layers up to that scale.
    """
    I, phi, Im, h, Z = _inputs()
    Im, h, I = Im.double(), h.double(), I.double()
    T = 2 * Im - 0.05
    R = T + 0.2 * I.std(1)

    def move(k, e):
        w = span_weights(Im * k, Z, phi, e, SPAN, I_peak=(I * k).max(1).values)
        return span_blend(T * k, R * k, Im * k, h * k, Z, phi, w, sigma, 2.0 * 2 * Im * k, 0.25 * 2 * Im * k)

    a, b = move(1.0, 1.3), move(1 / 1.11, 1.3 * 1.11)
    torch.testing.assert_close(b[0] * 1.11, a[0], rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(b[1] * 1.11, a[1], rtol=1e-6, atol=1e-9)
    assert float((a[1] - R).abs().max()) > 1e-3
