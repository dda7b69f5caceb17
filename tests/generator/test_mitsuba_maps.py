"""Tier ``maps`` (generator/tiers_mitsuba.py + mitsuba_integrator.py) against the analytic tier and Fresnel."""

from __future__ import annotations

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene

pytestmark = pytest.mark.mitsuba

COEFS = ("R_perp", "R_par", "T_perp", "T_par", "G_perp", "G_par")


def _opts(**kw):
    from generator.render import RenderOptions

    return RenderOptions(tier="maps", **{"spp": 4, "spectral": False, **kw})


def _compare(scene, tol, **kw):
    from generator import tiers_mitsuba as tm
    from generator.analytic import analytic_maps

    info: dict = {}
    m = tm.render_pane_maps(scene, _opts(**kw), info)
    a = analytic_maps(scene)
    errs = {k: float(np.abs(getattr(m, k) - getattr(a, k)).max()) for k in COEFS + ("theta",)}
    # phi_perp is defined where the reflection is polarized (away from normal incidence)
    pol = np.abs(a.R_perp - a.R_par) > 1e-4
    dphi = np.angle(np.exp(2j * (m.phi_perp - a.phi_perp))) / 2
    errs["phi_perp"] = float(np.abs(dphi[pol]).max())
    for k, v in errs.items():
        assert v <= tol, f"{scene.name} {scene.pane.model}: {k} max error {v:.3g} > {tol}"
    for k in COEFS + ("theta", "phi_perp"):
        assert np.all(np.isfinite(getattr(m, k))), k
    return m, info, errs


def test_maps_single_interface_matches_analytic_1e4():
    """Rendered maps vs analytic for a single interface within 1e-4 over the pane."""
    require_mitsuba()
    sc = small_scene("oblique_diagonal", model="single")
    m, info, errs = _compare(sc, 1e-4)
    assert info["variant"].endswith("mono_polarized") and info["spp"] == 4
    assert info["modelled"]["radiance_compression_1_over_n2"] is False


@pytest.mark.parametrize("name", ["brewster", "oblique_diagonal"])
def test_maps_slabs_match_incoherent_slab_law(name):
    """Two real interfaces, all interreflections traced: the incoherent slab 2R/(1+R) (and its ghost part G).

    One ray per pixel centre (spp = 1) like the analytic tier: at 40x25 with a wide lens the 2x2
    sub-pixel average differs from the centre value by up to ~2e-4 (curvature, not error).
    """
    require_mitsuba()
    _compare(small_scene(name, width=40, height=25), 1e-4, spp=1)


def test_maps_absorbing_slab():
    """Bulk absorption exp(-alpha L) per internal segment: slab law with internal transmittance a."""
    require_mitsuba()
    _compare(small_scene("brewster", width=40, height=25, absorption_per_mm=0.05, thickness_mm=6.0), 1e-4, spp=1)


def test_maps_spectral_is_band_weighted_sum():
    """Dispersive BK7 with --spectral: maps equal the response-weighted sum of per-band analytic maps."""
    require_mitsuba()

    from generator import tiers_mitsuba as tm
    from generator.analytic import analytic_maps
    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import incidence_geometry

    sc = small_scene("bk7_single", width=40, height=25)
    info: dict = {}
    m = tm.render_pane_maps(sc, _opts(spp=1, spectral=True), info, n_bands=4)
    wl, w = tm.spectral_bands(4)
    assert np.isclose(w.sum(), 1.0) and np.all(w > 0)
    theta = incidence_geometry(sc.camera_model(), sc.pane_plane())["theta"]
    ref = {k: sum(wb * pane_coefficients(theta, sc.pane.index(lb), "single")[k] for lb, wb in zip(wl, w)) for k in ("R_perp", "R_par")}
    for k in ref:
        assert np.abs(getattr(m, k) - ref[k]).max() < 1e-4
    # dispersion matters at this level: the mono 550 nm map differs measurably
    mono = analytic_maps(sc)
    assert np.abs(mono.R_perp - m.R_perp).max() > 1e-5
    assert "bands" in str(info["modelled"]["spectral"])


def test_mitsuba_fresnel_matches_polspike_fresnel():
    """mi.fresnel_polarized vs polphysics.fresnel over a grid of angles and indices (incl. TIR, n < 1).

    Transmittance from Mitsuba's amplitudes, not from 1 - R: boundary continuity gives t_s = 1 + r_s and
    n t_p = 1 + r_p, and the transmitted flux is (n cos_t / cos_i) |t|^2 with Mitsuba's own cos_t; those
    amplitudes must balance the energy, |r|^2 + (n cos_t / cos_i) |t|^2 = 1, and equal polphysics' T.
    """
    mi = require_mitsuba()
    from polphysics.fresnel import fresnel_power

    th = np.linspace(0.0, np.pi / 2 - 1e-3, 181)
    cos_i = np.cos(th)
    for n in (1.33, 1.5, 1.9, 1 / 1.5):
        a_s, a_p, cos_t, _, _ = mi.fresnel_polarized(mi.Float(cos_i.astype(np.float32)), mi.Complex2f(n, 0.0))
        r_s, r_p = (np.asarray(a.real, np.float64) + 1j * np.asarray(a.imag, np.float64) for a in (a_s, a_p))
        k = n * np.abs(np.asarray(cos_t, np.float64)) / cos_i  # flux ratio; 0 under total internal reflection
        tir = np.sin(th) > n
        k[tir] = 0.0
        T_s, T_p = k * np.abs(1 + r_s) ** 2, k * np.abs((1 + r_p) / n) ** 2
        for r, t in ((r_s, T_s), (r_p, T_p)):
            np.testing.assert_allclose(np.abs(r) ** 2 + t, 1.0, atol=5e-5, err_msg=f"n={n}: Mitsuba's amplitudes")
        Rs, Rp, Ts, Tp = fresnel_power(th, n)
        assert np.abs(np.abs(r_s) ** 2 - Rs).max() < 2e-5, n
        assert np.abs(np.abs(r_p) ** 2 - Rp).max() < 2e-5, n
        assert np.abs(T_s - Ts).max() < 5e-5 and np.abs(T_p - Tp).max() < 5e-5, n


def test_maps_scalar_backend_is_clear_error():
    """The maps tracer needs a JIT variant: forcing scalar is a one-line BackendUnavailableError."""
    require_mitsuba()
    from generator import tiers_mitsuba as tm
    from polinfra.errors import BackendUnavailableError

    with pytest.raises(BackendUnavailableError, match="JIT"):
        tm.render_pane_maps(small_scene(width=8, height=5), _opts(variant="scalar"), {})
