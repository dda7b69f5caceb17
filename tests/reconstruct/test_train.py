"""Training: tiny run in seconds, curriculum, resume after a stop, determinism, on-the-fly items."""

from __future__ import annotations

import csv
import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from polspike.errors import CheckpointError, ConfigError
from reconstruct.checkpoint import load_model, read_checkpoint
from reconstruct.onthefly import ImageLayerProvider, OnTheFlyWindows, SceneSample, WindowConfig, make_item, window_count_model
from reconstruct.train import TINY, TrainConfig, alpha_at, train


def _images(n=4, size=64, seed=0):
    rng = np.random.default_rng(seed)
    return [np.clip(ndimage.gaussian_filter(rng.random((size, size)), 2) * 4 - 1.5, 0, 1) for _ in range(n)]


@pytest.fixture(scope="module")
def sets():
    prov = ImageLayerProvider(_images())
    return OnTheFlyWindows(prov, TINY.window, length=TINY.train_items, seed=1), OnTheFlyWindows(prov, TINY.window, length=TINY.val_items, seed=2)


def test_curriculum_paper_fractions():
    cfg = TrainConfig()  # 60 epochs: 1-5 alpha 1, 6-15 alpha 0.5, 16-60 alpha 0 (paper Sec. 3.4)
    assert [alpha_at(e, cfg) for e in (0, 4, 5, 14, 15, 59)] == [1.0, 1.0, 0.5, 0.5, 0.0, 0.0]


def test_onthefly_item_is_pure_function_of_seed_and_index(sets):
    tr, _ = sets
    a, b = tr[3], tr[3]
    for k in a:
        assert torch.equal(a[k], b[k])
    assert not torch.equal(tr[3]["I"], tr[4]["I"])
    it = tr[0]
    assert it["I"].shape == (7, 16, 16) and it["zeta"].shape == (7, 16, 16)
    assert torch.all((it["zeta"] >= 0) & (it["zeta"] <= 1))


def test_onthefly_noise_free_counts_match_eq1():
    """Static scene, no noise: I_k equals paper Eq. (1) up to the count quantisation 1/(n exposure)."""
    cfg = WindowConfig(exposure_range=(1.0, 1.0), noise_std=0.0)
    S = 4
    one = np.ones((S, S))
    sample = SceneSample(T=0.6 * one, R=0.9 * one, R_perp=0.3 * one, R_par=0.05 * one, phi_perp=0.2 * one, phi=np.linspace(0, 3, 7))
    it = make_item(sample, cfg, np.random.default_rng(0), window_count_model(0.0))
    sinc = math.sin(cfg.span_rad) / cfg.span_rad
    z = 0.175 + 0.125 * sinc * np.cos(2 * (np.linspace(0, 3, 7) - 0.2))
    want = 0.5 * (z * 0.9 + (1 - z) * 0.6)
    assert np.all(np.abs(it["I"].numpy()[:, 0, 0] - want) <= 1.0 / cfg.n_steps + 1e-6)
    np.testing.assert_allclose(it["zeta"].numpy()[:, 0, 0], z, rtol=1e-5)


def test_tiny_training_runs_and_writes_outputs(tmp_path, sets):
    tr, va = sets
    res = train(TINY, tr, va, tmp_path / "run")
    assert res["step"] == TINY.epochs * TINY.steps_per_epoch
    for f in ("last.pt", "log.csv", "config.json", "curves.png"):
        assert (tmp_path / "run" / f).is_file()
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert {float(r["alpha"]) for r in rows} == {1.0, 0.5, 0.0} or {float(r["alpha"]) for r in rows} >= {1.0, 0.0}
    assert any(r["val_psnr_T"] for r in rows)
    assert all(math.isfinite(float(r["loss"])) for r in rows if r["loss"])
    model, data = load_model(tmp_path / "run" / "last.pt")
    assert data["step"] == res["step"]


def test_resume_continues_to_identical_weights(tmp_path, sets):
    tr, va = sets
    train(TINY, tr, va, tmp_path / "a")
    r1 = train(TINY, tr, va, tmp_path / "b", stop_after=3)  # "killed" after step 3 (checkpointed)
    assert r1["step"] == 3
    assert read_checkpoint(tmp_path / "b" / "last.pt")["step"] == 3
    r2 = train(TINY, tr, va, tmp_path / "b")
    assert r2["step"] == TINY.epochs * TINY.steps_per_epoch
    a = read_checkpoint(tmp_path / "a" / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "b" / "last.pt")["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_deterministic_for_a_seed_and_different_across_seeds(tmp_path, sets):
    tr, va = sets
    cfg = dataclasses.replace(TINY, epochs=1)
    train(cfg, tr, va, tmp_path / "x")
    train(cfg, tr, va, tmp_path / "y")
    train(dataclasses.replace(cfg, seed=7), tr, va, tmp_path / "z")
    sx, sy, sz = (read_checkpoint(tmp_path / d / "last.pt")["state_dict"] for d in "xyz")
    assert all(torch.equal(sx[k], sy[k]) for k in sx)
    assert not all(torch.equal(sx[k], sz[k]) for k in sx)


def test_resume_with_other_config_is_refused(tmp_path, sets):
    tr, va = sets
    train(dataclasses.replace(TINY, epochs=1), tr, va, tmp_path / "r")
    with pytest.raises(CheckpointError):
        train(dataclasses.replace(TINY, epochs=1, lr=1e-3), tr, va, tmp_path / "r")


def test_checkpoint_errors(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_model(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable"):
        load_model(bad)
    other = tmp_path / "other.pt"
    torch.save({"format": "something/9"}, other)
    with pytest.raises(CheckpointError, match="format"):
        load_model(other)


def test_incompatible_checkpoint(tmp_path, sets):
    tr, va = sets
    train(dataclasses.replace(TINY, epochs=1), tr, va, tmp_path / "c")
    data = torch.load(tmp_path / "c" / "last.pt", weights_only=True)
    data["net"]["feat_ch"] = 16
    torch.save(data, tmp_path / "inc.pt")
    with pytest.raises(CheckpointError, match="do not fit"):
        load_model(tmp_path / "inc.pt")


def test_crop_must_be_multiple_of_4():
    with pytest.raises(ConfigError):
        OnTheFlyWindows(ImageLayerProvider(_images()), WindowConfig(crop=18))
