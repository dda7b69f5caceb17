"""Render directories of the Mitsuba tiers: render.json contents, resumability, backend forcing and
fallback, ground truth shared with the analytic tier, every default scene, sensor response CSV.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba, small_scene
from typer.testing import CliRunner

from polinfra.errors import OutputError

pytestmark = pytest.mark.mitsuba


def _scene(name="brewster", width=16, height=10, duration_s=0.03, fps=100.0, **pane):
    import dataclasses

    sc = small_scene(name, width=width, height=height, **pane)
    return dataclasses.replace(sc, render=dataclasses.replace(sc.render, duration_s=duration_s, fps=fps))


def _opts(tier, **kw):
    from generator.render import RenderOptions

    return RenderOptions(tier=tier, **{"spp": 2, "spectral": False, **kw})


def _frame_bytes(out):
    return {p.name: p.read_bytes() for p in sorted((out / "frames").glob("*.exr"))}


@pytest.mark.parametrize("tier", ["maps", "full"])
def test_render_json_records_variant_spp_seed_timings_and_modelled(tmp_path, tier):
    """render.json of a Mitsuba tier: format fields, variant, spp, seed, timings, backend and what was modelled."""
    require_mitsuba()
    from generator.render import RENDER_FORMAT, render

    sc = _scene("oblique_diagonal")  # thick slab: ghost and slab entries
    meta = render(sc, tmp_path / "r", _opts(tier, seed=7, keyframe_hz=50.0 if tier == "full" else None))
    disk = json.loads((tmp_path / "r" / "render.json").read_text())
    assert disk == json.loads(json.dumps(meta))
    assert disk["format"] == RENDER_FORMAT and disk["tier"] == tier and disk["complete"] is True
    assert disk["variant"].endswith("_polarized") and disk["seed"] == 7 and disk["spp"] >= 1
    assert len(disk["frames"]) == len(disk["frame_times_s"]) == 4
    assert {"maps_s", "frames_s", "per_frame_s"} <= set(disk["timings"])
    mod = disk["modelled"]
    assert mod["backend"]["variant"] == disk["variant"] and mod["backend"]["requested"] == "auto"
    assert mod["slab"] and mod["spectral"] is False and mod["radiance_compression_1_over_n2"] is False
    if tier == "maps":
        assert "second-surface" in mod["ghost"] and "x" in mod["subpixel_rays"]
    else:
        assert mod["keyframes_rendered"] >= 2 and "50.0 Hz" in mod["keyframes"]
        assert "subpixel_rays" in mod["maps_exr"]  # provenance of maps.exr (two-lobe tracer)
    assert disk["resume_key"]["spp"] == 2 and disk["resume_key"]["seed"] == 7
    if tier == "full":
        assert disk["spp"] == 2  # path samples of the full tier (not the maps.exr sub-pixel grid)


def test_full_tier_resume_over_frames_is_bit_identical(tmp_path):
    """Rendering frames 0:2 then the rest equals a one-shot render byte for byte; an existing frame is
    not re-rendered; a deleted frame is re-rendered identically (keyframe seeds depend on the index only).
    """
    require_mitsuba()
    from generator.render import render

    sc = _scene()
    ref = tmp_path / "ref"
    render(sc, ref, _opts("full", keyframe_hz=50.0))
    out = tmp_path / "r"
    m1 = render(sc, out, _opts("full", keyframe_hz=50.0, frames=(0, 2)))
    assert not m1["complete"] and len(list((out / "frames").glob("*.exr"))) == 2
    t_before = (out / "frames" / "000000.exr").stat().st_mtime_ns
    m2 = render(sc, out, _opts("full", keyframe_hz=50.0))
    assert m2["complete"]
    assert (out / "frames" / "000000.exr").stat().st_mtime_ns == t_before  # kept, not re-rendered
    assert _frame_bytes(out) == _frame_bytes(ref)
    (out / "frames" / "000003.exr").unlink()
    render(sc, out, _opts("full", keyframe_hz=50.0))
    assert _frame_bytes(out) == _frame_bytes(ref)


def test_resume_with_different_pixel_options_is_refused(tmp_path):
    """Resuming with another spp (or fps) would mix frames of two renders: one-line OutputError."""
    require_mitsuba()
    from generator.render import render

    sc = _scene()
    render(sc, tmp_path / "r", _opts("maps", frames=(0, 1)))
    with pytest.raises(OutputError, match="spp = 2.*spp = 4") as ei:
        render(sc, tmp_path / "r", _opts("maps", spp=4))
    assert "\n" not in str(ei.value)
    with pytest.raises(OutputError, match="fps"):
        render(sc, tmp_path / "r", _opts("maps", fps=50.0))
    assert render(sc, tmp_path / "r", _opts("maps"))["complete"]  # same options: resumes


def test_forced_variant_is_used_and_auto_fallback_is_logged_and_recorded(tmp_path, monkeypatch, caplog):
    """--variant scalar really runs scalar; auto with broken CUDA/LLVM JITs falls back to scalar with a
    logged warning and the reasons in render.json; the maps tier then falls back to analytic maps (logged,
    recorded), and forcing scalar for it is a one-line error.
    """
    require_mitsuba()
    import generator.mitsuba_backend as mb
    from generator.render import render
    from polinfra.errors import BackendUnavailableError

    sc = _scene(duration_s=0.01)
    with caplog.at_level("WARNING"):
        meta = render(sc, tmp_path / "s", _opts("full", variant="scalar", spp=1))
    assert meta["variant"] == "scalar_spectral_polarized" and meta["modelled"]["backend"]["requested"] == "scalar"
    assert "analytic" in meta["modelled"]["maps_exr"]["maps_exr_source"]  # maps.exr without a JIT tracer
    assert any("maps.exr falls back" in r.getMessage() for r in caplog.records)
    caplog.clear()
    meta = render(sc, tmp_path / "l", _opts("full", variant="llvm", spp=1))
    assert meta["variant"] == "llvm_ad_mono_polarized"

    monkeypatch.setitem(mb._PROBED, "llvm_ad_mono_polarized", "RuntimeError: Cannot select fminimum (simulated)")
    monkeypatch.setitem(mb._PROBED, "cuda_ad_mono_polarized", "no CUDA device (simulated)")
    with caplog.at_level("WARNING"):
        meta = render(sc, tmp_path / "a", _opts("full", spp=1))
    assert meta["variant"] == "scalar_spectral_polarized"
    fb = meta["modelled"]["backend"]["fallbacks"]
    assert any("fminimum" in line for line in fb) and any("CUDA" in line for line in fb)
    assert any("falling back" in r.getMessage() for r in caplog.records)
    from spike_sim.renderdir import open_render

    assert np.all(np.isfinite(open_render(tmp_path / "a").stokes(0)))
    # maps tier with auto and no JIT backend: logged fallback to the analytic maps, recorded; never a crash
    caplog.clear()
    with caplog.at_level("WARNING"):
        meta = render(sc, tmp_path / "m", _opts("maps"))
    assert meta["complete"] and "analytic fallback" in meta["modelled"]["maps_source"]
    assert any("ANALYTIC coefficient maps" in r.getMessage() for r in caplog.records)
    # ...but forcing scalar for the maps tier is a one-line error
    with pytest.raises(BackendUnavailableError, match="JIT") as ei:
        render(sc, tmp_path / "m2", _opts("maps", variant="scalar"))
    assert "\n" not in str(ei.value)


def test_ground_truth_layers_are_the_analytic_tiers(tmp_path):
    """T and R ground truth are sampled exactly as in the analytic tier, whatever tier made the Stokes."""
    require_mitsuba()
    from generator.render import render
    from spike_sim.renderdir import open_render

    sc = _scene("oblique_diagonal", duration_s=0.01)
    for tier in ("analytic", "maps", "full"):
        render(sc, tmp_path / tier, _opts(tier, keyframe_hz=None))
    a = open_render(tmp_path / "analytic")
    for tier in ("maps", "full"):
        r = open_render(tmp_path / tier)
        for i in range(len(a.times_s)):
            for x, y in zip(a.layers(i), r.layers(i)):
                assert np.array_equal(x, y), tier
        # maps.exr geometry channels agree with the analytic ones
        assert np.abs(r.maps()["theta"] - a.maps()["theta"]).max() < 1e-4


@pytest.mark.parametrize("tier", ["maps", "full"])
@pytest.mark.parametrize("name", ["near_normal", "brewster", "oblique_diagonal", "bk7_single"])
def test_every_default_scene_renders_in_both_mitsuba_tiers(tmp_path, name, tier):
    """At 16x10: each default scene renders in each Mitsuba tier, finite output;
    maps agree with the analytic tier (mono scenes within 1e-4, dispersive BK7 within 2e-3).
    """
    require_mitsuba()
    from generator.analytic import analytic_maps
    from generator.render import render
    from spike_sim.renderdir import open_render

    sc = _scene(name, duration_s=0.01)
    meta = render(sc, tmp_path / "r", _opts(tier, spp=1, spectral=None, n_bands=3))
    assert meta["complete"]
    rd = open_render(tmp_path / "r")
    for i in range(len(rd.times_s)):
        assert np.all(np.isfinite(rd.stokes(i))) and np.all(rd.stokes(i)[0] >= -1e-6)
    if tier == "maps":
        a = analytic_maps(sc)
        tol = 2e-3 if sc.pane.glass else 1e-4
        for k in ("R_perp", "R_par", "T_perp", "T_par"):
            assert np.abs(rd.maps()[k] - getattr(a, k)).max() < tol, k
    if sc.pane.glass:
        assert "3 bands" in meta["modelled"]["spectral"]


def test_user_csv_sensor_response_reaches_the_render(tmp_path):
    """--response CSV: a blue-only sensor sees BK7's higher index (more reflection) than a red-only one;
    render.json names the CSV; a missing CSV is a one-line error, exit 2.
    """
    require_mitsuba()
    from polspike.cli import get_app
    from spike_sim.renderdir import open_render

    blue, red = tmp_path / "blue.csv", tmp_path / "red.csv"
    blue.write_text("wavelength_nm,response\n400,1\n450,1\n460,0\n700,0\n")
    red.write_text("# silicon-like tail only\n400,0\n640,0\n650,1\n700,1\n")
    from generator.scene import SCENES_DIR

    text = (SCENES_DIR / "bk7_single.toml").read_text().replace("width = 400", "width = 16").replace("height = 250", "height = 10")
    text = text.replace("duration_s = 0.05", "duration_s = 0.01")
    toml = tmp_path / "s.toml"
    toml.write_text(text)
    R = {}
    for name, csv in (("blue", blue), ("red", red)):
        res = CliRunner().invoke(get_app(), ["render", str(toml), "--tier", "maps", "--spp", "1", "--spectral", "--response", str(csv), "--bands", "6", "--out", str(tmp_path / name), "--quiet"])
        assert res.exit_code == 0, res.output
        meta = json.loads((tmp_path / name / "render.json").read_text())
        assert str(csv) in meta["modelled"]["spectral"] and meta["resume_key"]["response"] == str(csv)
        R[name] = open_render(tmp_path / name).maps()["R_perp"]
    assert np.all(R["blue"] > R["red"] + 1e-4)
    res = CliRunner().invoke(get_app(), ["render", str(toml), "--tier", "maps", "--spectral", "--response", str(tmp_path / "nope.csv"), "--out", str(tmp_path / "x"), "--quiet"])
    from polinfra.errors import ConfigError

    assert isinstance(res.exception, ConfigError) and "nope.csv" in str(res.exception)  # exit 2 via polspike.cli.main


def test_maps_are_evaluated_once_per_scene_not_per_frame(tmp_path, monkeypatch):
    """Tier maps: one two-lobe evaluation for the whole clip, whatever the number of frames."""
    require_mitsuba()
    from generator import tiers_mitsuba as tm
    from generator.render import render

    calls = []
    orig = tm.render_pane_maps
    monkeypatch.setattr(tm, "render_pane_maps", lambda *a, **k: calls.append(1) or orig(*a, **k))
    meta = render(_scene(duration_s=0.05), tmp_path / "r", _opts("maps"))
    assert len(meta["frames"]) == 6 and len(calls) == 1
    # re-running a complete render with the same options does nothing (no second evaluation)
    again = render(_scene(duration_s=0.05), tmp_path / "r", _opts("maps"))
    assert again == json.loads((tmp_path / "r" / "render.json").read_text()) and len(calls) == 1
    # a longer clip resumes: maps evaluated again (once), only the new frames rendered
    t0 = (tmp_path / "r" / "frames" / "000000.exr").stat().st_mtime_ns
    meta = render(_scene(duration_s=0.05), tmp_path / "r", _opts("maps", duration_s=0.08))  # --duration
    assert meta["complete"] and len(meta["frames"]) == 9 and len(calls) == 2
    assert (tmp_path / "r" / "frames" / "000000.exr").stat().st_mtime_ns == t0


def test_r_layer_beyond_the_pane_is_a_render_json_warning():
    """An R plane so close that part of it lies beyond the tilted pane: the full tier differs there -> warning."""
    require_mitsuba()
    from generator import tiers_mitsuba as tm
    from generator.scene import scene_from_dict
    from polinfra.config import to_dict

    d = to_dict(_scene())
    d["layers"]["reflection"]["distance_m"] = 0.2
    info: dict = {}
    tm.FullRenderer(scene_from_dict(d), _opts("full", spp=1), info)
    assert any("R layer plane crosses the pane" in w for w in info["modelled"]["warnings"])
    info = {}
    tm.FullRenderer(_scene(), _opts("full", spp=1), info)
    assert "warnings" not in info["modelled"]


def test_forcing_cuda_without_a_gpu_is_one_line_error():
    """--variant cuda on a machine without CUDA: BackendUnavailableError naming the variant (exit 2), no crash."""
    require_mitsuba()
    from generator.mitsuba_backend import resolve_backend
    from polinfra.errors import BackendUnavailableError

    try:
        resolve_backend("cuda")
    except BackendUnavailableError as exc:
        assert "cuda_ad_mono_polarized" in str(exc) and "\n" not in str(exc) and "--variant auto" in str(exc)
    else:
        pytest.skip("a CUDA device is present")
    finally:
        resolve_backend("auto")
