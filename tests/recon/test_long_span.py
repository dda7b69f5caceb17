"""The long span's first harmonic (net.use_harm): the spikes of the whole 17.5 ms span of the long spike
mean, not only the N windows', give R - T.  Checked against closed forms (a first harmonic, paper Eq. (1)-(2) on a
static scene), a direct least-squares fit of the raw spikes, the sign rule of the image symmetries, and the
stream / store / training-item paths agreeing with each other.
"""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError, ShapeError
from reconstruct.net.network import NetConfig, PolSpikeNet, SymmetryEnsemble, init_weights
from reconstruct.net.train import _widened
from reconstruct.physics.span import HARMONIC_FLOOR, harmonic_of, long_span_separation, zbar_of
from reconstruct.physics.symmetry import angle_map, harmonic_signs, symmetry_angles, symmetry_harmonic, symmetry_image
from reconstruct.physics.zeta import PaneMaps, zeta_from_maps
from reconstruct.stream.groups import SpikeMeanSums, span_harmonic, spike_mean_span

SMALL = NetConfig(arch="v2", feat_ch=8, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False, use_mean=True)


def _direct_fit(spikes: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(b, c) of s_t ~ a + b cos 2 phi_t + c sin 2 phi_t by numpy's lstsq on the raw spikes (the oracle)."""
    X = np.stack([np.ones_like(phi), np.cos(2 * phi), np.sin(2 * phi)], 1)
    coef = np.linalg.lstsq(X, spikes.reshape(len(phi), -1).astype(np.float64), rcond=None)[0]
    return coef[1:].reshape(2, *spikes.shape[1:])


def test_harmonic_of_recovers_a_first_harmonic_and_zbar_is_its_level():
    rng = np.random.default_rng(0)
    a, b, c = (rng.uniform(-1, 1, (2, 5, 6)) for _ in range(3))
    phi = 0.3 + np.arange(7) * math.radians(31.5) + rng.uniform(0, 0.1, (2, 7))
    z = a[:, None] + b[:, None] * np.cos(2 * phi)[..., None, None] + c[:, None] * np.sin(2 * phi)[..., None, None]
    got = harmonic_of(torch.from_numpy(z), torch.from_numpy(phi))
    for g, want in zip(got, (a, b, c)):
        np.testing.assert_allclose(g.numpy(), want, atol=1e-5)
    np.testing.assert_allclose(zbar_of(z, phi), a, atol=1e-5)  # numpy in, numpy out


@pytest.mark.parametrize("chunk", [1, 37, 5000])
def test_streamed_span_harmonic_is_the_direct_fit_of_the_raw_spikes(chunk):
    """SpikeMeanSums fed in chunks of any size gives each frame's span mean and first harmonic exactly as a direct
    least-squares fit of that span's raw spikes (numpy lstsq), spans clipped at the stream's ends included.
    """
    rng = np.random.default_rng(1)
    n, H, W = 1500, 4, 5
    phi = 0.2 + np.cumsum(rng.uniform(0.009, 0.010, n))  # ~30 rev/s at 20 kHz, with jitter
    spikes = (rng.random((n, H, W)) < 0.3 + 0.2 * np.cos(2 * phi - 0.4)[:, None, None]).astype(np.uint8)
    centres = np.array([100, 400, 700, 1000, 1450])
    sums = SpikeMeanSums(centres, 351, n, (H, W), phi)
    for s0 in range(0, n, chunk):
        sums.feed(s0, spikes[s0 : s0 + chunk])
    for j, c in enumerate(centres):
        lo, hi = spike_mean_span(c, 351, n)
        np.testing.assert_allclose(sums.harmonic(j, 0.5), _direct_fit(spikes[lo:hi], phi[lo:hi]) / 0.5, atol=2e-5)
        np.testing.assert_allclose(sums.mean(j, 0.5), spikes[lo:hi].sum(0) / ((hi - lo) * 0.5), rtol=1e-6)


@pytest.mark.parametrize("dtype", [np.uint8, np.bool_])
def test_harmonic_sums_are_the_weighted_step_sums_in_float64(dtype):
    """harmonic_accumulate adds sum_t s_t (1, cos 2 phi_t, sin 2 phi_t) per pixel: numpy's float64 sum of the same
    products is the oracle (integer counts exact), onto what the sums held before.
    """
    from reconstruct.stream.groups import harmonic_accumulate

    rng = np.random.default_rng(4)
    spikes = (rng.random((300, 6, 7)) < 0.35).astype(dtype)
    p = 2.0 * rng.uniform(0.0, 7.0, 300)
    acc = rng.normal(size=(3, 6, 7))
    want = acc + np.stack([spikes.sum(0, dtype=np.float64), (np.cos(p)[:, None, None] * spikes).sum(0), (np.sin(p)[:, None, None] * spikes).sum(0)])
    harmonic_accumulate(acc, spikes, np.cos(p), np.sin(p))
    np.testing.assert_allclose(acc, want, rtol=0, atol=1e-11)


def test_spike_mean_sums_without_angles_has_no_harmonic_and_the_same_mean():
    from polinfra.errors import DataFormatError

    rng = np.random.default_rng(2)
    spikes = (rng.random((800, 3, 3)) < 0.4).astype(np.uint8)
    a = SpikeMeanSums(np.array([400]), 351, 800, (3, 3))
    b = SpikeMeanSums(np.array([400]), 351, 800, (3, 3), np.linspace(0, 8, 800))
    a.feed(0, spikes)
    b.feed(0, spikes)
    with pytest.raises(DataFormatError, match="phi_step"):
        a.harmonic(0)
    np.testing.assert_allclose(a.mean(0), b.mean(0), rtol=0, atol=1e-7)


def test_a_span_too_short_to_see_the_harmonic_gives_none():
    """A still polarizer (every step at one angle) cannot tell the harmonic: b = c = 0, not a division by zero."""
    sums = np.stack([np.full((2, 2), 10.0), np.full((2, 2), 10.0), np.zeros((2, 2))])
    out = span_harmonic(sums, np.zeros(10))
    assert np.isfinite(out).all() and float(np.abs(out).max()) < 1e-3
    assert span_harmonic(np.zeros((3, 2, 2)), np.zeros(0)).shape == (2, 2, 2)


def _static_scene(seed=3, H=6, W=7):
    rng = np.random.default_rng(seed)
    T = rng.uniform(0.05, 0.6, (H, W))
    R = rng.uniform(0.05, 0.9, (H, W))
    maps = PaneMaps(R_perp=rng.uniform(0.08, 0.3, (H, W)), R_par=rng.uniform(0.0, 0.05, (H, W)), phi_perp=rng.uniform(0, math.pi, (H, W)))
    return T, R, maps


def test_long_span_separation_is_exact_on_a_static_scene():
    """Paper Eq. (1)-(2) per step over a 351-step span (a static scene, no noise): the span's mean and first harmonic
    give T and R = T + D, D shrunk only by the documented floor b^2 / (b^2 + floor).
    """
    T, R, maps = _static_scene()
    phi_t = 0.7 + np.arange(351) * 2 * math.pi * 30 / 20000  # 30 rev/s at 20 kHz
    z_t = zeta_from_maps(maps, phi_t, dtype=torch.float64).numpy()  # (351, H, W), per step
    I_t = 0.5 * (z_t * R + (1 - z_t) * T)  # paper Eq. (1)
    X = np.stack([np.ones_like(phi_t), np.cos(2 * phi_t), np.sin(2 * phi_t)])
    harm = span_harmonic(np.tensordot(X, I_t, axes=(1, 0)), phi_t)  # sums of the intensity itself: no noise
    # the span's plain mean of I is 1/2 [T + zbar_span D]; long_span_separation reads it as the harmonic level a,
    # which is exact where the span is a whole number of half turns of 2 phi: take such a span for the mean
    Im = I_t[: int(round(20000 / 60))].mean(0)  # half a polarizer turn (2 phi: one full cycle)
    win = 175 + (np.arange(7) - 3) * 58
    phi_w = torch.from_numpy(phi_t[win])[None]
    Zw = zeta_from_maps(maps, phi_w, dtype=torch.float64)
    Tl, Rl = long_span_separation(torch.from_numpy(Im)[None], torch.from_numpy(harm.astype(np.float64))[None], Zw, phi_w)
    B2 = (0.5 * (maps.R_perp - maps.R_par)) ** 2
    D = (R - T) * B2 / (B2 + HARMONIC_FLOOR)
    a = 0.5 * (maps.R_perp + maps.R_par)
    np.testing.assert_allclose(Rl[0].numpy() - Tl[0].numpy(), D, rtol=2e-3, atol=1e-4)
    np.testing.assert_allclose(Tl[0].numpy(), T + a * (R - T) - a * D, rtol=2e-3, atol=5e-4)


@pytest.mark.parametrize("code", range(8))
def test_symmetry_harmonic_is_the_fit_at_the_moved_angles(code):
    """The first harmonic of a pixel's spikes seen through a symmetry (the pixels moved, every angle a -> s a + o)
    equals the direct fit at the moved angles: (b, c) -> (e b, e s c) (harmonic_signs).
    """
    rng = np.random.default_rng(code)
    n, H, W = 400, 3, 4
    phi = np.cumsum(rng.uniform(0.008, 0.011, n))
    spikes = (rng.random((n, H, W)) < rng.uniform(0.1, 0.6, (1, H, W)) + 0.2 * np.cos(2 * phi - 1.0)[:, None, None] * rng.uniform(0, 1, (1, H, W))).astype(np.uint8)
    base = torch.from_numpy(_direct_fit(spikes, phi))
    sign, offset = angle_map(code)
    moved = symmetry_image(torch.from_numpy(spikes.astype(np.float64)), code).numpy()
    want = _direct_fit(moved, sign * phi + offset)
    torch.testing.assert_close(symmetry_harmonic(base, code), torch.from_numpy(want), rtol=0, atol=1e-9)
    e, es = harmonic_signs(code)
    assert {abs(e), abs(es)} == {1.0}


def _item(seed: int, **window):
    """(training item of a random 900-step 8 x 8 stream at exposure 0.7, its spikes, centres, angles)."""
    from reconstruct.net.onthefly import WindowConfig, item_from_stream

    rng = np.random.default_rng(seed)
    spikes = (rng.random((900, 8, 8)) < 0.2).astype(np.uint8)
    ck = 300 + np.arange(7) * 58
    phi = np.linspace(0, 5, 900)
    maps = {"R_perp": np.full((8, 8), 0.1), "R_par": np.full((8, 8), 0.01), "phi_perp": np.zeros((8, 8))}
    return item_from_stream(spikes, ck, phi, phi, (np.zeros((8, 8)),) * 2, maps, 0.7, WindowConfig(crop=8, **window)), spikes, ck, phi


def test_onthefly_item_harmonic_is_the_direct_fit_and_flips_with_the_angles():
    from reconstruct.net.onthefly import flip_item

    it, spikes, ck, phi = _item(4, mean_steps=350)
    lo, hi = spike_mean_span(ck[3], 350, 900)
    np.testing.assert_allclose(it["I_harm"].numpy(), _direct_fit(spikes[lo:hi], phi[lo:hi]) / 0.7, atol=1e-5)
    f = flip_item(it, 5)
    torch.testing.assert_close(f["I_harm"], symmetry_harmonic(it["I_harm"], 5))


def _window(seed=0, B=2, H=16, W=16):
    g = torch.Generator().manual_seed(seed)
    I = 0.05 + 0.4 * torch.rand(B, 7, H, W, generator=g)
    phi = (2.0 + (torch.arange(7) - 3) * math.radians(31.5) + torch.rand(B, 1, generator=g)).float()
    Im = 0.5 * I.mean(1)
    Ih = 0.02 * torch.randn(B, 2, H, W, generator=g)
    return I, phi, Im, Ih


def test_widened_harmonic_network_starts_as_the_mean_network_and_needs_the_harmonic():
    base = init_weights(PolSpikeNet(SMALL), torch.Generator().manual_seed(1)).eval()
    g = torch.Generator().manual_seed(12)
    for p in base.refine.parameters():  # non-zero decoders, so the refinement's input matters
        torch.nn.init.normal_(p, 0, 0.05, generator=g)
    wide = PolSpikeNet(dataclasses.replace(SMALL, use_harm=True)).eval()
    wide.load_state_dict(_widened(base.state_dict(), wide.state_dict()))
    I, phi, Im, Ih = _window()
    with torch.no_grad():
        a, b = base(I, phi, I_mean=Im), wide(I, phi, I_mean=Im, I_harm=Ih)
    torch.testing.assert_close(a.T, b.T, rtol=0, atol=1e-6)
    torch.testing.assert_close(a.R, b.R, rtol=0, atol=1e-6)
    with torch.no_grad():  # once the new weights move, the harmonic changes the output
        for n, v in wide.named_parameters():
            if n.startswith("refine.e1.0") and v.dim() == 4:
                v[:, 8:] = 0.1
        c, d = wide(I, phi, I_mean=Im, I_harm=Ih), wide(I, phi, I_mean=Im, I_harm=-Ih)
    assert float((c.T - d.T).abs().max()) > 1e-4
    with pytest.raises(ShapeError, match="I_harm"):
        wide(I, phi, I_mean=Im)
    with pytest.raises(ConfigError, match="use_harm needs use_mean"):  # a configuration problem, found when the config is made
        dataclasses.replace(SMALL, use_mean=False, base="solver", use_harm=True)


@pytest.mark.parametrize("size", [8, 4])
def test_ensemble_with_the_harmonic_is_equivariant(size):
    """The ensemble moves I_harm with the image and flips its signs with the angles: averaged over a group of
    symmetries a random harmonic network commutes with each of them.  Moving it as a plain image breaks that.
    """
    net = init_weights(PolSpikeNet(dataclasses.replace(SMALL, use_harm=True)), torch.Generator().manual_seed(2)).eval()
    with torch.no_grad():
        for n, v in net.named_parameters():
            if n.startswith("refine.e1.0") and v.dim() == 4:
                v[:, 8:] = 0.3  # the harmonic inputs matter
    I, phi, Im, Ih = _window(1, W=20)
    ens = SymmetryEnsemble(net, size)
    with torch.no_grad():
        base = ens(I, phi, I_mean=Im, I_harm=Ih)
        for g in range(size if size == 4 else 8):
            out = ens(symmetry_image(I, g), symmetry_angles(phi, g), I_mean=symmetry_image(Im, g), I_harm=symmetry_harmonic(Ih, g))
            torch.testing.assert_close(out.T, symmetry_image(base.T, g), rtol=1e-4, atol=1e-5)
        wrong = ens(symmetry_image(I, 1), symmetry_angles(phi, 1), I_mean=symmetry_image(Im, 1), I_harm=symmetry_image(Ih, 1))
    assert float((wrong.T - symmetry_image(base.T, 1)).abs().max()) > 1e-4


class _Recorder(torch.nn.Module):
    """Stands in for a network that reads the long-span input ``key`` (I_harm or I_wide): records what it is given."""

    def __init__(self, key: str, **cfg):
        super().__init__()
        self.key = key
        self.cfg = NetConfig(arch="v1", use_mean=True, **cfg)
        self.seen: list[np.ndarray] = []

    def forward(self, I, phi, I_mean=None, **kw):
        self.seen.append(kw[self.key].numpy().copy())
        T = 2 * I_mean
        return types.SimpleNamespace(T=T, R=T, T_base=T, R_base=T)


def _streamed(tmp_path, chunk: int, seed: int, rec: _Recorder):
    """(what ``rec`` was given per output frame, the stream source, the stored group) for a tiny group streamed in
    chunks of ``chunk`` steps.
    """
    from reconstruct.stream.groups import load_store_group
    from reconstruct.stream.sources import group_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream
    from tests.recon.test_windows import make_group

    make_group(tmp_path / "g", seed=seed, duration=0.04)
    src = group_source(tmp_path / "g", chunk_steps=chunk)
    s = reconstruct_stream(src, rec, tmp_path / "out", ReconstructConfig(video=False, chunk_steps=chunk, batch=2, tile=0, cache=False))
    got = np.concatenate(rec.seen)
    assert got.shape[0] == s["frames"] >= 3
    return got, src, load_store_group(tmp_path / "g")


@pytest.mark.parametrize("chunk", [37, 2000])
def test_stream_gives_the_network_the_store_harmonic(tmp_path, chunk):
    """reconstruct_stream (chunked) hands a use_harm network the same first harmonic per output frame as the stored
    group's own (load_store_group), both fitted from the raw spikes.
    """
    from spike_sim.aggregate import AggregateConfig, frame_centres
    from spike_sim.store import open_group

    got, src, g = _streamed(tmp_path, chunk, 3, _Recorder("I_harm", use_harm=True))
    np.testing.assert_allclose(got, g.I_harm[3 : 3 + got.shape[0]], rtol=1e-5, atol=1e-6)
    with open_group(tmp_path / "g") as sg:  # and both are the direct fit of the raw spikes (exposure 1 here or not)
        c, _ = frame_centres(sg.phi_nominal_rad, AggregateConfig())
        lo, hi = spike_mean_span(int(c[3]), 350, sg.n_steps)
        raw = sg.read(lo, hi)
        phi = sg.phi_nominal_rad[lo:hi]
    np.testing.assert_allclose(got[0], _direct_fit(raw, phi) / src.exposure, atol=1e-5)


def test_evaluate_scores_the_span_physics_row():
    """Evaluate --anchor mean adds the row 'span' (long_span_separation on the solvers' zeta); on a static, noise-free
    synthetic group with the true zeta it is exact up to the floor, far above the plain spike mean.
    """
    from reconstruct.evaluate.harness import SPAN_METHOD, EvalConfig, evaluate_groups
    from reconstruct.stream.synthetic import SyntheticConfig
    from reconstruct.stream.synthetic import make_group as synth

    g = synth(SyntheticConfig(width=24, height=16, n_groups=1, n_frames=11, noise="none", motion_px_per_frame=0.0), 0)
    rep = evaluate_groups([g], EvalConfig(methods="ls", zeta="gt", rir=False, anchor="mean", max_frames=2))
    rows = {r["method"]: r for r in rep.rows if r["group"] == "overall"}
    assert SPAN_METHOD in rows and rows[SPAN_METHOD]["psnr_T"] > 40 and rows[SPAN_METHOD]["psnr_T"] > rows["spike_mean"]["psnr_T"] + 10
    assert SPAN_METHOD not in {r["method"] for r in evaluate_groups([g], EvalConfig(methods="ls", zeta="gt", rir=False, max_frames=2)).rows}


# --------------------------------------------------------------------------- the wide window (net.use_wide)
def test_wide_window_is_the_largest_odd_count_within_a_stride():
    from reconstruct.stream.groups import wide_window_steps

    assert wide_window_steps(20000.0, 30.0, 31.5) == 57  # 58.3 steps per stride
    assert wide_window_steps(20000.0, 25.0, 31.5) == 69  # 70.0 -> 69
    assert wide_window_steps(40000.0, 30.0, 31.5) == 115  # 116.7 -> 116 -> 115
    assert wide_window_steps(20000.0, 0.0, 31.5) == 1  # a still polarizer: no stride to fill


def test_window_means_are_the_clipped_window_means_at_every_width():
    from reconstruct.stream.groups import window_means

    rng = np.random.default_rng(5)
    spikes = (rng.random((300, 3, 4)) < 0.3).astype(np.uint8)
    got, narrow = window_means(lambda a, b: spikes[a:b], np.array([10, 150, 295]), (57, 13), 300, 0.5)
    np.testing.assert_allclose(narrow[1], spikes[144:157].sum(0) / (13 * 0.5), rtol=1e-6)  # the same centre's narrow window
    np.testing.assert_allclose(narrow[0], spikes[4:17].sum(0) / (13 * 0.5), rtol=1e-6)
    np.testing.assert_allclose(got[0], spikes[0:39].sum(0) / (39 * 0.5), rtol=1e-6)  # clipped at the start
    np.testing.assert_allclose(got[1], spikes[122:179].sum(0) / (57 * 0.5), rtol=1e-6)
    np.testing.assert_allclose(got[2], spikes[267:300].sum(0) / (33 * 0.5), rtol=1e-6)  # and at the end


def test_onthefly_item_wide_windows_are_the_raw_window_sums_and_flip_with_the_image():
    from reconstruct.net.onthefly import WindowConfig, flip_item

    it, spikes, ck, phi = _item(6, mean_steps=350, wide_steps=57)
    want = np.stack([spikes[c - 28 : c + 29].sum(0) / (57 * 0.7) for c in ck])
    np.testing.assert_allclose(it["I_wide"].numpy(), want, rtol=1e-6)
    torch.testing.assert_close(flip_item(it, 6)["I_wide"], symmetry_image(it["I_wide"], 6))
    assert "I_wide" not in _item(6)[0]
    from polinfra.errors import ConfigError

    with pytest.raises(ConfigError, match="wide_steps"):
        WindowConfig(wide_steps=58)


def test_widened_wide_network_starts_as_the_mean_network_and_needs_the_wide_windows():
    base = init_weights(PolSpikeNet(SMALL), torch.Generator().manual_seed(3)).eval()
    g = torch.Generator().manual_seed(11)  # seeded: the global generator's state depends on which tests ran before
    for p in base.refine.parameters():
        torch.nn.init.normal_(p, 0, 0.05, generator=g)
    wide = PolSpikeNet(dataclasses.replace(SMALL, use_wide=True)).eval()
    wide.load_state_dict(_widened(base.state_dict(), wide.state_dict()))
    I, phi, Im, _ = _window(4)
    Iw = I * 0.9 + 0.02
    with torch.no_grad():
        a, b = base(I, phi, I_mean=Im), wide(I, phi, I_mean=Im, I_wide=Iw)
    torch.testing.assert_close(a.T, b.T, rtol=0, atol=1e-6)
    with torch.no_grad():
        for n, v in wide.named_parameters():
            if n.startswith("refine.e1.0") and v.dim() == 4:
                v[:, 8:] = 0.1
        # a wide window far from the narrow one; over 40 random refine weights the least change seen was 2e-3
        c, d = wide(I, phi, I_mean=Im, I_wide=1 - I), wide(I, phi, I_mean=Im, I_wide=I)
    assert float((c.T - d.T).abs().max()) > 1e-3
    with pytest.raises(ShapeError, match="I_wide"):
        wide(I, phi, I_mean=Im)


def test_ensemble_with_the_wide_windows_is_equivariant():
    net = init_weights(PolSpikeNet(dataclasses.replace(SMALL, use_wide=True)), torch.Generator().manual_seed(4)).eval()
    with torch.no_grad():
        for n, v in net.named_parameters():
            if n.startswith("refine.e1.0") and v.dim() == 4:
                v[:, 8:] = 0.3
    I, phi, Im, _ = _window(2, W=20)
    Iw = 0.8 * I + 0.05 * torch.rand(I.shape, generator=torch.Generator().manual_seed(9))
    ens = SymmetryEnsemble(net, 8)
    with torch.no_grad():
        base = ens(I, phi, I_mean=Im, I_wide=Iw)
        for g in (1, 5, 7):
            out = ens(symmetry_image(I, g), symmetry_angles(phi, g), I_mean=symmetry_image(Im, g), I_wide=symmetry_image(Iw, g))
            torch.testing.assert_close(out.T, symmetry_image(base.T, g), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("chunk", [37, 2000])
def test_stream_gives_the_network_the_store_wide_windows(tmp_path, chunk):
    """reconstruct_stream (chunked) hands a use_wide network each output's N wide windows exactly as the stored
    group's (load_store_group: counts over the clipped wide window / its length / exposure).
    """
    got, _, g = _streamed(tmp_path, chunk, 4, _Recorder("I_wide", use_wide=True))
    want = np.stack([g.I_wide[i - 3 : i + 4] for i in range(3, 3 + got.shape[0])])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert float(np.abs(g.I_wide - g.I).mean()) > 0  # not the narrow windows


def test_synthetic_wide_windows_carry_the_noise_of_their_steps():
    """The closed-form synthetic set's wide windows: the same light as the narrow ones, with the Poisson noise of 57
    steps instead of 13 (variance ratio 13 / 57 against the noiseless frames).
    """
    from reconstruct.stream.synthetic import SyntheticConfig
    from reconstruct.stream.synthetic import make_group as synth

    kw = dict(width=48, height=40, n_groups=1, n_frames=9, motion_px_per_frame=0.0)
    clean = synth(SyntheticConfig(noise="none", **kw), 0)
    noisy = synth(SyntheticConfig(**kw), 0)
    np.testing.assert_allclose(clean.I_wide, clean.I, atol=1e-6)
    ratio = float(((noisy.I_wide - clean.I) ** 2).mean() / ((noisy.I - clean.I) ** 2).mean())
    assert abs(ratio - 13 / 57) < 0.05


def test_wide_levels_move_only_low_frequencies_whatever_the_refinement():
    """t_level_px / r_level_from = wide replace the base's low frequencies by the wide windows' (inference only): the
    change of T (R) is G_s * (T_wide - T_base) (R likewise), the same for any refinement weights, and smooth.
    """
    from reconstruct.physics.span import gaussian_blur

    cfg0 = dataclasses.replace(SMALL, use_wide=True, base="anchored", anchor_zbar="harmonic", r_level_px=4.0, floor=False)  # the levels before the floor
    I, phi, Im, _ = _window(7, H=32, W=32)
    Iw = 0.9 * I + 0.03 * torch.rand(I.shape, generator=torch.Generator().manual_seed(1))
    zeta = 0.05 + 0.1 * torch.rand(I.shape, generator=torch.Generator().manual_seed(2))
    diffs = []
    for seed in (1, 2):
        nets = {}
        for name, kw in {"off": {}, "on": {"t_level_px": 3.0, "r_level_from": "wide"}}.items():
            n = init_weights(PolSpikeNet(dataclasses.replace(cfg0, **kw)), torch.Generator().manual_seed(0)).eval()
            with torch.no_grad():
                for pn, p in n.refine.named_parameters():  # the refinement differs between seeds, the rest does not
                    p.copy_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(seed * 100 + len(pn))))
            nets[name] = n
        with torch.no_grad():
            a = nets["off"](I, phi, zeta_gt=zeta, alpha=1.0, I_mean=Im, I_wide=Iw)
            b = nets["on"](I, phi, zeta_gt=zeta, alpha=1.0, I_mean=Im, I_wide=Iw)
        diffs.append((b.T - a.T, b.R - a.R))
        assert float((a.T - b.T).abs().max()) > 1e-4
    torch.testing.assert_close(diffs[0][0], diffs[1][0], rtol=0, atol=1e-5)
    torch.testing.assert_close(diffs[0][1], diffs[1][1], rtol=0, atol=1e-5)
    dT = diffs[0][0]
    assert float((dT - gaussian_blur(dT, 1.0)).abs().max()) < 0.2 * float(dT.abs().max())  # smooth at 1 px
    with pytest.raises(ShapeError, match="missing: I_wide"):
        PolSpikeNet(dataclasses.replace(SMALL, t_level_px=2.0))(I, phi, I_mean=Im)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("sigma", [1.0, 2.0, 8.0])
def test_gaussian_blur_is_scipys_mirrored_gaussian(dtype, tol, sigma):
    """gaussian_blur against scipy.ndimage.gaussian_filter (mirror borders, 3 sigma truncation: the same kernel)."""
    import scipy.ndimage as nd

    from reconstruct.physics.span import gaussian_blur

    x = np.random.default_rng(3).random((2, 64, 90))
    got = gaussian_blur(torch.from_numpy(x).to(dtype), sigma).double().numpy()
    want = np.stack([nd.gaussian_filter(m, sigma, mode="mirror", truncate=3.0) for m in x])
    assert np.abs(got - want).max() < tol


def test_span_blend_stays_finite_whatever_the_weights_dynamic_range():
    """The span's normalised convolution is local: weights spanning 1e-300 .. 1e300 (saturated and dark pixels beside
    bright ones) give finite layers, equal to the unblended ones where every weight in reach is zero.
    """
    from reconstruct.physics.span import gaussian_kernel, separable_blur

    g = np.random.default_rng(4)
    w = torch.from_numpy(10.0 ** g.uniform(-300, 300, (1, 40, 50)))
    w[:, :, :20] = 0.0
    y = separable_blur(w, gaussian_kernel(2.0))
    assert torch.isfinite(y).all() and float(y[:, :, :13].abs().max()) == 0.0
