"""On-the-fly training windows (generator analytic tier -> spike_sim) equal stored windows for the same seed."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from polinfra.errors import ConfigError
from polspike.pipeline.train_windows import TEST_CONTENT, GeneratorWindows, sample_scene, scene_pool, train_content
from reconstruct.net.onthefly import ITEM_KEYS, OnTheFlyWindows, WindowConfig


@pytest.fixture(scope="module")
def source():
    return GeneratorWindows(scene_pool(2, 0, "train"), WindowConfig(crop=16, keyframe_hz=1000.0))


def test_item_is_a_pure_function_of_seed_and_index(source):
    a, b, c = source(3, 5), source(3, 5), source(3, 6)
    assert set(a) == set(ITEM_KEYS)
    for k in ITEM_KEYS:
        assert torch.equal(a[k], b[k]), k
    assert not torch.equal(a["I"], c["I"])
    assert a["I"].shape == (7, 16, 16) and a["phi"].shape == (7,) and a["T"].shape == (16, 16)
    assert torch.isfinite(a["I"]).all() and float(a["I"].min()) >= 0.0


def test_item_physics(source):
    """Observations follow paper Eq. (1)-(3): the mean of I over the window is close to the mix of the GT layers."""
    it = source(0, 1)
    assert 0.0 <= float(it["phi"][3]) < math.pi  # centre angle in [0, pi)
    stride = np.diff(it["phi"].numpy())
    np.testing.assert_allclose(stride, math.radians(31.5), atol=math.radians(0.6))  # 31.5 deg stride, +-1 step rounding
    z, T, R = it["zeta"], it["T"], it["R"]
    mix = 0.5 * (z * R + (1 - z) * T)  # paper Eq. (1), static approximation inside 21 ms
    err = float((it["I"].mean(0) - mix.mean(0)).abs().mean())
    assert err < 0.03, err  # quantisation of <= 13-spike windows, noise, ~1 px motion
    assert float(z.min()) >= 0.0 and float(z.max()) <= 1.0
    assert torch.all(z >= torch.minimum(it["R_perp"], it["R_par"]) - 1e-6)
    assert torch.all(z <= torch.maximum(it["R_perp"], it["R_par"]) + 1e-6)


def test_train_and_test_content_are_disjoint():
    assert not set(train_content()) & set(TEST_CONTENT)
    rng = np.random.default_rng(0)
    for _ in range(5):
        s = sample_scene(rng, TEST_CONTENT)
        assert s.layers.transmission.source in TEST_CONTENT and s.layers.reflection.source in TEST_CONTENT
        assert s.layers.transmission.source != s.layers.reflection.source


def test_onthefly_item_equals_stored_item(source, tmp_path):
    """The window group of item (seed, i) built as a store and read by reconstruct.net.windows gives the same item."""
    windows = pytest.importorskip("reconstruct.net.windows")
    from spike_sim.aggregate import AggregateConfig
    from spike_sim.simulate import simulate

    seed, index = 7, 2
    w = source.window
    item = source(seed, index)
    g = source.window_group(seed, index)
    agg = AggregateConfig(window_steps=w.window_steps, stride_deg=w.stride_deg, n_obs=w.n_obs)
    simulate(g["source"], g["duration_s"], g["seed"], g["config"], out=tmp_path / "g", aggregate=agg, chunk_steps=97)
    ds = windows.StoreWindows(tmp_path / "g", w, split=None, centres="output", crop="centre")
    # the on-the-fly item is centred on the middle output frame of its window group
    cands = [j for j in range(len(ds)) if torch.equal(ds[j]["phi"], item["phi"])]
    assert len(cands) == 1
    stored = ds[cands[0]]
    assert set(stored) == set(item)
    for k in ITEM_KEYS:
        assert stored[k].shape == item[k].shape, k
        assert torch.allclose(stored[k], item[k], rtol=0, atol=1e-6), (k, float((stored[k] - item[k]).abs().max()))


def test_dataset_wraps_source(source):
    ds = OnTheFlyWindows(source, length=4, seed=1)
    assert len(ds) == 4
    assert torch.equal(ds[2]["I"], source(1, 2)["I"])
    with pytest.raises(IndexError):
        ds[4]


def test_manifest_scenes_and_cli_train_then_evaluate(tmp_path):
    """`polspike train` on the fly from a manifest's train groups, then `evaluate-checkpoint` on its test groups."""
    import json

    from typer.testing import CliRunner

    from polspike.cli import get_app
    from polspike.pipeline.train_windows import manifest_scenes

    man = str(Path(__file__).resolve().parents[2] / "datasets" / "manifests" / "small.toml")
    tr, te = manifest_scenes(man, "train"), manifest_scenes(man, "test")
    assert len(tr) == 2 and len(te) == 1
    assert tr[0].render.duration_s == pytest.approx(0.05)
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(
        f'epochs = 1\nsteps_per_epoch = 2\nbatch_size = 2\nval_items = 2\nmanifest = "{man}"\n'
        "[net]\nfeat_ch = 8\nref_ch = [8, 8, 8]\ndec_ch = [8, 8, 8]\nuse_rir = false\n[window]\ncrop = 16\nkeyframe_hz = 1000.0\n"
    )
    app = get_app()
    # in-process (CliRunner): this pytest process has run OpenMP already, so no forked data worker
    # (the worker path is tested in tests/recon/test_train.py with forkserver)
    r = CliRunner().invoke(app, ["train", str(cfg), "--out", str(tmp_path / "run"), "--threads", "1", "--workers", "0", "--quiet"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "run" / "last.pt").is_file()
    r = CliRunner().invoke(app, ["evaluate-checkpoint", str(tmp_path / "run" / "last.pt"), "--manifest", man, "--items", "2", "--crop", "16", "--threads", "1", "--out", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "ev" / "scores.json").read_text())["metrics"]
    assert {"psnr_T", "psnr_T_base", "psnr_R", "ssim_T", "ssim_T_base"} <= set(m)
    assert all(np.isfinite(v) for v in m.values())


def test_group_sensor_light_level_and_flips():
    """exposure_source = "group": each item's exposure is its manifest group's (the group's light level)
    times a factor inside exposure_jitter; the group's sensor preset is used; flips keep items pure.
    """
    from polinfra.errors import SceneError
    from polspike.pipeline.train_windows import manifest_scenes

    man = str(Path(__file__).resolve().parents[2] / "datasets" / "manifests" / "small.toml")
    scenes, sims = manifest_scenes(man, "train", with_sensor=True)
    sims = [dataclasses.replace(s, exposure=e) for s, e in zip(sims, (0.05, 3.0))]  # two very different light levels
    w = WindowConfig(crop=16, keyframe_hz=1000.0, sim_preset="group", exposure_source="group", exposure_jitter=(0.8, 1.25), flips=True)
    src = GeneratorWindows(scenes, w, sims=sims)
    seen = set()
    for i in range(6):
        g = src.window_group(0, i)
        base = sims[g["scene"]].exposure
        assert base * 0.8 - 1e-9 <= g["config"].exposure <= base * 1.25 + 1e-9
        assert dataclasses.replace(g["config"], width=0, height=0, exposure=0.0) == dataclasses.replace(sims[g["scene"]], width=0, height=0, exposure=0.0)  # the group's sensor
        seen.add(g["scene"])
    assert seen == {0, 1}
    a, b = src(0, 2), src(0, 2)
    assert all(torch.equal(a[k], b[k]) for k in ITEM_KEYS)
    assert float(a["exposure"]) == pytest.approx(src.window_group(0, 2)["config"].exposure)
    with pytest.raises(SceneError, match="manifest sensor"):
        GeneratorWindows(scenes, w)


def test_bright_prob_redraws_the_light_level_and_leaves_other_items_alone():
    """window.bright_prob: that share of the items takes a light level drawn in bright_rate spikes per pixel per
    step by the sampler's formula (exposure = rate / (0.5 * content mean * T brightness)); the rest are the
    items of the same config without it, draw for draw, so older configs keep their windows.
    """
    from polspike.pipeline.sampler import NOMINAL_CONTENT_MEAN
    from polspike.pipeline.train_windows import manifest_scenes

    man = str(Path(__file__).resolve().parents[2] / "datasets" / "manifests" / "small.toml")
    scenes, sims = manifest_scenes(man, "train", with_sensor=True)
    sims = [dataclasses.replace(s, exposure=0.05) for s in sims]  # dim groups: 0.05 * 0.5 * 0.25 * b <= 0.00625 spikes/px/step
    kw = dict(crop=16, keyframe_hz=1000.0, sim_preset="group", exposure_source="group", exposure_jitter=(0.8, 1.25))
    plain = GeneratorWindows(scenes, WindowConfig(**kw), sims=sims)
    bright = GeneratorWindows(scenes, WindowConfig(**kw, bright_prob=0.5, bright_rate=(0.05, 0.2)), sims=sims)
    n_bright = 0
    for i in range(40):
        g, p = bright.window_group(3, i), plain.window_group(3, i)
        assert (g["scene"], g["t0_s"], g["crop"]) == (p["scene"], p["t0_s"], p["crop"])
        rate = g["config"].exposure * 0.5 * NOMINAL_CONTENT_MEAN * scenes[g["scene"]].layers.transmission.brightness
        if g["config"].exposure == p["config"].exposure:
            assert rate < 0.01
        else:
            assert 0.05 - 1e-9 <= rate <= 0.2 + 1e-9
            n_bright += 1
    assert 10 <= n_bright <= 30  # binomial(40, 0.5): outside this with probability < 0.2 %
    with pytest.raises(ConfigError, match="exposure_source"):
        WindowConfig(crop=16, bright_prob=0.3)
    with pytest.raises(ConfigError, match="low <= high"):
        WindowConfig(**kw, bright_prob=0.3, bright_rate=(0.3, 0.03))


def test_mix_manifests_join_the_train_groups_only():
    """mix_manifests: the training windows draw from manifest's train groups and each mixed manifest's, no test
    group joins, and a mix without a manifest is refused.
    """
    from polspike.pipeline.train_windows import manifest_scenes, window_sets

    root = Path(__file__).resolve().parents[2] / "datasets" / "manifests"
    man, extra = str(root / "small.toml"), str(root / "paper_val.toml")
    w = WindowConfig(crop=16, keyframe_hz=1000.0, sim_preset="group", exposure_source="group")
    tr, _ = window_sets(w, 4, 2, 0, manifest=man, mix_manifests=(extra,))
    want = [repr(s) for s in manifest_scenes(man, "train") + manifest_scenes(extra, "train")]
    assert [repr(s) for s in tr.source.scenes] == want
    assert len(tr.source.sims) == len(want)
    drawn = {tr.source.window_group(0, i)["scene"] for i in range(60)}
    assert drawn & set(range(len(manifest_scenes(man, "train")), len(want)))  # the mixed groups are drawn
    with pytest.raises(ConfigError, match="set manifest"):
        window_sets(w, 4, 2, 0, mix_manifests=(extra,))


def test_validation_from_another_manifest_never_draws_the_test_groups():
    """val_manifest: the validation windows come from that manifest's val_split groups, not the test groups."""
    from polspike.pipeline.train_windows import manifest_scenes, window_sets

    root = Path(__file__).resolve().parents[2] / "datasets" / "manifests"
    man, val = str(root / "small.toml"), str(root / "paper_val.toml")
    w = WindowConfig(crop=16, keyframe_hz=1000.0)
    _, te = window_sets(w, 4, 2, 0, manifest=man)
    _, va = window_sets(w, 4, 2, 0, manifest=man, val_manifest=val, val_split="train")
    key = lambda sc: repr(sc)  # noqa: E731  (scenes are frozen dataclasses: equal draws give equal reprs)
    assert [key(s) for s in te.source.scenes] == [key(s) for s in manifest_scenes(man, "test")]
    assert [key(s) for s in va.source.scenes] == [key(s) for s in manifest_scenes(val, "train")]
    assert not {key(s) for s in va.source.scenes} & {key(s) for s in manifest_scenes(man, "test")}
