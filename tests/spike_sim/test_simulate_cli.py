"""CLI wiring: `polspike simulate` on a render directory, `polspike bench spike-sim --json`."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from polspike.cli import get_app
from spike_sim.store import open_group
from spike_sim.vidar_dat import read_dat


def _render_dir(tmp_path, kf):
    from polinfra.exr import write_exr

    rd = tmp_path / "render"
    (rd / "frames").mkdir(parents=True)
    names = []
    for k in range(kf.times_s.size):
        st = kf.stokes(k)
        T_, R_ = kf.layers(k)
        names.append(f"frames/{k:06d}.exr")
        write_exr(rd / names[-1], {"S0": st[0], "S1": st[1], "S2": st[2], "T": T_, "R": R_})
    write_exr(rd / "maps.exr", kf.maps())
    meta = {"format": "polspike-render/1", "complete": True, "scene_hash": "h1", "tier": "analytic", "width": 24, "height": 16, "fps": 200.0,
            "frame_times_s": kf.times_s.tolist(), "frames": names, "scene": {"polarizer": {"rate_hz": 30.0}}, "modelled": {}, "timings": {}, "conventions": ""}
    (rd / "render.json").write_text(json.dumps(meta))
    return rd


def test_simulate_command(tmp_path, keyframes, polspike_main):
    rd = _render_dir(tmp_path, keyframes)
    cfg = tmp_path / "sim.toml"
    cfg.write_text("[spike_sim]\nexposure = 2.0\nshot_noise = false\n[aggregate]\nwindow_steps = 11\n")
    r = CliRunner().invoke(get_app(), ["simulate", str(rd), "--duration", "0.02", "--seed", "3", "--out", str(tmp_path / "g"), "--dat", str(tmp_path / "g.dat"), "--config", str(cfg), "--quiet"])
    assert r.exit_code == 0, r.output
    g = open_group(tmp_path / "g")
    assert g.json_attr("config_json")["exposure"] == 2.0 and g.json_attr("aggregate_json")["window_steps"] == 11
    assert np.array_equal(read_dat(tmp_path / "g.dat", 16, 24), g.read())
    # same again without --overwrite: refused with exit code 2 and a one-line message
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "g").rglob("*")}
    r2 = polspike_main("simulate", rd, "--duration", "0.02", "--out", tmp_path / "g", "--quiet")
    polspike_main.one_line_exit_2(r2, "--overwrite")
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "g").rglob("*")} == before  # the existing group is untouched


def test_bad_config_key_is_reported(tmp_path, keyframes, polspike_main):
    rd = _render_dir(tmp_path, keyframes)
    cfg = tmp_path / "sim.toml"
    cfg.write_text("[spike_sim]\nexposur = 2.0\n")
    r = polspike_main("simulate", rd, "--duration", "0.01", "--out", tmp_path / "g", "--config", cfg, "--quiet")
    polspike_main.one_line_exit_2(r, "exposur")
    assert not (tmp_path / "g").exists()


def test_bench_json(tmp_path):
    r = CliRunner().invoke(get_app(), ["bench", "spike-sim", "--json", "--out", str(tmp_path), "--steps", "64", "--numpy-steps", "4", "--width", "40", "--height", "20"])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "spike_sim.json").read_text())
    assert res["ratio_numba_over_numpy"] > 1.0
    assert res["numba"]["pixel_steps_per_s"] > 0 and res["peak_rss_mb"] > 0


def test_simulate_flags_preset_chunking_compression(tmp_path, keyframes):
    """--preset sets the base config; --chunk-steps and --compression never change the bits; bad values exit 2."""
    rd = _render_dir(tmp_path, keyframes)
    app = get_app()

    def run(name, *extra):
        return CliRunner().invoke(app, ["simulate", str(rd), "--duration", "0.02", "--seed", "5", "--out", str(tmp_path / name), "--quiet", *extra])

    assert run("a", "--preset", "ideal").exit_code == 0
    assert run("b", "--preset", "ideal", "--chunk-steps", "37", "--compression", "none").exit_code == 0
    ga, gb = open_group(tmp_path / "a"), open_group(tmp_path / "b")
    assert ga.json_attr("config_json")["shot_noise"] is False
    assert np.array_equal(ga.read(), gb.read()) and ga.read().shape == (400, 16, 24)
    assert ga.f["spikes"].compression == "gzip" and gb.f["spikes"].compression is None
    assert run("c").exit_code == 0  # default preset: a different (noisy) stream
    assert not np.array_equal(open_group(tmp_path / "c").read(), ga.read())
    ga.close()
    gb.close()
    from polinfra.errors import ConfigError

    r = run("d", "--preset", "bogus")  # PolspikeError -> exit 2 in polspike.cli.main
    assert isinstance(r.exception, ConfigError) and "bogus" in str(r.exception)
    assert run("a", "--preset", "ideal", "--overwrite", "--seed", "6").exit_code == 0
    assert open_group(tmp_path / "a").seed == 6  # --overwrite replaced the group
    r = run("e", "--chunk-steps", "0")
    assert isinstance(r.exception, ConfigError) and "chunk_steps" in str(r.exception)
    assert not (tmp_path / "e" / "group.json").exists()


def test_store_zeta_flag_writes_eq2_at_output_times(tmp_path, keyframes):
    """--store-zeta: gt/zeta (M, H, W) = paper Eq. (2) at each output frame's mean true angle (float16)."""
    from polphysics.zeta import zeta

    rd = _render_dir(tmp_path, keyframes)
    r = CliRunner().invoke(get_app(), ["simulate", str(rd), "--duration", "0.03", "--out", str(tmp_path / "g"), "--store-zeta", "--quiet"])
    assert r.exit_code == 0, r.output
    with open_group(tmp_path / "g") as g:
        z = g.f["gt/zeta"]
        M = g.array("output/step_index").size
        assert z.shape == (M, 16, 24) and M > 0
        m = g.maps()
        phi = g.array("output/phi_true_rad")
        for i in (0, M - 1):
            np.testing.assert_allclose(z[i], zeta(phi[i], m["R_perp"], m["R_par"], m["phi_perp"]), atol=2e-3)
