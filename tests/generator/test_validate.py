"""validate-zeta: the instrument passes a consistent model and catches a wrong one."""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.analytic import analytic_maps
from generator.validate import fit_reflection, fit_transmission, validate_zeta
from polphysics.zeta import stokes_from_layers


def test_probe_fit_inverts_stokes_form(np_rng):
    """Closed form: the unit-probe Stokes image of known coefficients fits back to them."""
    rs, rp = np_rng.uniform(0.05, 0.6, 50), np_rng.uniform(0.0, 0.05, 50)
    pp = np_rng.uniform(0, np.pi, 50)
    S = stokes_from_layers(0.0, 1.0, rs, rp, 1 - rs, 1 - rp, pp)
    a, b, c = fit_reflection(S)
    np.testing.assert_allclose(a, rs, atol=1e-12)
    np.testing.assert_allclose(b, rp, atol=1e-12)
    np.testing.assert_allclose(np.mod(c - pp + np.pi / 2, np.pi) - np.pi / 2, 0.0, atol=1e-9)
    St = stokes_from_layers(1.0, 0.0, rs, rp, 1 - rs, 1 - rp, pp)
    tp, tl = fit_transmission(St, pp)
    np.testing.assert_allclose(tp, 1 - rs, atol=1e-12)
    np.testing.assert_allclose(tl, 1 - rp, atol=1e-12)


def test_consistent_model_passes(tiny_scene, tmp_path):
    s = validate_zeta(tiny_scene, tmp_path / "v")
    assert s["verdict"] == "pass"
    assert s["errors"]["zeta_worst_over_phi"]["max"] < 1e-6  # float32 storage only
    assert (tmp_path / "v" / "figures" / "error_maps.png").is_file()
    assert json.loads((tmp_path / "v" / "summary.json").read_text())["verdict"] == "pass"


def test_wrong_model_fails(tiny_scene, tmp_path):
    """A thin_slab scene validated against the single-interface model must fail clearly."""
    assert tiny_scene.pane.model == "thin_slab"
    s = validate_zeta(tiny_scene, tmp_path / "v", model="single", tolerance=1e-3)
    assert s["verdict"] == "fail"
    # slab minus single = R1 (1 - R1) / (1 + R1): of the order of R itself
    m = analytic_maps(tiny_scene)
    assert s["errors"]["R_perp"]["max"] > 0.2 * float(m.R_perp.max())
