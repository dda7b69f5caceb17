"""Fresnel equations and pane models against textbook closed forms (Hecht, Optics, Sec. 4.6)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polphysics.fresnel import (
    brewster_angle,
    critical_angle,
    fresnel_amplitudes,
    fresnel_power,
    glass_index,
    pane_coefficients,
    slab_coefficients,
)

deg = np.deg2rad


def test_reference_values_at_45_deg():
    """N = 1.5 at 45 deg: R_s = 0.0920, R_p = 0.0085 (4 digits)."""
    Rs, Rp, _, _ = fresnel_power(deg(45.0), 1.5)
    assert round(float(Rs), 4) == 0.0920
    assert round(float(Rp), 4) == 0.0085


def test_normal_incidence():
    """((n - 1)/(n + 1))^2 = 0.04 for n = 1.5, both polarizations."""
    Rs, Rp, _, _ = fresnel_power(0.0, 1.5)
    assert Rs == pytest.approx(0.04, abs=1e-12)
    assert Rp == pytest.approx(0.04, abs=1e-12)


def test_brewster_law():
    """R_p vanishes at theta_B = arctan(n) = 56.31 deg for n = 1.5."""
    tb = brewster_angle(1.5)
    assert np.rad2deg(tb) == pytest.approx(56.31, abs=0.005)
    assert fresnel_power(tb, 1.5)[1] < 1e-15


def test_grazing_limit():
    """R -> 1 as theta -> 90 deg for any n != 1."""
    for n in (1.01, 1.5, 2.4, 0.7):
        Rs, Rp, _, _ = fresnel_power(deg(np.array([89.99, 90.0])), n)
        assert Rs[-1] == pytest.approx(1.0, abs=1e-12) and Rp[-1] == pytest.approx(1.0, abs=1e-12)
        assert Rs[0] > 0.99 and Rp[0] > 0.9


def test_matched_index_has_no_reflection():
    """N = 1: no interface, R = 0 at every angle including grazing."""
    Rs, Rp, Ts, Tp = fresnel_power(deg(np.linspace(0, 90, 91)), 1.0)
    assert np.all(Rs == 0) and np.all(Rp == 0) and np.all(Ts == 1) and np.all(Tp == 1)


def test_total_internal_reflection():
    """N < 1: R = 1 exactly beyond the critical angle arcsin(n), < 1 below it."""
    n = 1 / 1.5
    tc = critical_angle(n)
    assert np.rad2deg(tc) == pytest.approx(41.81, abs=0.01)
    above = np.linspace(tc + 1e-6, np.pi / 2, 50)
    Rs, Rp, _, _ = fresnel_power(above, n)
    np.testing.assert_allclose(Rs, 1.0, atol=1e-12)
    np.testing.assert_allclose(Rp, 1.0, atol=1e-12)
    Rs_b, Rp_b, _, _ = fresnel_power(tc - 0.05, n)
    assert Rs_b < 1 and Rp_b < 1


def test_finiteness_on_closed_interval():
    """Values in [0, 1], no NaN/Inf over theta in [0, 90] and n in (0, 4] (the edges: grazing, n = 1, TIR)."""
    th = deg(np.linspace(0.0, 90.0, 361))[:, None]
    n = np.array([0.2, 0.5, 1 / 1.5, 0.999999, 1.0, 1.000001, 1.33, 1.5, 2.0, 4.0])[None, :]
    Rs, Rp, Ts, Tp = fresnel_power(th, n)
    for a in (Rs, Rp, Ts, Tp):
        assert np.all(np.isfinite(a)) and np.all(a >= 0) and np.all(a <= 1)
    for a in fresnel_amplitudes(th, n):
        assert np.all(np.isfinite(a))


def test_power_coefficients_are_the_amplitudes_fluxes():
    """Energy balance from the amplitudes, not from T = 1 - R: the transmitted flux is (n cos_t / cos_i) |t|^2
    (n cos_t written here from Snell's law; 0 beyond the critical angle), and per polarization
    |r|^2 + (n cos_t / cos_i) |t|^2 = 1; fresnel_power's R and T equal |r|^2 and that flux, over
    theta in [0, 89.5] deg and n from 0.2 (TIR) to 4.
    """
    th = deg(np.linspace(0.0, 89.5, 180))[:, None]
    n = np.array([0.2, 0.5, 1 / 1.5, 0.999, 1.001, 1.33, 1.5, 2.0, 4.0])[None, :]
    rs, rp, ts, tp = fresnel_amplitudes(th, n)
    Rs, Rp, Ts, Tp = fresnel_power(th, n)
    sin_t = np.sin(th) / n
    k = n * np.sqrt(np.clip(1 - sin_t**2, 0, None)) / np.cos(th)
    assert np.any(sin_t > 1) and np.any(k > 1)  # the grid holds TIR and flux gains
    for r, t, R, T in ((rs, ts, Rs, Ts), (rp, tp, Rp, Tp)):
        np.testing.assert_allclose(np.abs(r) ** 2 + k * np.abs(t) ** 2, 1.0, atol=1e-12)
        np.testing.assert_allclose(R, np.abs(r) ** 2, atol=1e-12)
        np.testing.assert_allclose(T, k * np.abs(t) ** 2, atol=1e-12)


def test_amplitude_energy_balance():
    """Stokes relation: |r|^2 + (n cos_t / cos_i) |t|^2 = 1 below the critical angle (independent of R + T = 1 by construction)."""
    th = deg(np.linspace(0, 85, 30))
    n = 1.5
    rs, rp, ts, tp = fresnel_amplitudes(th, n)
    cos_t = np.sqrt(1 - (np.sin(th) / n) ** 2)
    k = n * cos_t / np.cos(th)
    np.testing.assert_allclose(np.abs(rs) ** 2 + k * np.abs(ts) ** 2, 1.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(rp) ** 2 + k * np.abs(tp) ** 2, 1.0, atol=1e-12)


def test_slab_lossless_closed_form():
    """Lossless incoherent slab: R = 2R1/(1+R1), T = (1-R1)/(1+R1)."""
    R1 = np.linspace(0, 0.99, 50)
    R, T, G = slab_coefficients(R1)
    np.testing.assert_allclose(R, 2 * R1 / (1 + R1), atol=1e-14)
    np.testing.assert_allclose(T, (1 - R1) / (1 + R1), atol=1e-14)
    np.testing.assert_allclose(G, R - R1, atol=1e-15)


def test_slab_matches_explicit_ray_series():
    """The slab formula equals the sum over interreflection orders, with absorption a per pass."""
    R1, a = 0.3, 0.8
    R_series = R1 + sum((1 - R1) ** 2 * R1 ** (2 * k + 1) * a ** (2 * k + 2) for k in range(200))
    T_series = sum((1 - R1) ** 2 * R1 ** (2 * k) * a ** (2 * k + 1) for k in range(200))
    R, T, _ = slab_coefficients(R1, a)
    assert R == pytest.approx(R_series, rel=1e-12)
    assert T == pytest.approx(T_series, rel=1e-12)
    assert R + T < 1  # absorption removes energy


def test_pane_models_consistent():
    th = deg(np.linspace(0, 89.99, 100))
    single = pane_coefficients(th, 1.5, "single")
    thin = pane_coefficients(th, 1.5, "thin_slab")
    thick = pane_coefficients(th, 1.5, "thick_slab", thickness_m=0.005)
    np.testing.assert_allclose(thin["R_perp"], 2 * single["R_perp"] / (1 + single["R_perp"]))
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        np.testing.assert_allclose(thick[k], thin[k])
        np.testing.assert_allclose(thin[k.replace("R", "T") if k[0] == "R" else k.replace("T", "R")] + thin[k], 1.0, atol=1e-14)
    np.testing.assert_allclose(thick["G_perp"], thick["R_perp"] - single["R_perp"], atol=1e-14)


def test_bk7_dispersion():
    """BK7 Sellmeier: n_d(587.6 nm) = 1.5168 (SCHOTT), normal dispersion."""
    assert glass_index("BK7", 587.56) == pytest.approx(1.5168, abs=1e-4)
    assert glass_index("bk7", 450.0) > glass_index("BK7", 650.0)


@settings(max_examples=200, deadline=None)
@given(theta=st.floats(0.0, np.pi / 2), n=st.floats(0.05, 4.0))
def test_reflectances_bounded_property(theta, n):
    Rs, Rp, Ts, Tp = fresnel_power(theta, n)
    assert 0.0 <= Rp <= 1.0 and 0.0 <= Rs <= 1.0
    if n >= 1.0:
        assert Rp <= Rs + 1e-15  # s always reflects at least as much as p from the rarer side
