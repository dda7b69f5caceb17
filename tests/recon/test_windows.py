"""reconstruct/net/windows.py: dense training windows from stored spike groups (paper Sec. 3.5, Eq. (3))."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError, DataFormatError
from polphysics.polarizer import PolarizerConfig
from polphysics.zeta import mix_eq1, stokes_from_layers, zeta
from reconstruct.net.onthefly import ITEM_KEYS, WindowConfig, window_centres
from reconstruct.net.windows import StoreWindows, open_window_datasets
from spike_sim.config import DEFAULT, IDEAL
from spike_sim.simulate import keyframes_from_arrays, simulate
from spike_sim.store import open_group

H, W = 16, 24
CFG = WindowConfig(crop=8)


def make_group(path, *, seed=0, config=DEFAULT, moving=True, constant=None, duration=0.03, pol=None, store_zeta=False):
    """A tiny group simulated from an analytic source: Eq. (1)-(2) Stokes of random layers and maps."""
    rng = np.random.default_rng(seed)
    K = 4 if moving else 1
    times = np.linspace(0.0, duration, K)
    if constant is not None:
        T = np.full((K, H, W), constant, np.float32)
        R = np.zeros((K, H, W), np.float32)
    else:
        T = rng.uniform(0.2, 1.0, (K, H, W)).astype(np.float32)
        R = rng.uniform(0.2, 1.0, (K, H, W)).astype(np.float32)
    Rp = rng.uniform(0.05, 0.4, (H, W)).astype(np.float32)  # unique per pixel: crops can be located
    Rs = (Rp * rng.uniform(0.0, 0.5, (H, W))).astype(np.float32)
    pp = rng.uniform(0, np.pi, (H, W)).astype(np.float32)
    if constant is not None:
        Rp = np.zeros((H, W), np.float32)
        Rs = np.zeros((H, W), np.float32)
    maps = {"R_perp": Rp, "R_par": Rs, "phi_perp": pp, "T_perp": 1 - Rp, "T_par": 1 - Rs, "theta": np.full((H, W), 0.7, np.float32)}
    st = np.stack([stokes_from_layers(T[k], R[k], Rp, Rs, 1 - Rp, 1 - Rs, pp) for k in range(K)]).astype(np.float32)
    src = keyframes_from_arrays(times if K > 1 else [0.0], st, (T, R), maps, polarizer=pol or PolarizerConfig(phase_deg=7.0))
    simulate(src, duration, seed, dataclasses.replace(config, height=H, width=W), out=path, chunk_steps=128, store_zeta=store_zeta)
    return maps


@pytest.fixture(scope="module")
def group(tmp_path_factory):
    p = tmp_path_factory.mktemp("win") / "g0"
    maps = make_group(p, seed=1, pol=PolarizerConfig(phase_deg=7.0, jitter_deg=0.2, calibration_offset_deg=0.5))
    return p, maps


def _locate_crop(full: np.ndarray, crop: np.ndarray) -> tuple[int, int]:
    S = crop.shape[0]
    win = np.lib.stride_tricks.sliding_window_view(full, (S, S))
    hit = np.argwhere(np.all(win == crop[None, None], axis=(2, 3)))
    assert hit.shape == (1, 2), f"crop found {len(hit)} times"
    return int(hit[0, 0]), int(hit[0, 1])


def test_item_equals_eq3_recomputed_from_raw_spikes(group):
    path, maps = group
    ds = StoreWindows(path, CFG, split=None, seed=3)
    j = len(ds) // 3
    item = ds[j]
    gi, c = ds.locate(j)
    S = CFG.crop
    y0, x0 = _locate_crop(maps["R_perp"], item["R_perp"].numpy())
    with open_group(path) as g:
        spikes = g.read()  # (T, H, W) whole stream, by hand
        phi_nom, phi_tr = g.phi_nominal_rad, g.phi_true_rad
        exposure = g.json_attr("config_json")["exposure"]
        out_steps = g.array("output/step_index")
        gtT = np.stack([g.gt_frame("T", m) for m in range(out_steps.size)])
    n, h = 13, 6  # 0.65 ms at 20 kHz
    stride = math.radians(31.5)
    ck = [int(np.argmin(np.abs(phi_nom - (phi_nom[c] + k * stride)))) for k in range(-3, 4)]
    assert ck[3] == c
    I_hand = np.stack([spikes[q - h : q + h + 1, y0 : y0 + S, x0 : x0 + S].sum(0) / (n * exposure) for q in ck])  # paper Eq. (3)
    np.testing.assert_allclose(item["I"].numpy(), I_hand, rtol=0, atol=1e-6)
    phi_hand = np.array([phi_nom[q - h : q + h + 1].mean() for q in ck])
    d = item["phi"].numpy() - phi_hand
    np.testing.assert_allclose(d - d[0], 0.0, atol=1e-5)  # same angles up to a whole number of pi
    assert abs(d[0] / math.pi - round(d[0] / math.pi)) < 1e-5 and 0 <= item["phi"][3] < math.pi
    # zeta: paper Eq. (2) averaged over the true per-step angles of each window
    sl = (slice(y0, y0 + S), slice(x0, x0 + S))
    z_hand = np.stack([zeta(phi_tr[q - h : q + h + 1, None, None], maps["R_perp"][sl], maps["R_par"][sl], maps["phi_perp"][sl]).mean(0) for q in ck])
    np.testing.assert_allclose(item["zeta"].numpy(), z_hand, atol=2e-5)
    # T: linear interpolation in time between the stored GT frames
    T_hand = np.array([[np.interp(c, out_steps, gtT[:, y, x]) for x in range(x0, x0 + S)] for y in range(y0, y0 + S)])
    np.testing.assert_allclose(item["T"].numpy(), T_hand, atol=1e-3)  # float16-rounded
    for k in ("R_perp", "R_par", "phi_perp", "T_perp", "T_par"):
        np.testing.assert_array_equal(item[k].numpy(), maps[k][sl])
    assert float(item["exposure"]) == pytest.approx(exposure)


def test_window_centres_follow_the_angle():
    phi = np.linspace(0, 10, 1001)  # 0.01 rad per step
    c = window_centres(phi, 500, 7, 0.5)
    np.testing.assert_array_equal(c, 500 + 50 * np.arange(-3, 4))


def test_items_equal_the_on_the_fly_item_builder(group):
    """Keys, shapes, dtypes and values agree with reconstruct.net.onthefly.item_from_stream on the same stream."""
    from reconstruct.net import onthefly

    path, maps = group
    ds = StoreWindows(path, CFG, split=None, centre_every=17, crop="centre")
    S = CFG.crop
    y0, x0 = (H - S) // 2, (W - S) // 2
    sl = (slice(y0, y0 + S), slice(x0, x0 + S))
    with open_group(path) as g:
        spikes = g.read()[:, sl[0], sl[1]]
        out_steps = g.array("output/step_index")
        exposure = g.json_attr("config_json")["exposure"]
        for j in (0, len(ds) // 2, len(ds) - 1):
            item = ds[j]
            c = ds.locate(j)[1]
            m = int(np.searchsorted(out_steps, c, side="right") - 1)
            w = (c - out_steps[m]) / (out_steps[m + 1] - out_steps[m])
            gt = tuple((1 - w) * g.gt_frame(n, m)[sl] + w * g.gt_frame(n, m + 1)[sl] for n in ("T", "R"))
            obs = window_centres(g.phi_nominal_rad, c, CFG.n_obs, math.radians(CFG.stride_deg))
            ref = onthefly.item_from_stream(spikes, obs, g.phi_nominal_rad, g.phi_true_rad, gt, {k: v[sl] for k, v in maps.items()}, exposure, CFG)
            assert set(item) == set(ref) == set(onthefly.ITEM_KEYS) == set(ITEM_KEYS)
            for k in ref:
                assert item[k].shape == ref[k].shape and item[k].dtype == ref[k].dtype == torch.float32, k
                np.testing.assert_allclose(item[k].numpy(), ref[k].numpy(), atol=1e-6, err_msg=k)


def test_determinism_order_and_crops_in_bounds(group):
    path, maps = group
    a = StoreWindows(path, CFG, split=None, seed=5, shuffle=True, centre_every=7)
    b = StoreWindows(path, CFG, split=None, seed=5, shuffle=True, centre_every=7)
    c = StoreWindows(path, CFG, split=None, seed=6, shuffle=True, centre_every=7)
    assert [a.locate(i) for i in range(len(a))] == [b.locate(i) for i in range(len(b))]
    assert [a.locate(i) for i in range(len(a))] != [c.locate(i) for i in range(len(c))]
    for i in (0, 3, len(a) - 1):
        x, y = a[i], b[i]
        assert all(torch.equal(x[k], y[k]) for k in x)
    S = CFG.crop
    seen = set()
    for i in range(len(a)):
        y0, x0 = _locate_crop(maps["R_perp"], a[i]["R_perp"].numpy())
        assert 0 <= y0 <= H - S and 0 <= x0 <= W - S
        seen.add((y0, x0))
    assert len(seen) > 5  # crops vary
    # dense centres: every 7th step of the valid range, all windows inside the stream
    steps = sorted(a.locate(i)[1] for i in range(len(a)))
    assert np.all(np.diff(steps) == 7) and len(steps) > 20


def test_noise_free_constant_light_gives_the_expected_radiance(tmp_path):
    exposure = 0.7
    make_group(tmp_path / "c", config=dataclasses.replace(IDEAL, exposure=exposure), moving=False, constant=0.6)
    ds = StoreWindows(tmp_path / "c", dataclasses.replace(CFG, crop=16), split=None, centre_every=11, crop="centre")
    expected = 0.5 * 0.6  # unpolarized light behind an ideal polarizer, paper Eq. (1) with zeta = 0
    I = np.stack([ds[i]["I"].numpy() for i in range(len(ds))])
    assert np.abs(I - expected).max() <= 1 / (13 * exposure) + 1e-6  # one spike of quantisation per window
    assert abs(I.mean() - expected) < 0.01
    np.testing.assert_allclose(ds[0]["T"].numpy(), 0.6, atol=1e-3)


def test_noise_free_items_obey_eq1_with_their_own_zeta(tmp_path):
    exposure = 2.0
    make_group(tmp_path / "p", config=dataclasses.replace(IDEAL, exposure=exposure), moving=False, seed=4)
    ds = StoreWindows(tmp_path / "p", CFG, split=None, centre_every=13, seed=1)
    for i in range(0, len(ds), 3):
        it = ds[i]
        L = mix_eq1(it["R"].numpy()[None], it["T"].numpy()[None], it["zeta"].numpy())  # paper Eq. (1)
        assert np.abs(it["I"].numpy() - L).max() <= 1 / (13 * exposure) + 2e-3


def _dataset(tmp_path):
    make_group(tmp_path / "groups" / "a", seed=2, moving=False, duration=0.025)
    make_group(tmp_path / "groups" / "b", seed=3, moving=False, duration=0.025)
    (tmp_path / "dataset.json").write_text(json.dumps({"groups": [{"name": "a", "path": "groups/a", "split": "train"}, {"name": "b", "path": "groups/b", "split": "test"}]}))
    return tmp_path


def test_split_filtering_loader_workers_and_training(tmp_path):
    root = _dataset(tmp_path)
    tr = StoreWindows(root, CFG, split="train", centre_every=5)
    te = StoreWindows(root, CFG, split="test", centre_every=5)
    assert [g.name for g in tr.groups] == ["a"] and [g.name for g in te.groups] == ["b"]
    assert {tr.locate(i)[0] for i in range(len(tr))} == {0}
    with pytest.raises(DataFormatError):
        StoreWindows(root, CFG, split="val")
    with pytest.raises(ConfigError):
        StoreWindows(root, dataclasses.replace(CFG, crop=32), split="train")
    # DataLoader workers reopen the HDF5 files lazily and give the same items
    from reconstruct.net.train import TINY, collate, train

    dl = torch.utils.data.DataLoader(tr, batch_size=4, num_workers=2, collate_fn=collate, multiprocessing_context="fork")
    first = next(iter(dl))
    ref = collate([tr[i] for i in range(4)])
    assert all(torch.equal(first[k], ref[k]) for k in ref)
    # the trainer consumes stored windows (what `polspike train --data` builds)
    cfg = dataclasses.replace(TINY, epochs=1, steps_per_epoch=1, val_items=2, train_items=8)
    tr2, va2 = open_window_datasets(root, cfg)
    assert len(tr2) == 8 and len(va2) == 2 and [g.name for g in va2.groups] == ["b"]
    res = train(cfg, tr2, va2, tmp_path / "run")
    assert res["step"] == res["total_steps"] and math.isfinite(res["metrics"]["psnr_T"])


def test_output_mode_uses_the_stored_cadence(group):
    """centres="output": observation k of frame i is stored output frame i + k, as spike_sim.aggregate reads it."""
    from spike_sim.aggregate import aggregate_group

    path, _ = group
    ds = StoreWindows(path, CFG, split=None, centres="output", crop="centre")
    S = CFG.crop
    y0, x0 = (H - S) // 2, (W - S) // 2
    with open_group(path) as g:
        agg = aggregate_group(g)
        exposure = g.json_attr("config_json")["exposure"]
        np.testing.assert_array_equal(agg["centre_step"], g.array("output/step_index"))
    assert len(ds) == agg["centre_step"].size - 6
    for j in (0, len(ds) - 1):
        i = int(np.searchsorted(agg["centre_step"], ds.locate(j)[1]))
        ref = agg["I"][i - 3 : i + 4, y0 : y0 + S, x0 : x0 + S] / exposure
        np.testing.assert_allclose(ds[j]["I"].numpy(), ref, atol=1e-6)
