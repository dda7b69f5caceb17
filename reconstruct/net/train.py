"""Training loop with the paper's curriculum, resumable and deterministic (paper Sec. 3.4).

* Adam, lr 3e-4, batch 8 (paper Sec. 3.4); every loss weight is a
  :class:`reconstruct.net.losses.LossConfig` value.
* Curriculum on the teacher-forcing ratio alpha (paper Sec. 3.4): epochs 1-5 of
  60 alpha = 1.0, epochs 6-15 alpha = 0.5, then 0.0; for other epoch counts the
  same *fractions* of the run (``curriculum_fracs`` = (5/60, 15/60)).
* Determinism on CPU: weights are initialised from a ``torch.Generator``
  seeded with ``seed``; batch b of step s is a pure function of (seed, epoch,
  position) through a per-epoch permutation drawn from a seeded generator; no
  global RNG is used, so a run killed and resumed from ``last.pt`` follows the
  same trajectory as an uninterrupted one.
* Outputs in the run directory: ``last.pt`` (model + optimizer + step, written
  atomically every ``ckpt_every`` steps and at the end), ``config.json``,
  ``log.csv`` (one row per logged step, validation PSNR columns where
  evaluated) and ``curves.png``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import logging
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polinfra.atomic import ensure_dir, write_json, write_text
from polinfra.config import opt, to_dict
from polinfra.errors import CheckpointError, ConfigError
from reconstruct.net.checkpoint import read_checkpoint, save_checkpoint
from reconstruct.net.distributed import SINGLE, Ranks, check_world
from reconstruct.net.losses import LossConfig, total_loss
from reconstruct.net.network import NetConfig, PolSpikeNet, count_parameters, init_weights
from reconstruct.net.onthefly import WindowConfig
from reconstruct.physics.identifiability import SHARE_MIN
from reconstruct.physics.solvers import SolverConfig
from reconstruct.stream.window_inputs import EXTRA_INPUTS, WindowInputs

__all__ = ["TrainConfig", "alpha_at", "lr_at", "collate", "evaluate_model", "train", "TINY"]

log = logging.getLogger(__name__)

MAX_SKIPPED = 20
"""Updates with a non-finite gradient norm a run may skip before it stops."""

ProgressFn = Callable[[int, int], None]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (written to ``config.json``)."""

    seed: int = opt(0, "seed of initialisation, data order and on-the-fly items", lo=0, hi=2**31 - 1)
    epochs: int = opt(60, "epochs (paper: 60)", lo=1, hi=100000)
    steps_per_epoch: int = opt(0, "optimizer steps per epoch; 0 = len(train set) // batch_size", lo=0, hi=10**9)
    batch_size: int = opt(8, "windows per step (paper: 8)", lo=1, hi=4096)
    lr: float = opt(3e-4, "Adam learning rate (paper: 3e-4)", lo=1e-8, hi=1.0)
    lr_schedule: str = opt("constant", "learning rate over the run: constant, or cosine (from lr down to lr_min at the last step; a function of the step, so resuming keeps it)", choices=("constant", "cosine"))
    lr_min: float = opt(0.0, "final learning rate of the cosine schedule", lo=0.0, hi=1.0)
    warmup_steps: int = opt(0, "steps over which the learning rate ramps up linearly from 0 to the schedule's (fine-tuning: a fresh Adam moves every weight by about lr per step whatever its gradient, so a converged network drifts before the moments settle); 0 = none", lo=0, hi=10_000_000)
    grad_clip: float = opt(1.0, "gradient-norm clip (0 = off)", lo=0.0, hi=1e6)
    curriculum_fracs: tuple[float, float] = opt((5 / 60, 15 / 60), "end of the alpha=1.0 and alpha=0.5 phases as fractions of the epochs (paper: 5/60, 15/60)", lo=0.0, hi=1.0)
    curriculum_alphas: tuple[float, float, float] = opt((1.0, 0.5, 0.0), "teacher-forcing ratio in the three phases (paper: 1.0, 0.5, 0.0)", lo=0.0, hi=1.0)
    val_every: int = opt(0, "validate every this many steps (0 = at each epoch end)", lo=0, hi=10**9)
    ckpt_every: int = opt(50, "write last.pt every this many steps", lo=1, hi=10**9)
    log_every: int = opt(10, "write a loss row every this many steps", lo=1, hi=10**9)
    device: str = opt("auto", "auto | cpu | cuda", choices=("auto", "cpu", "cuda"))
    net: NetConfig = opt(factory=NetConfig, doc="network architecture and ablation switches")
    solver: SolverConfig = opt(factory=SolverConfig, doc="physics solver parameters")
    loss: LossConfig = opt(factory=LossConfig, doc="loss weights, paper Eq. (8)-(12)")
    window: WindowConfig = opt(factory=WindowConfig, doc="window geometry and on-the-fly simulation knobs")
    train_items: int = opt(200000, "on-the-fly training items (index space)", lo=1, hi=10**12)
    val_items: int = opt(64, "on-the-fly validation items", lo=1, hi=10**7)
    train_scenes: int = opt(40, "on-the-fly: training scenes drawn from the documented ranges (paper: 40 train groups)", lo=1, hi=100000)
    test_scenes: int = opt(10, "on-the-fly: validation / test scenes, disjoint layer content (paper: 10 test groups)", lo=1, hi=100000)
    scene_seed: int = opt(0, "on-the-fly: seed of the scene pools", lo=0, hi=2**31 - 1)
    manifest: str = opt("", "on-the-fly: take the scenes of this dataset manifest's train / test groups (e.g. datasets/manifests/paper.toml); empty = sample train_scenes / test_scenes")
    mix_manifests: tuple[str, ...] = opt((), "on-the-fly, with manifest: also train on the train groups of these manifests (each group drawn alike, so the mix follows the group counts: e.g. paper.toml's still and bright scenes beside paper_motion.toml's camera motion)")
    val_manifest: str = opt("", "validation windows from this manifest's val_split groups instead of the test groups of manifest (a validation split that never touches the test groups); empty = the test groups")
    val_split: str = opt("train", "split of val_manifest whose groups validate")
    val_ssim: bool = opt(False, "also score SSIM of T at each validation (val_ssim_T, val_ssim_T_forced in log.csv; scikit-image)")
    force_prob: float = opt(0.0, "probability that a step (after the curriculum's alpha = 1 phase) feeds the solver the true zeta (alpha = 1) times a per-item factor exp(N(0, zeta_jitter)), instead of the curriculum's alpha: trains the refinement for an external, imperfect zeta (--zeta self); drawn from the seed and the step (resumable)", lo=0.0, hi=1.0)
    zeta_jitter: float = opt(0.0, "std of the per-item log factor on the forced zeta (force_prob)", lo=0.0, hi=2.0)
    zeta_shape_jitter: float = opt(0.0, "std of the per-item log factor on the forced zeta's modulation about its window mean (force_prob): the degree of polarization a wrong index or pane model gives the self-calibrated zeta", lo=0.0, hi=2.0)
    assumed_prob: float = opt(0.0, "probability that an item of a forced step (force_prob) is fed its zeta under the assumed glass (window.assumed_n) instead of the jittered true zeta: the model the self-calibration would pick (the one whose zeta is closer in scale to the true, with probability assumed_right) or the other one; the losses still compare with the true zeta", lo=0.0, hi=1.0)
    assumed_right: float = opt(0.7, "probability that an assumed-glass item takes the pane model closer in scale to the truth (the self-calibration's model is right where it claims one or the prior holds)", lo=0.0, hi=1.0)
    val_select: str = opt("learned", "validation score that picks best.pt: learned (psnr_T, the network on its own zeta) | mean (the mean of that and psnr_T_forced, the network on the true zeta: a network run with --zeta self where the stream calibrates) | r_share (the mean of psnrrefl_R and psnrrefl_R_forced: R over the pixels where the reflection carries >= 20 % of the light, for an R-only run with trainable) | ssim (the mean of ssim_T and ssim_T_forced, T's structure on both zetas; SSIM is then scored whatever val_ssim says)", choices=("learned", "mean", "r_share", "ssim"))
    init_zero: tuple[str, ...] = opt((), "parameter-name prefixes set to zero after init_from (e.g. refine.dec_t.out to restart a decoder's output as zero: the network starts as its base)")
    trainable: tuple[str, ...] = opt((), "parameter-name prefixes that train (e.g. refine.dec_r: the R decoder alone, every T output stays exactly as init_from's); the others are frozen; empty = all")
    max_skipped_frac: float = opt(0.0, "stop when more updates than this fraction of the steps so far (and more than 20) had a non-finite gradient and were skipped (a randomly initialised parameter branch's zeta can overflow the solver's backward now and then); 0 = after 20", lo=0.0, hi=0.5)
    teacher: str = opt("", "distil from this checkpoint (e.g. reconstruct/weights/polspike_v7.pt, or a shipped name): its T and R on the same windows and zeta feed (RIR as this network's [net] use_rir, no data floor) are a second target, L1 weighted lambda_teacher (l_teach in log.csv): a smaller network learns what the larger one learned; empty = none")
    lambda_teacher: float = opt(0.0, "weight of the teacher's L1 term (teacher)", lo=0.0, hi=100.0)
    bf16: bool = opt(False, "the network's learned layers (and the teacher's) in bfloat16 through torch.autocast, the physics and the optimizer's weights in float32 (reconstruct.net.inference.accelerate): faster on a CPU with AMX or AVX-512 BF16; elsewhere float32 with a warning")
    init_from: str = opt("", "start from these weights (a checkpoint or exported .pt of the same [net] architecture; path relative to the working directory) instead of a random initialisation: fine-tuning")


TINY = TrainConfig(
    epochs=4, steps_per_epoch=2, batch_size=2, ckpt_every=2, log_every=1, val_items=4, train_items=64,
    net=NetConfig(feat_ch=8, lr_ch=8, w_ch=4, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False),
    window=WindowConfig(crop=16), train_scenes=2, test_scenes=1,
)
"""Shrunken preset for tests: a few steps on 16x16 crops in seconds."""


def alpha_at(epoch: int, cfg: TrainConfig) -> float:
    """Teacher-forcing ratio for 0-based ``epoch`` (paper Sec. 3.4 curriculum)."""
    f = epoch / cfg.epochs
    a1, a2, a3 = cfg.curriculum_alphas
    e1, e2 = cfg.curriculum_fracs
    return a1 if f < e1 - 1e-12 else (a2 if f < e2 - 1e-12 else a3)


def lr_at(step: int, total: int, cfg: TrainConfig) -> float:
    """Learning rate of the optimizer step that follows ``step`` done steps (``cfg.lr_schedule``)."""
    ramp = min(1.0, (step + 1) / cfg.warmup_steps) if cfg.warmup_steps > 0 else 1.0
    if cfg.lr_schedule == "constant" or total <= 1:
        return cfg.lr * ramp
    f = min(max(step / (total - 1), 0.0), 1.0)
    return ramp * (cfg.lr_min + 0.5 * (cfg.lr - cfg.lr_min) * (1.0 + math.cos(math.pi * f)))


def collate(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack a list of item dicts (common keys) into a batch."""
    keys = set(items[0]).intersection(*items[1:]) if len(items) > 1 else set(items[0])
    return {k: torch.stack([it[k] for it in items]) for k in sorted(keys) if isinstance(items[0][k], torch.Tensor)}


def batch_inputs(b: dict[str, torch.Tensor], device, cfg: NetConfig) -> WindowInputs:
    """The windows of a batch (``I``, ``phi``) with what a network of configuration ``cfg`` reads beside them
    (``cfg.inputs``, those the batch carries), on ``device``; ConfigError where a ``span_level`` network's items lack the
    long span's length.
    """
    need = cfg.inputs
    if "span_steps" in need and "span_steps" not in b:
        raise ConfigError("a span_level network needs items with the long span (set [window] mean_steps, e.g. 350)")
    return WindowInputs(b["I"].to(device), b["phi"].to(device), **{k: b[k].to(device) for k in EXTRA_INPUTS if k in need and k in b})


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device = 'cuda' but no CUDA device is available; use device = 'auto' or 'cpu'")
    return torch.device(name)


def _psnr(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-image PSNR (dB) with data range 1 after clipping x to [0, 1]; (B,)."""
    mse = ((x.clamp(0, 1) - y) ** 2).flatten(1).mean(1).clamp_min(1e-10)
    return -10 * torch.log10(mse)


@torch.no_grad()
def evaluate_model(model: PolSpikeNet, dataset, batch_size: int = 8, device: torch.device | str = "cpu", ssim: bool = False, forced: bool = False) -> dict[str, float]:
    """Mean PSNR (and optionally SSIM) of T: full network, solver output, oracle RWPS (GT zeta).

    Args:
        model: network (put in eval mode here).
        dataset: items with ``I``, ``phi``, ``T``, ``R``, ``zeta``.
        batch_size: windows per forward pass.
        device: torch device.
        ssim: also compute SSIM (scikit-image, data range 1).

    Returns:
        dict with ``psnr_T`` (final), ``psnr_T_base`` (RWPS with learned zeta and w,
        before refinement), ``psnr_T_oracle`` (RWPS with GT zeta and Poisson weights),
        ``psnr_T_tfp`` (2 x window mean of I, the plain TFP image), ``psnr_R``, ``psnr_R_base``,
        ``psnr_R_oracle``, and ``ssim_*`` counterparts when requested.  PSNR / SSIM use data
        range 1 after clipping the estimate to [0, 1].  ``psnrrefl_T*``: PSNR of T pooled over the
        reflection-affected pixels only, where the reflected share of the mixed light
        zeta R / (zeta R + (1 - zeta) T) at the centre frame is >= ``REFL_SHARE`` (``refl_fraction``:
        their share of all pixels).  ``forced``: also ``psnr_T_forced`` / ``psnr_R_forced``, the network
        on the true zeta (alpha = 1: how it runs on an external zeta, ``--zeta self``).
    """
    from reconstruct.physics.solvers import solve

    was = model.training
    model.eval()
    acc: dict[str, list[float]] = {}
    sq: dict[str, list[float]] = {}
    n_refl = n_all = 0
    for s in range(0, len(dataset), batch_size):
        b = collate([dataset[i] for i in range(s, min(len(dataset), s + batch_size))])
        x = batch_inputs(b, device, model.cfg)
        I, phi = x.I, x.phi
        T, R, z = (b[k].to(device) for k in ("T", "R", "zeta"))
        out = model(I, phi, **x.extras())
        orc = solve("rwps", z, I, None, model.solver_cfg_in)
        ests = {"T": out.T, "T_base": out.T_base, "T_oracle": orc.T, "T_tfp": 2.0 * I.mean(1), "R": out.R, "R_base": out.R_base, "R_oracle": orc.R}
        if forced:
            fo = model(I, phi, zeta_gt=z, alpha=1.0, **x.extras())
            ests.update({"T_forced": fo.T, "R_forced": fo.R})
        zc = z[:, z.shape[1] // 2]
        share = zc * R / (zc * R + (1 - zc) * T + 1e-6)
        refl = share >= REFL_SHARE
        n_refl += int(refl.sum())
        n_all += refl.numel()
        for name in ("T", "T_base", "T_oracle", "T_tfp", "R", "R_base", *(("R_forced",) if forced else ())):
            sq.setdefault(name, []).append(float(((ests[name].clamp(0, 1) - (R if name.startswith("R") else T)) ** 2)[refl].sum()))
        for name, est in ests.items():
            ref = R if name.startswith("R") else T
            acc.setdefault(f"psnr_{name}", []).extend(_psnr(est, ref).cpu().tolist())
            if ssim:
                from skimage.metrics import structural_similarity

                for e, r in zip(est.clamp(0, 1).cpu().numpy(), ref.cpu().numpy()):
                    acc.setdefault(f"ssim_{name}", []).append(float(structural_similarity(r, e, data_range=1.0)))
    model.train(was)
    res = {k: float(np.mean(v)) for k, v in acc.items()}
    res["refl_fraction"] = n_refl / max(n_all, 1)
    if n_refl:
        for name, v in sq.items():
            res[f"psnrrefl_{name}"] = float(-10 * np.log10(max(sum(v) / n_refl, 1e-10)))
    return res


def assumed_glass_feed(batch: dict[str, torch.Tensor], zeta: torch.Tensor, scale: torch.Tensor, cfg: "TrainConfig", g: torch.Generator, draws: int | None = None, rows: slice = slice(None)) -> tuple[torch.Tensor, torch.Tensor]:
    """The forced zeta of a batch with assumed-glass items (:attr:`TrainConfig.assumed_prob`) -> (zeta_feed, scale).

    Each item is, with probability ``assumed_prob``, fed its zeta under the assumed glass (``zeta_a_<model>``,
    ``window.assumed_n``): with probability ``assumed_right`` the model whose mean zeta is closer to the true one in
    log scale (what a right claim or prior gives), else the other; such an item's scale jitter is reset to 1 (its
    error is the glass').  Other items keep the true zeta and their jitter.  ``draws``, ``rows``: the per-item draws are
    made for a global batch of ``draws`` items and this batch takes their ``rows`` (one rank of a data-parallel run).
    """
    from reconstruct.net.onthefly import ASSUMED_MODELS

    keys = [f"zeta_a_{m}" for m in ASSUMED_MODELS]
    if any(k not in batch for k in keys):
        raise ConfigError("assumed_prob > 0 needs items with the assumed-glass zeta: set [window] assumed_n (e.g. 1.5)")
    B = zeta.shape[0]
    use = (torch.rand(draws or B, generator=g) < cfg.assumed_prob)[rows]
    right = (torch.rand(draws or B, generator=g) < cfg.assumed_right)[rows]
    cand = torch.stack([batch[k].to(zeta.device, zeta.dtype) for k in keys], 1)  # (B, M, N, H, W)
    err = (torch.log(cand.mean((2, 3, 4)).clamp_min(1e-9)) - torch.log(zeta.mean((1, 2, 3)).clamp_min(1e-9))[:, None]).abs()  # (B, M)
    closest = err.argmin(1)
    pick = torch.where(right.to(closest.device), closest, 1 - closest) if len(keys) == 2 else closest
    chosen = cand[torch.arange(B, device=pick.device), pick]
    m = use.to(zeta.device)
    feed = torch.where(m[:, None, None, None], chosen, zeta)
    scale = torch.where(m, torch.ones_like(scale), scale)
    return feed, scale


def val_score(metrics: dict[str, float], select: str) -> float:
    """The validation score that picks best.pt (:attr:`TrainConfig.val_select`) from :func:`evaluate_model`'s metrics."""
    if select == "learned":
        return metrics["psnr_T"]
    if select == "mean":
        return 0.5 * (metrics["psnr_T"] + metrics["psnr_T_forced"])
    if select == "ssim":
        return 0.5 * (metrics["ssim_T"] + metrics["ssim_T_forced"])
    # r_share: R where the reflection carries >= REFL_SHARE of the light (whole-frame R where no pixel does)
    return 0.5 * (metrics.get("psnrrefl_R", metrics["psnr_R"]) + metrics.get("psnrrefl_R_forced", metrics["psnr_R_forced"]))


REFL_SHARE = SHARE_MIN
"""Reflected share of the mixed light above which a pixel counts as reflection-affected (evaluation; the same 20 %
as :data:`reconstruct.physics.identifiability.SHARE_MIN`, here with the centre window's zeta)."""

_LOG_FIELDS = ["step", "epoch", "alpha", "loss", "l_rec", "l_grad", "l_phys", "l_excl", "l_base", "l_ssim", "l_teach", "l_logmse", "val_psnr_T", "val_psnr_T_base", "val_psnr_T_oracle", "val_psnr_T_forced", "val_ssim_T", "val_ssim_T_forced", "val_score", "seconds"]


def _write_log(run: Path, rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=_LOG_FIELDS, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    write_text(run / "log.csv", buf.getvalue())


def _plot(run: Path, rows: list[dict[str, Any]]) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from polinfra.plotting import save_figure
    except Exception:  # pragma: no cover - plotting is optional
        return
    tr = [r for r in rows if r.get("loss") not in (None, "")]
    va = [r for r in rows if r.get("val_psnr_T") not in (None, "")]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    if tr:
        st = [int(r["step"]) for r in tr]
        for k in ("loss", "l_rec", "l_phys"):
            ax[0].plot(st, [float(r[k]) for r in tr], label=k)
        ax[0].set_yscale("log")
    ax[0].set_xlabel("step")
    ax[0].set_title("training losses (paper Eq. (8)-(12))")
    if tr:
        ax[0].legend()
    if va:
        st = [int(r["step"]) for r in va]
        for k, lab in (("val_psnr_T", "full network"), ("val_psnr_T_base", "RWPS (learned zeta, w)"), ("val_psnr_T_oracle", "RWPS (GT zeta)")):
            ax[1].plot(st, [float(r[k]) for r in va], marker="o", label=lab)
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("PSNR of T (dB)")
    ax[1].set_title("validation")
    if va:
        ax[1].legend()
    save_figure(fig, run / "curves.png")
    plt.close(fig)


def _read_log(run: Path, max_step: int) -> list[dict[str, Any]]:
    p = run / "log.csv"
    if not p.is_file():
        return []
    with open(p, newline="") as fh:
        return [r for r in csv.DictReader(fh) if int(r["step"]) <= max_step]


class _BatchOrder:
    """Item indices of steps ``start`` .. ``end`` - 1: batch b of step s is a pure function of (seed, epoch, position)."""

    def __init__(self, cfg: TrainConfig, n_items: int, spe: int, start: int, end: int, ranks: Ranks = SINGLE):
        self.cfg, self.n, self.spe, self.start, self.end, self.ranks = cfg, n_items, spe, start, end, ranks

    def __len__(self) -> int:
        return max(0, self.end - self.start)

    def __iter__(self):
        perm_epoch, perm = -1, None
        for step in range(self.start, self.end):
            epoch, pos = divmod(step, self.spe)
            if epoch != perm_epoch:
                g = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + epoch)
                perm = torch.randperm(self.n, generator=g)
                perm_epoch = epoch
            yield self.ranks.shard([int(perm[(pos * self.cfg.batch_size + j) % self.n]) for j in range(self.cfg.batch_size)])


def _widened(src: dict[str, torch.Tensor], dst: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``src`` weights for a model whose convolutions may take more input channels (e.g. ``net.use_mean``'s two
    refinement inputs): a conv kernel (O, I, kh, kw) going into (O, I', kh, kw) with I' > I keeps its I channels
    and gets zeros for the new ones, so the widened network starts as exactly the given one.
    """
    out = dict(src)
    for k, v in src.items():
        t = dst.get(k)
        if t is not None and v.dim() == 4 and t.dim() == 4 and t.shape[1] > v.shape[1] and (t.shape[0], *t.shape[2:]) == (v.shape[0], *v.shape[2:]):
            w = torch.zeros_like(t)
            w[:, : v.shape[1]] = v
            out[k] = w
    return out


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)


def train(
    cfg: TrainConfig,
    train_set,
    val_set,
    run_dir: str | os.PathLike,
    *,
    progress: ProgressFn | None = None,
    stop_after: int | None = None,
    max_seconds: float | None = None,
    workers: int = 0,
    mp_context: str | None = None,
    ranks: Ranks = SINGLE,
) -> dict[str, Any]:
    """Train (or resume) a :class:`PolSpikeNet`.

    Args:
        cfg: training configuration.
        train_set, val_set: map-style datasets of window items
            (:class:`reconstruct.net.onthefly.OnTheFlyWindows` or a stored-window dataset).
        run_dir: output directory; an existing ``last.pt`` there is resumed
            (its config must equal ``cfg``, else CheckpointError).
        progress: optional ``(done_steps, total_steps)`` callback.
        stop_after: stop (after checkpointing) once this global step is reached;
            for time-boxed runs and the resume test.
        max_seconds: stop (after checkpointing) once this much wall time has
            passed in this call; a later call resumes.
        workers: DataLoader worker processes that build the batches ahead of the
            optimizer (0 = in this process).  The batches are the same either way
            (items are pure functions of (seed, index), the order is this loop's), so
            the trajectory does not depend on it; on-the-fly window generation then
            overlaps the forward/backward pass.  The worker is forked: start a run with
            workers before this process ran multi-threaded OpenMP code (torch with more
            than one thread, spike_sim's parallel kernel), which GNU OpenMP forbids
            (``polspike train`` sets its threads first and forks at the start).
        mp_context: multiprocessing start method of the workers (None = the platform's,
            fork on Linux; "forkserver" / "spawn" need a picklable dataset but are safe
            in a process that already ran OpenMP code).
        ranks: this process's rank among data-parallel training processes (:mod:`reconstruct.net.distributed`;
            its process group already joined); the default is the single-process run.

    Returns:
        dict with ``step``, ``total_steps``, ``param_count`` and the last validation metrics.
    """
    if ranks.active:
        check_world(ranks.world, cfg.batch_size, "world size")
    run = ensure_dir(run_dir)
    dev = _device(cfg.device)
    spe = cfg.steps_per_epoch or max(1, len(train_set) // cfg.batch_size)
    total = cfg.epochs * spe
    model = PolSpikeNet(cfg.net, cfg.solver)
    init_weights(model, torch.Generator().manual_seed(cfg.seed))
    if cfg.init_from:
        src = read_checkpoint(cfg.init_from)
        try:
            model.load_state_dict(_widened(src["state_dict"], model.state_dict()))
        except RuntimeError as e:
            raise CheckpointError(f"init_from = {cfg.init_from}: its weights do not fit [net] of this config ({str(e).splitlines()[0]}); use weights of the same architecture") from None
        log.info("initialised from %s", cfg.init_from)
    if cfg.init_zero:
        hit = [p for n, p in model.named_parameters() if n.startswith(tuple(cfg.init_zero))]
        if not hit:
            raise CheckpointError(f"init_zero = {list(cfg.init_zero)} names no parameter of this network")
        with torch.no_grad():
            for p in hit:
                p.zero_()
        log.info("zeroed %d parameter tensors (init_zero)", len(hit))
    if cfg.trainable:
        named = list(model.named_parameters())
        keep = [n for n, _ in named if n.startswith(tuple(cfg.trainable))]
        if not keep:
            raise ConfigError(f"trainable = {list(cfg.trainable)} names no parameter of this network (names start with param., refine.e1, refine.dec_t, refine.dec_r, ...)")
        for n, p in named:
            p.requires_grad_(n in keep)
        log.info("training %d of %d parameter tensors (trainable = %s); the rest frozen", len(keep), len(named), list(cfg.trainable))
    model.to(dev)
    teacher = None
    if cfg.teacher and cfg.lambda_teacher > 0:
        from reconstruct.net.checkpoint import load_model

        teacher = load_model(cfg.teacher, dev, use_rir=cfg.net.use_rir, floor=False)[0]
        for p in teacher.parameters():
            p.requires_grad_(False)
        log.info("distilling from %s (lambda_teacher %g)", cfg.teacher, cfg.lambda_teacher)
    if cfg.bf16:
        from reconstruct.net.inference import accelerate

        log.info("bfloat16 layers: %s", accelerate(model, bf16=True).bf16)
        if teacher is not None:
            accelerate(teacher, bf16=True)
    opt_ = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
    step = 0
    metrics: dict[str, float] = {}
    best: dict[str, Any] = {}  # the best validation so far: {"step", "psnr_T"}; best.pt holds its weights
    ck = run / "last.pt"
    if ck.exists():
        data = read_checkpoint(ck)
        if data.get("train") != to_dict(cfg):
            raise CheckpointError(f"{ck} was written with a different training config; use a new --out directory or the same config")
        model.load_state_dict(data["state_dict"])
        opt_.load_state_dict(data["optimizer"])
        step = int(data["step"])
        metrics = dict(data.get("metrics", {}))
        best = dict(data.get("best", {}))
        if (run / "best.pt").exists():  # the file is the truth (written before last.pt)
            bd = read_checkpoint(run / "best.pt")
            bm = bd.get("metrics", {})
            best = {"step": int(bd.get("step", 0)), "psnr_T": float(bm.get("psnr_T", -math.inf)), "score": float(bm.get("score", bm.get("psnr_T", -math.inf)))}
        log.info("resumed %s at step %d/%d", ck, step, total)
    if ranks.is_writer:
        write_json(run / "config.json", to_dict(cfg))
    rows = _read_log(run, step)
    n_par = count_parameters(model)
    log.info("PolSpikeNet: %d trainable parameters; %d steps (%d epochs x %d)", n_par, total, cfg.epochs, spe)

    def checkpoint(plot: bool = False) -> None:
        if not ranks.is_writer:
            return
        save_checkpoint(ck, model, extra={"train": to_dict(cfg), "optimizer": opt_.state_dict(), "step": step, "metrics": metrics, "best": best})
        _write_log(run, rows)
        if plot:
            _plot(run, rows)

    t0 = time.perf_counter()
    skipped = 0
    model.train()
    end = total if stop_after is None else min(total, stop_after)
    batches = _BatchOrder(cfg, len(train_set), spe, step, end, ranks)
    net = ranks.wrap(model, dev)  # the module the step runs (DDP averages the ranks' gradients)
    if workers > 0:
        loader = torch.utils.data.DataLoader(train_set, batch_sampler=batches, num_workers=workers, collate_fn=collate, worker_init_fn=_worker_init, prefetch_factor=4, persistent_workers=False, multiprocessing_context=mp_context)
    else:
        loader = (collate([train_set[i] for i in idx]) for idx in batches)
    for b in loader:
        epoch = step // spe
        alpha = alpha_at(epoch, cfg)
        x = batch_inputs(b, dev, cfg.net)
        I, phi = x.I, x.phi
        T, R, z = (b[k].to(dev) for k in ("T", "R", "zeta"))
        scale = shape = feed = None
        if cfg.force_prob > 0 and alpha < 1.0:
            g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
            if float(torch.rand((), generator=g)) < cfg.force_prob:
                alpha = 1.0
                rws = ranks.rows(cfg.batch_size)  # per-item draws of the global batch; this rank's rows
                scale = torch.exp(cfg.zeta_jitter * torch.randn(cfg.batch_size, generator=g)[rws]).to(dev)
                if cfg.zeta_shape_jitter > 0:  # drawn after scale: configs without it keep their trajectory
                    shape = torch.exp(cfg.zeta_shape_jitter * torch.randn(cfg.batch_size, generator=g)[rws]).to(dev)
                if cfg.assumed_prob > 0:  # drawn last, for the same reason
                    feed, scale = assumed_glass_feed(b, z, scale, cfg, g, cfg.batch_size, rws)
        out = net(I, phi, zeta_gt=z, alpha=alpha, **x.extras(), zeta_scale=scale, zeta_shape=shape, zeta_feed=feed)
        loss, parts = total_loss(out, T, R, alpha, cfg.loss)
        if teacher is not None:  # the teacher on the same windows, zeta feed and alignment; eval mode (no floor)
            with torch.no_grad():
                tout = teacher(I, phi, zeta_gt=z, alpha=alpha, **x.extras(), zeta_scale=scale, zeta_shape=shape, zeta_feed=feed)
            l_teach = (out.T - tout.T).abs().mean() + (out.R - tout.R).abs().mean()
            loss = loss + cfg.lambda_teacher * l_teach
            parts = {**parts, "loss": float(loss.detach()), "l_teach": float(l_teach.detach())}
        if not math.isfinite(parts["loss"]):
            raise FloatingPointError(f"non-finite loss at step {step}: {parts}")
        if not loss.requires_grad:
            raise ConfigError(f"step {step}: the loss depends on no trainable weight (trainable = {list(cfg.trainable)}, alpha {alpha}); train a part of the network that these steps' outputs pass through")
        opt_.zero_grad(set_to_none=True)
        loss.backward()
        for group in opt_.param_groups:
            group["lr"] = lr_at(step, total, cfg)
        trained = [p for p in model.parameters() if p.requires_grad]
        gnorm = torch.nn.utils.clip_grad_norm_(trained, cfg.grad_clip if cfg.grad_clip > 0 else math.inf)
        if not torch.isfinite(gnorm):  # a finite loss with a non-finite gradient: skip the update, never poison the weights
            skipped += 1
            log.warning("step %d: non-finite gradient norm; update skipped (%d so far)", step, skipped)
            if skipped > max(MAX_SKIPPED, int(cfg.max_skipped_frac * max(step, 1))):
                raise FloatingPointError(f"non-finite gradients on {skipped} steps (last at step {step}); lower lr or check the data")
            opt_.zero_grad(set_to_none=True)
        else:
            opt_.step()
        step += 1
        ranks.stepped()
        row: dict[str, Any] = {}
        if step % cfg.log_every == 0 or step == total:
            parts = ranks.mean_parts(parts, dev)
            row = {"step": step, "epoch": epoch + 1, "alpha": alpha, **{k: f"{v:.6g}" for k, v in parts.items()}, "seconds": f"{time.perf_counter() - t0:.1f}"}
        val_now = (cfg.val_every and step % cfg.val_every == 0) or (not cfg.val_every and step % spe == 0) or step == total
        if val_now and val_set is not None and len(val_set) and ranks.is_writer:
            metrics = evaluate_model(model, val_set, cfg.batch_size, dev, forced=cfg.val_select != "learned", ssim=cfg.val_ssim or cfg.val_select == "ssim")
            metrics["score"] = val_score(metrics, cfg.val_select)
            row = row or {"step": step, "epoch": epoch + 1, "alpha": alpha, "seconds": f"{time.perf_counter() - t0:.1f}"}
            row.update({f"val_{k}": f"{v:.4f}" for k, v in metrics.items()})
            log.info("step %d: val PSNR T %.2f dB (solver %.2f, oracle %.2f)", step, metrics["psnr_T"], metrics["psnr_T_base"], metrics["psnr_T_oracle"])
            if not best or metrics["score"] > best.get("score", best["psnr_T"]):  # best.pt before last.pt: a kill in between loses nothing
                best = {"step": step, "psnr_T": metrics["psnr_T"], "score": metrics["score"]}
                save_checkpoint(run / "best.pt", model, extra={"train": to_dict(cfg), "step": step, "metrics": metrics})
                log.info("step %d: new best validation, written %s", step, run / "best.pt")
        if row:
            rows.append(row)
        out_of_time = max_seconds is not None and ranks.any_true(time.perf_counter() - t0 > max_seconds, dev)
        if step % cfg.ckpt_every == 0 or step == end or out_of_time:
            checkpoint(plot=step == end or out_of_time or step % (10 * cfg.ckpt_every) == 0)
        if progress is not None:
            progress(step, total)
        if out_of_time:
            log.info("time budget of %.0f s reached at step %d; resume with the same command", max_seconds, step)
            break
    if step == end and not (run / "log.csv").exists():
        checkpoint(plot=True)
    ranks.barrier()  # the last checkpoint is written before any rank reports the run done
    return {"step": step, "total_steps": total, "param_count": n_par, "metrics": metrics, "best": best, "run_dir": str(run)}
