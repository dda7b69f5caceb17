"""Numerics at the physical extremes (issue: validate-zeta / extremes). Each case has its tolerance; none
may produce NaN or Inf.
"""

from __future__ import annotations

import numpy as np
import pytest

from polphysics.fresnel import fresnel_power, pane_coefficients
from polphysics.stokes import aolp, dop, polarizer_intensity
from polphysics.zeta import mix_eq1, stokes_from_layers, zeta

deg = np.deg2rad


@pytest.mark.parametrize("model", ["single", "thin_slab", "thick_slab"])
@pytest.mark.parametrize("theta_deg", [0.0, 1e-9, 56.309932474020215, 89.99, 90.0])
@pytest.mark.parametrize("n", [1.0, 1.0 + 1e-9, 1.5, 3.9])
def test_pane_coefficients_finite_and_bounded(model, theta_deg, n):
    c = pane_coefficients(deg(theta_deg), n, model, thickness_m=0.005, absorption_per_m=10.0)
    for k, v in c.items():
        assert np.all(np.isfinite(v)), k
        assert np.all((v >= -1e-15) & (v <= 1 + 1e-15)), (k, v)
    assert c["R_perp"] + c["T_perp"] <= 1 + 1e-12


def test_n_to_one_no_reflection():
    """N -> 1: r is linear in eps = n - 1 away from grazing, so R scales as eps^2 and vanishes."""
    th = deg(np.linspace(0, 80, 9))
    R2 = fresnel_power(th, 1 + 1e-2)[0]
    R4 = fresnel_power(th, 1 + 1e-4)[0]
    R6 = fresnel_power(th, 1 + 1e-6)[0]
    np.testing.assert_allclose((R4 / R2)[:7], 1e-4, rtol=0.1)  # eps = 1e-2 is not yet asymptotic near grazing
    np.testing.assert_allclose(R6 / R4, 1e-4, rtol=0.1)
    assert np.all(R6 < 1e-9)


def test_normal_incidence_phi_perp_irrelevant():
    """At theta = 0, R_perp = R_par, so zeta is the same whatever phi_perp is."""
    Rs, Rp, _, _ = fresnel_power(0.0, 1.5)
    z = [zeta(p, Rs, Rp, pp) for p in np.linspace(0, np.pi, 7) for pp in (0.0, 1.0, np.pi - 1e-12)]
    np.testing.assert_allclose(z, 0.04, atol=1e-15)


def test_brewster_reflection_fully_polarized():
    Rs, Rp, Ts, Tp = fresnel_power(np.arctan(1.5), 1.5)
    S = stokes_from_layers(0.0, 1.0, Rs, Rp, Ts, Tp, 0.7)
    assert dop(*S) == pytest.approx(1.0, abs=1e-12)
    assert polarizer_intensity(*S, 0.7 + np.pi / 2) == pytest.approx(0.0, abs=1e-15)


def test_total_internal_reflection_zeta_is_one():
    z = zeta(np.linspace(0, np.pi, 13), *fresnel_power(deg(60.0), 1 / 1.5)[:2], 0.3)
    np.testing.assert_allclose(z, 1.0, atol=1e-12)


def test_phi_wraparound():
    """Phi and phi + pi, and phi_perp near 0 vs near pi, describe the same polarizer / plane."""
    for p in (0.0, 1e-12, np.pi - 1e-12, np.pi, 2 * np.pi):
        assert zeta(p, 0.3, 0.1, 0.0) == pytest.approx(zeta(p + np.pi, 0.3, 0.1, np.pi), abs=1e-12)
    a = aolp(np.array([1.0, 1.0]), np.array([-1e-15, 1e-15]))
    assert np.all((a >= 0) & (a < np.pi))
    assert min(a[0], np.pi - a[0]) < 1e-12


def test_dop_extremes():
    assert dop(1.0, 0.0, 0.0) == 0.0
    assert dop(1.0, np.cos(0.4), np.sin(0.4)) == pytest.approx(1.0)
    assert dop(0.0, 0.0, 0.0) == 0.0


def test_zero_and_saturated_light():
    c = pane_coefficients(deg(45.0), 1.5, "thin_slab")
    S0 = stokes_from_layers(0.0, 0.0, c["R_perp"], c["R_par"], c["T_perp"], c["T_par"], 0.2)
    assert np.all(S0 == 0)
    S1 = stokes_from_layers(1.0, 1.0, c["R_perp"], c["R_par"], c["T_perp"], c["T_par"], 0.2)
    assert S1[0] == pytest.approx(1.0, abs=1e-15)  # lossless: R + T = 1 per polarization
    assert dop(*S1) == pytest.approx(0.0, abs=1e-12)  # and the sum is unpolarized


def test_float32_path_matches_float64(np_rng):
    """Stokes stored as float32 (EXR) reproduce Eq. (1) to float32 precision."""
    n = 1000
    th = np_rng.uniform(0, np.pi / 2, n)
    c = pane_coefficients(th, 1.5, "thin_slab")
    lt, lr, pp, phi = np_rng.random(n), np_rng.random(n), np_rng.uniform(0, np.pi, n), np_rng.uniform(0, np.pi, n)
    S64 = stokes_from_layers(lt, lr, c["R_perp"], c["R_par"], c["T_perp"], c["T_par"], pp)
    S32 = S64.astype(np.float32)
    i32 = polarizer_intensity(S32[0], S32[1], S32[2], np.float32(phi))
    i64 = mix_eq1(lr, lt, zeta(phi, c["R_perp"], c["R_par"], pp))
    np.testing.assert_allclose(i32, i64, atol=2e-7, rtol=0)
