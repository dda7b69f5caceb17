"""The live path's numba kernels against the torch code they replace.

Oracles: the torch RWPS solver (``solve("rwps", ..., PHYSICS_SOLVER_CONFIG)``, after ``warp`` when shifted) on seeded
paper Eq. (1)-(2) windows with Poisson noise; the true layers of a noise-free Eq. (1)-(2) window; the solvers' box
mean; the torch Gauss-Newton translation fit; the table lookup of the 8-bit display.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG

N, H, W = 7, 48, 64
TOL_MAX, TOL_MEAN = 2e-5, 1e-6  # fused (float64 sums) vs torch (float32), relative to the layer's peak


def _window(seed: int, noise: bool = True, counts: float = 26.0):
    """Window of N frames: zeta by paper Eq. (2) on random pane maps, I by Eq. (1) on random layers, Poisson counts when ``noise``."""
    rng = np.random.default_rng(seed)
    phi = np.linspace(0.0, math.pi, N, endpoint=False) + rng.uniform(0, math.pi)
    rp = rng.uniform(0.05, 0.4, (H, W))
    rl = rp * rng.uniform(0.0, 0.5, (H, W))
    pp = rng.uniform(0, math.pi, (H, W))
    Z = 0.5 * (rp + rl) + 0.5 * (rp - rl) * np.cos(2 * (phi[:, None, None] - pp))  # Eq. (2)
    R = rng.uniform(0.0, 1.0, (H, W))
    T = rng.uniform(0.0, 1.0, (H, W))
    I = 0.5 * (Z * R + (1 - Z) * T)  # Eq. (1)
    if noise:
        I = rng.poisson(I * counts) / counts
    return Z.astype(np.float32), I.astype(np.float32), T, R


def _torch(Z, I, shifts=None):
    from reconstruct.physics.rir import warp
    from reconstruct.physics.solvers import solve

    z, i = torch.from_numpy(Z), torch.from_numpy(I)
    if shifts is not None:
        s = torch.from_numpy(shifts).float()
        z, i = warp(z, s), warp(i, s)
    r = solve("rwps", z, i, config=PHYSICS_SOLVER_CONFIG)
    return r.T.clamp_min(0).numpy(), r.R.clamp_min(0).numpy()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shifted", [False, True])
def test_fused_rwps_equals_the_torch_solver(seed, shifted):
    from reconstruct.physics.fused_rwps import rwps_fused

    Z, I, _, _ = _window(seed)
    sh = None
    if shifted:
        sh = np.random.default_rng(100 + seed).uniform(-1.7, 1.7, (N, 2))
        sh[N // 2] = 0.0
    T0, R0 = _torch(Z, I, sh)
    T1, R1 = rwps_fused(Z, I, PHYSICS_SOLVER_CONFIG, sh)
    assert T1.dtype == np.float32 and T1.shape == (H, W)
    for a, b in ((T0, T1), (R0, R1)):
        peak = float(a.max())
        d = np.abs(a - b)
        assert peak > 0 and float(d.max()) <= TOL_MAX * peak and float(d.mean()) <= TOL_MEAN * peak, (float(d.max()) / peak, float(d.mean()) / peak)


@pytest.mark.parametrize("span", [6.0, 90.0])
def test_fused_rwps_equals_the_torch_solver_under_large_shifts(span):
    """Shifts of several pixels and beyond the frame's width (64): the reads of each frame are clamped at the borders
    (the whole row for the largest), the rest through the unclamped interior columns; the oracle warps with torch.
    """
    from reconstruct.physics.fused_rwps import rwps_fused

    Z, I, _, _ = _window(6)
    sh = np.random.default_rng(7).uniform(-span, span, (N, 2))
    sh[N // 2] = 0.0
    T0, R0 = _torch(Z, I, sh)
    T1, R1 = rwps_fused(Z, I, PHYSICS_SOLVER_CONFIG, sh)
    for a, b in ((T0, T1), (R0, R1)):
        peak = float(a.max())
        d = np.abs(a - b)
        assert peak > 0 and float(d.max()) <= TOL_MAX * peak and float(d.mean()) <= TOL_MEAN * peak, (float(d.max()) / peak, float(d.mean()) / peak)


def test_fused_rwps_on_bands_of_rows_in_parallel_equals_one_band():
    """The passes split the rows (pixel pass, box means' row pass) and the columns (box means' column pass) into bands
    on numba's threads: every pixel sums in the same order, so 2 and 3 bands give the one-band result bit for bit.
    """
    import reconstruct.physics.fused_rwps as F

    def poisoned(threads):  # the work arrays persist between calls: NaN first, so a pixel a band leaves out shows
        for sc in F._scratch.values():
            for a in (sc.s, sc.work, sc.box, sc.cs):
                a.fill(np.nan)
        return F.rwps_fused(Z, I, PHYSICS_SOLVER_CONFIG, sh, threads=threads)

    box_mean, rwps_fused = F.box_mean, F.rwps_fused
    Z, I, _, _ = _window(4)
    sh = np.random.default_rng(9).uniform(-1.7, 1.7, (N, 2))
    one = rwps_fused(Z, I, PHYSICS_SOLVER_CONFIG, sh, threads=1)
    x = np.random.default_rng(1).normal(size=(3, H, W))
    for bands in (2, 3):
        par = poisoned(bands)
        assert np.array_equal(par[0], one[0]) and np.array_equal(par[1], one[1])
        assert np.array_equal(box_mean(x, 7, threads=bands), box_mean(x, 7, threads=1))


def test_fused_rwps_window_shared_by_two_threads_equals_the_one_thread_kernel():
    """The pixel pass on chunks of rows two threads take in turn, the maps on one (the live path's split): T and R
    bit for bit those of ``rwps_fused``, whichever thread makes which rows (all on one, all on the other, both at
    once); the sums array is poisoned with NaN first, so a row no thread made shows.
    """
    import threading

    import reconstruct.physics.fused_rwps as F

    Z, I, _, _ = _window(5)
    sh = np.random.default_rng(11).uniform(-1.7, 1.7, (N, 2))
    T0, R0 = F.rwps_fused(Z, I, PHYSICS_SOLVER_CONFIG, sh)
    for mode in ("helper takes all", "finisher takes all", "both at once"):
        for chunks in (1, 5, H):
            sums = np.full((9, H, W), np.nan)
            win = F.RwpsWindow(Z, I, PHYSICS_SOLVER_CONFIG, sh, sums=sums, chunks=chunks)
            got = {}
            if mode == "helper takes all":
                assert win.pixels() == chunks
            helper = threading.Thread(target=lambda: got.setdefault("n", win.pixels())) if mode == "both at once" else None
            if helper is not None:
                helper.start()
            T1, R1 = win.finish()
            if helper is not None:
                helper.join()
            assert np.array_equal(T1.view(np.uint32), T0.view(np.uint32)) and np.array_equal(R1.view(np.uint32), R0.view(np.uint32)), (mode, chunks)
            assert win.pixels() == 0  # every chunk taken
        assert 0 <= got.get("n", 0) <= chunks


def test_fused_rwps_window_given_up_releases_the_finishing_thread():
    """A chunk taken by a thread that never finishes it (its caller failed) leaves ``finish`` waiting; ``cancel``
    releases it, and it raises instead of returning layers made without that chunk.
    """
    import threading

    import reconstruct.physics.fused_rwps as F

    Z, I, _, _ = _window(5)
    win = F.RwpsWindow(Z, I, PHYSICS_SOLVER_CONFIG, chunks=4)
    with win.lock:
        win.next += 1  # the first chunk taken, never made
    got = {}

    def finish():
        try:
            got["out"] = win.finish()
        except RuntimeError as e:
            got["err"] = e

    t = threading.Thread(target=finish, daemon=True)
    t.start()
    t.join(0.5)
    assert t.is_alive() and not got
    win.cancel()
    t.join(10)
    assert not t.is_alive() and "err" in got and "out" not in got


def test_fused_rwps_recovers_the_layers_of_a_noise_free_window():
    """Without noise the residual variance is 0, Conf -> 1 and lambda -> lambda_low = 0: the plain weighted least
    squares, which is exact on Eq. (1)-(2) data.
    """
    from reconstruct.physics.fused_rwps import rwps_fused

    Z, I, T, R = _window(5, noise=False)
    T1, R1 = rwps_fused(Z, I, PHYSICS_SOLVER_CONFIG)
    assert float(np.abs(T1 - T).max()) < 2e-4 and float(np.abs(R1 - R).max()) < 3e-3


@pytest.mark.parametrize("k", [1, 4, 5, 31])
def test_box_mean_equals_the_solvers_box(k):
    from reconstruct.physics.fused_rwps import box_mean
    from reconstruct.physics.solvers import _box

    x = np.random.default_rng(k).normal(size=(2, 23, 37))
    np.testing.assert_allclose(box_mean(x, k), _box(torch.from_numpy(x), k).numpy(), rtol=0, atol=1e-12)


def test_fused_rwps_takes_only_the_configuration_it_computes():
    import dataclasses

    from polinfra.errors import ConfigError
    from reconstruct.physics.fused_rwps import rwps_fused, rwps_fused_supports

    Z, I, _, _ = _window(0)
    for cfg in (dataclasses.replace(PHYSICS_SOLVER_CONFIG, rwps_irls_iters=1), dataclasses.replace(PHYSICS_SOLVER_CONFIG, rwps_prior="zero"),
                dataclasses.replace(PHYSICS_SOLVER_CONFIG, lambda_map="fixed")):
        assert not rwps_fused_supports(cfg)
        with pytest.raises(ConfigError):
            rwps_fused(Z, I, cfg)
    assert rwps_fused_supports(PHYSICS_SOLVER_CONFIG)


def test_fused_gauss_newton_equals_the_torch_fit():
    from scipy.ndimage import gaussian_filter, shift

    from reconstruct.physics.fused_rir import gauss_newton_fused
    from reconstruct.physics.rir import _gauss_newton, _with_gradient

    rng = np.random.default_rng(7)
    ref = gaussian_filter(rng.normal(size=(90, 120)), 3.0)
    mov = shift(ref, (0.6, -1.2), order=3, mode="nearest")
    st = _with_gradient(torch.from_numpy(mov))
    pts = torch.from_numpy(np.argwhere(np.ones(ref.shape, bool))[::5]).double()
    r = torch.from_numpy(ref)[pts[:, 0].long(), pts[:, 1].long()]
    for s0 in (np.zeros(2), np.array([0.3, -0.4])):
        a = _gauss_newton(r, st, pts, torch.from_numpy(s0), 8).numpy()
        b = gauss_newton_fused(r.numpy(), st.numpy(), pts.numpy(), s0, 8)
        assert np.abs(a - b).max() < 1e-9 and np.abs(a - [-0.6, 1.2]).max() < 0.05, (a, b)


def _harmonic_window(seed: int, noise: bool = True):
    """A window whose zeta is Eq. (2) in angle-sum form (the live path's zeta): the coefficient maps, cos and sin of
    2 phi, the float32 zeta frames made from them as the live path made them, I by Eq. (1), and the true layers.
    """
    rng = np.random.default_rng(seed)
    phi = (np.arange(N) * math.radians(31.5) + rng.uniform(0, math.pi)).astype(np.float32).astype(np.float64)
    rp = rng.uniform(0.05, 0.4, (H, W))
    rl = rp * rng.uniform(0.0, 0.5, (H, W))
    pp = rng.uniform(0, math.pi, (H, W))
    a = 0.5 * (rp - rl) * 0.98
    m, ac, as_ = (x.astype(np.float32) for x in (0.5 * (rp + rl), a * np.cos(2 * pp), a * np.sin(2 * pp)))
    c, s = np.cos(2 * phi), np.sin(2 * phi)
    Z = np.stack([ac * np.float32(c[k]) + np.float32(s[k]) * as_ + m for k in range(N)])
    T, R = rng.uniform(0.0, 1.0, (H, W)), rng.uniform(0.0, 1.0, (H, W))
    I = 0.5 * (Z * R + (1 - Z) * T)  # Eq. (1)
    if noise:
        I = rng.poisson(I * 26.0) / 26.0
    return I.astype(np.float32), c, s, (m, ac, as_), Z, T, R


@pytest.mark.parametrize("seed", [0, 1])
def test_fused_ls_on_zetas_closed_form_equals_the_torch_solver(seed):
    """The LS pass that takes zeta's coefficient maps (no zeta frames) against ``solve("ls")`` on the float32 zeta
    frames (torch sums in float32: within the fused RWPS kernel's bounds; measured 3.7e-6 and 1.6e-7) and against the
    fused LS pass on the same frames (both sum in float64; only zeta's float32 rounding parts them: 1e-6 and 5e-8,
    measured 1.6e-7 and 7e-9).
    """
    from reconstruct.physics.fused import ls_fused, ls_fused_harmonic
    from reconstruct.physics.solvers import solve

    I, c, s, maps, Z, _, _ = _harmonic_window(seed)
    T, R = ls_fused_harmonic(I, c, s, *(x.astype(np.float64) for x in maps))
    r = solve("ls", torch.from_numpy(Z), torch.from_numpy(I))
    T1, R1 = ls_fused(Z, I)
    for (got, want), (tol_max, tol_mean) in zip(((T, r.T.clamp_min(0).numpy()), (R, r.R.clamp_min(0).numpy()), (T, T1), (R, R1)), [(TOL_MAX, TOL_MEAN)] * 2 + [(1e-6, 5e-8)] * 2):
        d = np.abs(got - want) / want.max()
        assert d.max() < tol_max and d.mean() < tol_mean, (d.max(), d.mean())


def test_fused_ls_on_zetas_closed_form_recovers_the_layers_of_a_noise_free_window():
    from reconstruct.physics.fused import ls_fused_harmonic

    I, c, s, maps, _, T, R = _harmonic_window(3, noise=False)
    Tg, Rg = ls_fused_harmonic(I, c, s, *maps)
    assert np.abs(Tg - T).max() < 2e-4 and np.abs(Rg - R).max() < 3e-3, (np.abs(Tg - T).max(), np.abs(Rg - R).max())


def test_display_frames_equal_the_table_lookup():
    from reconstruct.video.display8 import to8_frames
    from reconstruct.video.live import _TO8, _to8_fast

    rng = np.random.default_rng(3)
    I2, T, R = (rng.uniform(-0.2, 1.4, (31, 45)).astype(np.float32) for _ in range(3))
    g = {"T": 0.93, "R": 1.7, "preview": 0.8}
    t8, r8, p8 = to8_frames(I2, T, R, g, _TO8)
    assert np.array_equal(t8, _to8_fast(T, g["T"])) and np.array_equal(r8, _to8_fast(R, g["R"]))
    assert np.array_equal(p8, np.concatenate([_to8_fast(x, g["preview"]) for x in (I2, T, R)], 1))
    a8, b8, none = to8_frames(I2, T, R, g, _TO8, preview=False)  # without the preview: T and R alone, the same values
    assert none is None and np.array_equal(a8, t8) and np.array_equal(b8, r8)


def test_live_flags_reject_bad_values_through_the_console_script(tmp_path, polspike_cli):
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(8 * 16 * 20))
    geo = ("--height", 16, "--width", 20, "--phi0-deg", 0, "--rev-per-s", 30)
    r = polspike_cli("reconstruct", f, *geo, "--method", "ls", "--video-quality", "best", "--out", tmp_path / "o")
    polspike_cli.one_line_exit_2(r, "--video-quality", "fast", "high")
    assert not (tmp_path / "o").exists()
    r = polspike_cli("reconstruct", f, *geo, "--method", "ls", "--video-codec", "av1", "--out", tmp_path / "o")
    polspike_cli.one_line_exit_2(r, "--video-codec", "h264-gray", "y4m")
    assert not (tmp_path / "o").exists()
    r = polspike_cli("reconstruct", f, *geo, "--threads", -1, "--out", tmp_path / "o")
    polspike_cli.one_line_exit_2(r, "--threads", "0 for auto")
    assert not (tmp_path / "o").exists()
    r = polspike_cli("bench", "realtime", "--live-variants", "torch,turbo", "--out", tmp_path / "b")
    polspike_cli.one_line_exit_2(r, "--live-variants", "coarse-rir")
    assert not (tmp_path / "b").exists()


def test_video_codec_on_the_streaming_path_exits_2(tmp_path, polspike_main):
    """``--video-codec`` other than h264 is an option of the live path: on the streaming path one line, exit 2 (the
    entry point in this process; bad values through the console script above).
    """
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(8 * 16 * 20))
    r = polspike_main("reconstruct", f, "--height", 16, "--width", 20, "--phi0-deg", 0, "--rev-per-s", 30, "--method", "ls", "--video-codec", "y4m",
                      "--path", "stream", "--out", tmp_path / "o")
    polspike_main.one_line_exit_2(r, "--video-codec", "live path")
    assert not (tmp_path / "o").exists()


def test_cpu_threads_takes_the_idle_cores(monkeypatch):
    """Asked for n: n.  Auto: the core count minus the 1-minute load average, rounded, within 1 .. cores."""
    import os

    from reconstruct.video.stream import cpu_threads

    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    for load, want in ((0.0, 8), (0.4, 8), (2.6, 5), (7.9, 1), (30.0, 1)):
        monkeypatch.setattr(os, "getloadavg", lambda load=load: (load, 0.0, 0.0))
        assert cpu_threads(0) == want, (load, cpu_threads(0))
        assert cpu_threads(3) == 3


@pytest.mark.parametrize("finest", [1, 2])
def test_fused_rir_levels_equal_the_scipy_levels(finest):
    """Oracle: the frame smoothed by scipy's gaussian_filter (reflect mode), block-averaged by the numpy block mean and
    differentiated by np.gradient, as the chained fit built its levels before.
    """
    from scipy.ndimage import gaussian_filter

    from reconstruct.physics.fused_rir import pyramid_fused, smooth_fused
    from reconstruct.physics.rir import _block_sum_mean

    rng = np.random.default_rng(11)
    frame = rng.uniform(0.0, 2.0, (H + 2, W + 3)).astype(np.float32)  # not a multiple of the blocks
    base = frame.astype(np.float64) if finest == 1 else _block_sum_mean(frame.astype(np.float64), finest)
    sm = gaussian_filter(base, 1.0 / finest)
    got = pyramid_fused(frame, 1.0 / finest, finest, (8, 2, 1)[: 3 - finest // 2])
    for lv, st in got.items():
        img = _block_sum_mean(sm, lv // finest) if lv > finest else sm
        want = np.stack([img, *np.gradient(img)])
        assert st.shape == want.shape and float(np.abs(st - want).max()) < 1e-12, lv
    for sigma, shape in ((0.5, (5, 7)), (3.0, (4, 30)), (1.0, (1, 9))):  # kernels wider than the image: reflected again
        x = rng.normal(size=shape)
        assert float(np.abs(smooth_fused(x, sigma) - gaussian_filter(x, sigma)).max()) < 1e-12, (sigma, shape)


def test_fused_erosion_equals_scipy():
    from scipy.ndimage import binary_erosion

    from reconstruct.physics.fused_rir import erode_fused

    rng = np.random.default_rng(12)
    for shape in ((23, 31), (3, 3), (1, 5)):
        m = rng.uniform(size=shape) < 0.85
        for it in (1, 2, 4):
            assert np.array_equal(erode_fused(m, it), binary_erosion(m, iterations=it, border_value=0)), (shape, it)


def test_quantile_by_selection_equals_torch_quantile():
    from reconstruct.physics.rir import _quantile

    g = torch.Generator().manual_seed(13)
    for n in (1, 2, 7, 1000, 25001):
        x = torch.rand(n, generator=g)
        for q in (0.0, 0.37, 0.99, 1.0):
            assert torch.equal(_quantile(x, q), torch.quantile(x, q)), (n, q)
    x = torch.rand(3, 2, 999, generator=g)  # along a dimension, as the anchor's per-frame noise tail takes it
    for q in (0.1, 0.5):  # to one rounding of the interpolation (torch interpolates a batch in another order)
        torch.testing.assert_close(_quantile(x, q, dim=-1), torch.quantile(x, q, dim=-1), rtol=2e-7, atol=0)


def test_chained_rir_on_the_compiled_kernels_equals_the_torch_and_scipy_steps():
    """The fused chained RIR (compiled mask, levels and fit) against ``ChainedRir(fused=False)`` (scipy, numpy and the
    torch Gauss-Newton) on a moving synthetic group: the same shifts to 1e-9 px (the fused one given the frames as a
    list of arrays, as the live path passes its ring's views).
    """
    import reconstruct.stream.synthetic as S
    from reconstruct.physics.rir import ChainedRir

    g = S.make_group(S.SyntheticConfig(width=96, height=64, n_frames=11, motion_px_per_frame=0.4, noise="integrate_fire", exposure=3.0, seed=2), 0)
    I = torch.from_numpy(np.asarray(g.I, np.float32))
    phi = torch.from_numpy(np.asarray(g.phi_nominal))
    a, b = ChainedRir(mask_every=2), ChainedRir(mask_every=2, fused=False)
    for i in range(3, 8):
        sa = a.window_shifts([x.numpy() for x in I[i - 3 : i + 4]], phi[i - 3 : i + 4], np.arange(i - 3, i + 4)).numpy()  # as the ring's views
        sb = b.window_shifts(I[i - 3 : i + 4], phi[i - 3 : i + 4], np.arange(i - 3, i + 4)).numpy()
        assert np.abs(sa).max() > 0.3 and np.abs(sa - sb).max() < 1e-9, (i, sa, sb)
