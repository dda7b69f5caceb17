"""Rendering at the extremes: spp 1 and 1024, n -> 1, normal and steep incidence, through the
real tiers. Every output is finite, S0 >= 0, the degree of polarization stays <= 1, and the limits match
closed forms (no reflection at n = 1, R_perp = R_par at normal incidence).
"""

from __future__ import annotations

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene


def _render(scene, tmp_path, **opts):
    from generator.render import RenderOptions, render
    from spike_sim.renderdir import open_render

    render(scene, tmp_path / "r", RenderOptions(duration_s=0.0, **opts))
    return open_render(tmp_path / "r")


def _check_stokes(S: np.ndarray, tol: float = 1e-5) -> None:
    assert np.all(np.isfinite(S))
    s0, s1, s2 = S.astype(np.float64)
    assert np.all(s0 >= -tol)
    assert np.all(np.hypot(s1, s2) <= s0 * (1 + tol) + tol)


@pytest.mark.mitsuba
@pytest.mark.parametrize("spp", [1, 1024])
def test_full_tier_extreme_spp_is_finite_and_physical(tmp_path, spp):
    require_mitsuba()
    rd = _render(small_scene("brewster", 12, 8), tmp_path, tier="full", spp=spp, variant="llvm")
    _check_stokes(rd.stokes(0))


@pytest.mark.mitsuba
def test_maps_tier_n_to_one_has_no_reflection(tmp_path):
    require_mitsuba()
    rd = _render(small_scene("brewster", 16, 10, n=1.0 + 1e-6, model="single"), tmp_path, tier="maps", spp=1, variant="llvm")
    m = rd.maps()
    for k in ("R_perp", "R_par"):
        assert np.all(np.isfinite(m[k])) and float(np.max(m[k])) < 1e-9, k
    assert np.allclose(m["T_perp"], 1.0, atol=1e-6) and np.allclose(m["T_par"], 1.0, atol=1e-6)
    _check_stokes(rd.stokes(0))


@pytest.mark.parametrize("tier", ["analytic", pytest.param("maps", marks=pytest.mark.mitsuba)])
def test_normal_incidence_pixel_has_equal_reflectances(tmp_path, tier):
    """Tilt 0: the centre pixel looks along the pane normal, phi_perp is undefined there and must not matter."""
    if tier == "maps":
        require_mitsuba()
    rd = _render(small_scene("near_normal", 17, 11, tilt_deg=0.0), tmp_path, tier=tier, spp=1)
    m = rd.maps()
    for k, v in m.items():
        assert np.all(np.isfinite(v)), k
    c = (m["R_perp"].shape[0] // 2, m["R_perp"].shape[1] // 2)
    assert m["theta"][c] < 1e-3
    assert abs(m["R_perp"][c] - m["R_par"][c]) < 1e-6
    _check_stokes(rd.stokes(0))


def test_steep_incidence_analytic(tmp_path):
    """A pane tilted 70 deg (large enough to fill the view): the view's edge sees it at theta ~ 88.9 deg (grazing);
    reflectances rise toward 1 and stay in [0, 1].
    """
    rd = _render(small_scene("brewster", 16, 10, tilt_deg=70.0, size_m=[40.0, 8.0]), tmp_path, tier="analytic")
    m = rd.maps()
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        assert np.all(np.isfinite(m[k])) and np.all((m[k] >= 0) & (m[k] <= 1)), k
    assert float(m["theta"].max()) > np.deg2rad(88.5)
    from polphysics.fresnel import fresnel_power

    k = np.unravel_index(np.argmax(m["theta"]), m["theta"].shape)
    assert float(m["R_perp"][k]) >= float(fresnel_power(m["theta"][k], 1.5)[0]) - 1e-6  # a slab reflects at least one interface's share
    assert float(m["R_perp"][k]) > 0.85
    _check_stokes(rd.stokes(0))
