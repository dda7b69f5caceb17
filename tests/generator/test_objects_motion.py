"""Moving 3-D objects and the ``objects3d`` sampler profile: shapes advance with their velocity and spin,
sides are checked along the whole clip, the sampler is a function of its seed and its manifests validate,
and a moving object changes the full tier's keyframes (mitsuba).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba

from polinfra.config import to_dict
from polinfra.errors import SceneError


def _street(**shape0):
    from generator.scene import load_scene, scene_from_dict

    d = to_dict(load_scene("glossy_street"))
    d["objects"]["shapes"][1].update(shape0)
    d["camera"].update(width=40, height=25)
    return scene_from_dict(d)


def test_shape_moves_with_its_velocity_and_spin():
    sc = _street(velocity_m_per_s=[0.5, 0.0, -0.2], spin_deg_per_s=[0.0, 90.0, 0.0])
    s0 = sc.objects.shapes[1]
    s1 = sc.objects.at(0.2).shapes[1]
    assert np.allclose(np.subtract(s1.center, s0.center), [0.1, 0.0, -0.04])
    assert np.allclose(np.subtract(s1.rotate_deg, s0.rotate_deg), [0.0, 18.0, 0.0])
    assert not sc.objects.is_static
    st = _street()
    assert st.objects.is_static and st.objects.at(1.0) is st.objects


def test_object_that_crosses_the_pane_during_the_clip_is_refused():
    from generator.objects3d import object_sides

    sc = _street(velocity_m_per_s=[0.0, 0.0, 0.5])  # the red sphere at z = -3.6 m stays behind for 0.05 s
    object_sides(sc)
    far = dataclasses.replace(sc, render=dataclasses.replace(sc.render, duration_s=10.0))  # ... not for 10 s
    with pytest.raises(SceneError, match=r"objects.shapes\[1\] .*t = [0-9.]+ s\) crosses the pane's plane"):
        object_sides(far)


def test_objects3d_sampler_is_seeded_and_validates():
    from polspike.pipeline.manifest import parse_manifest
    from polspike.pipeline.sampler_objects3d import objects3d_manifest

    a = objects3d_manifest(2, 7, width=60, height=40, duration_s=0.05, shipped=())
    b = objects3d_manifest(2, 7, width=60, height=40, duration_s=0.05, shipped=())
    c = objects3d_manifest(2, 8, width=60, height=40, duration_s=0.05, shipped=())
    assert a == b and a != c
    m = parse_manifest(a)
    from generator.objects3d import object_sides
    from generator.scene import scene_from_dict

    for g in m.groups:
        assert g.tier == "full"
        sc = scene_from_dict(g.scene)
        shapes, lights = object_sides(sc)
        assert "behind" in shapes and "front" in shapes and sorted(lights) == ["behind", "front"]
        assert not sc.objects.is_static


@pytest.mark.slow  # three path-traced renders per keyframe
def test_moving_object_changes_the_full_tier_keyframes():
    require_mitsuba()
    from generator.render import RenderOptions
    from generator.tiers_mitsuba import FullRenderer

    sc = _street(velocity_m_per_s=[4.0, 0.0, 0.0])  # the red sphere sweeps 0.2 m in 0.05 s
    sc = dataclasses.replace(sc, render=dataclasses.replace(sc.render, duration_s=0.05))
    fr = FullRenderer(sc, RenderOptions(tier="full", spp=8, seed=3, fps=20.0), {})
    assert not fr.static
    T0, _ = fr.layers(0.0)
    T1, _ = fr.layers(0.05)
    Th, _ = fr.layers(0.025)
    moved = np.abs(T1 - T0)
    assert np.percentile(moved, 99) > 0.1  # the sphere left pixels and entered others
    assert np.allclose(Th, 0.5 * (T0 + T1))  # between keyframes: linear interpolation of the ground truth
