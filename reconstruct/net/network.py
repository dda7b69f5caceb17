"""The learned reconstructor: parameter branch with angle attention, RWPS, refinement.

Paper Sec. 3.2-3.3 and supp. Sec. 10 ("Network architecture"):

1. **RIR** (optional, :mod:`reconstruct.physics.rir`): the window is aligned to its centre
   frame; the shift estimate is not differentiated, the warp is.
2. **Parameter branch**: each of the N = 2K+1 observations is encoded by three
   64-channel ConvBlocks and two 3x3 convolutions (weights shared over k); a
   two-head **angle attention** block projects features to queries, injects the
   angle embedding [cos 2phi_k, sin 2phi_k] into keys and values, takes a softmax
   over the N observations at every pixel, and adds the attended feature back.
   Heads predict per-pixel (a0, ac, as) and per-observation reliability logits;
   zeta_k = sigmoid(a0 + ac cos 2phi_k + as sin 2phi_k) (supp. Eq. (19)) and
   w_k = softmax_k(logits) (supp. Sec. 10).
3. **RWPS** (:func:`reconstruct.physics.solvers.solve`, method ``rwps``) with those zeta
   and w; during training the zeta fed to the solver is
   alpha zeta_gt + (1 - alpha) zeta_hat (teacher forcing, paper Sec. 3.4).
4. **Refinement** on x = [T^, R^, 2I, 2I_min, Conf, 2Res] of the centre frame,
   Res = I - I^ the back-projection residual of paper Eq. (7); a shared encoder
   and two light decoders predict Delta_t, Delta_r; T = T^ + Delta_t,
   R = R^ + Delta_r (paper Sec. 3.3).

Units: I in radiance units of paper Eq. (1) (I = 1/2 (zeta R + (1 - zeta) T),
1.0 = brightest layer value); T, R in the same units.  Ablation switches
(paper Table 1): ``use_rir``, ``use_attention``, ``use_conf``.

Running a trained checkpoint (stable API for evaluation harnesses)::

    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
    model, meta = load_model(DEFAULT_WEIGHTS, "cpu")            # eval mode; meta["step"], meta["net"], ...
    model, _ = load_model(path, "cpu", use_rir=True)            # NetConfig overrides at load time
    out = model(I, phi)   # I (B, N, H, W) float32 radiance units, phi (B, N) rad; H, W multiples of 4
    out.T, out.R                  # final layers (B, H, W)                 -> "final" / method full
    out.T_base, out.R_base        # RWPS with the learned zeta and w       -> "RWPS-only" / solver-only
    out.zeta_hat, out.weights     # (B, N, H, W); out.conf (B, H, W)

For any H, W (padding, tiling with overlap) use
:func:`reconstruct.video.tiling.run_model_on_windows`.  Ablations: ``use_rir`` has no
weights and may be toggled at load; ``use_attention`` and ``use_conf`` need
checkpoints trained with them (``reconstruct/configs/ablation_*.toml``);
``solver_method`` ("ls", "ridge", "irls", "rwps") may be overridden at load
to run another solver before the same refinement (supp. Table 3).
"""

from __future__ import annotations

import dataclasses
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError
from reconstruct.net.floor import network_floor
from reconstruct.physics.solvers import SolverConfig, solve
from reconstruct.physics.span import anchor_to_mean, gaussian_blur, gaussian_radius, long_span_separation, span_blend, span_weights, zbar_of
from reconstruct.physics.symmetry import symmetry_angles, symmetry_harmonic, symmetry_image
from reconstruct.stream.window_inputs import WindowInputs

__all__ = ["GAIN_SPREAD_AUTO", "GAIN_SPREAD_ESTIMATE", "NetConfig", "NetOutput", "AngleAttention", "ParameterBranch", "LowResParameterBranch", "Refinement", "window_scale", "PolSpikeNet", "count_parameters", "init_weights", "predict_parameters", "SYMMETRY_CODES", "check_ensemble_size", "SymmetryEnsemble"]


GAIN_SPREAD_AUTO = -1.0
"""``NetConfig.floor_gain_spread`` (``--gain-spread auto``, the default): the stream's own spread where its reader knows
it (:func:`reconstruct.net.checkpoint.set_stream_gain_spread`), else 0."""

GAIN_SPREAD_ESTIMATE = -2.0
"""``NetConfig.floor_gain_spread`` (``--gain-spread estimate``): the floor's allowance for the sensor's gain spread as the
windows show it (:func:`reconstruct.physics.consistency.estimate_gain_spread`)."""


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """Architecture and ablation switches of :class:`PolSpikeNet`.

    ``arch`` selects the parameter branch: ``"v1"`` (:class:`ParameterBranch`, full
    resolution, the shipped ``polspike_v1.pt``) or ``"v2"``
    (:class:`LowResParameterBranch`, features at 1/``down`` resolution plus a light
    full-resolution path for w_k; per-observation features cacheable).  Checkpoints
    written before the field existed have no ``arch`` key and load as ``"v1"``
    (:func:`reconstruct.net.checkpoint.load_model`).
    """

    arch: str = opt("v2", "parameter branch: v1 (full resolution, 257 GFLOP/frame) | v2 (low resolution + light full-resolution w path)", choices=("v1", "v2"))
    down: int = opt(4, "v2: downsampling factor of the per-observation features (pixel-unshuffle), 2 | 4 | 8", choices=(2, 4, 8))
    lr_ch: int = opt(48, "v2: channels of the low-resolution per-observation features (and of the angle attention)", lo=4, hi=512)
    w_ch: int = opt(8, "v2: channels of the full-resolution reliability (w_k) path", lo=1, hi=64)
    n_obs: int = opt(7, "observations per window N = 2K+1", lo=3, hi=31)
    feat_ch: int = opt(64, "v1: channels of the parameter branch ConvBlocks (supp. Sec. 10: 64)", lo=4, hi=512)
    heads: int = opt(2, "angle attention heads (supp. Sec. 10: 2)", lo=1, hi=16)
    ref_ch: tuple[int, int, int] = opt((32, 64, 80), "refinement encoder widths at scales 1, 1/2, 1/4", lo=4, hi=1024)
    dec_ch: tuple[int, int, int] = opt((40, 32, 32), "each refinement decoder's widths at scales 1/4->1/2, 1/2->1, full", lo=4, hi=1024)
    use_rir: bool = opt(True, "align the window with RIR before the network (ablation: without RIR)")
    use_attention: bool = opt(True, "angle attention block (ablation: without angle attention)")
    use_conf: bool = opt(True, "Conf-driven lambda in RWPS and Conf input to the refinement (ablation: without Conf)")
    use_mean: bool = opt(False, "the refinement also sees the long spike mean I_mean (window.mean_steps) and T anchored to it, 2 I_mean - zbar (R^ - T^) (paper Eq. (1) over a half turn): the level from ~27x more spikes")
    base: str = opt("solver", "what the refinement's Delta_t, Delta_r are added to: solver (T^, R^, paper Sec. 3.3) | anchored (T^, R^ anchored to the long spike mean, reconstruct.physics.span.anchor_to_mean; needs use_mean): the untrained refinement then returns the anchored physics", choices=("solver", "anchored"))
    anchor_zbar: str = opt("window", "zbar of the anchor: window (mean of zeta over the N windows, what polspike_v2_mean.pt was trained with) | harmonic (the first-harmonic level of zeta over the window's angles, reconstruct.physics.span.zbar_of: the half-turn mean paper Eq. (1) needs)", choices=("window", "harmonic"))
    solver_method: str = opt("rwps", "physics solver run on the predicted zeta and w", choices=("ls", "ridge", "irls", "rwps"))
    use_harm: bool = opt(False, "the refinement also sees T and R separated from the first harmonic of the whole long span of spikes (I_harm; reconstruct.physics.span.long_span_separation): about 4x the spikes of the N windows for the difference R - T; needs use_mean")
    use_wide: bool = opt(False, "the refinement also sees T and R from the solver on the N observations over the wide window (I_wide: the whole stride, every spike between the windows' centres, ~4x the spikes of the 0.65 ms windows), anchored to I_mean as the base; needs use_mean")
    t_level_px: float = opt(0.0, "T's level from the wide windows' anchored physics: T += G_s * (T_wide - T_base), G_s a Gaussian blur of this sigma in pixels (0 = off; the network then reads I_wide; needs use_mean): the refinement follows its base's low frequencies, whose noise the wide windows' ~4x spikes lower; no weights, only inference", lo=0.0, hi=256.0)
    r_level_from: str = opt("base", "where r_level_px takes R's level: base (the anchored physics on the N windows) | wide (the same on the wide windows, ~4x the spikes; the network then reads I_wide)", choices=("base", "wide"))
    r_level_px: float = opt(0.0, "R's level from the base, its structure from the refinement: R = R_ref + G_s * (R_base - R_ref), G_s a Gaussian blur of this sigma in pixels (0 = off, the refined R). The refinement shrinks R's level where the spikes do not identify it; the base (the anchored physics with base = anchored) keeps it; no weights, only inference", lo=0.0, hi=256.0)
    span_level: bool = opt(False, "D = R - T toward the long span's first harmonic where the span identifies it (reconstruct.physics.span.span_blend with span_weights: inverse-variance, saturated pixels left out), keeping the long mean: every spike of 17.5 ms for the difference the refinement's spikes leave noisy or biased. Applied on an external zeta only (self-calibrated or given, fed with alpha = 1), never on the learned per-window zeta, whose orientation nothing checks over the span; the network then reads I_harm and needs the stream's exposure and span length (training items carry both); no weights, and no gradient through the move; needs use_mean")
    span_level_px: float = opt(2.0, "span_level: sigma in pixels of the normalised convolution of the span's correction (0 = per pixel)", lo=0.0, hi=256.0)
    span_level_tol: float = opt(2.0, "span_level: the error of the refined D, relative to the pixel's light 2 I_mean, the span's noise is weighed against: its gain is tol^2 / (tol^2 + var) (relative, so the move does not depend on the brightness scale, e.g. an estimated exposure)", lo=1e-6, hi=1e6)
    span_level_tol_t: float = opt(0.25, "span_level: also keep T, which moves by zbar times the change of D, no noisier than this fraction of the pixel's light 2 I_mean (gain min(tol^2 / (tol^2 + var), tol_t^2 / (tol_t^2 + zbar^2 var)); 0 = off): where zeta's mean is large (a glancing pane, or a calibration that put it there) the span's noise reaches T", lo=0.0, hi=1e6)
    span_rad: float = opt(math.radians(7.02), "polarizer rotation inside one aggregation window (0.65 ms at 30 rev/s), rad; recorded with the weights, not used by the layers", lo=0.0, hi=math.pi)
    floor: bool = opt(True, "data-consistency floor at inference (reconstruct.physics.consistency): the final (T, R) must predict the N aligned windows (paper Eq. (1)-(2)) within floor_tol noise variances of the physics-only RWPS's residual on the same zeta; where it does not, it is pulled back toward that physics. No weights; off while training")
    floor_tol: float = opt(4.0, "the floor's allowed excess residual, in noise variances of one observation (4: the floored error is the smaller of the refinement's and the physics', reconstruct.physics.consistency)", lo=0.0, hi=1e6)
    floor_anchor: str = opt("blend", "what the floor falls back to where the data check fails: blend (per pixel the physics-only RWPS and the best closed-form physics weighed by their error powers, reconstruct.physics.anchor.error_blend; on an external zeta, else rwps) | rwps (the physics-only RWPS) | best (the best closed-form physics alone, reconstruct.physics.anchor: far below the RWPS where zeta barely modulates under a bright reflection; docs/motion.md)", choices=("rwps", "best", "blend"))
    floor_layers: bool = opt(False, "with floor_anchor = best or blend: also judge T and R by their own move from the anchor against its stated error power (in proportion to the windows' expected spikes up to one per window). It lifts bright strong-reflection motion cells by 0.3-0.6 dB but costs 1.0 dB on the paper-profile test windows (RIR on), where the anchor errs 2-4 x more than it states")
    floor_gain_spread: float = opt(GAIN_SPREAD_AUTO, "the sensor's per-pixel gain spread (relative sd) the floor allows for: a gain error scales a pixel's 7 observations alike and a fit absorbs it, so a move along the physics itself within three spreads is not counted (reconstruct.physics.consistency.move_excess). -1 (the default): the stream's own where it is known (a stored simulation's fixed pattern, set by the reader: reconstruct.net.checkpoint.set_stream_gain_spread; a recording's calibration is given as a number), else 0. -2: estimated from the windows, per image, only its pixel-white part freed (reconstruct.physics.consistency.estimate_gain_spread; it reads the network's own pixel-level errors as a pattern where the sensor has none: docs/motion.md). 0: none", lo=-2.0, hi=0.5)
    floor_mode: str = opt("shrink", "the floor: shrink (keep the fraction min(1, floor_tol sigma^2 / excess) of the refinement's move from the physics) | hard (the physics wherever the excess exceeds floor_tol sigma^2)", choices=("shrink", "hard"))

    def __post_init__(self) -> None:
        """The feature combinations: a :class:`ConfigError` naming what cannot be built."""
        anchored = [k for k, on in (("base = anchored", self.base == "anchored"), ("use_harm", self.use_harm), ("use_wide", self.use_wide), ("t_level_px", self.t_level_px > 0),
                                    ("r_level_from = wide", self.r_level_from == "wide"), ("span_level", self.span_level)) if on]
        if anchored and not self.use_mean:
            raise ConfigError(f"{', '.join(anchored)} need{'s' if len(anchored) == 1 else ''} use_mean = true (the anchor is the long spike mean)")
        ch = self.feat_ch if self.arch == "v1" else self.lr_ch
        if self.use_attention and ch % self.heads:
            raise ConfigError(f"{'feat_ch' if self.arch == 'v1' else 'lr_ch'} = {ch} must be a multiple of heads = {self.heads} (the angle attention splits its channels over the heads)")

    @property
    def inputs(self) -> frozenset[str]:
        """What the network reads beside its windows (names of :class:`reconstruct.stream.window_inputs.WindowInputs`)."""
        return frozenset(k for k, on in (("I_mean", self.use_mean), ("I_harm", self.harm_input), ("I_wide", self.wide_input),
                                         ("exposure", self.span_level), ("span_steps", self.span_level)) if on)

    @property
    def reach_px(self) -> int:
        """Pixels an output pixel reads around itself beyond the convolutions: the widest blur of the levels and the span's
        correction (a tile's margin must cover it).
        """
        return max(gaussian_radius(self.r_level_px), gaussian_radius(self.t_level_px), gaussian_radius(self.span_level_px) if self.span_level else 0)

    @property
    def wide_input(self) -> bool:
        """Whether the network reads the wide windows ``I_wide``: as refinement inputs (``use_wide``) or for T's / R's
        levels (``t_level_px``, ``r_level_from = wide``).
        """
        return bool(self.use_wide or self.t_level_px > 0 or self.r_level_from == "wide")

    @property
    def harm_input(self) -> bool:
        """Whether the network reads the long span's first harmonic ``I_harm``: as refinement inputs (``use_harm``) or
        for D's level (``span_level``, which also needs the stream's exposure and span length).
        """
        return bool(self.use_harm or self.span_level)


@dataclasses.dataclass
class NetOutput:
    """Forward results; maps (B, H, W), per-observation tensors (B, N, H, W)."""

    T: torch.Tensor
    R: torch.Tensor
    T_base: torch.Tensor
    R_base: torch.Tensor
    zeta_hat: torch.Tensor
    zeta_used: torch.Tensor
    weights: torch.Tensor
    conf: torch.Tensor
    res: torch.Tensor
    I: torch.Tensor
    zeta_gt: torch.Tensor | None
    floor_keep: torch.Tensor | None = None
    """(B, H, W) the floor's kept fraction of the refinement's move from the physics (1 = unchanged), when it ran."""


class ConvBlock(nn.Module):
    """3x3 convolution + LeakyReLU(0.1)."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, stride=stride, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.conv(x), 0.1)


class AngleAttention(nn.Module):
    """Two-head attention over the N observations at each pixel (paper Sec. 3.3).

    Queries come from the features only; the angle embedding e_k =
    [cos 2phi_k, sin 2phi_k] is projected and added to keys and values; the
    softmax runs over the N observations of one pixel; the attended feature is
    projected and added back to the input feature (residual).
    """

    def __init__(self, ch: int, heads: int = 2):
        super().__init__()
        if ch % heads:
            raise ConfigError(f"attention channels {ch} must be a multiple of heads {heads}")
        self.heads = heads
        self.q = nn.Linear(ch, ch)
        self.k = nn.Linear(ch, ch)
        self.v = nn.Linear(ch, ch)
        self.ek = nn.Linear(2, ch, bias=False)
        self.ev = nn.Linear(2, ch, bias=False)
        self.o = nn.Linear(ch, ch)

    def forward(self, f: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
        """F (B, N, C, H, W), phi (B, N) radians -> (B, N, C, H, W)."""
        B, N, C, H, W = f.shape
        x = f.permute(0, 3, 4, 1, 2).reshape(B * H * W, N, C)
        e = torch.stack([torch.cos(2 * phi), torch.sin(2 * phi)], -1).to(f.dtype)  # (B, N, 2) angle embedding
        e = e[:, None, None].expand(B, H, W, N, 2).reshape(B * H * W, N, 2)
        d = C // self.heads
        q = self.q(x).view(-1, N, self.heads, d).transpose(1, 2)
        k = (self.k(x) + self.ek(e)).view(-1, N, self.heads, d).transpose(1, 2)  # angle into keys
        v = (self.v(x) + self.ev(e)).view(-1, N, self.heads, d).transpose(1, 2)  # and values
        att = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(d), dim=-1)  # softmax over the N observations
        y = (att @ v).transpose(1, 2).reshape(-1, N, C)
        y = x + self.o(y)  # attended feature added back
        return y.view(B, H, W, N, C).permute(0, 3, 4, 1, 2)


class ParameterBranch(nn.Module):
    """Predicts zeta_hat (B, N, H, W) and reliability weights w (B, N, H, W)."""

    IN_CH = 3

    def __init__(self, cfg: NetConfig):
        super().__init__()
        c = cfg.feat_ch
        self.cfg = cfg
        self.enc = nn.Sequential(ConvBlock(self.IN_CH, c), ConvBlock(c, c), ConvBlock(c, c))  # three 64-ch ConvBlocks
        self.conv1 = nn.Conv2d(c, c, 3, padding=1)  # two 3x3 convolutions
        self.conv2 = nn.Conv2d(c, c, 3, padding=1)
        self.att = AngleAttention(c, cfg.heads) if cfg.use_attention else None
        self.rel = nn.Conv2d(c, 1, 1)  # reliability logit per observation
        self.par1 = nn.Conv2d(c, c // 2, 3, padding=1)  # (a0, ac, as) head on the window-pooled feature
        self.par2 = nn.Conv2d(c // 2, 3, 1)

    def forward(self, I: torch.Tensor, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """I (B, N, H, W) radiance units, phi (B, N) -> (zeta_hat, w, (a0, ac, as) stacked (B, 3, H, W))."""
        B, N, H, W = I.shape
        scale = I.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-4)
        x = I / scale  # brightness-normalised stack
        mean = x.mean(1, keepdim=True).expand_as(x)
        inp = torch.stack([x, mean, x - mean], 2).reshape(B * N, self.IN_CH, H, W)
        f = self.enc(inp)
        f = F.leaky_relu(self.conv1(f), 0.1)
        f = self.conv2(f).view(B, N, -1, H, W)
        if self.att is not None:
            f = self.att(f, phi)
        logits = self.rel(f.reshape(B * N, -1, H, W)).view(B, N, H, W)
        w = torch.softmax(logits, dim=1)  # w_k: softmax over the window, supp. Sec. 10
        g = F.leaky_relu(self.par1(f.mean(1)), 0.1)
        a = self.par2(g)
        a0, ac, as_ = a[:, 0:1], a[:, 1:2], a[:, 2:3]
        c2 = torch.cos(2 * phi)[..., None, None].to(I.dtype)
        s2 = torch.sin(2 * phi)[..., None, None].to(I.dtype)
        zeta = torch.sigmoid(a0 - 2.0 + ac * c2 + as_ * s2)  # supp. Eq. (19); -2 centres the init near glass reflectance
        return zeta, w, a


def window_scale(I: torch.Tensor) -> torch.Tensor:
    """Brightness normaliser of the v2 branch: the window mean rounded to a power of two, (B,) -> shaped (B, 1, 1, 1).

    Rounding makes the scale the same for overlapping windows of a stream (it changes only
    when the mean brightness crosses a power of two), so per-observation features computed
    for one window are exact for the next (:meth:`LowResParameterBranch.encode_obs`).
    """
    m = I.detach().float().mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-4)
    return torch.exp2(torch.round(torch.log2(m))).to(I.dtype)


class LowResParameterBranch(nn.Module):
    """v2 parameter branch: (a0, ac, as) from features at 1/``down`` resolution, w_k from a light full-resolution path.

    Per observation k (weights shared over k; a function of I_k and the scale only, so a
    stream computes it once per Eq. (3) frame, :meth:`encode_obs`):

    * low resolution: pixel-unshuffle of x_k = I_k / s by ``down`` (no information lost),
      three ``lr_ch`` ConvBlocks -> f_k (C, H/down, W/down);
    * full resolution: two ``w_ch`` ConvBlocks on x_k -> g_k (w_ch, H, W).

    Per window: two-head **angle attention** over the N low-resolution features (as v1);
    (a0, ac, as) from the window-mean feature (3x3 + 1x1 convolutions) at low resolution,
    upsampled bilinearly to full resolution (zeta is smooth by physics:
    it follows from the pane geometry); zeta_k = sigmoid(a0 + ac cos 2phi_k + as sin 2phi_k)
    (supp. Eq. (19)); reliability logits from [g_k, upsampled projection of the attended f_k,
    x_k - mean_k x] by two 1x1 convolutions at full resolution, w = softmax over k.
    """

    def __init__(self, cfg: NetConfig):
        super().__init__()
        c, d, wc = cfg.lr_ch, cfg.down, cfg.w_ch
        self.cfg = cfg
        self.down = d
        self.enc = nn.Sequential(ConvBlock(d * d, c), ConvBlock(c, c), ConvBlock(c, c))
        self.wenc = nn.Sequential(ConvBlock(1, wc), ConvBlock(wc, wc))
        self.att = AngleAttention(c, cfg.heads) if cfg.use_attention else None
        self.wproj = nn.Conv2d(c, wc, 1)
        self.whead1 = nn.Conv2d(2 * wc + 1, wc, 1)
        self.rel = nn.Conv2d(wc, 1, 1)
        self.par1 = nn.Conv2d(c, c // 2, 3, padding=1)
        self.par2 = nn.Conv2d(c // 2, 3, 1)

    def encode_obs(self, I: torch.Tensor, scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-observation features: I (M, H, W) radiance units, scale (M,) -> (f (M, C, H/d, W/d), g (M, w_ch, H, W))."""
        x = (I / scale.reshape(-1, 1, 1))[:, None]
        f = self.enc(F.pixel_unshuffle(x, self.down))
        g = self.wenc(x)
        return f, g

    def forward(
        self, I: torch.Tensor, phi: torch.Tensor, feats: tuple[torch.Tensor, torch.Tensor] | None = None, scale: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """I (B, N, H, W), phi (B, N) -> (zeta_hat, w, (a0, ac, as) (B, 3, H, W)).

        ``feats``: optional precomputed :meth:`encode_obs` output for the B*N observations
        (with the same ``scale``); computed here when omitted.  ``scale``: optional (B, 1, 1, 1)
        brightness normaliser; default ``window_scale(I)``.  A caller that cuts a frame into tiles
        passes the whole frame's scale, so every tile is normalised alike (no seams between tiles
        whose own means round to different powers of two).
        """
        B, N, H, W = I.shape
        scale = window_scale(I) if scale is None else scale.to(I.dtype).reshape(B, 1, 1, 1)
        if feats is None:
            feats = self.encode_obs(I.reshape(B * N, H, W), scale.expand(B, N, 1, 1).reshape(B * N))
        f, g = feats
        h, w_ = f.shape[-2:]
        f = f.reshape(B, N, -1, h, w_)
        if self.att is not None:
            f = self.att(f, phi)
        a = self.par2(F.leaky_relu(self.par1(f.mean(1)), 0.1))
        a = F.interpolate(a, size=(H, W), mode="bilinear", align_corners=False).float()
        x = I / scale
        dx = (x - x.mean(1, keepdim=True)).reshape(B * N, 1, H, W)
        p = F.interpolate(self.wproj(f.reshape(B * N, -1, h, w_)), size=(H, W), mode="bilinear", align_corners=False)
        z = F.leaky_relu(self.whead1(torch.cat([g, p, dx.to(g.dtype)], 1)), 0.1)
        logits = self.rel(z).view(B, N, H, W).float()
        w = torch.softmax(logits, dim=1)
        a0, ac, as_ = a[:, 0:1], a[:, 1:2], a[:, 2:3]
        c2 = torch.cos(2 * phi)[..., None, None].float()
        s2 = torch.sin(2 * phi)[..., None, None].float()
        zeta = torch.sigmoid(a0 - 2.0 + ac * c2 + as_ * s2)  # supp. Eq. (19), as v1
        return zeta, w, a


class Refinement(nn.Module):
    """Shared encoder, two light decoders predicting Delta_t and Delta_r (paper Sec. 3.3)."""

    IN_CH = 6

    def __init__(self, cfg: NetConfig):
        super().__init__()
        c1, c2, c3 = cfg.ref_ch
        self.e1 = nn.Sequential(ConvBlock(self.IN_CH + (2 if cfg.use_mean else 0) + (2 if cfg.use_harm else 0) + (2 if cfg.use_wide else 0), c1), ConvBlock(c1, c1))
        self.e2 = nn.Sequential(ConvBlock(c1, c2, stride=2), ConvBlock(c2, c2))
        self.e3 = nn.Sequential(ConvBlock(c2, c3, stride=2), ConvBlock(c3, c3))
        self.dec_t = _Decoder(cfg.ref_ch, cfg.dec_ch)
        self.dec_r = _Decoder(cfg.ref_ch, cfg.dec_ch)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """X (B, 6, H, W), H and W multiples of 4 -> (Delta_t, Delta_r), each (B, H, W)."""
        f1 = self.e1(x)
        f2 = self.e2(f1)
        f3 = self.e3(f2)
        return self.dec_t(f1, f2, f3), self.dec_r(f1, f2, f3)


class _Decoder(nn.Module):
    def __init__(self, enc: tuple[int, int, int], dec: tuple[int, int, int]):
        super().__init__()
        c1, c2, c3 = enc
        d1, d2, d3 = dec
        self.u1 = ConvBlock(c3, d1)
        self.m1 = ConvBlock(d1 + c2, d2)
        self.m2 = ConvBlock(d2 + c1, d3)
        self.out = nn.Conv2d(d3, 1, 3, padding=1)

    def forward(self, f1, f2, f3):
        y = self.u1(f3)
        y = F.interpolate(y, size=f2.shape[-2:], mode="bilinear", align_corners=False)
        y = self.m1(torch.cat([y, f2], 1))
        y = F.interpolate(y, size=f1.shape[-2:], mode="bilinear", align_corners=False)
        y = self.m2(torch.cat([y, f1], 1))
        return self.out(y)[:, 0]


class PolSpikeNet(nn.Module):
    """Full reconstructor: (RIR) -> parameter branch -> RWPS -> refinement."""

    def __init__(self, cfg: NetConfig = NetConfig(), solver: SolverConfig = SolverConfig()):
        super().__init__()
        self.cfg = cfg
        self.solver_cfg_in = solver
        self.solver_cfg = solver if cfg.use_conf else dataclasses.replace(solver, lambda_low=solver.ridge_lambda, lambda_high=solver.ridge_lambda)
        self.param = ParameterBranch(cfg) if cfg.arch == "v1" else LowResParameterBranch(cfg)
        self.refine = Refinement(cfg)

    @property
    def pad_multiple(self) -> int:
        """H and W must be multiples of this (refinement: 4; v2 pixel-unshuffle: ``down``)."""
        return 4 if self.cfg.arch == "v1" else max(4, self.cfg.down)

    @property
    def cacheable(self) -> bool:
        """Per-observation features may be computed once per frame and reused (v2 with RIR off)."""
        return self.cfg.arch == "v2" and not self.cfg.use_rir

    def encode_obs(self, I: torch.Tensor, scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """v2: per-observation features of frames I (M, H, W) at scales (M,) (see :class:`LowResParameterBranch`)."""
        if not self.cacheable:
            raise ConfigError("encode_obs needs a v2 network with RIR off")
        return self.param.encode_obs(I, scale)

    @property
    def accepts_shifts(self) -> bool:
        """The network aligns its windows (RIR on), so :meth:`forward` takes their ``shifts`` estimated once by the caller."""
        return bool(self.cfg.use_rir)

    def align(self, I: torch.Tensor, phi: torch.Tensor, zeta_gt: torch.Tensor | None, *more: torch.Tensor | None, shifts: torch.Tensor | None = None) -> tuple[torch.Tensor | None, ...]:
        """RIR per batch item (shift estimates are not differentiated; the warp is): (I, zeta_gt, *more) aligned, each
        of ``more`` a (B, N, H, W) stack on the windows' centres (e.g. the wide windows) moved with the same shifts;
        ``shifts`` (B, N, 2): the windows' shifts estimated by the caller, used instead of estimating them here.
        """
        from reconstruct.physics.rir import estimate_shifts, warp

        maps = (zeta_gt, *more)
        outI, outM = [], [[] for _ in maps]
        for b in range(I.shape[0]):
            with torch.no_grad():
                est = estimate_shifts(I[b].detach().double().cpu(), phi[b].detach().double().cpu()) if shifts is None else torch.as_tensor(shifts[b])
                sh = est.to(I.device, I.dtype)
            moved = bool((sh != 0).any())
            outI.append(warp(I[b], sh) if moved else I[b])
            for o, m in zip(outM, maps):
                o.append(None if m is None else (warp(m[b], sh.to(m.dtype)) if moved else m[b]))
        return (torch.stack(outI), *(None if m is None else torch.stack(o) for o, m in zip(outM, maps)))

    def forward(
        self,
        I: torch.Tensor,
        phi: torch.Tensor,
        zeta_gt: torch.Tensor | None = None,
        alpha: float = 0.0,
        feats: tuple[torch.Tensor, torch.Tensor] | None = None,
        scale: torch.Tensor | None = None,
        I_mean: torch.Tensor | None = None,
        zeta_scale: torch.Tensor | None = None,
        zeta_shape: torch.Tensor | None = None,
        zeta_feed: torch.Tensor | None = None,
        I_harm: torch.Tensor | None = None,
        I_wide: torch.Tensor | None = None,
        exposure: float | torch.Tensor | None = None,
        span_steps: int | torch.Tensor | None = None,
        shifts: torch.Tensor | None = None,
    ) -> NetOutput:
        """Reconstruct the centre frame of each window.

        Args:
            I: (B, N, H, W) observations, radiance units (I = 1/2 mix, paper Eq. (1)); H, W multiples of 4.
            phi: (B, N) polarizer angles (window centres), radians.
            zeta_gt: optional (B, N, H, W) ground-truth zeta for teacher forcing and L_phys.
            alpha: teacher-forcing ratio in [0, 1] (needs ``zeta_gt`` when > 0).
            feats: v2 only: precomputed per-observation features of the B*N frames
                (:meth:`encode_obs` with :func:`window_scale`), e.g. cached by a stream;
                not allowed with RIR on (RIR warps the frames first).
            scale: v2 only: (B,) or (B, 1, 1, 1) brightness normaliser of the parameter branch
                (default :func:`window_scale` of ``I``); tiles of one frame share the frame's.
            I_mean: (B, H, W) the long spike mean around the centre frame, radiance units; required by a
                ``use_mean`` network.  Each input beside the windows is given exactly when ``cfg.inputs`` names it
                (:meth:`reconstruct.stream.window_inputs.WindowInputs.check`: a ShapeError names what is missing or extra).
            zeta_scale: optional (B,) factors applied to ``zeta_gt`` where it is fed to the solver (teacher
                forcing), not where the losses compare with it: training for an imperfect external zeta
                (``--zeta self``, whose errors are mostly of scale; RECONSTRUCTION_NOTES "scale vs shape").
            zeta_shape: optional (B,) factors on the modulation of that fed zeta about its window mean,
                zeta' = m + f (zeta - m), m = mean over the N observations (applied before ``zeta_scale``): the
                degree of polarization an assumed index or pane model gets wrong.
            zeta_feed: optional (B, N, H, W) zeta fed to the solver in place of ``zeta_gt`` (teacher forcing; before
                ``zeta_shape`` / ``zeta_scale``), the losses still comparing with ``zeta_gt``: e.g. the window's zeta under
                the glass the self-calibration assumes (``window.assumed_n``).
            I_harm: (B, 2, H, W) the first harmonic (cos 2 phi, sin 2 phi) of the spikes over I_mean's span, radiance
                units; required by a ``use_harm`` or ``span_level`` network.
            I_wide: (B, N, H, W) the observations over the wide window (same centres and angles as ``I``), radiance
                units; required where ``NetConfig.wide_input`` (use_wide, t_level_px, r_level_from = wide).  Its solver takes zeta as given for
                the narrow windows (the wide window's averaging lowers zeta's modulation by ~5 % at 57 steps).
            exposure, span_steps: the stream's exposure (spikes per step per unit radiance) and the number of steps of
                I_mean's span, numbers or (B,) tensors; required by a ``span_level`` network (the span's noise and
                saturation).
            shifts: optional (B, N, 2) RIR shifts of the windows estimated once by the caller (the stream); with RIR on they replace :meth:`align`'s estimate.

        Returns:
            :class:`NetOutput`.
        """
        WindowInputs(I, phi, I_mean, I_harm, I_wide, exposure, span_steps, shifts).check(self.cfg)  # what this configuration reads, of the windows' shapes
        H, W = I.shape[-2:]
        m = self.pad_multiple
        if H % m or W % m:
            raise ShapeError(f"H and W must be multiples of {m} (pad the input); got {H}x{W}", actual_shape=(H, W), expected_shape=f"multiples of {m}")
        if feats is not None and not self.cacheable:
            raise ConfigError("precomputed features need a v2 network with RIR off")
        if alpha > 0 and zeta_gt is None:
            raise ShapeError("teacher forcing alpha > 0 needs zeta_gt", actual_shape=None, expected_shape="(B, N, H, W)")
        if self.cfg.use_rir:
            I, zeta_gt, zeta_feed, I_wide = self.align(I, phi, zeta_gt, zeta_feed, I_wide, shifts=shifts)
        if self.cfg.arch == "v1":
            if scale is not None:
                raise ConfigError("scale is a v2 option (v1 normalises each window by its own mean)")
            zeta_hat, w, _ = self.param(I, phi)
        else:
            zeta_hat, w, _ = self.param(I, phi, feats, scale)
        zeta_hat, w = zeta_hat.float(), w.float()  # the solver runs in float32 (also under bf16 autocast)
        I = I.float()
        if zeta_feed is not None and (zeta_gt is None or zeta_feed.shape != zeta_gt.shape):
            raise ShapeError("zeta_feed needs zeta_gt of its shape (the losses compare with zeta_gt)", actual_shape=tuple(zeta_feed.shape), expected_shape=None if zeta_gt is None else tuple(zeta_gt.shape))
        z_force = zeta_gt if zeta_feed is None else zeta_feed
        if zeta_gt is not None and zeta_shape is not None:
            zm = z_force.mean(1, keepdim=True)
            z_force = zm + zeta_shape.reshape(-1, 1, 1, 1).to(zeta_gt.dtype) * (z_force - zm)
        if zeta_gt is not None and zeta_scale is not None:
            z_force = z_force * zeta_scale.reshape(-1, 1, 1, 1).to(zeta_gt.dtype)
        if z_force is not zeta_gt:
            z_force = z_force.clamp(0.0, 1.0)
        zeta_used = zeta_hat if (alpha <= 0 or zeta_gt is None) else alpha * z_force + (1 - alpha) * zeta_hat  # teacher forcing
        res = solve(self.cfg.solver_method, zeta_used, I, w, self.solver_cfg)
        T0, R0 = res.T, res.R
        c = I.shape[1] // 2
        I_c = I[:, c]
        I_hat = 0.5 * (zeta_used[:, c] * R0 + (1 - zeta_used[:, c]) * T0)  # paper Eq. (7)
        resid = I_c - I_hat
        conf = res.conf if self.cfg.use_conf else torch.zeros_like(res.conf)
        ch = [T0, R0, 2 * I_c, 2 * I.min(1).values, conf, 2 * resid]
        Tb, Rb = T0, R0
        Rlev = None
        if self.cfg.use_mean:
            I_mean = I_mean.float()
            zbar = zeta_used.mean(1) if self.cfg.anchor_zbar == "window" else zbar_of(zeta_used, phi)
            Ta, Ra = anchor_to_mean(T0, R0, I_mean, zbar)
            ch += [2 * I_mean, Ta]  # the spike mean and T anchored to it
            if self.cfg.use_harm:
                Tl, Rl = long_span_separation(I_mean, I_harm.float(), zeta_used, phi)
                lim = 50.0 * I_mean.abs() + 0.05  # per pixel (tiles agree): bounded inputs where noise is divided by a weak modulation
                ch += [torch.maximum(torch.minimum(Tl, lim), -lim), torch.maximum(torch.minimum(Rl, lim), -lim)]
            if self.cfg.wide_input:
                # an input like I_mean: no gradient into zeta through this second solve (its Poisson weights' backward overflows)
                with torch.no_grad():
                    rw = solve(self.cfg.solver_method, zeta_used.detach(), I_wide.float(), None, self.solver_cfg)
                    Tw, Rw = anchor_to_mean(rw.T, rw.R, I_mean, zbar.detach())
                if self.cfg.use_wide:
                    ch += [Tw, Rw]
                if self.cfg.r_level_from == "wide":
                    Rlev = Rw
            if self.cfg.base == "anchored":
                Tb, Rb = Ta, Ra
        x = torch.stack(ch, 1)
        dT, dR = self.refine(x)
        R = Rb + dR
        Rlev = Rb if Rlev is None else Rlev
        if self.cfg.r_level_px > 0:
            R = R + gaussian_blur(Rlev - R, self.cfg.r_level_px)  # the base's level, the refinement's structure
        T = Tb + dT
        if self.cfg.t_level_px > 0:
            T = T + gaussian_blur(Tw - Tb, self.cfg.t_level_px)
        if self.cfg.span_level and zeta_gt is not None and alpha >= 1.0:  # on an external zeta only (self-calibrated or given):
            # the span's D is as right as zeta's orientation over the whole span, which the learned per-window zeta does not check
            with torch.no_grad():  # a move of D computed without gradient, like the other levels' inputs
                peak = I.max(1).values if I_wide is None else torch.maximum(I.max(1).values, I_wide.float().max(1).values)
                zs = zeta_used.detach()
                wsp = span_weights(I_mean, zs, phi, exposure, span_steps, I_peak=peak)
                light = 2.0 * I_mean.double().clamp_min(0.0)  # tolerances relative to the pixel's light: any brightness scale gives the same move
                tol_t = self.cfg.span_level_tol_t * light if self.cfg.span_level_tol_t > 0 else None
                Ts, Rs = span_blend(T, R, I_mean, I_harm, zs, phi, wsp, self.cfg.span_level_px, self.cfg.span_level_tol * light, tol_t)
            # in training the move is an input (no gradient through it), and T's and R's gradients pass on to the refinement
            T, R = (T + (Ts - T.detach()), R + (Rs - R.detach())) if T.requires_grad else (Ts, Rs)
        keep = None
        if self.cfg.floor and not self.training:
            T, R, keep = self.data_floor(T, R, zeta_used, I, exposure, I_mean if self.cfg.use_mean else None, phi, external=zeta_gt is not None and alpha >= 1.0)
        return NetOutput(T=T, R=R, T_base=T0, R_base=R0, zeta_hat=zeta_hat, zeta_used=zeta_used, weights=w, conf=res.conf, res=resid, I=I, zeta_gt=zeta_gt, floor_keep=keep)

    def data_floor(self, T: torch.Tensor, R: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor, exposure=None, I_mean=None, phi=None, external: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The data-consistency floor of this configuration (:func:`reconstruct.net.floor.network_floor`) -> (T, R, T's kept fraction)."""
        c = self.cfg.floor_gain_spread
        gs = c if c >= 0 else None if c <= GAIN_SPREAD_ESTIMATE else getattr(self, "stream_gain_spread", 0.0)
        return network_floor(self.cfg, T, R, zeta, I, exposure, I_mean, phi, external, gs)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def init_weights(model: nn.Module, generator: torch.Generator) -> nn.Module:
    """Re-initialise every conv/linear layer from ``generator`` (no global RNG).

    Kaiming-uniform weights (LeakyReLU 0.1 gain), zero biases; the last layers of the decoders start at zero so the untrained network returns the solver output.
    """
    with torch.no_grad():
        for name, m in model.named_modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_uniform_(m.weight, a=0.1, nonlinearity="leaky_relu", generator=generator)
                if m.bias is not None:
                    m.bias.zero_()
        if isinstance(model, PolSpikeNet):
            for dec in (model.refine.dec_t, model.refine.dec_r):
                dec.out.weight.mul_(0.01)
            model.param.par2.weight.mul_(0.1)
    return model


@torch.no_grad()
def predict_parameters(model: PolSpikeNet, I: torch.Tensor, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Learned zeta_hat and reliability weights w, each (B, N, H, W), for the evaluation harness.

    ``I`` (B, N, H, W) radiance units (already RIR-aligned by the caller), ``phi`` (B, N).  Use as the ``learned`` zeta source and as ``weights_fn`` of RWPS.
    """
    zeta, w, _ = model.param(I.to(next(model.parameters()).dtype), phi)
    return zeta, w


SYMMETRY_CODES = {1: (0,), 2: (0, 3), 4: (0, 1, 2, 3), 8: tuple(range(8))}
"""Symmetries averaged by :class:`SymmetryEnsemble` for each ensemble size (codes of :mod:`reconstruct.physics.symmetry`:
3 = rotation by 180 deg, 0-3 the mirrors, 4-7 with the transpose)."""


def check_ensemble_size(size: int, what: str = "ensemble size") -> int:
    """``size`` if it is an ensemble size of :data:`SYMMETRY_CODES`; else a :class:`ConfigError` naming ``what``."""
    if size not in SYMMETRY_CODES:
        raise ConfigError(f"{what} {size}: choose one of {', '.join(map(str, SYMMETRY_CODES))}")
    return int(size)


_IMAGE_KWARGS = ("I_mean", "zeta_feed", "I_harm", "I_wide")
"""Keyword inputs of :meth:`PolSpikeNet.forward` that are maps (moved with the image by each ensemble member)."""


class SymmetryEnsemble(nn.Module):
    """Test-time self-ensemble of a :class:`PolSpikeNet` over symmetries of the image (``size`` 1, 2, 4 or 8).

    Each member sees the window mirrored / transposed with its polarizer angles carried along
    (:func:`symmetry_angles`; an external zeta moves with its pixels, paper Eq. (2) keeps its values), the outputs
    are mapped back and averaged.  The network was trained on all 8 symmetries (``[window] flips``), so each
    member is an equally valid estimate whose noise differs; the per-pixel solver outputs (T_base, R_base) are the
    same for every member given an external zeta.  Costs ``size`` forward passes; no feature cache.
    """

    def __init__(self, net: PolSpikeNet, size: int = 8):
        super().__init__()
        self.net, self.codes, self.cfg = net, SYMMETRY_CODES[check_ensemble_size(size)], net.cfg

    @property
    def pad_multiple(self) -> int:
        return self.net.pad_multiple

    @property
    def cacheable(self) -> bool:
        return False

    @property
    def param(self) -> nn.Module:
        """The network's parameter branch (the ``learned`` zeta source reads one member: zeta needs no ensemble)."""
        return self.net.param

    def encode_obs(self, I: torch.Tensor, scale: torch.Tensor):
        return self.net.encode_obs(I, scale)

    def forward(self, I: torch.Tensor, phi: torch.Tensor, zeta_gt: torch.Tensor | None = None, alpha: float = 0.0, feats=None, **kw) -> NetOutput:
        if feats is not None:
            raise ConfigError("a symmetry ensemble takes no precomputed features")
        acc: dict[str, torch.Tensor] = {}
        for code in self.codes:
            def fw(t):
                return None if t is None else symmetry_image(t, code)

            def fk(k, v):
                if v is None or k not in _IMAGE_KWARGS:
                    return v
                return symmetry_harmonic(v, code) if k == "I_harm" else fw(v)

            o = self.net(fw(I), symmetry_angles(phi, code), fw(zeta_gt), alpha, **{k: fk(k, v) for k, v in kw.items()})
            for f in dataclasses.fields(NetOutput):
                v = getattr(o, f.name)
                if f.name in ("I", "zeta_gt") or v is None:
                    continue
                v = symmetry_image(v, code, inverse=True)
                acc[f.name] = v if f.name not in acc else acc[f.name] + v
        n = len(self.codes)
        return NetOutput(**{k: v / n for k, v in acc.items()}, I=I, zeta_gt=zeta_gt)
