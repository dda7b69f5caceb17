"""The planner's sampling term: the analytic tier's point sample against the path tracer's pixel (box
filter over nearest texels, clipped layers), checked against a step edge's covered fraction, against
scenes where it must vanish, and against a path-traced render.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene, uniform_layers

from polinfra.config import to_dict


def test_box_mean_of_a_step_edge_is_the_covered_fraction():
    """Texels 0-1 hold 0, texels 2-3 hold 1; a one-texel footprint centred at texel coordinate c covers
    [c - 0.5, c + 0.5]: its mean is the part of it right of 2 (closed form), 0 off the plane.
    """
    from generator.planner_footprint import _box_mean

    tex = np.zeros((4, 4))
    tex[:, 2:] = 1.0
    rows = np.arange(3) + 0.5
    for c, expect in ((1.25, 0.0), (2.25, 0.75), (1.9, 0.4), (3.25, 1.0), (5.5, 0.0)):
        xs = (c + np.arange(-2, 3)) / 4.0 - 0.5  # view coordinates (extent 1, 4 texels) of rays one texel apart, the middle one at c
        Xr, Yr = np.meshgrid(xs, rows / 4.0 - 0.5)
        assert _box_mean(tex, 1.0, Xr, Yr)[1, 2] == pytest.approx(expect, abs=1e-12), c


def test_sampling_term_vanishes_where_each_footprint_is_one_texel():
    """Near-normal view through a thin slab: each pixel maps onto one texel (texels at the pixel pitch),
    so the point sample is the box mean; uniform layers behind a tilted thick slab: any mean of a
    constant is that constant (left: the Fresnel coefficients' variation inside a pixel, ~1e-6).
    """
    from generator.planner_footprint import sampling_term

    assert sampling_term(small_scene("near_normal", 80, 50)) < 1e-3
    assert sampling_term(uniform_layers(small_scene("brewster", 80, 50, model="thick_slab", thickness_mm=9.0))) < 1e-4


def _sprite_slab_scene(width: int = 80, height: int = 50):
    """A textured T with a hard-edged sprite behind a thick slab at 54 deg (sub-texel shift of T and the ghost)."""
    from generator.scene import scene_from_dict

    d = to_dict(small_scene("brewster", width, height, model="thick_slab", n=1.7465, tilt_deg=53.7, tilt_axis_deg=52.1,
                            thickness_mm=8.94, distance_m=0.772, size_m=[3.0, 3.0]))
    d["camera"].update(fov_deg=36.0)
    d["layers"]["transmission"] = {"source": "skimage:moon", "brightness": 0.8, "distance_m": 3.5,
                                   "sprites": [{"source": "skimage:coins", "size": 0.3, "start": [0.6, 0.45], "brightness": 1.0}]}
    d["layers"]["reflection"] = {"source": "procedural:stripes", "brightness": 1.0, "distance_m": 2.1}
    return scene_from_dict(d)


def test_sampling_term_predicts_the_path_tracers_difference():
    """The analytic image against a 512 spp path-traced one (two seeds; their noise taken out in
    quadrature) differs by what the sampling term predicts, within a factor of 2.
    """
    require_mitsuba()
    from generator.planner import _worst, scene_features
    from generator.render import RenderOptions
    from generator.tiers_mitsuba import FullRenderer
    from polspike.pipeline.tradeoff import Candidate, _render_first

    sc = _sprite_slab_scene()
    f = scene_features(sc)
    S_a, _, _ = _render_first(sc, Candidate("a", "analytic", None))
    S = [np.asarray(FullRenderer(sc, RenderOptions(tier="full", spp=512, variant="llvm", seed=s), {"modelled": {}}).stokes(0.0, 0)) for s in (1, 2)]
    noise = float(np.percentile(_worst(S[0], S[1]), 99)) / 2.0  # p99 of the two seeds' mean's noise
    err = float(np.percentile(_worst(S_a, 0.5 * (S[0] + S[1])), 99))
    measured = math.sqrt(max(err * err - noise * noise, 0.0))
    assert f["sampling_p99"] > 2 * noise, (f["sampling_p99"], noise)  # the case resolves the effect
    assert 0.5 <= f["sampling_p99"] / measured <= 2.0, (f["sampling_p99"], measured, noise)


def _steep_single_scene(width: int = 40, height: int = 25):
    """A single interface tilted 58.5 deg whose R layer plane crosses the pane inside the view."""
    from generator.scene import scene_from_dict

    d = to_dict(small_scene("brewster", width, height, model="single", n=1.7183, tilt_deg=58.533, tilt_axis_deg=85.057,
                            distance_m=1.147, size_m=[19.5, 8.8]))
    d["camera"].update(fov_deg=53.822, look_at=[-0.13884, -0.10998, -0.98419], roll_deg=-0.091)
    d["layers"]["transmission"] = {"source": "procedural:noise", "seed": 44240, "brightness": 0.871, "distance_m": 3.042}
    d["layers"]["reflection"] = {"source": "procedural:stripes", "brightness": 0.351, "distance_m": 1.827}
    return scene_from_dict(d)


def test_r_plane_in_front_of_the_pane_is_seen_directly_by_the_path_tracer():
    """Where the R layer's plane stands between the camera and a steep pane, the path tracer's pixel is R itself
    (unpolarized: S1 = S2 = 0), not the pane's mixture; the emulated image matches a 256 spp render to its noise
    there, and the analytic image does not.
    """
    require_mitsuba()
    from generator.analytic import layer_planes
    from generator.layers import LayerContent
    from generator.planner import _worst
    from generator.planner_footprint import _r_plane_in_front, footprint_stokes
    from generator.render import RenderOptions
    from generator.tiers_mitsuba import FullRenderer, _texture

    sc = _steep_single_scene()
    _, r_plane = layer_planes(sc)
    rc = LayerContent(sc.layers.reflection, (sc.camera.height, sc.camera.width))
    occ, _ = _r_plane_in_front(sc, r_plane, _texture(rc, 0.0), rc.extent)
    assert 0.05 < occ.mean() < 0.5  # a strip of the view
    from scipy.ndimage import binary_erosion

    occ = binary_erosion(occ, border_value=1)  # pixels wholly in the strip (their edge pixels mix both)
    S_a, S_box = footprint_stokes(sc)
    assert np.all(S_box[1:, occ] == 0.0)
    S = [np.asarray(FullRenderer(sc, RenderOptions(tier="full", spp=256, variant="llvm", seed=s), {"modelled": {}}).stokes(0.0, 0)) for s in (1, 2)]
    S_f = 0.5 * (S[0] + S[1])
    noise = float(np.percentile(_worst(S[0], S[1])[occ], 99)) / 2.0
    assert float(np.percentile(_worst(S_box, S_f)[occ], 99)) < 2.5 * noise + 0.01
    assert float(np.percentile(_worst(S_a, S_f)[occ], 99)) > 4 * noise + 0.05


@pytest.mark.parametrize("scale", [1.0, 1.13, 1.37, 2.05])
def test_enlarged_t_texture_keeps_the_contents_own_texels(scale):
    """The enlarged T plane of a single interface is the content's texture padded by whole texels: its middle
    block is the content's own frame texel for texel (no re-gridding), its padding mirrors the frame about the
    edge texel (as the analytic tier's mirrored sampling), and it covers at least ``scale`` of the plane.
    """
    from generator.layers import LayerContent
    from generator.scene import load_scene
    from generator.tiers_mitsuba import _texture, texture_grid

    sc = load_scene("bk7_single")
    tc = LayerContent(sc.layers.transmission, (25, 40))
    frame = np.clip(tc.cfg.offset + tc.cfg.brightness * tc.frames[0], 0.0, 1.0)
    th, tw = tc.tex_shape
    (Th, Tw), (sx, sy) = texture_grid(tc, scale)
    tex = _texture(tc, 0.0, scale)
    assert tex.shape == (Th, Tw) and min(sx, sy) >= scale - 1e-12
    assert (Th - th) % 2 == 0 and (Tw - tw) % 2 == 0 and sx == Tw / tw and sy == Th / th
    ph, pw = (Th - th) // 2, (Tw - tw) // 2
    np.testing.assert_allclose(tex[ph:ph + th, pw:pw + tw], frame, atol=1e-12)
    if pw:
        np.testing.assert_allclose(tex[ph:ph + th, pw - 1], frame[:, 1], atol=1e-12)  # mirrored about texel 0
