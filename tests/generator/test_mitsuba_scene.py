"""Scene translation to Mitsuba (generator/mitsuba_scene.py): camera, pane models, slab depolarization pin."""

from __future__ import annotations

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene

from polinfra.errors import SceneError

pytestmark = pytest.mark.mitsuba


def test_camera_rays_match_pinhole_model():
    """Mitsuba's perspective sensor rays equal polphysics.geometry's pixel rays (roll included)."""
    mi = require_mitsuba()
    from generator.mitsuba_scene import build_scene_dict, specs_from_scene
    from generator.scene import scene_from_dict
    from polinfra.config import to_dict

    for roll in (0.0, 17.0):
        d = to_dict(small_scene("oblique_diagonal"))
        d["camera"]["roll_deg"] = roll
        sc = scene_from_dict(d)
        cam, pane = specs_from_scene(sc)
        msc = mi.load_dict(build_scene_dict(mi, cam, pane, []))
        W, H = cam.width, cam.height
        yy, xx = np.mgrid[0:H, 0:W]
        ray, _ = msc.sensors()[0].sample_ray(0.0, 0.5, mi.Point2f(mi.Float(((xx.ravel() + 0.5) / W).astype(np.float32)), mi.Float(((yy.ravel() + 0.5) / H).astype(np.float32))), mi.Point2f(0.5, 0.5))
        d_mi = np.asarray(ray.d, dtype=np.float64).T.reshape(H, W, 3)
        d_ref = sc.camera_model().ray_directions()
        assert np.abs(d_mi - d_ref).max() < 2e-6, roll


def test_pane_interfaces_models():
    """single: one interface facing the camera; slabs: two faces thickness apart, normals out of the glass."""
    from generator.mitsuba_scene import PaneSpec, pane_interfaces

    n = np.array([0.0, 0.0, 1.0])
    one = pane_interfaces(PaneSpec("single", 1.5, (0, 0, -1), tuple(n), (2, 2)))
    assert len(one) == 1 and np.allclose(one[0][1], n)
    two = pane_interfaces(PaneSpec("thin_slab", 1.5, (0, 0, -1), tuple(n), (2, 2), thickness_m=0.004))
    assert len(two) == 2
    (m0, n0), (m1, n1) = two
    assert np.allclose(n0, n) and np.allclose(n1, -n)
    assert np.isclose(m0[2, 3] - m1[2, 3], 0.004)
    # Mitsuba's rectangle normal is cross(col0, col1): must match the stated normal
    for m, nn in two:
        c = np.cross(m[:3, 0], m[:3, 1])
        assert np.allclose(c / np.linalg.norm(c), nn)


@pytest.mark.parametrize("bad", [0.9, float("nan"), 7.0])
def test_non_physical_index_is_scene_error(bad):
    from generator.mitsuba_scene import PaneSpec, pane_interfaces

    with pytest.raises(SceneError, match="refractive index"):
        pane_interfaces(PaneSpec("thin_slab", bad, (0, 0, -1), (0, 0, 1), (2, 2), thickness_m=0.004))


def test_thindielectric_depolarizes_so_slabs_use_two_interfaces():
    """Measurement pin: Mitsuba's thindielectric returns UNPOLARIZED reflection (DoP 0),
    while two real dielectric interfaces give the polarized incoherent slab 2R/(1+R)
    (so thin_slab / thick_slab are modelled with two interfaces).
    """
    mi = require_mitsuba()
    from generator.mitsuba_integrator import pane_coefficients
    from generator.mitsuba_scene import build_scene_dict, specs_from_scene
    from polphysics.fresnel import pane_coefficients as ref

    sc = small_scene("brewster", width=40, height=25)
    cam, pane = specs_from_scene(sc)
    d = build_scene_dict(mi, cam, pane, [])
    slab = pane_coefficients(mi, mi.load_dict(d), pane.axes()[2], cam.up, cam.width, cam.height, model="thin_slab", n=1.5, sub=1)
    # same geometry, one thindielectric rectangle instead
    d_thin = {k: v for k, v in d.items() if not k.startswith("pane_")}
    d_thin["pane_0"] = dict(d["pane_0"], bsdf={"type": "thindielectric", "int_ior": 1.5, "ext_ior": 1.0})
    thin = pane_coefficients(mi, mi.load_dict(d_thin), pane.axes()[2], cam.up, cam.width, cam.height, model="thin_slab", n=1.5, sub=1)
    dop = lambda S: np.hypot(S[1], S[2]) / S[0]  # noqa: E731
    assert dop(thin["S_R"]).max() < 1e-5  # depolarized
    assert dop(slab["S_R"]).min() > 0.4  # near Brewster the slab reflection is strongly polarized
    co = ref(_theta(sc), 1.5, "thin_slab")
    assert np.abs(slab["R_perp"] - co["R_perp"]).max() < 1e-4
    assert np.abs(slab["R_par"] - co["R_par"]).max() < 1e-4
    # thindielectric applies the slab law to the UNPOLARIZED single-interface R = (R_s + R_p)/2:
    # R_thin = 2R/(1+R), unpolarized.  That is neither the polarized slab's mean nor its zeta(phi).
    one = ref(_theta(sc), 1.5, "single")
    r_unpol = 0.5 * (one["R_perp"] + one["R_par"])
    assert np.abs(thin["S_R"][0] - 2 * r_unpol / (1 + r_unpol)).max() < 1e-4
    brightness_err = np.abs(thin["S_R"][0] - 0.5 * (co["R_perp"] + co["R_par"])).max()
    zeta_err = max(np.abs(thin["S_R"][0] - co["R_perp"]).max(), np.abs(thin["S_R"][0] - co["R_par"]).max())
    assert brightness_err > 0.01 and zeta_err > 0.1


def _theta(sc):
    from polphysics.geometry import incidence_geometry

    return incidence_geometry(sc.camera_model(), sc.pane_plane())["theta"]
