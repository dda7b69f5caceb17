"""A single interface bends the transmitted rays: the analytic tier samples the T layer where the
refracted ray lands (Snell, per pixel), checked against a 2-D closed form on the optical axis, against
Snell's law at every pixel, and against the path-traced full tier (Monte Carlo noise only).
"""

from __future__ import annotations

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene


def _maps(sc):
    from generator.analytic import analytic_maps

    return analytic_maps(sc)


def test_axis_pixel_lands_where_the_2d_closed_form_puts_it():
    """bk7_single with an odd pixel count: the centre pixel's ray runs along the optical axis, meets the
    pane (distance D) at theta_i = tilt, leaves it at theta_t = asin(sin theta_i / n) from the normal,
    i.e. turned by theta_i - theta_t from the axis in the plane of incidence (vertical: the pane is
    tilted about the horizontal axis), and reaches the T plane (distance L) (L - D) tan(theta_i - theta_t)
    off the axis; view fractions: X = 0, |Y| = that / (2 L tan(fov_x / 2) H / W).
    """
    sc = small_scene("bk7_single", 81, 51)
    assert sc.pane.tilt_axis_deg == 0.0
    m = _maps(sc)
    n = sc.pane.index(550.0)
    ti = np.deg2rad(sc.pane.tilt_deg)
    tt = np.arcsin(np.sin(ti) / n)
    D, L = sc.pane.distance_m, sc.layers.transmission.distance_m
    Y_expect = (L - D) * np.tan(ti - tt) / (2 * L * np.tan(0.5 * np.deg2rad(sc.camera.fov_deg)) * 51 / 81)
    X, Y = m.t_xy[0][25, 40], m.t_xy[1][25, 40]
    assert abs(abs(Y) - Y_expect) < 1e-9 and abs(X) < 1e-12, (X, Y, Y_expect)
    assert Y_expect > 0.1  # a visible shift: a tenth of the view
    # a slab keeps the straight (only laterally displaced) transmitted ray: its shift is far smaller
    slab = _maps(small_scene("bk7_single", 81, 51, model="thin_slab", thickness_mm=4.0))
    assert abs(slab.t_xy[1][25, 40]) < 0.01 * Y_expect


def test_every_pixel_obeys_snell_into_the_glass():
    """From each pixel's T sampling point back to its pane point: the ray makes theta_t with the pane
    normal, n sin(theta_t) = sin(theta_i), and lies in the plane of incidence (pane tilted about a diagonal).
    """
    from generator.analytic import layer_planes
    from polphysics.geometry import incidence_geometry

    sc = small_scene("oblique_diagonal", 48, 30, model="single")
    m = _maps(sc)
    t_plane, _ = layer_planes(sc)
    X, Y = m.t_xy
    P = t_plane.center + (2 * t_plane.view_half_w * X)[..., None] * t_plane.right - (2 * t_plane.view_half_h * Y)[..., None] * t_plane.up
    geo = incidence_geometry(sc.camera_model(), sc.pane_plane())
    nrm = np.asarray(sc.pane_plane().normal, float)
    nrm /= np.linalg.norm(nrm)
    v = P - geo["hit"]
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    cos_t = np.abs(v @ nrm)
    sin_t = np.sqrt(1 - cos_t**2)
    n = sc.pane.index(550.0)
    assert np.max(np.abs(n * sin_t - np.sin(geo["theta"]))) < 1e-9
    assert np.max(np.abs(np.sum(v * np.cross(geo["d"], nrm), axis=-1))) < 1e-9  # coplanar with d and the normal
    assert np.all(v @ (-nrm) > 0)  # continues into the glass, away from the camera side


def _analytic_s0(sc, straight: bool = False):
    from generator.analytic import frame_stokes, layer_planes, sample_layers
    from generator.layers import LayerContent

    H, W = sc.camera.height, sc.camera.width
    m = _maps(sc)
    if straight:  # paper Eq. (1)'s straight-ray view of T (the model before refraction): must be rejected
        t_plane, _ = layer_planes(sc)
        cam = sc.camera_model()
        d = cam.ray_directions((0.5, 0.5))
        m.t_xy = t_plane.uv(cam.position + np.zeros_like(d), d)
    return frame_stokes(m, *sample_layers(m, LayerContent(sc.layers.transmission, (H, W)), LayerContent(sc.layers.reflection, (H, W)), 0.0))[0]


def _full_pair(sc, spp):
    from generator import tiers_mitsuba as tm
    from generator.render import RenderOptions

    return [tm.FullRenderer(sc, RenderOptions(tier="full", spp=spp, spectral=False, seed=s), {}).stokes(0.0)[0] for s in (1, 2)]


def _p99(a):
    return float(np.percentile(np.abs(a), 99))


@pytest.mark.mitsuba
def test_analytic_matches_the_full_tier_on_bk7_single_within_its_noise():
    """Proxy of the 1024 spp goal at 80x50, 256 spp (about 2 s): p99 |analytic - full| S0 error is within
    1.6x the full tier's own Monte Carlo noise (p99 of seed 1 - seed 2, / sqrt 2), while the straight-ray
    model is several times the noise.
    """
    require_mitsuba()
    sc = small_scene("bk7_single", 80, 50)
    F1, F2 = _full_pair(sc, 256)
    noise = _p99(F1 - F2) / np.sqrt(2)
    err = _p99(_analytic_s0(sc) - F1)
    err_straight = _p99(_analytic_s0(sc, straight=True) - F1)
    assert err <= 1.6 * noise, (err, noise)
    assert err_straight > 3.0 * noise, (err_straight, noise)


@pytest.mark.slow
@pytest.mark.mitsuba
def test_bk7_single_160x100_at_1024spp_within_1_5x_noise():
    """Issue goal: bk7_single at 160x100, keyframe 0, analytic vs full (mono, 1024 spp) S0 p99 error
    <= 1.5x the full tier's Monte Carlo noise (two seeds).  Measured 0.0152 vs 0.0111 (1.37x); the
    straight-ray model was 0.196.
    """
    require_mitsuba()
    sc = small_scene("bk7_single", 160, 100)
    F1, F2 = _full_pair(sc, 1024)
    noise = _p99(F1 - F2) / np.sqrt(2)
    err = _p99(_analytic_s0(sc) - F1)
    assert err <= 1.5 * noise, (err, noise)
