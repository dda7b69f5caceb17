"""Integrate-and-fire kernel: exact noise-free counts, determinism, equivalence with the numpy reference."""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import pytest

from spike_sim.calibrate import isi_cv
from spike_sim.config import DEFAULT, IDEAL
from spike_sim.integrate_fire import (
    make_pixel_params,
    noise_scalars,
    packed_frame_bytes,
    run_numba,
    simulate_constant,
    step_keys,
)


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_constant_radiance_gives_exact_spike_count_noise_free(engine):
    """Ideal pixel at intensity g (dyadic, exact in float32) fires floor(n g) times in n steps, ISIs 1/g."""
    cfg = dataclasses.replace(IDEAL, width=16, height=8)
    g = (np.arange(128, dtype=np.float32).reshape(8, 16) + 1) / 128.0  # 1/128 .. 1
    n = 640
    s = simulate_constant(g, n, cfg, seed=0, engine=engine)
    np.testing.assert_array_equal(s.sum(0), np.floor(n * g.astype(np.float64)))
    # g = 1/4: every 4th step exactly
    j = np.argwhere(np.isclose(g, 0.25))[0]
    assert np.array_equal(np.flatnonzero(s[:, j[0], j[1]]), np.arange(3, n, 4))


def test_exposure_scales_rate():
    cfg = dataclasses.replace(IDEAL, width=8, height=8, exposure=0.5)
    s = simulate_constant(np.full((8, 8), 0.5, np.float32), 400, cfg, seed=0)
    assert np.all(s.sum(0) == 100)


def test_spikes_never_exceed_steps_and_dark_pixel_fires_from_dark_current_only():
    cfg = dataclasses.replace(DEFAULT, width=40, height=25, hot_pixel_fraction=0.0)
    s = simulate_constant(np.zeros((25, 40), np.float32), 4000, cfg, seed=2)
    rate = s.mean()
    assert rate == pytest.approx(cfg.dark_mean, rel=0.25)  # 10 Hz dark rate at 20 kHz
    # an input of 3 thresholds per step would integrate to 150 spikes in 50 steps; the binary readout
    # clips it at one per step: every pixel of the noisy sensor fires on every one of the 50 steps
    bright = simulate_constant(np.ones((25, 40), np.float32), 50, dataclasses.replace(cfg, exposure=3.0), seed=2)
    assert np.all(bright.sum(0) == 50), np.unique(bright.sum(0))
    half = simulate_constant(np.ones((25, 40), np.float32), 50, dataclasses.replace(cfg, exposure=0.5), seed=2)
    assert 20 < half.sum(0).mean() < 30  # below the threshold rate nothing clips: ~25


def _run_chunked(cfg, g, n, seed, chunks):
    params = make_pixel_params(cfg, seed)
    V = params.v0.copy()
    P = cfg.n_pixels
    basis = np.zeros((6, P), np.float32)
    basis[0] = g.ravel() * params.gain
    coef = np.zeros((n, 6), np.float32)
    coef[:, 0] = 1.0 + 0.5 * np.sin(np.arange(n) / 7.0)
    out = np.zeros((n, packed_frame_bytes(P)), np.uint8)
    edges = np.unique(np.concatenate([[0], np.cumsum(chunks), [n]]))
    edges = edges[edges <= n]
    for a, b in zip(edges[:-1], edges[1:]):
        run_numba(basis, coef[a:b], step_keys(a, b, seed), params, V, noise_scalars(cfg), out[a:b])
    return out


def test_deterministic_across_chunking_and_thread_count():
    """Counter-based randomness: same bits for any chunking in time and any number of threads."""
    cfg = dataclasses.replace(DEFAULT, width=37, height=11)  # P = 407: a partial block and a partial byte
    g = np.random.default_rng(0).random((11, 37)).astype(np.float32) * 0.4
    ref = _run_chunked(cfg, g, 300, 9, [300])
    old = numba.get_num_threads()
    try:
        for threads, chunks in ((1, [1] * 7 + [50, 113]), (numba.config.NUMBA_NUM_THREADS, [299]), (1, [100, 100])):
            numba.set_num_threads(threads)
            assert np.array_equal(_run_chunked(cfg, g, 300, 9, chunks), ref)
    finally:
        numba.set_num_threads(old)
    assert not np.array_equal(_run_chunked(cfg, g, 300, 10, [300]), ref)


def test_numba_kernel_is_statistically_equivalent_to_numpy_reference():
    """Gaussian-for-Poisson and triangular normals: same rate, ISI CV and per-pixel spread (fixed seed).

    A deliberately noisy camera (Q = 100 photoelectrons per threshold) makes the
    noise dominate the ISI jitter so the comparison has power.
    """
    cfg = dataclasses.replace(DEFAULT, width=50, height=40, photons_per_threshold=100.0, reset_sigma=0.02)
    g = np.tile(np.array([0.02, 0.05, 0.1, 0.25, 0.5], np.float32), (40, 10))  # 5 rate classes, 400 pixels each
    n = 1500
    a = simulate_constant(g, n, cfg, seed=3, engine="numba").reshape(n, -1)
    b = simulate_constant(g, n, cfg, seed=3, engine="numpy").reshape(n, -1)
    cls = g.ravel()
    for level in np.unique(cls):
        m = cls == level
        ra, rb = a[:, m].mean(0), b[:, m].mean(0)
        assert ra.mean() == pytest.approx(rb.mean(), rel=0.02), level  # rate
        assert ra.std() == pytest.approx(rb.std(), rel=0.25, abs=2e-4), level  # per-pixel spread (fixed pattern + noise)
        ca, cb = np.nanmedian(isi_cv(a[:, m])), np.nanmedian(isi_cv(b[:, m]))
        assert ca == pytest.approx(cb, rel=0.12), level  # ISI CV
    # ISI distribution shape at one level: two-sample KS statistic small
    from scipy.stats import ks_2samp

    m = cls == 0.1
    da = np.concatenate([np.diff(np.flatnonzero(col)) for col in a[:, m].T])
    db = np.concatenate([np.diff(np.flatnonzero(col)) for col in b[:, m].T])
    assert ks_2samp(da, db).statistic < 0.04


def test_counter_hash_noise_is_uncorrelated_between_neighbours():
    """Adjacent pixels and consecutive steps see independent noise (shot-noise driven ISI jitter)."""
    cfg = dataclasses.replace(DEFAULT, width=64, height=32, photons_per_threshold=30.0, fixed_pattern=False, random_init=False)
    s = simulate_constant(np.full((32, 64), 0.3, np.float32), 2000, cfg, seed=1).reshape(2000, -1).astype(np.float64)
    c = np.corrcoef(s[:, :-1].ravel(), s[:, 1:].ravel())[0, 1]
    assert abs(c) < 0.05  # identical zero initial state: only the noise decorrelates them
    counts = s.sum(0)
    assert counts.std() > 2.0  # noise really acts
