"""Spectral integration of the Mitsuba tiers: sensor response and band quadrature."""

from __future__ import annotations

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene, uniform_layers

from polinfra.errors import ConfigError


def test_sensor_response_cie_y_flat_and_csv(tmp_path):
    """CIE Y peaks at 555 nm (value 1.0); flat is 1; a user CSV is interpolated, 0 outside its range."""
    pytest.importorskip("colour")
    from generator.tiers_mitsuba import sensor_response, spectral_bands

    wl = np.array([450.0, 555.0, 650.0])
    y = sensor_response("cie_y", wl)
    assert np.isclose(y[1], 1.0, atol=1e-3) and y[0] < 0.1 and y[2] < 0.2
    assert np.all(sensor_response("flat", wl) == 1.0)
    csv = tmp_path / "qe.csv"
    csv.write_text("wavelength_nm,response\n500,0.5\n600,1.0\n")
    r = sensor_response(str(csv), np.array([450.0, 550.0, 600.0, 700.0]))
    assert np.allclose(r, [0.0, 0.75, 1.0, 0.0])
    c, w = spectral_bands(6, "flat")
    assert np.allclose(w, 1 / 6) and np.allclose(c, 425 + 50 * np.arange(6))
    with pytest.raises(ConfigError, match="neither"):
        sensor_response("silicon_nonexistent.csv", wl)


@pytest.mark.mitsuba
def test_full_tier_spectral_bands_match_weighted_analytic():
    """Dispersive BK7 slab with --spectral: the path-traced image matches the response-weighted
    sum of per-band analytic Stokes images (uniform layers; mean within MC error).
    """
    require_mitsuba()
    from generator import tiers_mitsuba as tm
    from generator.analytic import frame_stokes
    from generator.render import RenderOptions
    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import incidence_geometry

    sc = uniform_layers(small_scene("bk7_single", width=40, height=25, model="thin_slab", thickness_mm=4.0), 0.5, 1.0)
    info: dict = {}
    fr = tm.FullRenderer(sc, RenderOptions(tier="full", spp=64, spectral=True, seed=5), info, n_bands=4)
    assert len(fr.idx) == 4 and fr.idx[0] > fr.idx[-1]  # normal dispersion: n falls with wavelength
    S = fr.stokes(0.0)
    geo = incidence_geometry(sc.camera_model(), sc.pane_plane())
    ref = 0.0
    for n_b, w_b in zip(fr.idx, fr.wts):
        co = pane_coefficients(geo["theta"], n_b, "thin_slab")
        ones = np.ones_like(geo["theta"])

        class M:  # minimal PaneMaps stand-in for frame_stokes
            R_perp, R_par, T_perp, T_par, phi_perp = co["R_perp"], co["R_par"], co["T_perp"], co["T_par"], geo["phi_perp"]
            G_perp = G_par = None

        ref = ref + w_b * frame_stokes(M, 0.5 * ones, 1.0 * ones)
    e = (S - ref).reshape(3, -1)
    se = e.std(axis=1) / np.sqrt(e.shape[1])
    assert np.all(np.abs(e.mean(axis=1)) < 4 * se + 1e-3), (e.mean(axis=1), se)
    assert "4 bands" in info["modelled"]["spectral"]
