"""The network on a zeta it did not estimate: `polspike reconstruct --method net --zeta self` and
`polspike evaluate --method full --zeta self` / `--net-zeta`.

Oracles: a stand-in model that returns the zeta it is given (so tiled and whole-frame runs must hand
it exactly the windows' zeta); the step-level pane stream of test_physics_video (closed-form pane,
Fresnel, paper Eq. (1)-(2)) on which the network fed the self-calibrated zeta must do as well as when
fed the true pane's zeta, and beat the plain TFP image.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from reconstruct.net.checkpoint import DEFAULT_WEIGHTS

from .test_physics_video import PHI0, REV, H, W, _psnr, _stream, stream  # noqa: F401  (module fixture)

needs_ckpt = pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason=f"shipped checkpoint {DEFAULT_WEIGHTS} not present")


class _EchoZeta:
    """Returns T = the centre zeta it receives (zeta_gt, alpha = 1), R = the centre frame."""

    pad_multiple = 4

    def __init__(self, n_obs=5):
        self.cfg = type("C", (), {"n_obs": n_obs, "inputs": frozenset()})()

    def __call__(self, I, phi, zeta_gt=None, alpha=0.0):
        assert alpha == 1.0 and zeta_gt is not None and zeta_gt.shape == I.shape
        o = type("O", (), {})()
        c = I.shape[1] // 2
        o.T, o.R = zeta_gt[:, c], I[:, c]
        o.T_base, o.R_base = o.T, o.R
        return o


@pytest.mark.parametrize("tile", [0, 16])
def test_windows_zeta_reaches_the_model_whole_and_tiled(tile):
    from reconstruct.stream.window_inputs import WindowInputs
    from reconstruct.video.tiling import run_model_on_windows

    rng = np.random.default_rng(0)
    I = rng.random((2, 5, 37, 45)).astype(np.float32)
    Z = rng.random((2, 5, 37, 45)).astype(np.float32)
    out = run_model_on_windows(_EchoZeta(), WindowInputs(I, np.zeros((2, 5), np.float32)), tile=tile, margin=4, zeta=Z)
    np.testing.assert_array_equal(out["T"], Z[:, 2])
    np.testing.assert_array_equal(out["R"], I[:, 2])


@needs_ckpt
def test_net_on_self_zeta_matches_net_on_true_zeta(stream, tmp_path):  # noqa: F811
    """Strong reflection (R about 5x T): the network on the self-calibrated zeta is within 1.5 dB of the
    network on the true pane's zeta and 3 dB above the TFP image (measured with polspike_v7 and the default
    floor: self 17.1, gt 18.3 dB; with the floor at the RWPS alone 17.3 and 18.3; polspike_v2: self 13.2, gt 13.0,
    its own learned zeta 8.3, TFP 7.3 dB).
    """
    import torch

    from polinfra.exr import read_exr
    from reconstruct.net.checkpoint import load_model
    from reconstruct.net.net_zeta import MapsZetaNet, build_net_zeta_model
    from reconstruct.physics.zeta import PaneMaps
    from reconstruct.stream.sources import group_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    torch.set_num_threads(1)
    net = load_model(DEFAULT_WEIGHTS, use_rir=False)[0]
    src = group_source(stream["group"])
    cfg = ReconstructConfig(frames="exr", video=False, max_frames=2)
    m = stream["maps"]
    models = {"gt": MapsZetaNet(net, PaneMaps(m["R_perp"], m["R_par"], m["phi_perp"]), 2 * math.pi * REV * 13 / 20000.0)}
    models["self"], info = build_net_zeta_model(net, "self", src, group_dir=stream["group"])
    assert info["zeta"] == "self" and info["selfcal"]["ok"] and isinstance(models["self"], MapsZetaNet)
    psnr = {}
    for z, mod in models.items():
        s = reconstruct_stream(src, mod, tmp_path / z, cfg)
        assert s["frames"] == 2 and s["nan_frames"] == 0
        psnr[z] = np.mean([_psnr(read_exr(tmp_path / z / "frames" / f"{i:06d}.exr", ["T"])["T"], stream["T"]) for i in range(2)])
    sp = next(src.chunks())[1]
    tfp = 2.0 * sp[: 7 * 58].reshape(7, 58, H, W)[:, :13].sum(1).mean(0) / 13.0
    assert psnr["self"] > psnr["gt"] - 1.5, psnr
    assert psnr["self"] > _psnr(tfp, stream["T"]) + 3.0, (psnr, _psnr(tfp, stream["T"]))


@needs_ckpt
def test_default_floor_holds_the_rwps_where_the_best_physics_fails(stream, tmp_path):  # noqa: F811
    """R about 5 x T under a pane that barely modulates in most of the view (true zeta): least squares, and so the best
    closed-form physics, is far off in the corner where zeta is large, and the RWPS's spatial prior holds it.  The
    network floored at the default blend of the two scores within 0.5 dB of the network floored at the RWPS alone or
    better, and the floor at the best physics alone is > 2 dB below (measured 18.5, 18.4 and 15.7 dB; 11.7 before its
    fallback was held at layers >= 0).
    """
    import torch

    from polinfra.exr import read_exr
    from reconstruct.net.checkpoint import load_model
    from reconstruct.net.net_zeta import MapsZetaNet
    from reconstruct.physics.zeta import PaneMaps
    from reconstruct.stream.sources import group_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    torch.set_num_threads(1)
    m = stream["maps"]
    psnr = {}
    for fa in ("blend", "rwps", "best"):
        net = load_model(DEFAULT_WEIGHTS, use_rir=False, floor_anchor=fa)[0]
        mod = MapsZetaNet(net, PaneMaps(m["R_perp"], m["R_par"], m["phi_perp"]), 2 * math.pi * REV * 13 / 20000.0)
        s = reconstruct_stream(group_source(stream["group"]), mod, tmp_path / fa, ReconstructConfig(frames="exr", video=False, max_frames=1))
        assert s["frames"] == 1 and s["nan_frames"] == 0
        psnr[fa] = _psnr(read_exr(tmp_path / fa / "frames" / "000000.exr", ["T"])["T"], stream["T"])
    assert psnr["blend"] >= psnr["rwps"] - 0.5, psnr
    assert psnr["best"] < psnr["rwps"] - 2.0, psnr


@needs_ckpt
def test_cli_dat_net_with_self_zeta(stream, polspike_main, tmp_path):  # noqa: F811
    out = tmp_path / "o"
    r = polspike_main("reconstruct", stream["dat"], "--height", H, "--width", W, "--phi0-deg", math.degrees(PHI0), "--rev-per-s", REV,
                      "--out", out, "--zeta", "self", "--max-frames", 1, "--quiet", "--device", "cpu", "--exposure", 1.0)
    assert r.returncode == 0, r.stderr[-2000:]
    info = json.loads((out / "zeta.json").read_text())
    assert info["method"] == "net" and info["zeta"] == "self" and info["selfcal"]["ok"]
    s = json.loads((out / "reconstruct.json").read_text())
    assert s["zeta"] == "self" and s["frames"] == 1 and s["nan_frames"] == 0


@needs_ckpt
def test_evaluate_labels_the_network_zeta():
    """--zeta self makes the network run on self too (rows full@self, full@self:solver); --net-zeta
    overrides; by-regime gets net@self columns and R tables.
    """
    import dataclasses

    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups, net_zeta_of
    from reconstruct.evaluate.regimes import evaluate_by_regime, regime_report
    from reconstruct.stream.synthetic import SyntheticConfig, make_group

    assert net_zeta_of(EvalConfig(zeta="self")) == "self" and net_zeta_of(EvalConfig(zeta="gt")) == "learned"
    assert net_zeta_of(EvalConfig(zeta="self", net_zeta="learned")) == "learned"
    g = dataclasses.replace(make_group(SyntheticConfig(width=24, height=16, n_groups=1, n_frames=9, seed=5), 0), name="refl-strong_inc-normal")
    cfg = EvalConfig(methods="full", max_frames=1, rir=False, net_zeta="gt")
    rep = evaluate_groups([g], cfg)
    lab = rep.config["network"]["label"]  # full, or full-norir for a checkpoint trained with RIR
    assert rep.config["network"]["zeta"] == "gt"
    assert {r["method"] for r in rep.rows} >= {f"{lab}@gt", f"{lab}@gt:solver"}
    learned = evaluate_groups([g], dataclasses.replace(cfg, net_zeta="learned"))
    t = {r["method"]: r["psnr_T"] for r in rep.rows + learned.rows if r["group"] == "overall"}
    assert t[f"{lab}@gt"] != t[lab]  # the zeta is used
    res = evaluate_by_regime([g], dataclasses.replace(cfg, net_zeta=""), zetas=(), net_zetas=("learned", "gt"))
    assert {"net", "net:solver", "net@gt", "net:solver@gt"} <= set(res["columns"])
    rowR = {r["regime"]: r for r in res["rows_R"]}["refl=strong"]
    assert rowR["tfp"] is None and rowR["net@gt"] is not None
    assert "PSNR of R" in regime_report(res)


def test_a_stream_shorter_than_half_a_turn_falls_back_to_zero_zeta_or_the_learned_one():
    """--zeta self (the default) on a stream too short to self-calibrate: zeta = 0 (the default fallback) or, asked
    for, the network itself, the reason in info; the physics path, which has no fallback, refuses with the one-line
    error's type.
    """
    from polinfra.errors import ConfigError
    from reconstruct.net.net_zeta import NET_FALLBACK_ZETA, ZeroZetaNet, build_net_zeta_model
    from reconstruct.pane.source import calibrate_stream
    from reconstruct.stream.sources import StreamTooShortError, array_source

    sp = (np.random.default_rng(0).random((200, 16, 24)) < 0.1).astype(np.uint8)  # 10 ms at 30 rev/s: 15 frames < 26
    net = _tiny_net()
    m, info = build_net_zeta_model(net, "self", array_source(sp, 0.0, 30.0))
    assert NET_FALLBACK_ZETA == "auto" and isinstance(m, ZeroZetaNet) and m.net is net  # auto: nothing measured -> none
    assert info["zeta"].startswith("none (no self-calibration: the stream is shorter")
    m, info = build_net_zeta_model(net, "self", array_source(sp, 0.0, 30.0), fallback="learned")
    assert m is net and info["zeta"].startswith("learned (no self-calibration: the stream is shorter")
    with pytest.raises(ConfigError):
        build_net_zeta_model(net, "self", array_source(sp, 0.0, 30.0), fallback="gt")
    with pytest.raises(StreamTooShortError):
        calibrate_stream(array_source(sp, 0.0, 30.0))
    assert issubclass(StreamTooShortError, ConfigError)


def _tiny_net():
    import torch

    from reconstruct.net.network import PolSpikeNet, init_weights
    from reconstruct.net.train import TINY

    net = PolSpikeNet(TINY.net, TINY.solver)
    init_weights(net, torch.Generator().manual_seed(0))
    with torch.no_grad():  # a refinement that changes T, so the test below sees the solver's own output in T_base
        net.refine.dec_t.out.weight.mul_(100.0)
    return net.eval()


def test_zero_zeta_solves_for_the_whole_light():
    """Zeta = 0 in paper Eq. (1) leaves I_k = T / 2 for every observation: the solver's T is a weighted mean of the
    2 I_k, within [2 min_k I_k, 2 max_k I_k] (times the solver's ridge shrinkage, a few per cent here), and R has no
    say in it; tiles are fine (no per-pixel maps).
    """
    import torch

    from reconstruct.net.net_zeta import ZeroZetaNet

    net = _tiny_net()
    g = torch.Generator().manual_seed(1)
    N = net.cfg.n_obs
    I = 0.05 + 0.4 * torch.rand(2, N, 16, 16, generator=g)
    phi = torch.linspace(0, 1.2, N).repeat(2, 1)
    with torch.no_grad():
        o = ZeroZetaNet(net)(I, phi)
    assert torch.count_nonzero(o.zeta_used) == 0
    assert (o.T_base <= 2 * I.max(1).values + 1e-6).all() and (o.T_base >= 0.8 * 2 * I.min(1).values).all()
    assert torch.isfinite(o.R).all() and not torch.allclose(o.T, o.T_base)  # the refinement still runs
    assert ZeroZetaNet(net).pad_multiple == net.pad_multiple and not hasattr(ZeroZetaNet(net), "stream_tile")


def test_a_stream_without_polarizer_does_not_self_calibrate(shared_data):
    """The independent simulator's REDS stream has no polarizer. At 48.95 rev/s its moving scene aliases into an
    orientation field that a narrow pane explains 11 sigmas above chance (z_min 8), yet no pixel modulates above
    noise: the modulating-block gate (min_modulating_blocks) is what refuses it; without the gate a pane is claimed.
    """
    import dataclasses

    from polspike.pipeline.real_eval import RECORDINGS, _load
    from reconstruct.pane.selfcal import SelfCalConfig
    from reconstruct.pane.source import calibrate_stream
    from reconstruct.stream.exposure import estimate_exposure
    from reconstruct.stream.sources import array_source

    rec = next(r for r in RECORDINGS if r.file.endswith(".dat"))
    if not (shared_data / "real_spikes" / rec.file).is_file():
        pytest.skip("REDS sample absent")
    sp = _load(rec, shared_data / "real_spikes", 0)
    src = array_source(sp, 0.0, 48.95, name=rec.file)
    exp = estimate_exposure(sp).exposure
    r = calibrate_stream(src, None, 13, exp, None, 1.5, "single")
    assert not r.ok and "pixel blocks modulate above noise (need" in r.reason, r.reason
    assert r.diagnostics["modulating_blocks"] < SelfCalConfig().min_modulating_blocks and r.diagnostics["z"] > SelfCalConfig().z_min
    r0 = calibrate_stream(src, None, 13, exp, dataclasses.replace(SelfCalConfig(), min_modulating_blocks=0.0), 1.5, "single")
    assert r0.ok  # the gate, not another test, refuses it


def test_fallback_for_follows_the_refused_calibrations_modulation():
    """auto: the learned zeta where a refused calibration still shows >= FALLBACK_LEARNED_PX of the pixels modulating
    (polarization the planar fit could not follow), zeta = 0 where nothing modulates or nothing was measured; the
    explicit choices pass through; anything else is a one-line ConfigError.
    """
    from types import SimpleNamespace

    from polinfra.errors import ConfigError
    from reconstruct.net.net_zeta import FALLBACK_LEARNED_PX, fallback_for

    res = lambda px: SimpleNamespace(ok=False, diagnostics={"modulating_px": px})  # noqa: E731
    assert fallback_for(res(0.18)) == "learned" and fallback_for(res(FALLBACK_LEARNED_PX)) == "learned"
    assert fallback_for(res(0.0)) == "none" and fallback_for(res(0.017)) == "none" and fallback_for(None) == "none"
    assert fallback_for(res(0.18), "none") == "none" and fallback_for(res(0.0), "learned") == "learned"
    with pytest.raises(ConfigError, match="fallback"):
        fallback_for(None, "gt")
