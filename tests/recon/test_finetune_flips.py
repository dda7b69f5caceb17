"""Training knobs: mirror / transpose augmentation with the angles carried along (checked
against paper Eq. (2) recomputed on the mirrored inputs), fine-tuning from given weights, best.pt.
"""

from __future__ import annotations

import csv
import dataclasses
import math

import numpy as np
import pytest
import torch

from polinfra.errors import CheckpointError, ConfigError
from reconstruct.net.checkpoint import read_checkpoint, save_checkpoint
from reconstruct.net.network import NetConfig, PolSpikeNet
from reconstruct.net.onthefly import OnTheFlyWindows, WindowConfig, flip_item, item_from_stream
from reconstruct.net.train import TINY, train

RATE_HZ, POL_HZ = 20000.0, 30.0
CFG = WindowConfig(crop=12, n_obs=5, window_steps=9)

_OPS = {1: (np.fliplr, np.array([[-1, 0], [0, 1]])), 2: (np.flipud, np.array([[1, 0], [0, -1]])), 4: (lambda a: a.T, np.array([[0, 1], [1, 0]]))}
"""Each symmetry bit: the array operation on an (H, W) image and its matrix on (x = column, y = row) vectors."""


def _spatial(a: np.ndarray, code: int) -> np.ndarray:
    for bit in (1, 2, 4):
        if code & bit:
            a = np.stack([_OPS[bit][0](x) for x in a]) if a.ndim == 3 else _OPS[bit][0](a)
    return np.ascontiguousarray(a)


def _angle(a: np.ndarray, code: int) -> np.ndarray:
    """Axis direction at angle a, moved by the symmetry's matrix: atan2 of the image of (cos a, sin a)."""
    v = np.stack([np.cos(a), np.sin(a)])
    for bit in (1, 2, 4):
        if code & bit:
            v = np.tensordot(_OPS[bit][1], v, axes=1)
    return np.arctan2(v[1], v[0])


def _inputs(seed: int):
    """A random stream with spatially varying pane maps (so a wrong flip of phi_perp shows in zeta)."""
    rng = np.random.default_rng(seed)
    S = CFG.crop
    n = 400
    phi = rng.uniform(0, np.pi) + 2 * np.pi * POL_HZ * (np.arange(n) + 0.5) / RATE_HZ
    yy, xx = np.mgrid[0:S, 0:S] / S
    maps = {"R_perp": 0.1 + 0.2 * xx, "R_par": 0.02 * yy, "phi_perp": 0.3 + 1.2 * xx + 0.5 * yy**2}
    spikes = (rng.random((n, S, S)) < 0.3).astype(np.uint8)
    T, R = rng.random((S, S)), rng.random((S, S))
    ck = 40 + np.arange(CFG.n_obs) * 60
    return spikes, ck, phi, phi + 0.01, (T, R), maps


@pytest.mark.parametrize("code", range(8))
def test_flip_equals_the_item_of_the_mirrored_scene(code):
    """flip_item(item(scene)) == item(mirrored scene): the item of the mirrored inputs recomputes zeta by
    paper Eq. (2) from mirrored polarizer angles and a mirrored phi_perp map.
    """
    spikes, ck, phn, pht, (T, R), maps = _inputs(code)
    a = flip_item(item_from_stream(spikes, ck, phn, pht, (T, R), maps, 1.3, CFG), code)
    mm = {k: _spatial(_angle(v, code) if k == "phi_perp" else v, code) for k, v in maps.items()}
    u = lambda p: np.unwrap(_angle(p, code))  # noqa: E731  (per-step angle series stay continuous)
    b = item_from_stream(_spatial(spikes, code), ck, u(phn), u(pht), (_spatial(T, code), _spatial(R, code)), mm, 1.3, CFG)
    for k in ("I", "T", "R", "zeta", "R_perp", "R_par", "exposure"):
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=2e-6, msg=k)
    d = torch.remainder(a["phi"] - b["phi"] + math.pi / 2, math.pi) - math.pi / 2  # phi: same angles (mod pi)
    assert float(d.abs().max()) < 1e-5
    assert 0 <= float(a["phi"][len(a["phi"]) // 2]) < math.pi
    dp = torch.remainder(a["phi_perp"] - b["phi_perp"] + math.pi / 2, math.pi) - math.pi / 2
    assert float(dp.abs().max()) < 1e-5


def test_a_wrong_angle_map_would_show():
    """The oracle has teeth: an image mirror that kept the polarizer angles (or phi_perp) as they were
    disagrees with the mirrored scene's angles far beyond the tolerance.
    """
    spikes, ck, phn, pht, (T, R), maps = _inputs(0)
    it = item_from_stream(spikes, ck, phn, pht, (T, R), maps, 1.3, CFG)
    mm = {k: _spatial(_angle(v, 1) if k == "phi_perp" else v, 1) for k, v in maps.items()}
    u = lambda p: np.unwrap(_angle(p, 1))  # noqa: E731
    b = item_from_stream(_spatial(spikes, 1), ck, u(phn), u(pht), (_spatial(T, 1), _spatial(R, 1)), mm, 1.3, CFG)
    d = torch.remainder(it["phi"] - b["phi"] + math.pi / 2, math.pi) - math.pi / 2
    assert float(d.abs().max()) > 0.1
    dp = torch.remainder(it["phi_perp"].flip(-1) - b["phi_perp"] + math.pi / 2, math.pi) - math.pi / 2
    assert float(dp.abs().max()) > 0.1


def test_flip_code_checked():
    it = item_from_stream(*_inputs(0)[:6], 1.0, CFG)
    assert flip_item(it, 0) is it
    with pytest.raises(ConfigError, match="0..7"):
        flip_item(it, 8)


def test_window_config_group_sensor_checks():
    with pytest.raises(ConfigError, match="go together"):
        WindowConfig(sim_preset="group")
    with pytest.raises(ConfigError, match="low <= high"):
        WindowConfig(sim_preset="group", exposure_source="group", exposure_jitter=(2.0, 1.0))


def _item(seed: int, index: int):
    rng = np.random.default_rng([seed, index])
    S = TINY.window.crop
    T, R = torch.rand(S, S, generator=torch.Generator().manual_seed(index)), torch.rand(S, S, generator=torch.Generator().manual_seed(index + 1))
    z = torch.full((7, S, S), 0.2)
    phi = torch.tensor(np.arange(7) * math.radians(31.5) + rng.uniform(0, 0.5), dtype=torch.float32)
    zeta = z * (1 + 0.5 * torch.cos(2 * phi))[:, None, None]
    I = 0.5 * (zeta * R + (1 - zeta) * T)
    return {"I": I, "phi": phi, "T": T, "R": R, "zeta": zeta}


def _saved_source(tmp_path):
    """A TINY network with random weights saved as src.pt, and small train / validation sets."""
    torch.set_num_threads(1)
    src = PolSpikeNet(TINY.net, TINY.solver)
    for p in src.parameters():
        torch.nn.init.normal_(p, 0.0, 0.01)
    save_checkpoint(tmp_path / "src.pt", src)
    return src, (OnTheFlyWindows(_item, length=16, seed=0), OnTheFlyWindows(_item, length=2, seed=1))


def test_init_from_loads_the_weights_and_refuses_another_architecture(tmp_path):
    src, sets = _saved_source(tmp_path)
    cfg = dataclasses.replace(TINY, init_from=str(tmp_path / "src.pt"))
    train(cfg, *sets, tmp_path / "run", stop_after=0)
    got = read_checkpoint(tmp_path / "run" / "last.pt")["state_dict"]
    for k, v in src.state_dict().items():
        assert torch.equal(got[k], v), k
    other = dataclasses.replace(cfg, net=NetConfig(feat_ch=4, lr_ch=4, w_ch=4, ref_ch=(4, 4, 4), dec_ch=(4, 4, 4), use_rir=False))
    with pytest.raises(CheckpointError, match="same architecture"):
        train(other, *sets, tmp_path / "run2", stop_after=0)


def test_init_zero_restarts_the_named_parameters_and_refuses_unknown_names(tmp_path):
    src, sets = _saved_source(tmp_path)
    cfg = dataclasses.replace(TINY, init_from=str(tmp_path / "src.pt"), init_zero=("refine.dec_t.out",))
    train(cfg, *sets, tmp_path / "run", stop_after=0)
    got = read_checkpoint(tmp_path / "run" / "last.pt")["state_dict"]
    for k, v in src.state_dict().items():
        if k.startswith("refine.dec_t.out"):
            assert float(got[k].abs().max()) == 0.0, k
        else:
            assert torch.equal(got[k], v), k
    with pytest.raises(CheckpointError, match="names no parameter"):
        train(dataclasses.replace(cfg, init_zero=("refine.nothing",)), *sets, tmp_path / "run2", stop_after=0)


def test_forced_zeta_steps_are_drawn_from_the_seed_and_logged(tmp_path):
    """force_prob = 1: every step after the curriculum runs on the (jittered) true zeta, logged as alpha = 1;
    force_prob = 0 leaves the curriculum's alpha.
    """
    torch.set_num_threads(1)
    sets = OnTheFlyWindows(_item, length=16, seed=0), OnTheFlyWindows(_item, length=2, seed=1)
    base = dataclasses.replace(TINY, curriculum_fracs=(0.0, 0.0), log_every=1)
    for prob, want in ((1.0, 1.0), (0.0, 0.0)):
        run = tmp_path / f"run{prob}"
        train(dataclasses.replace(base, force_prob=prob, zeta_jitter=0.2), *sets, run, stop_after=3)
        alphas = {float(r["alpha"]) for r in csv.DictReader(open(run / "log.csv")) if r.get("loss")}
        assert alphas == {want}


def test_best_checkpoint_is_the_best_validation_row(tmp_path):
    torch.set_num_threads(1)
    sets = OnTheFlyWindows(_item, length=64, seed=0), OnTheFlyWindows(_item, length=4, seed=1)
    cfg = dataclasses.replace(TINY, epochs=6, val_every=2)
    res = train(cfg, *sets, tmp_path / "run")
    rows = [r for r in csv.DictReader(open(tmp_path / "run" / "log.csv")) if r["val_psnr_T"]]
    assert len(rows) >= 3
    top = max(rows, key=lambda r: float(r["val_psnr_T"]))  # first maximum: later ties do not replace it
    b = read_checkpoint(tmp_path / "run" / "best.pt")
    assert b["step"] == int(top["step"]) == res["best"]["step"]
    assert b["metrics"]["psnr_T"] == pytest.approx(float(top["val_psnr_T"]), abs=1e-4)


def test_val_select_mean_scores_both_zeta_paths_and_picks_best_by_their_mean(tmp_path):
    torch.set_num_threads(1)
    sets = OnTheFlyWindows(_item, length=64, seed=0), OnTheFlyWindows(_item, length=4, seed=1)
    cfg = dataclasses.replace(TINY, epochs=6, val_every=2, val_select="mean")
    res = train(cfg, *sets, tmp_path / "run")
    rows = [r for r in csv.DictReader(open(tmp_path / "run" / "log.csv")) if r["val_psnr_T"]]
    assert len(rows) >= 3
    for r in rows:
        assert float(r["val_score"]) == pytest.approx(0.5 * (float(r["val_psnr_T"]) + float(r["val_psnr_T_forced"])), abs=2e-4)
    top = max(rows, key=lambda r: float(r["val_score"]))
    assert read_checkpoint(tmp_path / "run" / "best.pt")["step"] == int(top["step"]) == res["best"]["step"]
