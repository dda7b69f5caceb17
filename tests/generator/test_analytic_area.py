"""The area-sampled analytic tier (``--supersample K``): convergence to a step edge's covered fraction, the
planner's choice of it where the point sample misses the tolerance, and its render / CLI plumbing.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from _mitsuba_common import small_scene

from polinfra.config import to_dict


def _step_scene(tmp_path, width: int = 24, height: int = 16):
    """A vertical step edge on T (0 left, 1 right; R black) behind a 12 mm slab tilted 45 deg about the image's
    vertical axis, seen through a 2 deg lens (the view is affine to 1e-4, no shear), with T's texels 1 / 0.6
    pixels wide: each pixel's footprint is 0.6 texel (as refraction shrinks it on bk7_single), so the pixels
    at the edge hold the covered fraction while a point sample reads a ramp one texel wide.
    """
    import imageio.v3 as iio

    from generator.layers import LayerContent
    from generator.scene import scene_from_dict

    d = to_dict(small_scene("brewster", width, height, model="thick_slab", n=1.5, tilt_deg=45.0, tilt_axis_deg=90.0, thickness_mm=12.0,
                            distance_m=1.0, size_m=[3.0, 3.0]))
    d["camera"].update(fov_deg=2.0)
    d["layers"]["reflection"] = {"source": "procedural:flat", "brightness": 0.0, "offset": 0.0, "distance_m": 2.0}
    d["layers"]["transmission"] = {"source": "procedural:flat", "distance_m": 4.0, "texture_scale": 0.6}
    th, tw = LayerContent(scene_from_dict(d).layers.transmission, (height, width)).tex_shape
    img = np.zeros((th, tw), np.uint8)
    img[:, tw // 2 + 2:] = 255  # the edge right of the centre (the slab shifts it onto the view; covered fraction 0.16)
    iio.imwrite(tmp_path / "step.png", img)
    d["layers"]["transmission"] = {"source": f"image:{tmp_path / 'step.png'}", "distance_m": 4.0, "texture_scale": 0.6}
    return scene_from_dict(d)


def _covered_fraction(sc) -> np.ndarray:
    """Exact mean of the step over each pixel: the part of the pixel's span in texel columns right of the edge
    (the texel coordinate is affine along the pixel row; taken at the pixel's left and right edges).
    """
    from generator.analytic import analytic_maps
    from generator.layers import LayerContent
    from generator.planner_footprint import _texel_coords
    from generator.tiers_mitsuba import _texture

    tc = LayerContent(sc.layers.transmission, (sc.camera.height, sc.camera.width))
    tex = _texture(tc, 0.0)
    assert np.allclose(tex, np.round(tex), atol=1e-9) and np.allclose(tex, tex[:1], atol=1e-9)  # a hard 0 / 1 step, the same on every row
    edge = int(np.argmax(tex[0] > 0.5))
    cl = _texel_coords(tex.shape, tc.extent, *analytic_maps(sc, subpixel=(0.0, 0.5)).t_xy)[0]
    cr = _texel_coords(tex.shape, tc.extent, *analytic_maps(sc, subpixel=(1.0, 0.5)).t_xy)[0]
    lo, hi = np.minimum(cl, cr), np.maximum(cl, cr)
    return np.clip((hi - edge) / (hi - lo), 0.0, 1.0)


def test_area_sampling_converges_to_a_step_edges_covered_fraction(tmp_path):
    """K x K stratified point samples (the oracle estimator) approach the exact covered fraction within
    1 / (2K) (a step crossing a row of K cells), falling with K; the tier's per-ray box means are exact for
    this affine view already at one ray per pixel; the point sample is not.
    """
    from generator.analytic import analytic_maps, sample_layers
    from generator.analytic_area import area_frames
    from generator.layers import LayerContent

    sc = _step_scene(tmp_path)
    exact = _covered_fraction(sc)
    straddle = (exact > 0.1) & (exact < 0.9)
    assert straddle.sum() >= sc.camera.height  # a column of pixels sits on the edge, part of each on either side
    errs = {}
    for K in (2, 4, 16):
        L_T = area_frames(sc, [0.0], K, prefilter=False)[0][1]
        errs[K] = float(np.max(np.abs(L_T - exact)))
        assert errs[K] <= 0.5 / K + 1e-3, (K, errs[K])
    assert errs[2] > errs[4] > errs[16] and errs[16] < 0.035, errs
    for K in (1, 2):
        L_T = area_frames(sc, [0.0], K)[0][1]
        assert float(np.max(np.abs(L_T - exact))) < 2e-3, K
    hw = (sc.camera.height, sc.camera.width)
    L_point = sample_layers(analytic_maps(sc), LayerContent(sc.layers.transmission, hw), LayerContent(sc.layers.reflection, hw), 0.0)[0]
    assert float(np.max(np.abs(L_point - exact)[straddle])) > 0.1


def _scene(name: str, width: int, height: int):
    from generator.scene import load_scene

    s = load_scene(name)
    return dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=width, height=height))


def test_bk7_single_at_1e_3_picks_the_area_sampled_tier():
    """bk7_single (200 x 125): the point-sampled analytic tiers miss 1e-3 by their sampling term (refraction
    shrinks the T footprint below a texel), the full tier by its noise; the pick is the analytic tier on the
    pixel's area, predicted to meet it, cheaper than the full tier at any spp the planner offers.
    """
    from generator.planner import plan_tier

    p = plan_tier(_scene("bk7_single", 200, 125), 1e-3)
    c = p.choice
    assert c.tier == "analytic" and c.supersample >= 1 and c.predicted_p99 <= 1e-3, c
    assert all(e.predicted_p99 > 1e-3 for e in p.estimates if e.tier in ("analytic", "maps") and not e.supersample)
    assert all(e.predicted_p99 > 1e-3 for e in p.estimates if e.tier == "full")
    steps = {e.supersample: e.predicted_p99 for e in p.estimates if e.tier == "analytic" and e.spectral and e.supersample}
    assert steps[1] > steps[2] > steps[4]  # the area term falls with K
    assert p.features["area_step_p99"] < p.features["sampling_p99"] / 4  # the area tier is an order closer than the point sample


def test_supersampled_render_is_the_area_frame_and_resumes_only_with_it(tmp_path):
    from generator.analytic_area import area_frames
    from generator.render import RenderOptions, render
    from polinfra.errors import OutputError
    from polinfra.exr import read_exr

    sc = small_scene("bk7_single", 40, 25)
    meta = render(sc, tmp_path / "a", RenderOptions(tier="analytic", supersample=2, duration_s=0.01))
    assert meta["resume_key"]["supersample"] == 2 and "2x2" in meta["modelled"]["supersample"]
    f = read_exr(tmp_path / "a" / "frames" / "000001.exr")
    S, L_T, _ = area_frames(sc, [0.01], 2)[0]
    np.testing.assert_allclose(f["S0"], S[0], atol=1e-6)
    np.testing.assert_allclose(f["T"], L_T, atol=1e-6)
    with pytest.raises(OutputError, match="supersample"):
        render(sc, tmp_path / "a", RenderOptions(tier="analytic", supersample=4, duration_s=0.01))
    assert "supersample" not in json.dumps(to_dict(sc))  # the default leaves scene hashes as they were


def test_supersample_on_another_tier_is_one_line_exit_2(polspike_main, tmp_path):
    r = polspike_main("render", "near_normal", "--out", tmp_path / "a", "--tier", "full", "--supersample", "2", "--quiet")
    polspike_main.one_line_exit_2(r, "--supersample is for the analytic tier")
    assert not (tmp_path / "a").exists()
    r = polspike_main("render", "near_normal", "--out", tmp_path / "a", "--supersample", "65", "--quiet")
    polspike_main.one_line_exit_2(r, "--supersample 65")
    r = polspike_main("render", "near_normal", "--out", tmp_path / "a", "--tier", "auto", "--tolerance", "1e-2", "--supersample", "2", "--quiet")
    polspike_main.one_line_exit_2(r, "--supersample is chosen by --tier auto")
    assert not (tmp_path / "a").exists()


def test_cli_unreachable_tolerance_names_the_area_tier(polspike_cli, tmp_path):
    """bk7_single at 80 x 50: no tier reaches 1e-7; the line names the best, the spectral area-sampled tier at
    the largest K offered.
    """
    from generator.scene import SCENES_DIR

    assert not (tmp_path / "a").exists()
    text = (SCENES_DIR / "bk7_single.toml").read_text().replace("width = 400", "width = 80").replace("height = 250", "height = 50")
    (tmp_path / "bk7.toml").write_text(text)
    r = polspike_cli("render", tmp_path / "bk7.toml", "--out", tmp_path / "b", "--tier", "auto", "--tolerance", "1e-7", "--quiet")
    line = polspike_cli.one_line_exit_2(r, "cannot be reached", "best reachable p99 error is", "--supersample 4")
    best = float(line.split("best reachable p99 error is ")[1].split()[0])
    assert 1e-7 < best < 1e-3
    assert not (tmp_path / "b").exists()


def test_manifest_auto_group_gets_the_area_tier_and_the_builder_renders_it():
    """bk7_single at 80 x 50, tolerance 1e-3: the group resolves to the analytic tier with render.supersample
    set (mono: the dataset builder's analytic source is mono), and the builder's keyframes are the area frames.
    """
    from generator.analytic_area import area_frames
    from generator.scene import scene_from_dict
    from polspike.pipeline.dataset import _AnalyticSource
    from polspike.pipeline.manifest import parse_manifest

    data = {"format": "polspike-manifest/1", "name": "m", "defaults": {"duration_s": 0.05, "camera": {"width": 80, "height": 50}},
            "groups": [{"name": "a", "split": "test", "scene": "bk7_single", "tier": "auto", "tolerance": 1e-3}]}
    g = parse_manifest(data).groups[0]
    K = g.scene["render"].get("supersample", 0)
    assert g.tier == "analytic" and K >= 1 and not g.tier_plan["choice"]["spectral"] and g.tier_plan["choice"]["supersample"] == K
    sc = scene_from_dict(g.scene)
    S, L_T, _ = _AnalyticSource(sc).frame(1, 0.01)
    S_a, L_a, _ = area_frames(sc, [0.01], K)[0]
    np.testing.assert_allclose(S, S_a, atol=1e-6)
    np.testing.assert_allclose(L_T, L_a, atol=1e-6)
