"""Physics-only `polspike reconstruct --method ls|ridge|irls|rwps --zeta self|learned|physics|gt`.

The input is a step-level spike stream behind a pane of known geometry (closed form: polphysics geometry
and Fresnel, paper Eq. (1)-(2), integrate-and-fire pixels with a random phase), written both as a raw
.dat and as a group store with its true pane maps.  Checked: the console script on the .dat form with
the new options (self-calibrated pane near the truth, PNG frames), T from the physics stream closer to
the true T than the plain TFP image and self within 1 dB of gt, bad option combinations -> one line, exit 2.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from polphysics.fresnel import pane_coefficients
from polphysics.geometry import PinholeCamera, Plane, incidence_geometry

from ._pane_groups import true_normal
from ._synth import periodic_texture

H, W, STEPS, RATE, REV = 48, 72, 2600, 20000.0, 30.0
TILT, AZ, PHI0 = 58.0, 130.0, 0.4


def _stream(tilt=TILT, seed=0, exposure=1.0):
    """(spikes (STEPS, H, W) uint8, phi per step, maps dict, T and R per step-block function)."""
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=60.0, width=W, height=H)
    geo = incidence_geometry(cam, Plane(np.array([0.0, 0.0, 1.0]), true_normal(tilt, AZ, cam)))
    co = pane_coefficients(geo["theta"], 1.5)
    phi = PHI0 + 2 * math.pi * REV * (np.arange(STEPS) + 0.5) / RATE
    tT = periodic_texture(np.random.default_rng([seed, 1]), H, W)
    tR = periodic_texture(np.random.default_rng([seed, 2]), H, W)
    T = np.clip(0.25 * (1 + 0.4 * tT), 0.02, None)
    R = np.clip(1.2 * (1 + 0.5 * tR), 0.02, None)  # strong reflection, static layers
    acc = rng.uniform(0, 1, (H, W))
    sp = np.zeros((STEPS, H, W), np.uint8)
    for s in range(STEPS):
        z = co["R_perp"] * np.cos(phi[s] - geo["phi_perp"]) ** 2 + co["R_par"] * np.sin(phi[s] - geo["phi_perp"]) ** 2  # paper Eq. (2)
        acc += exposure * 0.5 * (z * R + (1 - z) * T)  # paper Eq. (1), thresholds per step
        fire = acc >= 1.0
        sp[s] = fire
        acc -= fire
    maps = {"R_perp": co["R_perp"], "R_par": co["R_par"], "phi_perp": geo["phi_perp"], "theta": geo["theta"]}
    return sp, phi, maps, T, R


def _write(d, exposure=1.0):
    from spike_sim.store import GroupWriter
    from spike_sim.vidar_dat import write_dat

    sp, phi, maps, T, R = _stream(exposure=exposure)
    d.mkdir(parents=True, exist_ok=True)
    write_dat(d / "pane.dat", sp)
    w = GroupWriter(d / "group", H, W, RATE, STEPS, attrs={"polarizer_json": {"rate_hz": REV}, "config_json": {"exposure": exposure}})
    w.write_spikes(np.packbits(sp.reshape(STEPS, -1), axis=1, bitorder="little"))
    for k in ("phi_true_rad", "phi_nominal_rad"):
        w.write_array(f"polarizer/{k}", phi)
    for k, v in maps.items():
        w.write_array(f"maps/{k}", v.astype(np.float32))
    w.close()
    return {"dir": d, "dat": d / "pane.dat", "group": d / "group", "T": T, "R": R, "maps": maps}


@pytest.fixture(scope="module")
def stream(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("pv"))


def test_dat_form_with_method_and_self_zeta(stream, polspike_cli, tmp_path):
    out = tmp_path / "o"
    r = polspike_cli("reconstruct", stream["dat"], "--height", H, "--width", W, "--phi0-deg", math.degrees(PHI0), "--rev-per-s", REV,
                     "--frames", "png", "--out", out, "--method", "ls", "--zeta", "self", "--no-rir", "--max-frames", 2, "--quiet", "--device", "cpu")
    assert r.returncode == 0, r.stderr[-2000:]
    info = json.loads((out / "physics.json").read_text())
    sc = info["selfcal"]
    assert info["zeta"] == "self" and sc["ok"]
    assert abs(sc["tilt_deg"] - TILT) < 3.0
    assert json.loads((out / "reconstruct.json").read_text())["frames"] == 2
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["R_000000.png", "R_000001.png", "T_000000.png", "T_000001.png"]
    # the fitted pane is kept: --pane OUT reconstructs on the same zeta without calibrating again (the same frames)
    assert info["pane_maps"] == "maps.exr" and (out / "maps.exr").is_file()
    again = tmp_path / "again"
    r = polspike_cli("reconstruct", stream["dat"], "--height", H, "--width", W, "--phi0-deg", math.degrees(PHI0), "--rev-per-s", REV,
                     "--frames", "png", "--out", again, "--method", "ls", "--pane", out, "--no-rir", "--max-frames", 2, "--quiet", "--device", "cpu")
    assert r.returncode == 0, r.stderr[-2000:]
    info2 = json.loads((again / "physics.json").read_text())
    assert info2["zeta"] == f"pane ({out})" and info2["selfcal"] is None and info2["pane_maps"] is None and not (again / "maps.exr").exists()
    for f in ("T_000000.png", "R_000001.png"):
        assert (again / "frames" / f).read_bytes() == (out / "frames" / f).read_bytes(), f
    # a reconstruction that did not self-calibrate wrote no maps: --pane says so in one line
    r = polspike_cli("reconstruct", stream["dat"], "--height", H, "--width", W, "--phi0-deg", math.degrees(PHI0), "--rev-per-s", REV,
                     "--out", tmp_path / "third", "--method", "ls", "--pane", again, "--no-rir", "--max-frames", 1, "--quiet")
    polspike_cli.one_line_exit_2(r, "that reconstruction did not self-calibrate")


def test_fov_deg_is_the_self_calibrations_field_of_view(stream, polspike_cli, tmp_path):
    """--fov-deg gives the self-calibration the lens: the fit keeps it, and the pane's normal keeps its vanishing point
    (the orientation field pins it: tan(tilt) / tan(fov / 2) is what the spikes see), so a narrower fov is a smaller tilt.
    """
    got = {}
    for fov in (None, 60.0, 40.0):
        out = tmp_path / f"o{fov}"
        r = polspike_cli("reconstruct", stream["dat"], "--height", H, "--width", W, "--phi0-deg", math.degrees(PHI0), "--rev-per-s", REV, "--out", out,
                         "--method", "ls", "--no-rir", "--max-frames", 1, "--quiet", *(() if fov is None else ("--fov-deg", fov)))
        assert r.returncode == 0, r.stderr[-2000:]
        assert ("give --fov-deg" in " ".join(r.stdout.split())) == (fov is None)  # the hint only where the fov was fitted
        got[fov] = json.loads((out / "physics.json").read_text())["selfcal"]
    assert got[None]["fov_fitted"] and abs(got[None]["fov_deg"] - 60.0) < 3.0  # this wide view pins the fov too (measured 59.9)
    for fov in (60.0, 40.0):
        assert got[fov]["fov_deg"] == fov and not got[fov]["fov_fitted"]
    assert abs(got[60.0]["tilt_deg"] - TILT) < 0.5  # measured 58.02
    want = math.degrees(math.atan(math.tan(math.radians(TILT)) * math.tan(math.radians(20.0)) / math.tan(math.radians(30.0))))
    assert abs(got[40.0]["tilt_deg"] - want) < 1.5, (got[40.0]["tilt_deg"], want)  # measured 45.9 vs 45.3


def _psnr(a, b):
    return float(10 * np.log10(float(b.max()) ** 2 / np.mean((a - b) ** 2)))


def test_physics_stream_separates_and_self_is_within_1db_of_gt(stream, tmp_path):
    from polinfra.exr import read_exr
    from reconstruct.stream.sources import group_source
    from reconstruct.video.physics import build_physics_model
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    src = group_source(stream["group"])
    cfg = ReconstructConfig(frames="exr", video=False, max_frames=2)
    psnr = {}
    # self: the pane's glass given (single, n 1.5: the user knows it) and fitted (auto: the spikes do not tell this
    # pane's model, so the thin-slab prior stands)
    for tag, z, kw in (("gt", "gt", {}), ("self", "self", {"pane_n": 1.5, "pane_model": "single"}), ("self_auto", "self", {})):
        model, info = build_physics_model("ls", z, src, group_dir=stream["group"], rir=False, **kw)
        s = reconstruct_stream(src, model, tmp_path / tag, cfg)
        assert s["frames"] == 2 and s["nan_frames"] == 0
        fr = read_exr(tmp_path / tag / "frames" / "000000.exr", ["T", "R"])
        psnr[tag] = _psnr(fr["T"], stream["T"])
        if tag == "self_auto":
            assert info["selfcal"]["model"] == "thin_slab" and info["selfcal"]["n"] == 1.5, info["selfcal"]
    # TFP of the same window: 2 x mean of the 7 Eq. (3) frames = what the stream saw, reflection included
    sp = src.chunks().__next__()[1]
    tfp = 2.0 * sp[: 7 * 58].reshape(7, 58, H, W)[:, :13].sum(1).mean(0) / 13.0
    assert psnr["gt"] > _psnr(tfp, stream["T"]) + 3.0, (psnr, _psnr(tfp, stream["T"]))
    assert psnr["self"] > psnr["gt"] - 1.0, psnr
    assert psnr["self_auto"] > psnr["gt"] - 2.5, psnr  # measured -1.8 dB: LS with a slab's DoP on a single pane


def test_anchor_mean_on_a_static_stream_beats_the_plain_solver(tmp_path):
    """--anchor mean: the level from the 17.5 ms spike mean, R - T from the solver; on a static scene it is
    closer to the true T than the plain RWPS output on a dim stream (~0.05 spikes per step: the level's noise
    is that of 350 steps, not 7 x 13), both on the true zeta.
    """
    from polinfra.exr import read_exr
    from reconstruct.stream.sources import group_source
    from reconstruct.video.physics import build_physics_model
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    stream = _write(tmp_path / "dim", exposure=0.15)
    src = group_source(stream["group"])
    cfg = ReconstructConfig(frames="exr", video=False, max_frames=2)
    psnr = {}
    for a in ("none", "mean"):
        model, _ = build_physics_model("rwps", "gt", src, group_dir=stream["group"], rir=False, anchor=a)
        s = reconstruct_stream(src, model, tmp_path / a, cfg)
        assert s["frames"] == 2 and s["nan_frames"] == 0
        psnr[a] = np.mean([_psnr(read_exr(tmp_path / a / "frames" / f"{i:06d}.exr", ["T"])["T"], stream["T"]) for i in range(2)])
    assert psnr["mean"] > psnr["none"] + 2.0, psnr  # measured 9.09 vs 6.38 dB (strong R, dim: both far from T)


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--method", "net", "--anchor", "mean"], "physics methods"),
        (["--method", "ls", "--anchor", "median"], "--anchor"),
        (["--method", "net", "--zeta", "gt"], "physics --method"),
        (["--method", "ls", "--zeta", "gt"], "raw .dat"),
        (["--method", "ls", "--zeta", "physics"], "raw .dat"),
        (["--method", "magic"], "--method"),
        (["--method", "ls", "--zeta", "oracle"], "--zeta"),
        (["--method", "ls", "--pane", "/nonexistent/cal"], "no such directory"),
        (["--method", "ls", "--pane", "/nonexistent/cal", "--zeta", "self"], "drop --zeta"),
        (["--pane", "/nonexistent/cal", "--pane-n", "1.52"], "drop --pane-n"),
        (["--fov-deg", "200"], "--fov-deg 200"),
        (["--fov-deg", "0"], "--fov-deg 0"),
        (["--method", "ls", "--zeta", "learned", "--fov-deg", "40"], "drop --fov-deg"),
        (["--method", "net", "--zeta", "none", "--fov-deg", "40"], "drop --fov-deg"),
        (["--pane", "/nonexistent/cal", "--fov-deg", "40"], "drop --fov-deg"),
    ],
)
def test_bad_combinations_are_one_line_exit_2(stream, polspike_main, tmp_path, args, fragment):
    r = polspike_main("reconstruct", stream["dat"], "--height", H, "--width", W, "--phi0-deg", 0, "--rev-per-s", REV, "--out", tmp_path / "o", *args)
    polspike_main.one_line_exit_2(r, fragment)


def test_pane_from_calibrate_pane_drives_the_solvers(stream, polspike_cli, tmp_path):
    """calibrate-pane on the .dat, then reconstruct --pane with its output (on the group store of the same stream, whose
    exposure is stored): T within 1 dB of the true maps' T.  The true maps written as a calibration give bit for bit
    what --zeta gt gives.  (This view is edge-on in a corner: calibrate-pane writes no pane.toml, and says so.)
    """
    from polinfra.exr import read_exr, write_exr

    dat = ["--height", H, "--width", W, "--phi0-deg", math.degrees(PHI0), "--rev-per-s", REV]
    r = polspike_cli("calibrate-pane", stream["dat"], *dat, "--out", tmp_path / "cal")
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads((tmp_path / "cal" / "report.json").read_text())
    assert rep["pane_toml"]["written"] == (tmp_path / "cal" / "pane.toml").is_file() == ("pane.toml" in rep["files"])
    assert rep["pane_toml"]["written"] or "no pane.toml" in r.stdout
    common = ["--method", "ls", "--no-rir", "--max-frames", 2, "--frames", "exr", "--quiet", "--device", "cpu"]
    r = polspike_cli("reconstruct", stream["group"], *common, "--pane", tmp_path / "cal", "--out", tmp_path / "o_pane")  # the group: its stored exposure
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((tmp_path / "o_pane" / "physics.json").read_text())["zeta"].startswith("pane (")
    r = polspike_cli("reconstruct", stream["group"], *common, "--zeta", "gt", "--out", tmp_path / "o_gt")
    assert r.returncode == 0, r.stderr[-2000:]
    T = {k: read_exr(tmp_path / k / "frames" / "000000.exr", ["T"])["T"] for k in ("o_pane", "o_gt")}
    assert _psnr(T["o_pane"], stream["T"]) > _psnr(T["o_gt"], stream["T"]) - 1.0
    # the true maps as a calibration: the same frames as --zeta gt
    write_exr(tmp_path / "true" / "maps.exr", {k: np.asarray(v, np.float32) for k, v in stream["maps"].items()})
    r = polspike_cli("reconstruct", stream["group"], *common, "--pane", tmp_path / "true", "--out", tmp_path / "o_true")
    assert r.returncode == 0, r.stderr[-2000:]
    for k in ("T", "R"):
        a = read_exr(tmp_path / "o_true" / "frames" / "000001.exr", [k])[k]
        np.testing.assert_array_equal(a, read_exr(tmp_path / "o_gt" / "frames" / "000001.exr", [k])[k])
    # the network takes the same maps (its zeta input)
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS

    if DEFAULT_WEIGHTS.is_file():
        r = polspike_cli("reconstruct", stream["group"], "--method", "net", "--no-rir", "--max-frames", 1, "--quiet", "--device", "cpu", "--pane", tmp_path / "true", "--out", tmp_path / "o_net")
        assert r.returncode == 0, r.stderr[-2000:]
        z = json.loads((tmp_path / "o_net" / "zeta.json").read_text())
        assert z["zeta"].startswith("pane (") and z["selfcal"] is None and "net on zeta: pane" in r.stdout
    # maps of another camera: one line, exit 2
    write_exr(tmp_path / "small" / "maps.exr", {k: np.asarray(v[:, :40], np.float32) for k, v in stream["maps"].items()})
    r = polspike_cli("reconstruct", stream["group"], *common, "--pane", tmp_path / "small", "--out", tmp_path / "o_small")
    polspike_cli.one_line_exit_2(r, "maps of 40 x 48 for a stream of 72 x 48")


def test_self_falls_back_to_learned_where_nothing_modulates(tmp_path):
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
    from reconstruct.stream.sources import array_source
    from reconstruct.video.physics import build_physics_model

    if not DEFAULT_WEIGHTS.is_file():
        pytest.skip(f"shipped checkpoint {DEFAULT_WEIGHTS} not present")
    sp, *_ = _stream(tilt=0.0, seed=2)  # normal incidence: R_perp = R_par, nothing modulates
    src = array_source(sp, PHI0, REV)
    calls = []

    def load():
        calls.append(1)
        return load_model(DEFAULT_WEIGHTS)[0]

    model, info = build_physics_model("ridge", "self", src, rir=False, load_learned=load)
    assert calls == [1] and model.learned_model is not None and model.maps is None
    assert info["zeta"].startswith("learned") and not info["selfcal"]["ok"] and "modulat" in info["selfcal"]["reason"]  # nothing modulates / near-normal
    # without a checkpoint loader the fallback is a clear one-line project error
    from polinfra.errors import PolspikeError

    with pytest.raises(PolspikeError, match="checkpoint"):
        build_physics_model("ridge", "self", src, rir=False, load_learned=None)

