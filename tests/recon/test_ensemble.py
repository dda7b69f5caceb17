"""Test-time self-ensemble (reconstruct.net.network.SymmetryEnsemble): its symmetries are flip_item's (which is checked
against paper Eq. (2) on mirrored scenes), and averaging over a group of symmetries makes any network equivariant.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError
from reconstruct.net.network import SYMMETRY_CODES, NetConfig, PolSpikeNet, SymmetryEnsemble, init_weights
from reconstruct.net.onthefly import flip_item
from reconstruct.physics.symmetry import symmetry_angles, symmetry_image


def _net(seed=0, **kw):
    cfg = NetConfig(arch="v2", use_rir=False, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), **kw)
    return init_weights(PolSpikeNet(cfg), torch.Generator().manual_seed(seed)).eval()


def _window(B=2, H=16, W=24, seed=0):
    g = torch.Generator().manual_seed(seed)
    I = 0.05 + 0.4 * torch.rand(B, 7, H, W, generator=g)
    phi = 2.0 + (torch.arange(7) - 3) * math.radians(31.5) + torch.rand(B, 1, generator=g)
    return I, phi.float()


@pytest.mark.parametrize("code", range(8))
def test_symmetries_are_flip_items(code):
    """Per window, symmetry_image / symmetry_angles move the frames and the polarizer angles as flip_item moves a
    training item (same pixels, same angles mod pi, centre angle in [0, pi)).
    """
    I, phi = _window(H=12, W=12, seed=code)
    for b in range(I.shape[0]):
        it = flip_item({"I": I[b], "phi": phi[b]}, code)
        torch.testing.assert_close(symmetry_image(I, code)[b], it["I"], rtol=0, atol=0)
        a = symmetry_angles(phi, code)[b]
        d = torch.remainder(a - it["phi"] + math.pi / 2, math.pi) - math.pi / 2
        assert float(d.abs().max()) < 1e-5
        assert 0 <= float(a[3]) < math.pi


@pytest.mark.parametrize("code", range(8))
def test_inverse_undoes_the_symmetry_on_non_square_maps(code):
    x = torch.arange(2 * 3 * 5 * 7, dtype=torch.float32).reshape(2, 3, 5, 7)
    y = symmetry_image(x, code)
    assert y.shape[-2:] == ((7, 5) if code & 4 else (5, 7))
    torch.testing.assert_close(symmetry_image(y, code, inverse=True), x, rtol=0, atol=0)


def _act(x, code):
    return None if x is None else symmetry_image(x, code)


@pytest.mark.parametrize("size,codes", [(8, range(8)), (4, range(4)), (2, (3,))])
@pytest.mark.parametrize("external_zeta", [False, True])
def test_ensemble_is_equivariant(size, codes, external_zeta):
    """Averaging over a group of symmetries makes the output of a random (not equivariant) network commute with
    every symmetry of that group: E(g x) = g E(x), on the learned and on an external zeta.  A wrong angle map
    (members that disagree with the group law) breaks it, and so does the bare network.
    """
    net = _net(1)
    I, phi = _window()
    zeta = (0.2 + 0.3 * torch.rand(I.shape, generator=torch.Generator().manual_seed(5))) if external_zeta else None
    kw = {"zeta_gt": zeta, "alpha": 1.0} if external_zeta else {}
    ens = SymmetryEnsemble(net, size)
    with torch.no_grad():
        base = ens(I, phi, **kw)
        for g in codes:
            kg = {"zeta_gt": _act(zeta, g), "alpha": 1.0} if external_zeta else {}
            out = ens(symmetry_image(I, g), symmetry_angles(phi, g), **kg)
            for k in ("T", "R"):
                torch.testing.assert_close(out.__dict__[k], symmetry_image(base.__dict__[k], g), rtol=1e-4, atol=1e-5)
        if size == 8:  # the bare network is not equivariant: the property above is the ensemble's
            o1 = net(symmetry_image(I, 1), symmetry_angles(phi, 1), **({"zeta_gt": _act(zeta, 1), "alpha": 1.0} if external_zeta else {}))
            o0 = net(I, phi, **kw)
            assert float((o1.T - symmetry_image(o0.T, 1)).abs().max()) > 1e-4


def test_wrong_angles_break_equivariance(monkeypatch):
    """The oracle has teeth: members that move the frames but not their polarizer angles disagree with the
    mirrored window (frames and angles moved, as flip_item moves them): E(g x) != g E(x).
    """
    import reconstruct.net.network as network

    net = _net(2)
    I, phi = _window(seed=3)
    moved = symmetry_angles(phi, 1)
    monkeypatch.setattr(network, "symmetry_angles", lambda p, code: p)  # the name SymmetryEnsemble calls
    ens = SymmetryEnsemble(net, 8)
    with torch.no_grad():
        base = ens(I, phi)
        out = ens(symmetry_image(I, 1), moved)
    assert float((out.T - symmetry_image(base.T, 1)).abs().max()) > 1e-4


def test_size_one_is_the_network_and_outputs_average():
    net = _net(3, use_mean=True)
    I, phi = _window(seed=4)
    Im = I.mean(1)
    with torch.no_grad():
        a, b = net(I, phi, I_mean=Im), SymmetryEnsemble(net, 1)(I, phi, I_mean=Im)
        torch.testing.assert_close(a.T, b.T, rtol=0, atol=0)
        two = SymmetryEnsemble(net, 2)(I, phi, I_mean=Im)
        r = net(symmetry_image(I, 3), symmetry_angles(phi, 3), I_mean=symmetry_image(Im, 3))
        torch.testing.assert_close(two.T, 0.5 * (a.T + symmetry_image(r.T, 3, inverse=True)), rtol=1e-5, atol=1e-6)
    assert SYMMETRY_CODES[2] == (0, 3)


def test_bad_size_and_features_are_errors():
    with pytest.raises(ConfigError, match="ensemble size 3: choose one of 1, 2, 4, 8"):
        SymmetryEnsemble(_net(), 3)
    ens = SymmetryEnsemble(_net(), 2)
    assert not ens.cacheable and ens.pad_multiple == ens.net.pad_multiple
    I, phi = _window()
    with pytest.raises(ConfigError, match="precomputed features"):
        ens(I, phi, feats=(torch.zeros(1), torch.zeros(1)))


def test_ensemble_runs_in_the_video_path():
    """run_model_on_windows with tiles: the ensemble goes through the tiled path (tiles are square or not) and its
    T is the mean of its members, each computed here as the single network run through the same tiled path on the
    mirrored window and mirrored back.  Measured: the members differ by up to 0.44 (an untrained network is far from
    equivariant), the ensemble is within 0.009 of their mean (tile borders fall on other pixels of a mirrored
    window); the bound 0.03 is 3x that and 7 % of the spread (an ensemble of one member, code 0 four times, is 0.44 off).
    """
    from reconstruct.stream.window_inputs import WindowInputs
    from reconstruct.video.tiling import run_model_on_windows

    net = _net(4)
    I, phi = _window(B=1, H=40, W=56, seed=6)
    ens = run_model_on_windows(SymmetryEnsemble(net, 4), WindowInputs(I.numpy(), phi.numpy()), tile=16, margin=16)
    members = []
    for code in SYMMETRY_CODES[4]:
        r = run_model_on_windows(net, WindowInputs(symmetry_image(I, code).numpy(), symmetry_angles(phi, code).numpy()), tile=16, margin=16)
        members.append(symmetry_image(torch.as_tensor(r["T"]), code, inverse=True).numpy())
    mean = np.mean(members, 0)
    assert ens["T"].shape == mean.shape and np.isfinite(ens["T"]).all()
    assert max(float(np.abs(m - mean).max()) for m in members) > 0.2  # the members do differ: the mean is a real check
    assert float(np.abs(ens["T"] - mean).max()) < 0.03


def test_cli_ensemble_usage_errors(tmp_path, polspike_cli, polspike_main):
    """Through the installed console script: an ensemble size outside 1, 2, 4, 8, and an ensemble for a physics
    solver, are one-line usage errors (exit 2), nothing written; the same for evaluate, evaluate-real and the bench.
    """
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(8 * 16 * 20))
    geo = ("--height", 16, "--width", 20, "--phi0-deg", 0, "--rev-per-s", 30)
    r = polspike_cli("reconstruct", f, *geo, "--ensemble", 3, "--out", tmp_path / "o")
    polspike_cli.one_line_exit_2(r, "--ensemble 3", "1, 2, 4, 8")
    r = polspike_cli("reconstruct", f, *geo, "--method", "rwps", "--ensemble", 2, "--out", tmp_path / "o")
    polspike_cli.one_line_exit_2(r, "--ensemble", "--method net")
    assert not (tmp_path / "o").exists()
    r = polspike_main("evaluate", tmp_path, "--method", "full", "--net-ensemble", 5, "--out", tmp_path / "e")
    polspike_main.one_line_exit_2(r, "net_ensemble")
    r = polspike_main("evaluate-real", tmp_path, "--ensemble", 6, "--out", tmp_path / "e")
    polspike_main.one_line_exit_2(r, "--ensemble 6")
    r = polspike_main("bench", "ensemble", "synthetic", "--sizes", "1,3", "--out", tmp_path / "b")
    polspike_main.one_line_exit_2(r, "--sizes: 3")
    assert not (tmp_path / "e").exists() and not (tmp_path / "b").exists()


def test_bench_ensemble_rows(tmp_path):
    """bench_ensemble: size 1 always runs first and is the evaluation's own network row; every size scores finite
    numbers; the table and the figure are written.
    """
    import dataclasses

    from reconstruct.evaluate.bench import bench_ensemble, ensemble_figure, ensemble_table
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups
    from reconstruct.net.checkpoint import V1_WEIGHTS
    from reconstruct.stream.synthetic import SyntheticConfig, make_group

    if not V1_WEIGHTS.is_file():
        pytest.skip("shipped v1 checkpoint not present")
    torch.set_num_threads(1)
    syn = SyntheticConfig(width=24, height=16, n_groups=1, n_frames=9, seed=4)
    groups = [make_group(syn, 0)]
    cfg = EvalConfig(zeta="gt", net_zeta="gt", rir=False, max_frames=1, checkpoint=str(V1_WEIGHTS))
    res = bench_ensemble(groups, cfg, (2,))
    assert [r["ensemble"] for r in res["rows"]] == [1, 2]
    rep = evaluate_groups(groups, dataclasses.replace(cfg, methods="full", figure_frames=0))
    own = next(r for r in rep.rows if r["group"] == "overall" and r["method"].startswith("full") and not r["method"].endswith(":solver"))
    assert res["rows"][0]["psnr_T"] == pytest.approx(own["psnr_T"]) and res["rows"][0]["time_ratio"] == pytest.approx(1.0)
    assert all(np.isfinite(r["psnr_T"]) and np.isfinite(r["ssim_T"]) and r["s_per_frame"] > 0 for r in res["rows"])
    md = ensemble_table(res)
    assert md.count("\n") == 4 and "| 2 |" in md
    ensemble_figure(res, tmp_path / "e.png")
    assert (tmp_path / "e.png").stat().st_size > 1000


def test_integer_choices_are_enforced_by_the_config_layer():
    """opt(choices=...) holds for integers as for strings (EvalConfig.net_ensemble, NetConfig.down)."""
    from polinfra.config import from_dict
    from reconstruct.evaluate.harness import EvalConfig

    assert from_dict(EvalConfig, {"net_ensemble": 4}).net_ensemble == 4
    with pytest.raises(ConfigError, match=r"net_ensemble = 3 is not allowed; choose one of \[1, 2, 4, 8\]"):
        from_dict(EvalConfig, {"net_ensemble": 3})
    with pytest.raises(ConfigError, match="down = 3 is not allowed"):
        from_dict(NetConfig, {"down": 3})


def test_cli_bench_ensemble_writes_json_table_and_plot(tmp_path, polspike_main):
    """`polspike bench ensemble` end to end on the closed-form set with the v1 checkpoint (no long-mean input):
    rows for 1 (the reference, always run) and 2, the table and the plot written.
    """
    import json

    from reconstruct.net.checkpoint import V1_WEIGHTS

    if not V1_WEIGHTS.is_file():
        pytest.skip("shipped v1 checkpoint not present")
    out = tmp_path / "b"
    r = polspike_main("bench", "ensemble", "synthetic:3", "--sizes", "2", "--zeta", "gt", "--checkpoint", V1_WEIGHTS, "--max-frames", 1, "--quiet", "--out", out)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((out / "ensemble.json").read_text())
    assert [row["ensemble"] for row in res["rows"]] == [1, 2]
    assert res["rows"][0]["time_ratio"] == pytest.approx(1.0) and res["rows"][1]["time_ratio"] > 0
    # the numbers derivable from the others: each size's time over size 1's, and the table shows the JSON's values
    one = res["rows"][0]["s_per_frame"]
    md = (out / "ensemble.md").read_text()
    for row in res["rows"]:
        assert row["s_per_frame"] > 0 and row["time_ratio"] == pytest.approx(row["s_per_frame"] / one, rel=1e-9)
        assert f"| {row['ensemble']} | {row['psnr_T']:.2f} | {row['ssim_T']:.3f} |" in md, md
        assert f"| {row['s_per_frame']:.3f} | {row['time_ratio']:.2f}x |" in md, md
    assert (out / "ensemble.png").stat().st_size > 1000


def test_ensemble_moves_a_fed_zeta_with_the_image():
    """zeta_feed is a map like zeta_gt: the ensemble of a network fed zeta_gt itself equals the ensemble fed nothing."""
    net = _net(5)
    I, phi = _window(seed=7)
    z = 0.2 + 0.3 * torch.rand(I.shape, generator=torch.Generator().manual_seed(8))
    ens = SymmetryEnsemble(net, 4)
    with torch.no_grad():
        a = ens(I, phi, zeta_gt=z, alpha=1.0)
        b = ens(I, phi, zeta_gt=z, alpha=1.0, zeta_feed=z)
    torch.testing.assert_close(a.T, b.T, rtol=0, atol=1e-6)
