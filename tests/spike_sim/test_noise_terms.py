"""Each noise term of SpikeSimConfig is switchable and acts as documented (both engines);
the polarizer's finite extinction ratio reaches the spike counts; exposure is the documented gain.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from polphysics.polarizer import PolarizerConfig
from spike_sim.calibrate import isi_cv
from spike_sim.config import IDEAL
from spike_sim.integrate_fire import simulate_constant
from spike_sim.simulate import keyframes_from_arrays, simulate

H, W, N = 8, 16, 800
G = 0.25  # dyadic: the ideal pixel fires exactly every 4th step


def _run(engine, **flags):
    cfg = dataclasses.replace(IDEAL, width=W, height=H, **flags)
    return simulate_constant(np.full((H, W), G, np.float32), N, cfg, seed=5, engine=engine).reshape(N, -1)


def _isi_cv(x):
    return float(np.nanmedian(isi_cv(x)))


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_each_noise_term_switches_on_alone_and_does_what_it_says(engine):
    ideal = _run(engine)
    assert np.all(ideal.sum(0) == N * G) and _isi_cv(ideal) == 0.0  # the reference: perfectly regular
    # photon shot noise: ISI jitter ~ 1/sqrt(Q) (Q = 100 photoelectrons per threshold here)
    assert 0.02 < _isi_cv(_run(engine, shot_noise=True, photons_per_threshold=100.0)) < 0.3
    # thermal noise on the comparison and reset noise on the residue: ISI jitter too
    assert _isi_cv(_run(engine, thermal_noise=True, thermal_sigma=0.05)) > 0.01
    assert _isi_cv(_run(engine, reset_noise=True, reset_sigma=0.05)) > 0.01
    # fixed pattern: per-pixel rate spread under uniform light (gain spread dominates)
    fp = _run(engine, fixed_pattern=True).sum(0) / N
    assert fp.std() / fp.mean() > 0.02 and np.isclose(fp.mean(), G, rtol=0.05)
    # leakage: a leaky accumulator needs more light per spike -> fewer spikes
    leaky = _run(engine, leakage=True, leak_rate_hz=2000.0).sum(0)
    assert np.all(leaky < N * G)
    # random initial accumulator: first spikes spread over the first ISI instead of all at step 3
    first = np.argmax(_run(engine, random_init=True) > 0, axis=0)
    assert np.all(np.argmax(ideal > 0, axis=0) == 3) and len(np.unique(first)) == 4
    # dark current: a pixel in the dark fires only with it on (mean dark_mean spikes per step)
    cfg = dataclasses.replace(IDEAL, width=W, height=H)
    assert simulate_constant(np.zeros((H, W), np.float32), N, cfg, seed=5, engine=engine).sum() == 0
    dark = simulate_constant(np.zeros((H, W), np.float32), 4000, dataclasses.replace(cfg, dark_current=True, dark_mean=0.01, dark_std=0.002, hot_pixel_fraction=0.0), seed=5, engine=engine)
    assert dark.mean() == pytest.approx(0.01, rel=0.15)


def test_exposure_is_the_radiance_to_photocurrent_gain():
    """Documented mapping: noise-free, intensity g behind the polarizer fires exposure * g spikes per step;
    an unpolarized S0 = 1 gives g = 1/2 behind the polarizer.
    """
    for exposure in (0.25, 1.0, 1.5):
        cfg = dataclasses.replace(IDEAL, width=4, height=2, exposure=exposure)
        st = np.zeros((1, 3, 2, 4), np.float32)
        st[0, 0] = 0.5  # unpolarized S0 = 0.5 -> g = 0.25
        chunks = []
        simulate(keyframes_from_arrays([0.0], st), 0.05, 0, cfg, out=None, spikes_sink=lambda n0, o: chunks.append(o))
        bits = np.unpackbits(np.concatenate(chunks), axis=1, bitorder="little", count=8)
        assert np.all(np.abs(bits.sum(0) - 1000 * 0.25 * exposure) <= 1), exposure


@pytest.mark.parametrize("er", [None, 10.0, 100.0])
def test_finite_extinction_ratio_leaks_the_crossed_polarization(er):
    """Fully polarized flat target S = g (1, 1, 0): over whole half-turns the mean intensity is
    g (1 + k) / 2 with k = 1/ER; at the crossed angle the polarizer leaks k g instead of 0.
    """
    g = 0.8
    cfg = dataclasses.replace(IDEAL, width=4, height=2)
    st = np.zeros((1, 3, 2, 4), np.float32)
    st[0, 0], st[0, 1] = g, g
    pol = PolarizerConfig(rate_hz=30.0, extinction_ratio=er)
    chunks = []
    simulate(keyframes_from_arrays([0.0], st, polarizer=pol), 0.05, 0, cfg, out=None, spikes_sink=lambda n0, o: chunks.append(o))
    bits = np.unpackbits(np.concatenate(chunks), axis=1, bitorder="little", count=8)
    k = 0.0 if er is None else 1.0 / er
    # 0.05 s at 30 rev/s = 3 periods of cos 2 phi (1000 steps)
    assert np.all(np.abs(bits.sum(0) - 1000 * g * (1 + k) / 2) <= 1)
    # step by step: cumulative count = floor of the closed-form integral of I(phi(t)) (phi0 = 0)
    n = np.arange(1, 1001)
    w2 = 2 * (2 * np.pi * 30.0) * cfg.dt_s  # 2 phi per step

    def cum(kk):
        return g / 2 * ((1 + kk) * n + (1 - kk) * np.sin(w2 * n) / w2)

    cs = np.cumsum(s := bits[:, 0].astype(np.int64))
    assert np.abs(cs - np.floor(cum(k))).max() <= 1
    if er is not None:  # ...and it is not the ideal polarizer's
        assert np.abs(cs - np.floor(cum(0.0))).max() >= 3
    assert s.sum() > 0
