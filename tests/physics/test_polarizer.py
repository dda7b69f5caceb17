"""Rotating polarizer: phi(t) model and the CLOSED-FORM step integral (vs fine Riemann sums)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polphysics.polarizer import (
    PolarizerConfig,
    phi_nominal,
    phi_true,
    step_jitter,
    step_keyframe_weights,
    step_mean_intensity,
    step_moments,
)
from polphysics.stokes import polarizer_intensity

DT = 5e-5
RIEMANN = 20000  # midpoint samples per step: error ~ (0.0094 rad)^2 / RIEMANN^2, far below the tolerances


def _riemann_step(s0, s1, s2, phi_a, phi_b, er=None):
    u = (np.arange(RIEMANN) + 0.5) / RIEMANN
    phi = phi_a + (phi_b - phi_a) * u
    return polarizer_intensity(s0, s1, s2, phi, er).mean()


@pytest.mark.parametrize("er", [None, 1000.0, 3.0])
@pytest.mark.parametrize("span_deg", [0.54, 5.0, 90.0, 1e-7])
def test_closed_form_step_integral_matches_riemann(er, span_deg):
    """Malus' law integrated over one step: closed form == fine midpoint sum (atol 1e-10)."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        s0 = rng.uniform(0.1, 1.0)
        d, a = rng.uniform(0, 1), rng.uniform(0, np.pi)
        s1, s2 = s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)
        pa = rng.uniform(-7, 7)
        pb = pa + np.deg2rad(span_deg)
        got = step_mean_intensity(s0, s1, s2, pa, pb, er)
        assert abs(got - _riemann_step(s0, s1, s2, pa, pb, er)) < 1e-10


def test_zero_length_step_is_malus():
    """phi_a == phi_b reduces to the instantaneous polarizer_intensity."""
    phi = np.linspace(0, np.pi, 17)
    got = step_mean_intensity(1.0, 0.3, -0.2, phi, phi)
    np.testing.assert_allclose(got, polarizer_intensity(1.0, 0.3, -0.2, phi), atol=1e-15)


def test_u_weighted_moments_match_riemann():
    """Int u cos 2phi du and int u sin 2phi du over sub-ranges (used by keyframe interpolation)."""
    rng = np.random.default_rng(5)
    for _ in range(10):
        pa = rng.uniform(-3, 3)
        pb = pa + rng.uniform(0, 0.3)
        u0 = rng.uniform(0, 0.5)
        u1 = rng.uniform(u0, 1.0)
        m = step_moments(pa, pb, u0, u1)
        u = u0 + (u1 - u0) * (np.arange(RIEMANN) + 0.5) / RIEMANN
        phi2 = 2 * (pa + (pb - pa) * u)
        L = u1 - u0
        ref = {"1": L, "u": (u * L).mean() * 1, "c": np.cos(phi2).mean() * L, "s": np.sin(phi2).mean() * L, "uc": (u * np.cos(phi2)).mean() * L, "us": (u * np.sin(phi2)).mean() * L}
        for k, v in ref.items():
            assert abs(float(m[k]) - v) < 1e-10, k  # midpoint-rule error ~ 4e-11 at span 0.3 rad


@pytest.mark.parametrize("er", [None, 200.0])
def test_keyframe_weights_match_riemann_with_linear_stokes(er):
    """Stokes linear in time between irregular keyframes (steps straddle them) x polarizer: exact."""
    cfg = PolarizerConfig(phase_deg=10.0, extinction_ratio=er, wobble_frac=0.01, wobble_hz=2.0, calibration_offset_deg=2.0)
    kt = np.array([0.0, 0.00101, 0.00203, 0.0030])
    S = np.random.default_rng(0).uniform(-0.3, 1.0, (4, 3))
    k_lo, W = step_keyframe_weights(0, 70, DT, kt, cfg)
    x = np.einsum("nks,nks->n", W, S[np.clip(k_lo[:, None] + np.arange(3), 0, 3)])
    for n in range(70):
        t = (n + (np.arange(4000) + 0.5) / 4000) * DT
        St = np.stack([np.interp(t, kt, S[:, j]) for j in range(3)])
        ref = polarizer_intensity(St[0], St[1], St[2], phi_true(t, cfg), er).mean()
        # 4000-sample midpoint rule: error ~ 1e-9 at the keyframe kinks
        assert abs(ref - x[n]) < 5e-9, n


def test_single_keyframe_weights():
    cfg = PolarizerConfig(phase_deg=33.0)
    k_lo, W = step_keyframe_weights(5, 9, DT, np.array([0.0]), cfg)
    assert np.all(k_lo == 0)
    assert np.allclose(W[:, 0, 0], 0.5) and np.all(W[:, 1:, :] == 0)


def test_phi_model():
    """phi(0) = phase + offset; nominal lacks offset/wobble; mean speed = f; wobble changes speed by a."""
    cfg = PolarizerConfig(rate_hz=30.0, phase_deg=12.0, calibration_offset_deg=1.5, wobble_frac=0.05, wobble_hz=3.0)
    assert phi_true(0.0, cfg) == pytest.approx(np.deg2rad(13.5), abs=1e-15)
    assert phi_nominal(0.0, cfg) == pytest.approx(np.deg2rad(12.0), abs=1e-15)
    one_wobble = 1.0 / 3.0
    assert (phi_true(one_wobble, cfg) - phi_true(0.0, cfg)) == pytest.approx(2 * np.pi * 30.0 * one_wobble, rel=1e-12)
    t = np.array([0.0, 1e-6])
    speed = np.diff(phi_true(t + 1 / 12, cfg))[0] / 1e-6 / (2 * np.pi)  # sin(2 pi 3 /12) = 1: peak speed
    assert speed == pytest.approx(30.0 * 1.05, rel=1e-5)


def test_jitter_is_counter_based_and_has_the_right_spread():
    cfg = PolarizerConfig(jitter_deg=0.3)
    a = step_jitter(np.arange(0, 40000), cfg, seed=4)
    b = np.concatenate([step_jitter(np.arange(0, 17000), cfg, 4), step_jitter(np.arange(17000, 40000), cfg, 4)])
    assert np.array_equal(a, b)
    assert np.std(np.rad2deg(a)) == pytest.approx(0.3, rel=0.03)
    assert abs(np.corrcoef(a[:-1], a[1:])[0, 1]) < 0.03
    assert not np.array_equal(a, step_jitter(np.arange(0, 40000), cfg, seed=5))
    assert np.all(step_jitter(np.arange(10), PolarizerConfig(), 1) == 0)


@settings(max_examples=60, deadline=None)
@given(
    s0=st.floats(0.0, 10.0),
    dop=st.floats(0.0, 1.0),
    aolp=st.floats(0.0, np.pi),
    pa=st.floats(-20.0, 20.0),
    span=st.floats(0.0, 3.0),
)
def test_step_intensity_is_physical(s0, dop, aolp, pa, span):
    """0 <= <I> <= S0 for physical Stokes, any step span; period pi in phi."""
    s1, s2 = s0 * dop * np.cos(2 * aolp), s0 * dop * np.sin(2 * aolp)
    i = step_mean_intensity(s0, s1, s2, pa, pa + span)
    assert -1e-12 <= i <= s0 + 1e-12
    assert abs(i - step_mean_intensity(s0, s1, s2, pa + np.pi, pa + np.pi + span)) < 1e-9 * (1 + s0)


def test_wobble_linearisation_error_is_within_the_documented_bound():
    """Within a step phi is linear; a fast wobble bends it by <= 2 pi f a 2 pi f_w dt^2 / 8 rad."""
    cfg = PolarizerConfig(wobble_frac=0.05, wobble_hz=200.0)
    bound = 2 * np.pi * 30.0 * 0.05 * 2 * np.pi * 200.0 * DT**2 / 8
    k_lo, W = step_keyframe_weights(0, 40, DT, np.array([0.0]), cfg)
    x = W[:, 0, 0] * 1.0 + W[:, 0, 1] * 1.0  # S = (1, 1, 0)
    for n in range(40):
        t = (n + (np.arange(4000) + 0.5) / 4000) * DT
        ref = polarizer_intensity(1.0, 1.0, 0.0, phi_true(t, cfg)).mean()
        assert abs(ref - x[n]) <= bound + 1e-9
