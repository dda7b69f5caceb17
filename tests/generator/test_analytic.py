"""Analytic tier output: maps, frames, conventions, resumability."""

from __future__ import annotations

import json

import numpy as np

from generator.render import render
from polinfra.exr import read_exr
from polphysics.stokes import polarizer_intensity
from polphysics.zeta import mix_eq1, zeta
from spike_sim.renderdir import open_render


def test_render_writes_format_and_eq1_holds(tiny_scene, tmp_path):
    meta = render(tiny_scene, tmp_path / "r")
    assert meta["complete"] and meta["tier"] == "analytic" and len(meta["frames"]) == 3
    rd = open_render(tmp_path / "r")
    m = rd.maps()
    assert set(m) == {"theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par"}
    S = rd.stokes(1).astype(np.float64)
    T, R = rd.layers(1)
    for phi in np.linspace(0, np.pi, 7):
        z = zeta(phi, m["R_perp"], m["R_par"], m["phi_perp"])
        np.testing.assert_allclose(polarizer_intensity(*S, phi), mix_eq1(R, T, z), atol=2e-6)
    for f in meta["frames"]:
        for v in read_exr(tmp_path / "r" / f).values():
            assert np.all(np.isfinite(v))


def test_render_is_resumable_and_deterministic(tiny_scene, tmp_path):
    out = tmp_path / "r"
    render(tiny_scene, out)
    first = (out / "frames/000002.exr").read_bytes()
    (out / "frames/000002.exr").unlink()
    meta = render(tiny_scene, out)
    assert meta["complete"]
    assert (out / "frames/000002.exr").read_bytes() == first
    assert json.loads((out / "render.json").read_text())["scene_hash"] == meta["scene_hash"]


def test_motion_changes_layers_over_time(tiny_scene, tmp_path):
    render(tiny_scene, tmp_path / "r")
    rd = open_render(tmp_path / "r")
    assert not np.allclose(rd.layers(0)[1], rd.layers(2)[1])  # the sprite moves


def test_zero_and_saturated_light_stay_finite(tiny_scene, tmp_path):
    import dataclasses

    layers = tiny_scene.layers
    dark = dataclasses.replace(layers, transmission=dataclasses.replace(layers.transmission, brightness=0.0),
                               reflection=dataclasses.replace(layers.reflection, brightness=0.0, sprites=()))
    meta = render(dataclasses.replace(tiny_scene, layers=dark), tmp_path / "d")
    S = open_render(tmp_path / "d").stokes(0)
    assert np.all(S == 0)
    sat = dataclasses.replace(layers, transmission=dataclasses.replace(layers.transmission, brightness=1.0, offset=1.0),
                              reflection=dataclasses.replace(layers.reflection, brightness=1.0, offset=1.0))
    render(dataclasses.replace(tiny_scene, layers=sat), tmp_path / "s")
    S = open_render(tmp_path / "s").stokes(0)
    # unit radiance on both sides of a lossless pane: S0 = (R + T) = 1 per polarization
    np.testing.assert_allclose(S[0], 1.0, atol=1e-6)
    assert meta["complete"]
