"""Scene schema: defaults load, bad values are rejected with one-line messages naming the key."""

from __future__ import annotations

import numpy as np
import pytest

from generator.scene import check_scene_geometry, default_scenes, load_scene, scene_from_dict
from polinfra.errors import ConfigError, SceneError


def test_default_scenes_cover_distinct_geometries():
    from generator.analytic import analytic_maps

    names = default_scenes()
    assert {"near_normal", "brewster", "oblique_diagonal"} <= set(names)
    centre = {}
    spread = {}
    for n in names:
        s = load_scene(n)
        check_scene_geometry(s)
        m = analytic_maps(s)
        centre[n] = np.rad2deg(m.theta[s.camera.height // 2, s.camera.width // 2])
        pp = m.phi_perp
        spread[n] = np.rad2deg(np.ptp(np.mod(pp - pp[s.camera.height // 2, s.camera.width // 2] + np.pi / 2, np.pi)))
    assert centre["near_normal"] < 10
    assert 50 < centre["brewster"] < 62
    assert centre["oblique_diagonal"] > 40 and spread["oblique_diagonal"] > 30


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"pane": {"n": 0.0}}, "pane.n = 0.0 is out of range"),
        ({"pane": {"n": -1.5}}, "pane.n"),
        ({"pane": {"colour": 1}}, "unknown key pane.colour"),
        ({"camera": {"fov_deg": 200}}, "camera.fov_deg = 200.0 is out of range"),
        ({"camera": {"width": "wide"}}, "camera.width"),
        ({"pane": {"model": "triple"}}, "choose one of"),
        ({"pane": {"glass": "unobtainium"}}, "unknown"),
        ({"pane": {"model": "thin_slab", "n": 0.7}}, "slabs need n >= 1"),
        ({"render": {"duration_s": 0}}, "render.duration_s"),
        ({"layers": {"transmission": {"brightness": -0.1}}}, "brightness"),
        ({"polarizer": {"rate_hz": -3}}, "polarizer.rate_hz"),
        ({"camera": {"position": [0, 0]}}, "must have 3 elements"),
    ],
)
def test_bad_values_rejected_with_one_line(data, fragment):
    with pytest.raises(ConfigError) as ei:
        scene_from_dict(data, where="bad.toml")
    msg = str(ei.value)
    assert fragment in msg and "\n" not in msg


def test_malformed_toml(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[camera\nwidth = 3\n")
    with pytest.raises(ConfigError, match="malformed TOML"):
        load_scene(p)


def test_pane_not_covering_view_is_a_scene_error():
    s = scene_from_dict({"pane": {"size_m": [0.2, 0.2]}})
    with pytest.raises(SceneError, match="does not cover the view"):
        check_scene_geometry(s)


@pytest.mark.parametrize("bad", [float("inf"), float("nan"), -float("inf")])
def test_non_finite_numbers_rejected(bad):
    with pytest.raises(ConfigError, match="camera.position"):
        scene_from_dict({"camera": {"position": [0.0, bad, 0.0]}})
