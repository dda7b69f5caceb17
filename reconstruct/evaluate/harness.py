"""Evaluation harness: physics solvers and baselines on every window of every test group.

For each group, output frames i with K = N // 2 frames on either side and a GT
frame are reconstructed from the window {I(i+k), phi(i+k)}, k in [-K, K]:
RIR (optional, supp. Sec. 6) aligns frames and zeta maps to the centre frame,
then each solver of :mod:`reconstruct.physics.solvers` recovers (R, T).

Baselines, in the same table:

* ``tfp``: texture from playback, T = 2 * mean_k I(i+k), the window mean of
  spikes (unaligned) in radiance units.  It keeps the mean reflection.
* ``best_frame``: the best single observation 2 I(i+k), chosen per output frame
  by PSNR against the GT (an oracle pick: an upper bound for any rule that
  selects one frame).
* ``spike_mean``: the plain spike mean, 2 x spikes per step / exposure over
  17.5 ms centred on the frame (``EvalGroup.I_mean``; stored groups only): the
  "doing nothing" reference.

The learned reconstructor from a checkpoint (:func:`load_network`):

* method ``full``: the whole network (its own RIR, parameter branch, RWPS,
  refinement) on the unaligned window; two rows, ``full`` (final T, R) and
  ``full:solver`` (the RWPS output on the learned zeta and w, before refinement,
  supp. Table 3 "solver-only").  Ablations (paper Table 1) are checkpoints
  trained with a switch off: ``no_attention`` / ``no_conf`` / ``rir = False``
  check the checkpoint's recorded configuration and name the rows
  ``full-noatt``, ``full-noconf``, ``full-norir``.  RIR and Conf carry no
  weights, so a checkpoint trained with them can also be evaluated without
  them (a test-time ablation, logged as a warning); attention cannot.
* zeta source ``learned``: zeta_hat and w of the parameter branch
  (:func:`reconstruct.net.learned_zeta.zeta_learned`) on the RIR-aligned window,
  fed to the physics solvers (w to rwps only).

Scores: PSNR / SSIM (:mod:`reconstruct.evaluate.metrics`) of T and R per frame,
averaged per group and over all frames (``overall``); R also over the pixels where
the reflection is >= 20 % of the light, with the fraction of such pixels, the noise
floor of R for the least-squares estimate with the true zeta
(:mod:`reconstruct.physics.identifiability`) and a flat-R reference (:data:`SHARE_KEYS`).  Outputs (see
:func:`write_report`): ``results.csv``, ``results.md``, ``results.json``,
``figure.png`` (input / TFP / solver T / GT, the first frame of the first
``figure_frames`` groups), ``config.json``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch

from polinfra.config import opt, to_dict
from polinfra.errors import ConfigError, DataFormatError
from reconstruct.evaluate.metrics import LPIPS_NA, lpips_status, masked_psnr, masked_score, psnr, score
from reconstruct.net.checkpoint import FLOOR_ANCHORS
from reconstruct.net.learned_zeta import zeta_learned
from reconstruct.net.net_zeta import NET_FALLBACKS, fallback_for
from reconstruct.net.network import GAIN_SPREAD_AUTO, SYMMETRY_CODES
from reconstruct.physics.identifiability import SHARE_MIN, bound_psnr, ls_layer_variance, reflected_share, window_mean_variance
from reconstruct.physics.rir import RirConfig, estimate_shifts, warp
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, SOLVERS, SolverConfig, solve
from reconstruct.physics.span import anchor_to_mean, long_span_separation, zbar_of
from reconstruct.physics.zeta import ZETA_SOURCES, PaneMaps, zeta_from_maps
from reconstruct.stream.groups import EvalGroup, network_inputs
from spike_sim.config import pixel_gain_spread

__all__ = ["BOUND_GOAL_DB", "SHARE_KEYS", "SHARE_FRAME_KEYS", "group_noise", "share_context", "share_scores", "net_zeta_of", "REGIME_FACTORS", "EvalConfig", "EvalReport", "finite_means", "BASELINES", "ANCHOR_SUFFIX", "SPAN_METHOD", "NET_METHOD", "load_network", "group_zeta", "evaluate_groups", "write_report", "parse_methods", "load_groups", "markdown_table"]

log = logging.getLogger(__name__)

BASELINES = ("tfp", "best_frame", "spike_mean")
"""Reference rows in every table (module docstring)."""


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Evaluation harness parameters (window, stride, solvers, zeta source)."""

    n_obs: int = opt(7, "observations per output frame N = 2K + 1 (odd)", lo=1, hi=101)
    dt_ms: float = opt(0.65, "aggregation window dt, milliseconds (rounded to an odd number of steps)", lo=0.01, hi=1000.0)
    stride_deg: float = opt(31.5, "polarizer rotation between output frames, degrees", lo=0.01, hi=360.0)
    methods: str = opt("ls,ridge,irls,rwps", "comma-separated methods from ls, ridge, irls, rwps, full (the network)")
    zeta: str = opt("gt", "where zeta comes from", choices=ZETA_SOURCES)
    rir: bool = opt(True, "align each window with reflection-invariant registration")
    floor: bool = opt(True, "method full: the network's data-consistency floor (reconstruct.net.network.NetConfig.floor, anchored as the checkpoint sets floor_anchor); false: the refinement's output as it is")
    floor_anchor: str = opt("", "method full with the floor: what it falls back to where the data check fails, best (the best physics per pixel, reconstruct.physics.anchor) or rwps (the physics-only RWPS); empty = the checkpoint's", choices=("", *FLOOR_ANCHORS))
    gain_spread: str = opt("", "method full with the floor: its allowance for the sensor's per-pixel gain spread, auto (each group's own sensor, its simulator's fixed pattern) or a relative sd (reconstruct.net.network.NetConfig.floor_gain_spread); empty = the checkpoint's")
    max_frames: int = opt(0, "evaluate at most this many output frames per group (0 = all)", lo=0, hi=10**9)
    figure_frames: int = opt(3, "frames shown in the figure grid", lo=0, hi=20)
    batch: int = opt(4, "windows solved together", lo=1, hi=4096)
    pane_n: float = opt(1.5, "physics zeta: calibrated refractive index of the pane", lo=1.0, hi=4.0)
    pane_model: str = opt("single", "physics zeta: pane model", choices=("single", "thin_slab", "thick_slab"))
    self_pane_model: str = opt("auto", "self zeta: pane model (auto: from the DoP cone where the data constrain it, else from the layers' content test where it clearly separates the models, else thin slab; a model given here is used with pane_n)", choices=("auto", "single", "thin_slab", "thick_slab"))
    self_fov: str = opt("scene", "self zeta: the camera's field of view: scene (the group's, from its scene file, as a user who knows the lens gives --fov-deg) or fitted (from the orientation field alone, as polspike reconstruct does for a .dat without --fov-deg)", choices=("scene", "fitted"))
    dtype: str = opt("float32", "solver dtype", choices=("float32", "float64"))
    device: str = opt("cpu", "torch device for the solvers and the network (cpu, cuda, auto)")
    checkpoint: str = opt("", "network checkpoint for method full / zeta learned (empty: the shipped reconstruct/weights default)")
    no_attention: bool = opt(False, "method full: the checkpoint must be trained without angle attention (paper Table 1 ablation)")
    no_conf: bool = opt(False, "method full: evaluate without Conf (checkpoint trained without it, else a test-time ablation)")
    net_tile: int = opt(256, "method full: network tile size in pixels (bounded memory; 0 = whole frame)", lo=0, hi=100000)
    bf16: bool = opt(False, "method full: the network's learned layers in bfloat16 where the CPU computes it natively (reconstruct.net.inference.accelerate; its quality change)")
    net_solver: str = opt("", "method full: physics solver before the network's refinement instead of the trained one (supp. Table 3); empty = as trained", choices=("", "ls", "ridge", "irls", "rwps"))
    net_zeta: str = opt("", "method full: zeta of the network's solver and refinement: learned (its parameter branch), self, gt, physics, or none (zeta = 0: no separable reflection, T is the whole light); empty = self when zeta is self, else learned", choices=("", "learned", "self", "gt", "physics", "none"))
    net_ensemble: int = opt(1, "method full: test-time self-ensemble over 1, 2, 4 or 8 symmetries of the image (reconstruct.net.network.SymmetryEnsemble; that many forward passes)", choices=tuple(SYMMETRY_CODES))
    net_fallback: str = opt("auto", "method full with net zeta self, where the stream does not self-calibrate: auto (learned where the refused calibration still shows >= 5 % of pixels modulating, else none; reconstruct.net.net_zeta.fallback_for), none (zeta = 0, T is the whole light) or learned (the network's own zeta)", choices=NET_FALLBACKS)
    anchor: str = opt("none", "mean: also score each method anchored to the 17.5 ms spike mean, T = 2 I_mean - zbar (R^ - T^), R = T + (R^ - T^) (rows '<method>+mean'), and the physics of the whole span's first harmonic on the solvers' zeta (row 'span'; reconstruct.physics.span.long_span_separation); stored groups only", choices=("none", "mean"))


def _refused_fallback(cfg: EvalConfig) -> str:
    """The network's zeta (none or learned) for the group whose self-calibration just refused
    (:func:`reconstruct.net.net_zeta.fallback_for` of that calibration, ``cfg.net_fallback``).
    """
    from reconstruct.pane.selfcal import group_self_zeta

    return fallback_for(getattr(group_self_zeta, "last", None), cfg.net_fallback)


def net_zeta_of(cfg: EvalConfig) -> str:
    """The network's zeta source under ``cfg`` (``net_zeta``, or self when ``zeta`` is self, else learned)."""
    return cfg.net_zeta or ("self" if cfg.zeta == "self" else "learned")


NET_METHOD = "full"
"""Method name of the learned reconstructor in ``--method``."""


def parse_methods(methods: str) -> list[str]:
    """Split and validate a comma-separated method list (solvers of :data:`SOLVERS` and ``full``)."""
    out = list(dict.fromkeys(m.strip().lower() for m in methods.split(",") if m.strip()))
    ok = (*SOLVERS, NET_METHOD)
    bad = [m for m in out if m not in ok]
    if bad or not out:
        raise ConfigError(f"unknown method(s) {bad or methods!r}; choose from {list(ok)}, comma-separated")
    return out


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        from polinfra.errors import BackendUnavailableError

        raise BackendUnavailableError(f"device {name!r} requested but torch sees no CUDA device; use --device cpu or auto")
    return torch.device(name)


def load_network(cfg: EvalConfig) -> tuple[torch.nn.Module, dict]:
    """Load the network of ``cfg.checkpoint`` (or the shipped default) for method full / zeta learned.

    Checks the ablation switches against the configuration recorded in the
    checkpoint (module docstring).  Returns (model in eval mode, info) with
    info = {"path", "label", "trained": {use_rir, use_attention, use_conf}, "overrides", "step"}.

    Raises:
        CheckpointError: unreadable checkpoint, or one that does not fit the switches.
        ConfigError: the window length differs from the network's.
    """
    from polinfra.errors import CheckpointError
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, floor_overrides, load_model, read_checkpoint

    path = Path(cfg.checkpoint) if cfg.checkpoint else DEFAULT_WEIGHTS
    net = read_checkpoint(path)["net"]
    trained = {k: bool(net.get(k, True)) for k in ("use_rir", "use_attention", "use_conf")}
    if cfg.no_attention and trained["use_attention"]:
        raise CheckpointError(
            f"--no-attention: {path} was trained with angle attention; pass --checkpoint of a model trained with [net] use_attention = false"
        )
    if not cfg.no_attention and not trained["use_attention"]:
        raise CheckpointError(f"{path} was trained without angle attention; add --no-attention to evaluate it as that ablation")
    overrides = {}
    if not cfg.rir and trained["use_rir"]:
        overrides["use_rir"] = False
        log.warning("%s was trained with RIR; evaluating it without RIR (test-time ablation: RIR has no weights)", path)
    if cfg.rir and not trained["use_rir"]:
        overrides["use_rir"] = True  # alignment first, also for a checkpoint trained without it (RIR has no weights)
        log.info("%s was trained without RIR; evaluating it with RIR (--no-rir: as trained)", path)
    if cfg.no_conf and trained["use_conf"]:
        overrides["use_conf"] = False
        log.warning("%s was trained with Conf; evaluating it without Conf (test-time ablation; the paper retrains)", path)
    if not cfg.no_conf and not trained["use_conf"]:
        raise CheckpointError(f"{path} was trained without Conf; add --no-conf to evaluate it as that ablation")
    overrides.update(floor_overrides(cfg.floor, cfg.floor_anchor, cfg.gain_spread))
    if cfg.net_solver and cfg.net_solver != net.get("solver_method", "rwps"):
        overrides["solver_method"] = cfg.net_solver
    model, data = load_model(path, _device(cfg.device), **overrides)
    if model.cfg.n_obs != cfg.n_obs:
        raise ConfigError(f"the network in {path} takes N = {model.cfg.n_obs} observations; set --n-obs {model.cfg.n_obs} (got {cfg.n_obs})")
    used = {"use_rir": model.cfg.use_rir, "use_attention": model.cfg.use_attention, "use_conf": model.cfg.use_conf}
    label = NET_METHOD + "".join(f"-no{n}" for n, k in (("rir", "use_rir"), ("att", "use_attention"), ("conf", "use_conf")) if not used[k])
    if "solver_method" in overrides:
        label += f"-{overrides['solver_method']}"
    info = {"path": str(path), "label": label, "trained": trained, "overrides": overrides, "step": data.get("step"), "ensemble": cfg.net_ensemble, "floor": model.cfg.floor, "floor_anchor": model.cfg.floor_anchor if model.cfg.floor else None, "floor_gain_spread": model.cfg.floor_gain_spread if model.cfg.floor else None}
    if cfg.bf16:
        from reconstruct.net.inference import accelerate

        info["bf16"] = accelerate(model, bf16=True).bf16
    if cfg.net_ensemble > 1:
        from reconstruct.net.network import SymmetryEnsemble

        model = SymmetryEnsemble(model, cfg.net_ensemble).eval()
    return model, info


@dataclasses.dataclass
class EvalReport:
    """Per-frame scores and summaries.

    Attributes:
        frames: list of dicts (group, frame, method, psnr_T, ssim_T, psnr_R, ssim_R).
        rows: per-(group, method) means plus ``overall`` rows.
        figure: {"frames": [...], "columns": [...], "images": [[(H, W) arrays]]}.
        timings: seconds per stage.
        config: resolved configuration (plain data).
        order: the row methods in table order (:func:`summary_rows`).
    """

    frames: list[dict]
    rows: list[dict]
    figure: dict
    timings: dict
    config: dict
    order: list[str] = dataclasses.field(default_factory=list)


def group_zeta(group: EvalGroup, cfg: EvalConfig) -> np.ndarray | None:
    """Zeta (M, H, W) for every frame of a group from the configured source.

    ``gt``: the group's pane maps at the true window-mean angles (paper Eq. (2),
    window-averaged); ``physics``: Fresnel reflectances of the calibrated pane
    (``pane_n``, ``pane_model``) at the group's incidence-angle map, with the
    nominal (calibrated) angles; ``self``: the pane fitted to the group's own
    frames (:func:`reconstruct.pane.selfcal.group_self_zeta`; None where nothing
    modulates); ``learned``: per window from the network
    (:func:`reconstruct.net.learned_zeta.zeta_learned`), so this returns None.
    """
    if cfg.zeta == "learned":
        return None
    if cfg.zeta == "self":  # pane fitted to the stream (reconstruct.pane.selfcal); None where nothing modulates -> learned
        from reconstruct.pane.selfcal import group_self_zeta

        if cfg.self_fov == "fitted":
            group = dataclasses.replace(group, fov_deg=None)  # the scene's fov withheld: fitted, as for a .dat
        if cfg.self_pane_model == "auto":
            return group_self_zeta(group)  # index and pane model fitted where the data constrain them (--pane-n / --pane-model are for physics)
        return group_self_zeta(group, cfg.pane_n, cfg.self_pane_model)
    if cfg.zeta == "gt":
        if group.maps is not None:
            return zeta_from_maps(group.maps, group.phi_true, group.span_rad, dtype=torch.float64).numpy()
        if group.gt_zeta is not None:
            return np.asarray(group.gt_zeta, np.float64)
        raise DataFormatError(f"group {group.name}: no pane maps or GT zeta; use --zeta physics with a calibrated pane")
    from polphysics.fresnel import pane_coefficients

    if group.theta is None or group.maps is None:
        raise DataFormatError(f"group {group.name}: no incidence-angle / phi_perp maps for --zeta physics")
    co = pane_coefficients(group.theta, cfg.pane_n, model=cfg.pane_model)
    maps = PaneMaps(R_perp=co["R_perp"], R_par=co["R_par"], phi_perp=group.maps.phi_perp)
    return zeta_from_maps(maps, group.phi_nominal, group.span_rad, dtype=torch.float64).numpy()


# ---- R where the reflection is >= 20 % of the light, and its noise floor (reconstruct.physics.identifiability) ----

BOUND_GOAL_DB = 22.0
"""Issue 16's goal for R where the reflection is >= 20 % of the light; the share tables count the groups whose
R bound reaches it."""

SHARE_FRAME_KEYS = ("share_frac", "psnr_R_bound", "psnr_R_bound_all", "psnr_R_bound_gls", "bound_frac_22", "psnr_R_flat")
"""Per-frame values that do not depend on the method: the fraction of pixels with reflected share rho >=
:data:`SHARE_MIN`, the PSNR of R implied by the noise floor of the unbiased LS estimate with the true zeta
(:func:`reconstruct.physics.identifiability.ls_layer_variance`) over those pixels, over the whole frame, that of
the inverse-variance weighted LS (the Cramer-Rao bound for Gaussian noise) over those pixels, and the
fraction of those pixels whose own LS variance reaches :data:`BOUND_GOAL_DB` (var R^ <= 10^-2.2: a mean
variance is ruled by the few pixels where zeta hardly modulates, this count is not), and the PSNR over those
pixels of a flat R^ at the GT's mean there (an oracle level without any content: the reference that says how
much of an R score the layer's contrast leaves to explain; a dim or saturated R scores high flat)."""

SHARE_KEYS = ("psnr_R_share", "ssim_R_share", *SHARE_FRAME_KEYS)
"""Keys added to every frame and row: PSNR / SSIM of R over the pixels with rho >= :data:`SHARE_MIN`
(:func:`reconstruct.evaluate.metrics.masked_score`), then :data:`SHARE_FRAME_KEYS`; None where not defined (no GT R or
zeta; the bounds also need the stored group's exposure, :func:`group_noise`)."""


SHARE_NOTE = (
    "rho>=0.2: R scored over the pixels where the reflected share rho = zbar R / (zbar R + (1 - zbar) T) >= 0.2 "
    "(true layers, zbar = half-turn mean of the true zeta); frac = their fraction. R bound (LS, true zeta): PSNR of R over "
    "those pixels implied by the variance of the unbiased least-squares (T, R) from the window's N observations with the "
    "true zeta and the simulator's spike noise (reconstruct/physics/identifiability.py; unclipped, one window)."
)
"""Legend of the reflected-share columns."""


def group_noise(group: EvalGroup, cfg: EvalConfig) -> dict | None:
    """Noise of the group's Eq. (3) window means, as keywords of
    :func:`reconstruct.physics.identifiability.window_mean_variance`, read from the stored group's simulator
    configuration (integrate-and-fire pixel: exposure, window steps at its rate, shot and reset noise, gain
    and threshold spread); None for a group that is not a stored simulation (no ``source_dir`` or config).
    """
    if not group.source_dir:
        return None
    from reconstruct.stream.groups import window_steps_from_ms
    from spike_sim.store import open_group

    try:
        with open_group(group.source_dir) as s:
            sim = s.json_attr("config_json") or {}
            rate = float(s.rate_hz)
    except (OSError, ValueError, KeyError):
        return None
    if not sim:
        return None
    return {
        "exposure": float(sim.get("exposure", 1.0)),
        "window_steps": window_steps_from_ms(cfg.dt_ms, rate),
        "model": "integrate_fire",
        "photons_per_threshold": float(sim.get("photons_per_threshold", 1000.0)) if sim.get("shot_noise", True) else float("inf"),
        "reset_sigma": float(sim.get("reset_sigma", 0.0)) if sim.get("reset_noise", True) else 0.0,
        "rel_sigma": pixel_gain_spread(sim),
    }


def share_context(group: EvalGroup, cfg: EvalConfig) -> dict | None:
    """What :func:`share_scores` needs for a group: the TRUE zeta of every frame (pane maps, else the group's
    GT zeta; whatever ``cfg.zeta`` the solvers use), its half-turn mean zbar, the noise (:func:`group_noise`);
    None without GT layers or a true zeta.

    The share uses zbar = (R_perp + R_par) / 2, the mean of zeta over a half polarizer turn, not the centre
    window's zeta: "the share of reflection in the light" is then a property of the scene (what the camera
    receives without the polarizer), and the mask does not flicker with the polarizer's phase.
    """
    if group.T is None or group.R is None:
        return None
    if group.maps is not None:
        Z = zeta_from_maps(group.maps, group.phi_true, group.span_rad, dtype=torch.float64).numpy()
        zbar = 0.5 * (np.asarray(group.maps.R_perp, np.float64) + np.asarray(group.maps.R_par, np.float64))
    elif group.gt_zeta is not None:
        Z, zbar = np.asarray(group.gt_zeta, np.float64), None  # zbar per window (zbar_of)
    else:
        return None
    return {"Z": Z, "zbar": zbar, "phi": np.asarray(group.phi_true, np.float64), "T": group.T, "R": group.R, "noise": group_noise(group, cfg)}


def share_scores(ctx: dict | None, i: int, K: int) -> dict | None:
    """Frame ``i`` (window i - K .. i + K): {"mask": rho >= SHARE_MIN, "share_frac", "psnr_R_bound",
    "psnr_R_bound_all", "psnr_R_bound_gls"} (bounds None without the noise), or None without a context.

    The bound takes the centre frame's GT layers as static over the window (I_k = ((1 - zeta_k) T + zeta_k R) / 2
    with the window's true zeta_k) and the noise of each window mean at that I_k.
    """
    if ctx is None:
        return None
    Zw = ctx["Z"][i - K : i + K + 1]
    T = np.asarray(ctx["T"][i], np.float64)
    R = np.asarray(ctx["R"][i], np.float64)
    zbar = ctx["zbar"] if ctx["zbar"] is not None else zbar_of(Zw, ctx["phi"][i - K : i + K + 1])
    mask = reflected_share(T, R, zbar) >= SHARE_MIN
    out = {"mask": mask, "share_frac": float(mask.mean()), "psnr_R_bound": None, "psnr_R_bound_all": None, "psnr_R_bound_gls": None, "bound_frac_22": None,
           "psnr_R_flat": masked_psnr(np.full_like(R, R[mask].mean()), R, mask) if mask.any() else None}
    if ctx["noise"] is not None:
        var_I = window_mean_variance(0.5 * ((1.0 - Zw) * T + Zw * R), **ctx["noise"])
        _, vR = ls_layer_variance(Zw, var_I)
        _, vRg = ls_layer_variance(Zw, var_I, weighted=True)
        out.update(psnr_R_bound=bound_psnr(vR, mask), psnr_R_bound_all=bound_psnr(vR), psnr_R_bound_gls=bound_psnr(vRg, mask),
                   bound_frac_22=float((vR[mask] <= 10.0 ** (-BOUND_GOAL_DB / 10.0)).mean()) if mask.any() else None)
    return out


def finite_means(items: list[dict], keys: tuple[str, ...]) -> dict:
    """Per key, the mean of the items' finite values (None where there is none)."""
    out = {}
    for k in keys:
        v = [x[k] for x in items if x.get(k) is not None and np.isfinite(x[k])]
        out[k] = float(np.mean(v)) if v else None
    return out


def evaluate_groups(
    groups: Iterable[EvalGroup],
    cfg: EvalConfig = EvalConfig(),
    solver_cfg: SolverConfig = PHYSICS_SOLVER_CONFIG,
    rir_cfg: RirConfig = RirConfig(),
    weights_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> EvalReport:
    """Run the solvers and baselines over every window of every group.

    Args:
        groups: :class:`EvalGroup` instances (already aggregated with cfg's window and stride).
        cfg: harness configuration.
        solver_cfg: solver parameters (default: the adaptive physics configuration,
            :data:`reconstruct.physics.solvers.PHYSICS_SOLVER_CONFIG`; the network uses its own stored one).
        rir_cfg: registration parameters.
        weights_fn: optional reliability weights (I, phi) -> (B, N, H, W) in [0, 1] for rwps
            (the learned branch); default: :func:`reconstruct.physics.solvers.poisson_reliability`.
        progress: optional (done, total) callback, counted in groups.

    Returns:
        :class:`EvalReport`.
    """
    methods = parse_methods(cfg.methods)
    if cfg.n_obs % 2 == 0:
        raise ConfigError(f"n_obs = {cfg.n_obs} must be odd (N = 2K + 1); use {cfg.n_obs + 1}")
    K = cfg.n_obs // 2
    dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
    dev = _device(cfg.device)
    solvers = [m for m in methods if m in SOLVERS]
    model = net_info = None
    if NET_METHOD in methods or cfg.zeta == "learned":
        from reconstruct.net.checkpoint import set_stream_gain_spread
        from reconstruct.video.tiling import run_model_on_windows

        model, net_info = load_network(cfg)
    nz = net_zeta_of(cfg)
    net_label = None if net_info is None else net_info["label"] + ("" if nz == "learned" else f"@{nz}")
    net_rows = [net_label, net_label + ":solver"] if NET_METHOD in methods else []
    if net_info is not None:
        net_info["zeta"] = nz
    groups = list(groups)
    frames: list[dict] = []
    fig = {"frames": [], "columns": ["input 2I", "tfp", *solvers, *net_rows[:1], "GT T"], "images": []}
    t = defaultdict(float)
    for gi, g in enumerate(groups):
        t0 = time.perf_counter()
        Z = group_zeta(g, cfg)
        if Z is None and model is None:  # --zeta self found nothing modulating: the learned zeta instead
            model, net_info = load_network(cfg)
        Znet = None  # the network's zeta when not its own (None: learned)
        if net_rows and nz not in ("learned", "none"):
            Znet = Z if nz == cfg.zeta else group_zeta(g, dataclasses.replace(cfg, zeta=nz))
        if net_rows and Znet is None and (nz == "none" or (nz == "self" and _refused_fallback(cfg) == "none")):
            Znet = np.zeros(g.I.shape, np.float64)  # no separable reflection: zeta = 0, T is the whole light
        share = share_context(g, cfg)
        t["zeta"] += time.perf_counter() - t0
        M = g.I.shape[0]
        has = np.ones(M, bool) if g.has_gt is None else g.has_gt
        centres = [i for i in range(K, M - K) if has[i] and g.T is not None]
        if cfg.max_frames:
            centres = centres[: cfg.max_frames]
        if not centres:
            log.warning("group %s: no frame with %d neighbours on each side and GT; skipped", g.name, K)
        for b0 in range(0, len(centres), cfg.batch):
            cb = centres[b0 : b0 + cfg.batch]
            Iw = torch.stack([torch.from_numpy(np.ascontiguousarray(g.I[i - K : i + K + 1])) for i in cb]).to(dev, dtype)
            Pw = torch.stack([torch.from_numpy(np.asarray(g.phi_nominal[i - K : i + K + 1], np.float64)) for i in cb]).to(dev, dtype)
            Zw = None if Z is None else torch.stack([torch.from_numpy(np.ascontiguousarray(Z[i - K : i + K + 1])) for i in cb]).to(dev, dtype)
            raw = Iw
            if cfg.rir and cfg.n_obs > 1 and solvers:
                t0 = time.perf_counter()
                sh = torch.stack([estimate_shifts(Iw[j], Pw[j], config=rir_cfg) for j in range(len(cb))]).to(dtype)
                Iw = warp(Iw, sh)
                Zw = None if Zw is None else warp(Zw, sh)
                t["rir"] += time.perf_counter() - t0
            W_learned = None
            if Z is None and solvers:
                t0 = time.perf_counter()
                Zw, W_learned = zeta_learned(model, Iw, Pw)
                t["learned_zeta"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            est = {}
            for m in solvers:
                w = None
                if m == "rwps":
                    w = W_learned if W_learned is not None else (weights_fn(Iw, Pw) if weights_fn is not None else None)
                r = solve(m, Zw, Iw, weights=w, config=solver_cfg)
                est[m] = (r.T.cpu().numpy(), r.R.cpu().numpy())
            t["solve"] += time.perf_counter() - t0
            Im = None if g.I_mean is None else np.stack([g.I_mean[i] for i in cb])  # the long spike mean of each centre
            if net_rows:
                t0 = time.perf_counter()
                zn = None if Znet is None else np.stack([np.ascontiguousarray(Znet[i - K : i + K + 1], np.float32) for i in cb])
                x = network_inputs(g, model, raw.float().cpu().numpy(), Pw.float().cpu().numpy(), cb, K)  # with the long span it reads; ConfigError where the group lacks it
                if b0 == 0 and model.cfg.floor_gain_spread == GAIN_SPREAD_AUTO:  # once per group: the floor's allowance for its own sensor (--gain-spread auto)
                    set_stream_gain_spread(model, float(((share or {}).get("noise") or group_noise(g, cfg) or {}).get("rel_sigma", 0.0)))
                o = run_model_on_windows(model, x, device=next(model.parameters()).device, tile=cfg.net_tile, zeta=zn)
                est[net_rows[0]] = (o["T"], o["R"])
                est[net_rows[1]] = (o["T_base"], o["R_base"])
                t["network"] += time.perf_counter() - t0
            if cfg.anchor == "mean" and Im is not None:
                zbars = {m: Zw for m in solvers}
                if net_rows:
                    zl = torch.as_tensor(zn, dtype=dtype, device=dev) if zn is not None else zeta_learned(model, raw, Pw)[0]
                    zbars.update({net_rows[0]: zl, net_rows[1]: zl})
                for m, zz in zbars.items():
                    if zz is not None:
                        est[m + ANCHOR_SUFFIX] = anchor_to_mean(*est[m], Im, zbar_of(zz, Pw).float().cpu().numpy())
                if solvers and Zw is not None and g.I_harm is not None:  # every spike of the span (physics, the solvers' zeta)
                    Ts, Rs = long_span_separation(torch.as_tensor(Im, dtype=torch.float64), torch.as_tensor(np.stack([g.I_harm[i] for i in cb]), dtype=torch.float64), Zw.double().cpu(), Pw.double().cpu())
                    est[SPAN_METHOD] = (Ts.float().numpy(), Rs.float().numpy())
            t0 = time.perf_counter()
            tfp = (2.0 * raw.mean(1)).cpu().numpy()
            raw_np = (2.0 * raw).cpu().numpy()
            for j, i in enumerate(cb):
                gtT = g.T[i]
                gtR = None if g.R is None else g.R[i]
                shr = share_scores(share, i, K)  # the reflected-share mask and the R noise floor of this frame
                rows = {"tfp": (tfp[j], None)}
                best = max(range(cfg.n_obs), key=lambda k: psnr(raw_np[j, k], gtT))
                rows["best_frame"] = (raw_np[j, best], None)
                if g.I_mean is not None:
                    rows["spike_mean"] = (2.0 * g.I_mean[i], None)
                rows.update(est_j := {m: (v[0][j], v[1][j]) for m, v in est.items()})
                for name, (Th, Rh) in rows.items():
                    sT = score(Th, gtT)
                    has_R = Rh is not None and gtR is not None
                    sR = score(Rh, gtR) if has_R else {"psnr": None, "ssim": None}
                    sS = masked_score(Rh, gtR, shr["mask"]) if (has_R and shr is not None) else {"psnr": None, "ssim": None}
                    frames.append({"group": g.name, "frame": int(i), "method": name, "psnr_T": sT["psnr"], "ssim_T": sT["ssim"], "psnr_R": sR["psnr"], "ssim_R": sR["ssim"],
                                   "psnr_R_share": sS["psnr"], "ssim_R_share": sS["ssim"], **({k: None for k in SHARE_FRAME_KEYS} if shr is None else {k: shr[k] for k in SHARE_FRAME_KEYS})})
                if j == 0 and b0 == 0 and len(fig["frames"]) < cfg.figure_frames:  # first frame of each group
                    fig["frames"].append(f"{g.name} #{i}")
                    fig["images"].append([raw_np[j, K], tfp[j], *[est_j[m][0] for m in solvers], *[est_j[m][0] for m in net_rows[:1]], gtT])
            t["metrics"] += time.perf_counter() - t0
        if progress is not None:
            progress(gi + 1, len(groups))
    order = [*BASELINES, *[x for m in [*solvers, *net_rows] for x in (m, m + ANCHOR_SUFFIX)], SPAN_METHOD]
    conf = {"eval": to_dict(cfg), "solver": to_dict(solver_cfg), "rir": to_dict(rir_cfg), "groups": [g.name for g in groups]}
    if net_info is not None:
        conf["network"] = net_info
    return EvalReport(frames=frames, rows=summary_rows(frames, order), figure=fig, timings=dict(t), config=conf, order=order)


def summary_rows(frames: list[dict], order: list[str]) -> list[dict]:
    """Per-(group, method) means of the per-frame scores, groups in their first appearance, then the ``overall`` rows;
    methods in ``order``.
    """
    keys = ("psnr_T", "ssim_T", "psnr_R", "ssim_R", *SHARE_KEYS)
    rows = []
    by = defaultdict(list)
    for f in frames:
        by[(f["group"], f["method"])].append(f)
    for g in dict.fromkeys(f["group"] for f in frames):
        for m in order:
            items = by.get((g, m), [])
            if items:
                rows.append({"group": g, "method": m, "n_frames": len(items), **finite_means(items, keys), "lpips_T": lpips_status()})
    for m in order:
        items = [f for f in frames if f["method"] == m]
        if items:
            rows.append({"group": "overall", "method": m, "n_frames": len(items), **finite_means(items, keys), "lpips_T": lpips_status()})
    return rows


ANCHOR_SUFFIX = "+mean"
"""Row-name suffix of a method anchored to the spike mean (:func:`reconstruct.physics.span.anchor_to_mean`)."""

SPAN_METHOD = "span"
"""Row of ``--anchor mean`` (with a physics solver): the layers from the first harmonic of the whole 17.5 ms span of
spikes on the solvers' zeta (:func:`reconstruct.physics.span.long_span_separation`): physics from every spike of the span,
not only the N windows'."""


def _fmt(v, nd=3) -> str:
    return "n/a" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def markdown_table(report: EvalReport, overall_only: bool = False) -> str:
    """Markdown table of per-group and overall means (PSNR dB / SSIM for T and R; R also over the pixels with
    reflected share rho >= 0.2, their fraction and the R noise floor there, :data:`SHARE_KEYS`).
    """
    head = (
        "| group | method | frames | PSNR T (dB) | SSIM T | PSNR R (dB) | SSIM R | LPIPS T | PSNR R rho>=0.2 (dB) | SSIM R rho>=0.2 | rho>=0.2 frac | R bound (LS, true zeta) |\n"
        "|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|\n"
    )
    lines = []
    for r in report.rows:
        if overall_only and r["group"] != "overall":
            continue
        lines.append(
            f"| {r['group']} | {r['method']} | {r['n_frames']} | {_fmt(r['psnr_T'], 2)} | {_fmt(r['ssim_T'])} | {_fmt(r['psnr_R'], 2)} | {_fmt(r['ssim_R'])} | {r['lpips_T']} "
            f"| {_fmt(r.get('psnr_R_share'), 2)} | {_fmt(r.get('ssim_R_share'))} | {_fmt(r.get('share_frac'))} | {_fmt(r.get('psnr_R_bound'), 2)} |"
        )
    return head + "\n".join(lines) + "\n"


def write_report(report: EvalReport, out_dir: str | Path) -> dict[str, Path]:
    """Write results.csv, results.md, results.json, config.json and figure.png (atomically)."""
    import csv
    import io

    from polinfra.atomic import atomic_path, ensure_dir, write_json, write_text

    out = ensure_dir(out_dir)
    paths = {}
    buf = io.StringIO()
    cols = ["group", "method", "n_frames", "psnr_T", "ssim_T", "psnr_R", "ssim_R", "lpips_T", *SHARE_KEYS]
    wr = csv.DictWriter(buf, fieldnames=cols)
    wr.writeheader()
    for r in report.rows:
        wr.writerow({k: ("n/a" if r.get(k) is None else r[k]) for k in cols})
    paths["csv"] = write_text(out / "results.csv", buf.getvalue())
    md = "# Evaluation\n\n" + markdown_table(report) + f"\nLPIPS: {LPIPS_NA}: LPIPS needs pretrained backbone weights and there is no download here.\n"
    md += f"\nBaselines: tfp = 2 x window mean of I (unaligned); best_frame = best single 2 I(i+k) by PSNR (oracle pick).\n\n{SHARE_NOTE}\n\nTimings (s): {', '.join(f'{k} {v:.2f}' for k, v in report.timings.items())}\n"
    paths["md"] = write_text(out / "results.md", md)
    paths["json"] = write_json(out / "results.json", {"rows": report.rows, "timings": report.timings, "config": report.config})
    paths["config"] = write_json(out / "config.json", report.config)
    if report.figure["images"]:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        imgs = report.figure["images"]
        cols_ = report.figure["columns"]
        fig, axes = plt.subplots(len(imgs), len(cols_), figsize=(2.2 * len(cols_), 1.6 * len(imgs) + 0.4), squeeze=False)
        for r, row in enumerate(imgs):
            gain = 1.0 / max(float(np.percentile(row[-1], 99.5)), 1e-6)  # per-row display gain: GT T's 99.5th percentile -> white
            for c, im in enumerate(row):
                ax = axes[r, c]
                ax.imshow(np.clip(im * gain, 0, 1), cmap="gray", vmin=0, vmax=1)
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(cols_[c], fontsize=8)
                if c == 0:
                    ax.set_ylabel(f"{report.figure['frames'][r]}\n(gain {gain:.1f})", fontsize=7)
        fig.tight_layout()
        with atomic_path(out / "figure.png") as tmp:
            fig.savefig(tmp, dpi=110)
        plt.close(fig)
        paths["figure"] = out / "figure.png"
    return paths


def load_groups(dataset: str, split: str, cfg: EvalConfig, synthetic=None, progress: Callable[[int, int], None] | None = None) -> list[EvalGroup]:
    """Evaluation groups of ``dataset``: a dataset directory / group directory, or ``synthetic``.

    ``synthetic`` (optionally ``synthetic:SEED``) builds the closed-form set of
    :mod:`reconstruct.stream.synthetic` in-process (``synthetic`` is its config, window
    and stride are taken from cfg).
    """
    loaders = group_loaders(dataset, split, cfg, synthetic)
    out = []
    for j, load in enumerate(loaders):
        out.append(load())
        if progress:
            progress(j + 1, len(loaders))
    return out


def group_loaders(dataset: str, split: str, cfg: EvalConfig, synthetic=None) -> list[Callable[[], EvalGroup]]:
    """One picklable loader per group of :func:`load_groups` (``loader()`` -> :class:`EvalGroup`): a group can be
    loaded where it is evaluated (a Dask worker that sees the dataset).
    """
    import functools

    from reconstruct.stream.groups import list_groups, window_steps_from_ms

    if dataset.startswith("synthetic"):
        from reconstruct.stream.synthetic import SyntheticConfig, make_group

        sc = synthetic or SyntheticConfig()
        seed = int(dataset.split(":", 1)[1]) if ":" in dataset else sc.seed
        sc = dataclasses.replace(sc, seed=seed, window_steps=window_steps_from_ms(cfg.dt_ms, sc.rate_hz), stride_deg=cfg.stride_deg)
        return [functools.partial(make_group, sc, g) for g in range(sc.n_groups)]
    frames = cfg.max_frames + 2 * (cfg.n_obs // 2) if cfg.max_frames else 0
    return [functools.partial(_load_store, str(path), cfg.dt_ms, cfg.stride_deg, cfg.n_obs, frames, name) for name, path in list_groups(dataset, split)]


def _load_store(path: str, dt_ms: float, stride_deg: float, n_obs: int, frames: int, name: str) -> EvalGroup:
    from reconstruct.stream.groups import load_store_group, window_steps_from_ms
    from spike_sim.store import open_group

    with open_group(path) as g:
        rate = g.rate_hz
    return load_store_group(path, window_steps_from_ms(dt_ms, rate), stride_deg, n_obs, frames, name)


# ---- per-regime table (stress.toml) ---------------------------------------------------------------

REGIME_FACTORS: dict[str, tuple[str, ...]] = {
    "refl": ("weak", "strong", "dominant"),
    "motion": ("static", "fast"),
    "light": ("dim", "bright"),
    "inc": ("normal", "brewster", "glancing"),
    "pane": ("single", "slab"),
}
"""Factors and levels of the stress grid; a group named ``refl-weak_motion-fast_light-dim_inc-brewster_pane-slab``
(any order, ``FACTOR-LEVEL`` joined by ``_``) belongs to one level of each."""

