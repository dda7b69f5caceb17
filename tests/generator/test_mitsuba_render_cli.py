"""``polspike render --tier maps|full`` and ``polspike bench render`` end to end (tiny scenes)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba
from typer.testing import CliRunner

pytestmark = pytest.mark.mitsuba

TINY = """
name = "tiny"
[camera]
width = 40
height = 25
fov_deg = 40.0
[pane]
model = "{model}"
n = 1.5
distance_m = 1.0
tilt_deg = 56.0
size_m = [4.0, 2.0]
thickness_mm = 4.0
[layers.transmission]
source = "procedural:checker"
distance_m = 4.0
[layers.transmission.motion]
translate_per_s = [0.2, 0.05]
[layers.reflection]
source = "procedural:rings"
distance_m = 2.0
[render]
duration_s = 0.02
fps = 100.0
"""


def _run(args):
    from polspike.cli import get_app

    res = CliRunner().invoke(get_app(), args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res


@pytest.mark.parametrize("tier,model", [("maps", "single"), ("full", "thick_slab")])
def test_render_cli_mitsuba_tiers(tmp_path, tier, model):
    """Both Mitsuba tiers write the render-dir format; no NaN/Inf anywhere; maps agree with analytic."""
    require_mitsuba()
    from generator.analytic import analytic_maps
    from generator.scene import load_scene
    from spike_sim.renderdir import open_render

    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY.format(model=model))
    out = tmp_path / "out"
    _run(["render", str(scene), "--tier", tier, "--spp", "4", "--out", str(out), "--quiet"])
    meta = json.loads((out / "render.json").read_text())
    assert meta["tier"] == tier and meta["complete"] and meta["variant"].endswith("polarized")
    assert meta["modelled"]["backend"]["variant"] == meta["variant"]
    rd = open_render(out)
    for i in range(len(rd.times_s)):
        S = rd.stokes(i)
        assert S.shape == (3, 25, 40) and np.all(np.isfinite(S))
        assert np.all(S[0] >= -1e-6)
        assert np.all(np.isfinite(np.stack(rd.layers(i))))
    maps = rd.maps()
    for v in maps.values():
        assert np.all(np.isfinite(v))
    if tier == "maps":
        a = analytic_maps(load_scene(scene))
        for k in ("R_perp", "R_par", "T_perp", "T_par"):
            assert np.abs(maps[k] - getattr(a, k)).max() < 1e-4, k


def test_render_cli_unknown_variant_exits_2(tmp_path):
    """--variant metal: one-line error, exit code 2 (through the real entry point)."""
    import subprocess
    import sys
    from pathlib import Path

    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY.format(model="single"))
    exe = Path(sys.executable).parent / "polspike"
    r = subprocess.run([str(exe), "render", str(scene), "--tier", "maps", "--variant", "metal", "--out", str(tmp_path / "o"), "--quiet"], capture_output=True, text=True)
    assert r.returncode == 2
    assert "unknown variant 'metal'" in r.stderr
    assert not (tmp_path / "o").exists()  # refused before --out is touched


def test_render_cli_forced_llvm_that_cannot_load_exits_2_and_writes_nothing(tmp_path, polspike_cli):
    """--variant llvm with no loadable libLLVM: exit 2, no traceback, the fix named, and no --out folder left behind."""
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY.format(model="single"))
    out = tmp_path / "o"
    r = polspike_cli("render", scene, "--tier", "maps", "--variant", "llvm", "--out", out, "--quiet", env={"DRJIT_LIBLLVM_PATH": str(tmp_path / "no_libLLVM.so")})
    assert r.returncode == 2, (r.returncode, r.stderr[-1500:])
    assert "Traceback" not in r.stderr
    assert "--variant llvm" in r.stderr and "--variant auto" in r.stderr
    assert not out.exists()


def test_bench_render_cli_json(tmp_path):
    require_mitsuba()
    res = _run(["bench", "render", "--json", "--out", str(tmp_path), "--width", "16", "--height", "10", "--spp", "1", "--backend", "llvm", "--backend", "scalar", "--repeats", "1", "--no-maps"])
    data = json.loads(res.output[res.output.index("{"):])
    assert {(r["backend"], r["spp"]) for r in data["rows"]} == {("llvm", 1), ("scalar", 1)}
    assert all(r["later_s"] > 0 and r["finite"] for r in data["rows"])
    assert "1" in data["scalar_over_llvm_later_s"]
    assert (tmp_path / "render.json").is_file()
