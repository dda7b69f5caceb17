"""Training: tiny run in seconds, curriculum, resume after a stop, determinism, on-the-fly items."""

from __future__ import annotations

import csv
import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from polinfra.errors import CheckpointError, ConfigError
from reconstruct.net.checkpoint import load_model, read_checkpoint
from reconstruct.net.inference import native_bf16
from reconstruct.net.onthefly import ITEM_KEYS, OnTheFlyWindows, WindowConfig, item_from_stream
from reconstruct.net.train import TINY, TrainConfig, alpha_at, train

RATE_HZ = 20000.0
POL_HZ = 30.0
#: TINY with curriculum stage ends at 1/4 and 1/2 of its 4 epochs, so the short run passes through all
#: three stages (alpha 1.0, 0.5, 0.0, 0.0); with the paper's fractions (5/60, 15/60) a 4-epoch run
#: jumps from alpha 1.0 straight to 0.0 and the alpha = 0.5 stage would go untested.
CFG = dataclasses.replace(TINY, curriculum_fracs=(0.25, 0.5))

pytestmark = pytest.mark.usefixtures("one_thread")


def _stream_item(seed: int, index: int, cfg: WindowConfig = TINY.window, static: bool = False, noise: bool = True):
    """A window item from a closed-form integrate-and-fire stream (no generator): smooth random layers,
    uniform pane maps, paper Eq. (1)-(2) light behind an ideal polarizer at 30 rev/s, sampled at step
    midpoints; spikes = increments of floor(u + cumsum g) (exact noise-free integrate-and-fire).
    """
    from spike_sim.aggregate import AggregateConfig, frame_centres

    rng = np.random.default_rng([seed, index])
    S, N = cfg.crop, cfg.n_obs
    n = int(np.ceil((N + 1) * cfg.stride_deg / 360 / POL_HZ * RATE_HZ + cfg.window_steps))
    T = np.clip(ndimage.gaussian_filter(rng.random((S, S)), 2) * 4 - 1.5, 0, 1) * rng.uniform(0.4, 1.0)
    R = np.clip(ndimage.gaussian_filter(rng.random((S, S)), 2) * 4 - 1.5, 0, 1) * rng.uniform(0.3, 1.0)
    Rp, Rs, pp = np.full((S, S), rng.uniform(0.1, 0.4)), np.full((S, S), rng.uniform(0.0, 0.05)), np.full((S, S), rng.uniform(0, np.pi))
    phase = rng.uniform(0, 2 * np.pi)
    phi = phase + 2 * np.pi * POL_HZ * (np.arange(n) + 0.5) / RATE_HZ
    zeta = Rp[None] * np.cos(phi[:, None, None] - pp[None]) ** 2 + Rs[None] * np.sin(phi[:, None, None] - pp[None]) ** 2  # paper Eq. (2)
    exposure = 1.0 if static else rng.uniform(1.0, 1.8)
    g = np.clip(exposure * 0.5 * (zeta * R[None] + (1 - zeta) * T[None]), 0, 1)  # paper Eq. (1), thresholds per step
    u = rng.random((S, S)) if noise else np.zeros((S, S))
    V = np.floor(u[None] + np.cumsum(g, 0))
    spikes = np.diff(np.concatenate([np.floor(u)[None], V]), axis=0).astype(np.uint8)
    agg = AggregateConfig(window_steps=cfg.window_steps, stride_deg=cfg.stride_deg, n_obs=N)
    c, _ = frame_centres(phi, agg, phi_start_rad=phase)
    m = len(c) // 2
    ck = c[m - N // 2 : m + N // 2 + 1]
    return item_from_stream(spikes, ck, phi, phi, (T, R), {"R_perp": Rp, "R_par": Rs, "phi_perp": pp}, exposure, cfg)


@pytest.fixture(scope="module")
def sets():
    return OnTheFlyWindows(_stream_item, length=CFG.train_items, seed=1), OnTheFlyWindows(_stream_item, length=CFG.val_items, seed=2)


@pytest.fixture(scope="module")
def tiny_run(sets, tmp_path_factory):
    """One uninterrupted CFG run, shared by several tests."""
    tr, va = sets
    run = tmp_path_factory.mktemp("tiny") / "run"
    return run, train(CFG, tr, va, run)


def test_curriculum_paper_fractions():
    cfg = TrainConfig()  # 60 epochs: 1-5 alpha 1, 6-15 alpha 0.5, 16-60 alpha 0 (paper Sec. 3.4)
    assert [alpha_at(e, cfg) for e in (0, 4, 5, 14, 15, 59)] == [1.0, 1.0, 0.5, 0.5, 0.0, 0.0]


def test_onthefly_item_is_pure_function_of_seed_and_index(sets):
    tr, _ = sets
    a, b = tr[3], tr[3]
    assert set(a) == set(ITEM_KEYS)
    for k in a:
        assert torch.equal(a[k], b[k])
    assert not torch.equal(tr[3]["I"], tr[4]["I"])
    it = tr[0]
    assert it["I"].shape == (7, 16, 16) and it["zeta"].shape == (7, 16, 16)
    assert torch.all((it["zeta"] >= 0) & (it["zeta"] <= 1))


def test_item_from_stream_matches_eq1_to_count_quantisation():
    """Static scene, noise-free integrate-and-fire: I_k equals paper Eq. (1) with the window-averaged
    zeta of paper Eq. (2) up to one spike per window, 1/13 per exposure.
    """
    cfg = WindowConfig(crop=16)
    it = _stream_item(0, 0, cfg, static=True, noise=False)
    mix = 0.5 * (it["zeta"] * it["R"][None] + (1 - it["zeta"]) * it["T"][None])
    err = (it["I"] - mix).abs()
    assert float(err.max()) <= 1.0 / cfg.window_steps + 2e-3  # T, R stored as float16
    assert float(err.mean()) < 0.5 / cfg.window_steps
    d = np.diff(it["phi"].numpy())
    np.testing.assert_allclose(d, math.radians(31.5), atol=2 * math.pi * POL_HZ / RATE_HZ)  # stride to +-1 step
    assert 0 <= float(it["phi"][3]) < math.pi


def test_tiny_training_runs_and_writes_outputs(tiny_run):
    run, res = tiny_run
    tmp_path = run.parent
    assert res["step"] == CFG.epochs * CFG.steps_per_epoch
    for f in ("last.pt", "log.csv", "config.json", "curves.png"):
        assert (tmp_path / "run" / f).is_file()
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    # the curriculum: every epoch logs alpha_at(epoch), and the run passes through all three stages
    by_epoch = {int(r["epoch"]): float(r["alpha"]) for r in rows}
    assert by_epoch == {e + 1: alpha_at(e, CFG) for e in range(CFG.epochs)} == {1: 1.0, 2: 0.5, 3: 0.0, 4: 0.0}
    assert any(r["val_psnr_T"] for r in rows)
    assert all(math.isfinite(float(r["loss"])) for r in rows if r["loss"])
    model, data = load_model(tmp_path / "run" / "last.pt")
    assert data["step"] == res["step"]


def test_resume_continues_to_identical_weights(tmp_path, sets, tiny_run):
    tr, va = sets
    r1 = train(CFG, tr, va, tmp_path / "b", stop_after=3)  # "killed" after step 3 (checkpointed)
    assert r1["step"] == 3
    assert read_checkpoint(tmp_path / "b" / "last.pt")["step"] == 3
    r2 = train(CFG, tr, va, tmp_path / "b")
    assert r2["step"] == CFG.epochs * CFG.steps_per_epoch
    a = read_checkpoint(tiny_run[0] / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "b" / "last.pt")["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_kill_9_during_a_checkpoint_write_resumes_to_identical_weights(tmp_path, tiny_run, caplog):
    """A real SIGKILL while the second checkpoint (step 4) is being written (polinfra.faults point
    ``atomic:last.pt@2``: the new file complete under its temporary name, not yet renamed): the old
    checkpoint stays readable, and the rerun continues to the weights and log of the uninterrupted run.
    """
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    run = tmp_path / "killed"
    script = tmp_path / "train_tiny.py"
    script.write_text(
        "import importlib.util, sys, torch\n"
        "torch.set_num_threads(1)\n"
        f"spec = importlib.util.spec_from_file_location('train_items', {str(Path(__file__))!r})\n"
        "mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)\n"
        "from reconstruct.net.onthefly import OnTheFlyWindows\n"
        "from reconstruct.net.train import train\n"
        "tr = OnTheFlyWindows(mod._stream_item, length=mod.CFG.train_items, seed=1)\n"
        "va = OnTheFlyWindows(mod._stream_item, length=mod.CFG.val_items, seed=2)\n"
        "train(mod.CFG, tr, va, sys.argv[1])\n"
        "print('finished')\n"
    )
    env = {**os.environ, "POLSPIKE_FAULT_AT": "atomic:last.pt@2", "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, str(script), str(run)], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == -signal.SIGKILL and "finished" not in r.stdout, (r.returncode, r.stderr[-1500:])
    assert read_checkpoint(run / "last.pt")["step"] == CFG.ckpt_every  # the first checkpoint, intact
    assert list(run.glob(".last.tmp-*")), "the killed write leaves its temporary file, never a torn last.pt"
    tr, va = OnTheFlyWindows(_stream_item, length=CFG.train_items, seed=1), OnTheFlyWindows(_stream_item, length=CFG.val_items, seed=2)
    import logging

    with caplog.at_level(logging.INFO, logger="reconstruct.net.train"):
        res = train(CFG, tr, va, run)
    assert f"at step {CFG.ckpt_every}/{CFG.epochs * CFG.steps_per_epoch}" in caplog.text  # continued, not restarted
    assert res["step"] == CFG.epochs * CFG.steps_per_epoch
    a = read_checkpoint(tiny_run[0] / "last.pt")["state_dict"]
    b = read_checkpoint(run / "last.pt")["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    strip = lambda rows: [{k: v for k, v in row.items() if k != "seconds"} for row in rows]  # noqa: E731
    assert strip(csv.DictReader(open(run / "log.csv"))) == strip(csv.DictReader(open(tiny_run[0] / "log.csv")))


def test_loader_worker_gives_the_same_trajectory(tmp_path, sets, tiny_run):
    """Batches built by a DataLoader worker process (and a resume in between) give bit-identical weights."""
    tr, va = sets
    # forkserver: this pytest process may already have run OpenMP code (GNU OpenMP forbids fork then)
    train(CFG, tr, va, tmp_path / "w", stop_after=3, workers=1, mp_context="forkserver")
    r = train(CFG, tr, va, tmp_path / "w", workers=1, mp_context="forkserver")
    assert r["step"] == CFG.epochs * CFG.steps_per_epoch
    a = read_checkpoint(tiny_run[0] / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "w" / "last.pt")["state_dict"]
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_deterministic_for_a_seed_and_different_across_seeds(tmp_path, sets):
    tr, va = sets
    cfg = dataclasses.replace(CFG, epochs=1)
    train(cfg, tr, va, tmp_path / "x")
    train(cfg, tr, va, tmp_path / "y")
    train(dataclasses.replace(cfg, seed=7), tr, va, tmp_path / "z")
    sx, sy, sz = (read_checkpoint(tmp_path / d / "last.pt")["state_dict"] for d in "xyz")
    assert all(torch.equal(sx[k], sy[k]) for k in sx)
    assert not all(torch.equal(sx[k], sz[k]) for k in sx)


def test_resume_with_other_config_is_refused(sets, tiny_run):
    tr, va = sets
    with pytest.raises(CheckpointError):
        train(dataclasses.replace(CFG, lr=1e-3), tr, va, tiny_run[0])


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


def test_incompatible_checkpoint(tmp_path, tiny_run):
    data = torch.load(tiny_run[0] / "last.pt", weights_only=True)
    assert data["net"]["arch"] == "v2"
    data["net"]["lr_ch"] = 16  # the v2 branch's width: weights no longer fit
    torch.save(data, tmp_path / "inc.pt")
    with pytest.raises(CheckpointError, match="do not fit"):
        load_model(tmp_path / "inc.pt")


def test_window_config_checks():
    with pytest.raises(ConfigError):
        WindowConfig(crop=18)
    with pytest.raises(ConfigError):
        WindowConfig(n_obs=6)
    with pytest.raises(ConfigError):
        WindowConfig(window_steps=12)


def test_cosine_schedule_closed_form_and_resume(tmp_path, sets):
    """lr_at: lr at the first step, lr_min at the last, their mean half way; a cosine run killed half way and
    resumed ends with the weights of an uninterrupted one (the rate is a function of the step).
    """
    from reconstruct.net.train import lr_at

    cfg = dataclasses.replace(TINY, lr=1e-3, lr_schedule="cosine", lr_min=1e-5)
    total = 9
    assert lr_at(0, total, cfg) == pytest.approx(1e-3)
    assert lr_at(8, total, cfg) == pytest.approx(1e-5)
    assert lr_at(4, total, cfg) == pytest.approx(0.5 * (1e-3 + 1e-5))
    assert all(lr_at(k + 1, total, cfg) < lr_at(k, total, cfg) for k in range(total - 1))
    assert lr_at(3, total, TINY) == TINY.lr  # constant
    warm = dataclasses.replace(cfg, warmup_steps=4)  # a linear ramp times the schedule, then the schedule itself
    assert [lr_at(k, total, warm) / lr_at(k, total, cfg) for k in range(5)] == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0])
    assert lr_at(1, total, dataclasses.replace(TINY, warmup_steps=2)) == TINY.lr
    tr, va = sets
    train(cfg, tr, va, tmp_path / "whole")
    train(cfg, tr, va, tmp_path / "pieces", stop_after=3)
    train(cfg, tr, va, tmp_path / "pieces")
    a, b = (read_checkpoint(tmp_path / d / "last.pt") for d in ("whole", "pieces"))
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])
    assert a["optimizer"]["param_groups"][0]["lr"] == pytest.approx(lr_at(TINY.epochs * TINY.steps_per_epoch - 1, TINY.epochs * TINY.steps_per_epoch, cfg))


def test_every_shipped_training_config_loads_and_its_init_weights_exist():
    """Each reconstruct/configs/*.toml is a valid TrainConfig whose init_from / manifests are in the repository."""
    from pathlib import Path

    from polinfra.config import from_dict, load_toml

    root = Path(__file__).resolve().parents[2]
    files = sorted((root / "reconstruct" / "configs").glob("*.toml"))
    assert files
    for f in files:
        cfg = from_dict(TrainConfig, load_toml(f), where=str(f))
        for p in (cfg.init_from, cfg.manifest, cfg.val_manifest):
            assert not p or (root / p).is_file(), f"{f.name}: {p} missing"


def test_trainable_freezes_every_other_weight(tmp_path, sets):
    """Trainable = ("refine.dec_r",): after a run only the R decoder's weights moved (so T is exactly the start's);
    a prefix naming no parameter is a one-line ConfigError.
    """
    tr, va = sets
    train(TINY, tr, va, tmp_path / "base")
    init = str(tmp_path / "base" / "last.pt")
    cfg = dataclasses.replace(TINY, init_from=init, trainable=("refine.dec_r",), lr=1e-2)
    train(cfg, tr, va, tmp_path / "r")
    a, b = read_checkpoint(init)["state_dict"], read_checkpoint(tmp_path / "r" / "last.pt")["state_dict"]
    moved = {k for k in a if not torch.equal(a[k], b[k])}
    assert moved and all(k.startswith("refine.dec_r") for k in moved), moved
    # the checkpoint counts every parameter, also the frozen ones (the shipped-checkpoint pin compares with it)
    assert read_checkpoint(tmp_path / "r" / "last.pt")["param_count"] == read_checkpoint(init)["param_count"] == sum(
        t.numel() for k, t in b.items() if t.dtype.is_floating_point)
    with pytest.raises(ConfigError, match="trainable"):
        train(dataclasses.replace(cfg, trainable=("refine.nothing",)), tr, va, tmp_path / "bad")


def test_val_score_of_each_selection():
    """val_select: learned = psnr_T; mean = the mean over both zeta paths; r_share = R over the reflection pixels
    (both paths), whole-frame R where a validation set has none; ssim = T's SSIM over both paths.
    """
    from reconstruct.net.train import val_score

    m = {"psnr_T": 30.0, "psnr_T_forced": 34.0, "psnr_R": 18.0, "psnr_R_forced": 20.0, "psnrrefl_R": 12.0, "psnrrefl_R_forced": 16.0}
    assert val_score(m, "learned") == 30.0 and val_score(m, "mean") == 32.0 and val_score(m, "r_share") == 14.0
    m2 = {k: v for k, v in m.items() if not k.startswith("psnrrefl")}
    assert val_score(m2, "r_share") == 19.0
    assert val_score({**m, "ssim_T": 0.90, "ssim_T_forced": 0.94}, "ssim") == pytest.approx(0.92)  # ssim: both zeta paths


def test_teacher_term_is_the_distance_to_the_teachers_output(tmp_path, sets, tiny_run):
    """Distillation: a student started from its teacher's weights matches it on the first step (l_teach 0 up to float
    rounding: the same layers, the teacher in eval mode without the floor), then departs from it as it trains on the
    ground truth (l_teach > 0); no teacher, no term.
    """
    tr, va = sets
    init = str(tiny_run[0] / "last.pt")
    cfg = dataclasses.replace(CFG, init_from=init, teacher=init, lambda_teacher=1.0, lr=1e-2, epochs=1, val_items=2)
    train(cfg, tr, va, tmp_path / "d")
    rows = list(csv.DictReader((tmp_path / "d" / "log.csv").open()))
    lt = [float(r["l_teach"]) for r in rows if r["l_teach"]]
    assert len(lt) == 2 and lt[0] < 1e-5 < lt[1]
    assert all(float(r["loss"]) > 0 for r in rows)
    train(dataclasses.replace(cfg, teacher=""), tr, va, tmp_path / "n")
    assert not any(r["l_teach"] for r in csv.DictReader((tmp_path / "n" / "log.csv").open()))


@pytest.mark.skipif(not native_bf16(), reason="this CPU has no native bfloat16")
def test_bf16_training_follows_the_float32_run_within_bfloat16_rounding(tmp_path, sets, tiny_run):
    """``bf16 = true``: the same run with the learned layers in bfloat16 logs losses within bfloat16's rounding of the
    float32 run's (not equal to them: the layers did run in bfloat16), and keeps float32 weights.
    """
    import csv

    tr, va = sets
    run, _ = tiny_run
    train(dataclasses.replace(CFG, bf16=True), tr, va, tmp_path / "bf")
    rows = [list(csv.DictReader(open(d / "log.csv"))) for d in (run, tmp_path / "bf")]
    a, b = (float(r[0]["loss"]) for r in rows)
    assert a != b and abs(a - b) <= 2e-2 * abs(a), (a, b)
    sd = read_checkpoint(tmp_path / "bf" / "last.pt")["state_dict"]
    assert all(t.dtype == torch.float32 for t in sd.values() if t.dtype.is_floating_point)
