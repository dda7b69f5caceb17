"""Paper Eq. (1)-(2) and their Stokes form; polarizer and DoP helpers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polphysics.fresnel import pane_coefficients
from polphysics.stokes import aolp, dop, polarizer_intensity
from polphysics.zeta import mix_eq1, stokes_from_layers, zeta

unit = st.floats(0.0, 1.0)
angle = st.floats(-2 * np.pi, 2 * np.pi)


def test_zeta_at_phi_perp_is_R_perp():
    """Eq. (2): zeta(phi_perp) = R_perp, zeta(phi_perp + pi/2) = R_par."""
    assert zeta(0.3, 0.2, 0.05, 0.3) == pytest.approx(0.2)
    assert zeta(0.3 + np.pi / 2, 0.2, 0.05, 0.3) == pytest.approx(0.05)


@settings(max_examples=300, deadline=None)
@given(phi=angle, phi_perp=angle, rs=unit, rp=unit)
def test_zeta_between_R_par_and_R_perp(phi, phi_perp, rs, rp):
    z = zeta(phi, rs, rp, phi_perp)
    assert min(rs, rp) - 1e-12 <= z <= max(rs, rp) + 1e-12
    assert zeta(phi + np.pi, rs, rp, phi_perp) == pytest.approx(z, abs=1e-12)  # period pi


@settings(max_examples=300, deadline=None)
@given(phi=angle, phi_perp=angle, theta=st.floats(0.0, np.pi / 2), n=st.floats(1.0, 3.0), lt=unit, lr=unit,
       model=st.sampled_from(["single", "thin_slab"]))
def test_eq1_equals_stokes_form(phi, phi_perp, theta, n, lt, lr, model):
    """1/2 (S0 + S1 cos 2phi + S2 sin 2phi) of the Stokes form equals paper Eq. (1) to 1e-6."""
    c = pane_coefficients(theta, n, model)
    S = stokes_from_layers(lt, lr, c["R_perp"], c["R_par"], c["T_perp"], c["T_par"], phi_perp)
    i_stokes = polarizer_intensity(S[0], S[1], S[2], phi)
    i_eq1 = mix_eq1(lr, lt, zeta(phi, c["R_perp"], c["R_par"], phi_perp))
    assert i_stokes == pytest.approx(float(i_eq1), abs=1e-6)
    assert dop(S[0], S[1], S[2]) <= 1.0


def test_stokes_form_convention_horizontal():
    """s-direction along image x (phi_perp = 0): reflected light has S1 > 0, S2 = 0."""
    S = stokes_from_layers(0.0, 1.0, 0.3, 0.1, 0.7, 0.9, 0.0)
    assert S[1] > 0 and abs(S[2]) < 1e-15
    S45 = stokes_from_layers(0.0, 1.0, 0.3, 0.1, 0.7, 0.9, np.pi / 4)
    assert S45[2] > 0 and abs(S45[1]) < 1e-15
    assert aolp(S45[1], S45[2]) == pytest.approx(np.pi / 4)


def test_malus_law_and_extinction():
    """Fully polarized light along phi0: I(phi) = S0 cos^2(phi - phi0) (Malus); finite ER leaks 1/ER."""
    phi0 = 0.4
    s0, s1, s2 = 1.0, np.cos(2 * phi0), np.sin(2 * phi0)
    phis = np.linspace(0, np.pi, 37)
    np.testing.assert_allclose(polarizer_intensity(s0, s1, s2, phis), np.cos(phis - phi0) ** 2, atol=1e-12)
    crossed = polarizer_intensity(s0, s1, s2, phi0 + np.pi / 2, extinction_ratio=1000.0)
    assert crossed == pytest.approx(1e-3, rel=1e-9)


def test_dop_zero_light_is_zero_not_nan():
    assert dop(0.0, 0.0, 0.0) == 0.0
    assert np.all(np.isfinite(dop(np.zeros(4), np.zeros(4), np.zeros(4))))
