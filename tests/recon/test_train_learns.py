"""Training learns: a short run on a tiny generated set must improve the reconstruction, not just run.

The set is closed-form integrate-and-fire streams (no generator) of one fixed pane (R_perp 0.3, R_par 0.02,
phi_perp 0.6 rad, paper Eq. (2)) in front of smooth random layers, at an exposure of 2-3 thresholds per step
per radiance unit (bright pixels saturate: g = exposure I clipped at one spike per step).  One pane makes zeta
a function of the polarizer angle alone, so the parameter branch can learn it in a few dozen steps; the
saturation and the count noise leave the refinement something to correct.

The run: :data:`CFG`, 64 Adam steps of 4 windows (16 x 16, N = 7), lr 3e-3, the curriculum at 1/4 and 1/2 of
8 epochs; validation on 8 held-out windows, once, at the end.  Measured (torch 2.13, one thread, seed 0):

=====================================  =========  ============  ==============  ===========
quantity                               this run   L_rec zeroed  zeta of phi+90  threshold
=====================================  =========  ============  ==============  ===========
loss, mean of last 4 / first 4 steps   0.51       0.56          0.52            <= 0.6
val PSNR T: final - initial weights    +6.88 dB   +6.33 dB      +1.52 dB        >= +4.0 dB
val PSNR T_base (the physics core:     +6.26 dB   +4.73 dB      -0.06 dB        >= +5.5 dB
  RWPS on the learned zeta) - initial
val PSNR T - T_base (the refinement)   +0.67 dB   +1.64 dB      +1.63 dB        >= +0.3 dB
val PSNR T - RWPS on the true zeta     +1.75 dB   +1.20 dB      -3.62 dB        >= +1.0 dB
=====================================  =========  ============  ==============  ===========

The thresholds sit between the run and its deliberate breaks (the two columns; validation always on the true
items).  Zeroing L_rec (paper Eq. (8): ``reconstruct.net.losses.loss_rec`` returning 0, in both the final and the
solver-output terms) still lets L_grad / L_phys teach T, but the physics core gains 1.5 dB less.  Feeding the
zeta of the polarizer angle + 90 degrees (R_perp + R_par - zeta: the perpendicular and parallel axes swapped, an
offset slip in the angle pipeline) teaches the parameter branch the wrong zeta: the physics core ends where it
started and T gains 1.5 dB, from the refinement alone.  Regenerate the numbers by running the test with a
breakpoint on :func:`check` (``run_and_score`` returns them).
"""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
import torch
from scipy import ndimage

from reconstruct.net.network import PolSpikeNet, init_weights
from reconstruct.net.onthefly import OnTheFlyWindows, item_from_stream
from reconstruct.net.train import TINY, evaluate_model, train

RATE_HZ = 20000.0
POL_HZ = 30.0
PANE = (0.3, 0.02, 0.6)
"""R_perp, R_par, phi_perp (rad) of the one pane of the set."""

CFG = dataclasses.replace(
    TINY, epochs=8, steps_per_epoch=8, batch_size=4, lr=3e-3, ckpt_every=1000, log_every=1, val_every=10**6,
    val_items=8, train_items=64, curriculum_fracs=(0.25, 0.5),
)
"""The short run of the module docstring (validation only at the last step)."""

LOSS_RATIO_MAX = 0.6
GAIN_T_DB = 4.0
GAIN_BASE_DB = 5.5
REFINE_DB = 0.3
ABOVE_ORACLE_DB = 1.0

pytestmark = pytest.mark.usefixtures("one_thread")


def pane_item(seed: int, index: int, cfg=TINY.window) -> dict[str, torch.Tensor]:
    """One window of a closed-form stream: smooth layers (Gaussian sigma 4, wrapped, scaled to [0, T_max]),
    paper Eq. (1)-(2) light of :data:`PANE` behind an ideal polarizer at 30 rev/s sampled at step midpoints,
    spikes = increments of floor(u + cumsum g), g = exposure I clipped at 1 (saturating integrate-and-fire).
    """
    from spike_sim.aggregate import AggregateConfig, frame_centres

    rng = np.random.default_rng([seed, index])
    S, N = cfg.crop, cfg.n_obs
    n = int(np.ceil((N + 1) * cfg.stride_deg / 360 / POL_HZ * RATE_HZ + cfg.window_steps))

    def layer(top: float) -> np.ndarray:
        x = ndimage.gaussian_filter(rng.random((S, S)), 4, mode="wrap")
        return (x - x.min()) / (x.max() - x.min() + 1e-9) * top

    T = layer(rng.uniform(0.4, 1.0))
    R = layer(rng.uniform(0.3, 1.0))
    Rp, Rs, pp = (np.full((S, S), v) for v in PANE)
    phase = rng.uniform(0, 2 * np.pi)
    phi = phase + 2 * np.pi * POL_HZ * (np.arange(n) + 0.5) / RATE_HZ
    zeta = Rp[None] * np.cos(phi[:, None, None] - pp[None]) ** 2 + Rs[None] * np.sin(phi[:, None, None] - pp[None]) ** 2  # paper Eq. (2)
    exposure = 2.0 * rng.uniform(1.0, 1.5)
    g = np.clip(exposure * 0.5 * (zeta * R[None] + (1 - zeta) * T[None]), 0, 1)  # paper Eq. (1)
    u = rng.random((S, S))
    V = np.floor(u[None] + np.cumsum(g, 0))
    spikes = np.diff(np.concatenate([np.floor(u)[None], V]), axis=0).astype(np.uint8)
    agg = AggregateConfig(window_steps=cfg.window_steps, stride_deg=cfg.stride_deg, n_obs=N)
    c, _ = frame_centres(phi, agg, phi_start_rad=phase)
    m = len(c) // 2
    return item_from_stream(spikes, c[m - N // 2 : m + N // 2 + 1], phi, phi, (T, R), {"R_perp": Rp, "R_par": Rs, "phi_perp": pp}, exposure, cfg)


def run_and_score(tmp_path, source=pane_item) -> dict[str, float]:
    """Train :data:`CFG` on ``source`` items (validation always on the true :func:`pane_item`); the numbers the
    test asserts, measured against the same initial weights (``init_weights`` with the config's seed).
    """
    tr = OnTheFlyWindows(source, length=CFG.train_items, seed=1)
    va = OnTheFlyWindows(pane_item, length=CFG.val_items, seed=2)
    model = PolSpikeNet(CFG.net, CFG.solver)
    init_weights(model, torch.Generator().manual_seed(CFG.seed))
    m0 = evaluate_model(model, va, 8)
    res = train(CFG, tr, va, tmp_path / "run")
    m1 = res["metrics"]
    loss = [float(r["loss"]) for r in csv.DictReader(open(tmp_path / "run" / "log.csv")) if r["loss"]]
    return {
        "loss_ratio": float(np.mean(loss[-4:]) / np.mean(loss[:4])),
        "gain_T": m1["psnr_T"] - m0["psnr_T"],
        "gain_base": m1["psnr_T_base"] - m0["psnr_T_base"],
        "refine": m1["psnr_T"] - m1["psnr_T_base"],
        "above_oracle": m1["psnr_T"] - m1["psnr_T_oracle"],
    }


def check(s: dict[str, float]) -> None:
    """The learning criteria of the module docstring."""
    assert s["loss_ratio"] <= LOSS_RATIO_MAX, f"training loss fell only to {s['loss_ratio']:.2f} of its start: {s}"
    assert s["gain_T"] >= GAIN_T_DB, f"validation T gained {s['gain_T']:.2f} dB over the initial weights: {s}"
    assert s["gain_base"] >= GAIN_BASE_DB, f"the physics core (RWPS on the learned zeta) gained {s['gain_base']:.2f} dB: {s}"
    assert s["refine"] >= REFINE_DB, f"the refinement adds {s['refine']:.2f} dB over the physics core it refines: {s}"
    assert s["above_oracle"] >= ABOVE_ORACLE_DB, f"T is {s['above_oracle']:.2f} dB above RWPS on the true zeta: {s}"


@pytest.mark.slow
def test_a_short_run_learns(tmp_path):
    """64 steps lower the loss to <= 0.6 of its start and lift validation T by >= 4 dB, the physics core by
    >= 5.5 dB, the refinement >= 0.3 dB above that core and >= 1 dB above RWPS on the true zeta.

    Seen failing: with ``reconstruct.net.losses.loss_rec`` returning 0 (L_rec zeroed) ``AssertionError: the physics
    core (RWPS on the learned zeta) gained 4.73 dB``; with the training items' zeta replaced by
    R_perp + R_par - zeta (the zeta of the polarizer angle + 90 deg) ``AssertionError: validation T gained
    1.52 dB over the initial weights``.
    """
    check(run_and_score(tmp_path))
