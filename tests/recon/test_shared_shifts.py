"""The windows' RIR shifts estimated once and passed down: the same frames as a model that estimates them itself.

The stream estimates each window's shifts once (``reconstruct.video.tiling.window_shifts``: the frames as the model
sees them, float32 replicate-padded to its multiple) and hands them to the model (``WindowInputs.shifts``), to the
span (``--span rir`` / ``auto``) and to nothing else that registers again.  The oracle is the model's own estimate:
the output must be bit-identical, and the model must not estimate at all when given them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import reconstruct.physics.rir as rir_mod
from reconstruct.stream.motion_span import auto_part_shifts, part_shifts_from_windows
from reconstruct.stream.window_inputs import WindowInputs
from reconstruct.video.tiling import run_model_on_windows, window_shifts

N = 7


def _net(seed: int = 0):
    from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights

    cfg = NetConfig(arch="v2", use_rir=True, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8))
    return init_weights(PolSpikeNet(cfg), torch.Generator().manual_seed(seed)).eval()


def _panning_windows(B: int = 2, H: int = 38, W: int = 46, step_px: float = 0.8, seed: int = 0):
    """B windows of N frames of a smooth texture moving by ``step_px`` per frame along x (sizes not multiples of 4)."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    tex = torch.from_numpy(0.2 + gaussian_filter(rng.random((B, H, W)), 2.0))
    sh = torch.zeros(B, N, 2, dtype=torch.float64)
    sh[..., 1] = (torch.arange(N) - N // 2) * step_px
    I = rir_mod.warp(tex[:, None].expand(B, N, H, W).contiguous(), sh).float().numpy()
    phi = np.tile((np.arange(N) - N // 2) * math.radians(31.5), (B, 1)).astype(np.float32)
    return I, phi


@pytest.fixture
def count_estimates(monkeypatch):
    calls = []
    real = rir_mod.estimate_shifts

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(rir_mod, "estimate_shifts", counted)
    return calls


def test_passed_shifts_give_the_frames_of_the_models_own_estimate(count_estimates):
    m = _net()
    I, phi = _panning_windows()
    own = run_model_on_windows(m, WindowInputs(I, phi), tile=0)
    assert len(count_estimates) == 2  # one estimate per window inside the model
    sh = np.stack([window_shifts(m, I[b], phi[b]) for b in range(2)])
    assert np.abs(sh[:, 0, 1] - 2.4).max() < 0.3  # the pan is there to register: 3 frames x 0.8 px
    count_estimates.clear()
    given = run_model_on_windows(m, WindowInputs(I, phi, shifts=sh), tile=0)
    assert not count_estimates  # the model used them, estimating nothing
    for k in ("T", "R", "T_base", "R_base"):
        assert np.array_equal(own[k], given[k]), k
    # they are what aligns the windows: no shift gives other frames
    still = run_model_on_windows(m, WindowInputs(I, phi, shifts=np.zeros_like(sh)), tile=0)
    assert np.abs(still["T"] - own["T"]).max() > 1e-3
    # tiles of one frame share the frame's shifts: no estimate per tile
    tiled = run_model_on_windows(m, WindowInputs(I, phi, shifts=sh), tile=16, margin=8)
    assert not count_estimates and np.isfinite(tiled["T"]).all()


class _OwnShifts:
    """The network without ``accepts_shifts``: the stream passes no shifts and it estimates them itself."""

    def __init__(self, net):
        self.net, self.cfg = net, net.cfg

    def __call__(self, *a, **k):
        return self.net(*a, **k)


def test_stream_with_shared_shifts_equals_the_per_window_estimate(tmp_path, count_estimates):
    from polinfra.exr import read_exr
    from reconstruct.stream.sources import array_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    rng = np.random.default_rng(4)
    H, W, L = 34, 44, 720
    rate = 0.05 + 0.35 * np.repeat(rng.random((H, 2 * W)), 1, 1)
    x = (np.arange(L) * 0.004).astype(int)  # a pan of 80 px/s at 20 kHz
    spikes = np.stack([rng.random((H, W)) < rate[:, s : s + W] for s in x]).astype(np.uint8)
    m = _net(1)
    cfg = ReconstructConfig(frames="exr", video=False, max_frames=3)
    a = reconstruct_stream(array_source(spikes, 0.3, 30.0, chunk_steps=101), m, tmp_path / "shared", cfg)
    n_shared = len(count_estimates)
    b = reconstruct_stream(array_source(spikes, 0.3, 30.0, chunk_steps=101), _OwnShifts(m), tmp_path / "own", cfg)
    assert a["frames"] == b["frames"] == 3 and n_shared == 3 and len(count_estimates) == 6
    assert a["rir_shifts"] == "window" and b["rir_shifts"] is None
    for i in range(3):
        fa = read_exr(tmp_path / "shared" / "frames" / f"{i:06d}.exr", ["T", "R"])
        fb = read_exr(tmp_path / "own" / "frames" / f"{i:06d}.exr", ["T", "R"])
        for k in ("T", "R"):
            assert np.array_equal(fa[k], fb[k]), (i, k)
    # the chained estimator: no per-window estimate at all, recorded
    count_estimates.clear()
    c = reconstruct_stream(array_source(spikes, 0.3, 30.0, chunk_steps=101), m, tmp_path / "chained", ReconstructConfig(frames="exr", video=False, max_frames=3, rir="chained"))
    assert c["rir_shifts"] == "chained" and not count_estimates and c["frames"] == 3


def test_auto_span_is_plain_below_a_pixel_of_smear_and_the_rir_span_above():
    parts = [(a, a + 50) for a in range(0, 350, 50)]
    t = 175 + (np.arange(N) - N // 2) * 57.0
    for v, plain in ((0.5 / 350, True), (0.99 / 350, True), (1.01 / 350, False), (7.0 / 350, False)):
        ws = np.stack([np.zeros(N), (t - 175) * v], 1)  # windows moving along x at v px per step
        got = auto_part_shifts(ws, t, parts, smear_px=1.0)
        if plain:
            assert got is None, v
        else:
            want = part_shifts_from_windows(ws, t, parts)
            np.testing.assert_allclose(got, want)
            np.testing.assert_allclose(want[:, 1], ((np.arange(7) - 3) * 50 - 0.5) * v, atol=1e-9)  # closed form: v times each part's mid-step
    # windows whose registration scatters (noise-limited: a still dim scene's shifts of up to 2 px, no line through them)
    # leave the span plain however fast a velocity fitted to them would be
    scattered = np.array([[1.92, 1.05], [2.3, 1.59], [-0.11, -0.17], [0, 0], [-0.05, -0.35], [1.88, -0.7], [2.08, 1.83]])
    assert auto_part_shifts(scattered, t, parts, smear_px=1.0) is None
    assert auto_part_shifts(scattered, t, parts, smear_px=1.0, min_inliers=1) is not None  # the inlier test is what keeps it plain
