"""The best physics per pixel, chosen from the observations alone: the anchor of the data-consistency floor.

Paper Eq. (1)-(2) in the solvers' units, b_k = 2 I_k = (1 - zeta_k) T + zeta_k R, k = 1..N, written in the level L(z)
= T + z D and the difference D = R - T:

    b_k = L(zbar_w) + (zeta_k - zbar_w) D,        zbar_w = mean_k zeta_k.

Unweighted least squares (the ``ls`` solver) is exactly L_w = mean_k b_k and D_ls = sum_k dz_k (b_k - L_w) / sum_k dz_k^2
(dz_k = zeta_k - zbar_w), with independent errors of variance sigma^2 / N and v_D = sigma^2 / sum_k dz_k^2 for
observations of noise variance sigma^2 (:func:`reconstruct.physics.consistency.observation_noise`); T_ls = L_w - zbar_w
D_ls.  Every estimate here is a level L at a mean zeta z and a reflection R^, T = (L - z R^) / (1 - z); they differ
in where the level comes from and how much of the least-squares reflection they trust.

**The reflection, shrunk by what the windows resolve.**  R^ = R0 + w (R_ls - R0) with the Wiener weight
w = S^2 / (S^2 + v_R), v_R = sigma^2 / N + (1 - zbar_w)^2 v_D the variance of R_ls = L_w + (1 - zbar_w) D_ls, and
S^2 = max(0, <(R_ls - R0)^2> - <v_R>) the unbiased estimate of the reflection's texture power about R0 over a ``pool``
x ``pool`` box (<.>).  R0 is the neighbourhood's reflection: R_ls averaged over an ``r_pool`` x ``r_pool`` box (error
power v_R / r_pool^2), itself Wiener-shrunk toward 0 where that pooled noise hides it (``r_pool`` 0: R0 = 0).  Where
the texture is resolvable (S^2 >> v_R: bright light, a pane that modulates) w -> 1 and the estimate is least squares;
where the windows are noise-limited (dim light, weak modulation) w -> 0 and the reflection is the neighbourhood's:
its pooled level where that stands out of the noise (a strong, smooth reflection under a pane that barely modulates:
shrinking it to 0 leaves the whole reflection in T), and none where it does not, where T is the plain level with no
modulation model, the spike mean.  This is the statistic that tells "noise-limited, the mean is best" from "modulated
signal resolvable": the windows' explained modulation power against its own noise.  On the motion bench the pooled
R0 raised the anchor's mean T PSNR over 32 cells from 23.04 to 24.54 dB and R from 18.36 to 22.02 (r_pool 5 against
0; 15 and 31 gave 24.81 and 23.87).

**The level, from the windows or from the long span.**  Two levels: the windows' mean L_w at zbar_w (variance
sigma^2 / N, no bias: the windows are aligned), and the long span's spike mean m = 2 I_mean at zbar_s (the span's mean
zeta, :func:`reconstruct.physics.span.zbar_of`), from ``span_ratio`` times the windows' steps (variance
v_m = sigma^2 / span_ratio; 27 for the 351-step span against 13-step windows) but smeared by any motion over the span.
The smear is measured: the span's level against the windows' least-squares level at the same zbar_s,
q = m - (L_w + (zbar_s - zbar_w) D_ls), has E q^2 = bias^2 + v_m + sigma^2 / N + (zbar_s - zbar_w)^2 v_D, so the span
level's error power is r_s = max(v_m, <q^2> - sigma^2 / N - (zbar_s - zbar_w)^2 <v_D>).  The two levels are weighed by
their inverse error powers (the minimum-variance combination of two independent estimates), r_L = 1 / (1 / r_w + 1 / r_s)
with r_w = sigma^2 / N: the span wins where the scene holds still, the windows where a pan smeared the span.

**The anchor** (:func:`physics_anchor`) is T_a = (L - z R^) / (1 - z), R_a = R^ with L and z the weighted levels and
zbar's, and its stated error powers P_T = r_L / (1 - z)^2 + (z / (1 - z))^2 w v_R, P_R = w v_R.  It is, per pixel, the plain
spike mean (w = 0, span level), the mean anchored to the windows' difference (``--anchor mean``: w = 1, span level),
least squares (w = 1, window level), the mean of the windows (TFP-like: w = 0, window level), or a blend of them, as
the noise statistics decide: no constant is tuned, every weight is a ratio of measured error powers.  Without a span
mean only the window level is used.  Everything is closed form and vectorised (a few box filters per frame).

**The floor's fallback** (:func:`anchored_floor`, ``fallback = "blend"``, the network's default ``floor_anchor``): the
anchor and the physics-only RWPS weighed per pixel by their error powers (:func:`error_blend`).  The anchor fails
where zeta barely modulates under a bright reflection and the RWPS's spatial prior holds R (on the closed-form pane
stream of ``tests/recon/test_net_zeta.py`` the network floored at the anchor scores 11.7 dB, at the RWPS 18.4, at the
blend 18.5); the RWPS fails where its prior biases a strong reflection in bright light (the motion bench's strong and
dominant cells, 2-5 dB below the anchor).
"""

from __future__ import annotations

import dataclasses

import torch

from polinfra.config import opt
from reconstruct.physics.consistency import _check, bounded_noise, box_mean, estimate_gain_spread, finite_or, move_excess, observation_noise
from reconstruct.physics.rir import _quantile

SIG = 2.0
"""A power counts as resolved where its pooled estimate exceeds the noise's expectation by SIG standard deviations of
the pool's chi-square (sd = sqrt(2 / pool^2) of the mean; 2: ~2.5 % false detections where there is only noise)."""

__all__ = ["AnchorResult", "physics_anchor", "SPAN_RATIO", "BLIND_T", "AnchorFloorConfig", "AnchoredFloorResult", "anchored_floor", "error_blend"]

BLIND_T = 10.0
"""Where the anchor's stated sd of T (its error power P_T, pooled) exceeds this many times the pixel's light 2 I, T
counts as unobserved: the floor keeps the candidate's T (:func:`anchored_floor`).  At 1 - zeta = 0.015 with 2 % noise
the stated sd is about twice the light, and a T ten times too bright still shows in the data there."""

SPAN_RATIO = 351.0 / 13.0
"""Steps of the network's long span over the steps of one window: the span mean's variance is sigma^2 over this."""


def _null_log_sd(ratio: torch.Tensor, pool: int) -> torch.Tensor:
    """The spread, in log units, of the pooled power ratio where there is only noise, per frame (..., 1, 1): the larger
    of the pool's chi-square sd sqrt(2 / pool^2) and the frame's lower tail, -log(10th percentile) / 1.2816 (a
    log-normal's 10th percentile lies 1.2816 sd below its median, 1).  A smear only raises the ratio, so the lower tail
    is the noise's even where every pixel is smeared; it is wider than chi-square's because the noise estimate is itself
    pooled and local, and dim integrate-and-fire counts are far from Gaussian.
    """
    q10 = _quantile(ratio.flatten(-2).float(), 0.1, dim=-1).to(ratio.dtype).clamp(1e-6, 1.0)  # torch.quantile's, by selection
    return torch.clamp_min(-torch.log(q10) / 1.2816, (2.0 / pool**2) ** 0.5)[..., None, None]


@dataclasses.dataclass
class AnchorResult:
    """The anchor's layers (..., H, W), their stated error powers ``P_T``, ``P_R`` (same units as T^2), the Wiener
    weight ``w`` on the least-squares difference, the span level's share ``span_weight`` (0 = the windows' level),
    sigma^2 of one observation, and the least-squares layers.
    """

    T: torch.Tensor
    R: torch.Tensor
    P_T: torch.Tensor
    P_R: torch.Tensor
    P_T_max: torch.Tensor
    P_R_max: torch.Tensor
    w: torch.Tensor
    span_weight: torch.Tensor
    sigma2: torch.Tensor
    T_ls: torch.Tensor
    R_ls: torch.Tensor


def physics_anchor(zeta: torch.Tensor, I: torch.Tensor, I_mean: torch.Tensor | None = None, zbar_span: torch.Tensor | None = None,
                   span_ratio: float = SPAN_RATIO, pool: int = 5, sigma2: torch.Tensor | None = None, r_pool: int = 5) -> AnchorResult:
    """The best physics per pixel (module docstring) from N windows ``I`` (..., N, H, W) on ``zeta`` and, optionally, the
    long span's mean ``I_mean`` (..., H, W) with its mean zeta ``zbar_span`` (default: the windows' mean zeta).

    ``sigma2``: the noise variance of one observation b = 2 I (default :func:`observation_noise` over ``pool``).
    ``r_pool``: side of the box whose mean reflection R0 the least-squares reflection is shrunk toward (module
    docstring; 0 or 1: toward no reflection).
    """
    z, b = zeta.double(), 2.0 * I.double()
    N = b.shape[-3]
    tiny = 1e-30
    s2 = (observation_noise(z, I.double(), pool) if sigma2 is None else sigma2.double()).clamp_min(tiny)
    zw = z.mean(-3)
    dz = z - zw.unsqueeze(-3)
    szz = (dz * dz).sum(-3)
    mod = szz > 1e-12  # zeta modulates: D is determined (else only the level is)
    Lw = b.mean(-3)
    D_ls = torch.where(mod, (dz * (b - Lw.unsqueeze(-3))).sum(-3) / szz.clamp_min(tiny), torch.zeros_like(Lw))
    vD = torch.where(mod, s2 / szz.clamp_min(tiny), torch.full_like(s2, 1e30))
    r_w = s2 / N
    R_ls = Lw + (1.0 - zw) * D_ls
    vR = r_w + (1.0 - zw) ** 2 * vD
    R0 = torch.zeros_like(R_ls)
    if r_pool > 1:  # the neighbourhood's reflection, itself Wiener-shrunk toward 0 where its pooled noise hides it
        R0 = box_mean(R_ls, r_pool)
        v0 = box_mean(vR, r_pool) / r_pool**2
        R0 = R0 * (R0 * R0 / (R0 * R0 + v0 + tiny))
    dR0 = R_ls - R0
    pR2, pvR, sd = box_mean(dR0 * dR0, pool), box_mean(vR, pool), SIG * (2.0 / pool**2) ** 0.5
    R2 = (pR2 - pvR * (1.0 + sd)).clamp_min(0.0)
    R2_up = torch.minimum((pR2 - pvR * (1.0 - sd)).clamp_min(0.0), vR)  # the most reflection the windows cannot exclude
    w = R2 / (R2 + vR)
    Rh = R0 + w * dR0
    one = 1e-3
    uw = (1.0 - zw).clamp_min(one)
    rw_T = r_w / uw**2
    if I_mean is None:
        T = (Lw - zw * Rh) / uw
        zz, rL_T, sw = zw, rw_T, torch.zeros_like(Lw)
    else:
        m = 2.0 * I_mean.double()
        zs = zw if zbar_span is None else zbar_span.double()
        dzs = zs - zw
        q = m - (Lw + dzs * D_ls)
        v_m = s2 / span_ratio**2  # integrate-and-fire: a count's error is a fraction of one spike, so the mean's falls as 1 / steps
        e0 = v_m + r_w + box_mean(dzs * dzs * torch.where(mod, vD, torch.zeros_like(vD)), pool)  # E q^2 without smear
        ratio = box_mean(q * q, pool) / e0.clamp_min(tiny)
        r_s = v_m + ((ratio - torch.exp(SIG * _null_log_sd(ratio, pool))) * e0).clamp_min(0.0)  # smear beyond SIG sd of the statistic's null
        us = (1.0 - zs).clamp_min(one)
        rs_T = r_s / us**2
        sw = rw_T / (rw_T + rs_T)
        T = (1.0 - sw) * (Lw - zw * Rh) / uw + sw * (m - zs * Rh) / us
        zz = (1.0 - sw) * zw + sw * zs
        rL_T = rw_T * rs_T / (rw_T + rs_T)
    k2 = (zz / (1.0 - zz).clamp_min(one)) ** 2
    Rerr = (1.0 - w) ** 2 * R2_up + w * w * vR  # the shrunk reflection's error power at the largest reflection allowed
    dt = I.dtype if I.dtype.is_floating_point else torch.float32
    return AnchorResult(T=T.to(dt), R=Rh.to(dt), P_T=(rL_T + k2 * w * vR).to(dt), P_R=(w * vR).to(dt), P_T_max=(rL_T + k2 * Rerr).to(dt), P_R_max=Rerr.to(dt),
                        w=w.to(dt), span_weight=sw.to(dt), sigma2=s2.to(dt), T_ls=(Lw - zw * D_ls).to(dt), R_ls=R_ls.to(dt))


def error_blend(x_a: torch.Tensor, x_r: torch.Tensor, P_a: torch.Tensor, pool: int) -> torch.Tensor:
    """Per pixel, the anchor's ``x_a`` and a reference estimate ``x_r`` of the same layer weighed by their error powers.

    The anchor states its error power ``P_a``; the reference (the RWPS, whose spatial prior and per-pixel weights have
    no closed-form error) does not, so its error power is measured against the anchor: the two errors being
    independent, <(x_r - x_a)^2> = P_r + P_a over a ``pool`` x ``pool`` box, and P_r = max(0, <(x_r - x_a)^2> - <P_a>).
    The minimum-variance combination of the two is x_r + P_r / (P_r + P_a) (x_a - x_r): the reference where it agrees
    with the anchor within the anchor's own error (there the anchor is the noisier: a pane that barely modulates under a
    bright reflection, where least squares' T is noise and the RWPS's prior holds it), the anchor where the two differ
    by more than it (a strong reflection in bright light, where the RWPS's prior biases it).
    """
    d = x_r - x_a
    Pa = box_mean(P_a, pool).clamp_min(1e-30)
    Pr = (box_mean(d * d, pool) - Pa).clamp_min(0.0)
    return x_r + Pr / (Pr + Pa) * (-d)


@dataclasses.dataclass(frozen=True)
class AnchorFloorConfig:
    """Parameters of :func:`anchored_floor`; each tolerance is a multiple of a measured error power (docstring)."""

    tol: float = opt(4.0, "allowed excess residual over least squares' on the N windows, in noise variances of one observation (4 = twice least squares' own error power in the metric of the data, 2 dof)", lo=0.0, hi=1e6)
    tol_layer: float = opt(2.0, "allowed mean square move of T (of R) from the anchor, in units of the anchor's stated error power P_T (P_R) (2: the floored error is the smaller of the candidate's and the anchor's)", lo=0.0, hi=1e6)
    pool: int = opt(5, "side (pixels) of the box over which the noise, the powers and the moves are averaged", lo=1, hi=101)
    r_pool: int = opt(5, "side (pixels) of the box whose mean reflection the anchor's least-squares reflection is shrunk toward (physics_anchor; 0: toward no reflection)", lo=0, hi=101)
    layers: bool = opt(True, "also check T's and R's own moves from the anchor against its stated error powers (tol_layer); off: the data check alone, the fallback still the anchor")
    layer_counts: float = opt(1.0, "the layer checks count in full where the windows expect at least this many spikes per pixel (pooled), in proportion below (0 = in full everywhere): under one spike per window the residual cannot measure the noise the anchor's stated error power is built from", lo=0.0, hi=1e6)


@dataclasses.dataclass
class AnchoredFloorResult:
    """The floored layers, the kept fractions of T's and R's moves from the anchor (1 = the candidate, 0 = the
    anchor), and the :class:`AnchorResult`.
    """

    T: torch.Tensor
    R: torch.Tensor
    keep_T: torch.Tensor
    keep_R: torch.Tensor
    anchor: AnchorResult


def anchored_floor(T: torch.Tensor, R: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor, I_mean: torch.Tensor | None = None,
                   zbar_span: torch.Tensor | None = None, cfg: AnchorFloorConfig = AnchorFloorConfig(), model_var: torch.Tensor | None = None,
                   span_ratio: float = SPAN_RATIO, reference: tuple[torch.Tensor, torch.Tensor] | None = None,
                   noise_floor: torch.Tensor | float | None = None, counts: torch.Tensor | None = None,
                   gain_spread: float | None = 0.0, fallback: str = "anchor") -> AnchoredFloorResult:
    """Floor a candidate (T, R) (..., H, W) at the best physics (:func:`physics_anchor`) by the windows ``I`` on ``zeta``.

    Two checks, each a kept fraction of the candidate's move from the anchor (x = x_a + s (x_n - x_a)):

    * the data: the candidate's excess residual over least squares on the N windows, E = <RSS(x_n) - RSS(x_ls)>,
      s_d = min(1, tol sigma^2 / E) (:mod:`reconstruct.physics.consistency`: the truth's excess is sigma^2 chi^2_2);
    * each layer's own error: the move's power M_T = <(T_n - T_a)^2> against the anchor's stated error power P_T,
      s_T = min(1, tol_layer <P_T> / M_T) (and R alike).  The anchor's error being independent of the candidate's
      (power tau^2), M_T = P_T + tau^2, and the blend's error (1 - s)^2 P_T + s^2 tau^2 is min(tau^2, P_T) with
      tol_layer = 2 (:mod:`reconstruct.physics.consistency` derives it): a candidate better than the best physics
      passes, a worse one ends at the physics' error.

    T keeps min(s_d, s_T), R keeps min(s_d, s_R) (``cfg.layers = False``: both keep s_d).  The layer checks rest on the anchor's stated error powers, which
    are built from sigma^2, and sigma^2 is measured only where the windows count spikes: where a window expects fewer
    than one (``counts`` (..., H, W), the expected spikes per window, pooled, against ``cfg.layer_counts``), a pool's
    counts are mostly 0, its residual says nothing of the noise, and the anchor (there the long span's mean with the
    reflection the windows cannot resolve left in) errs by far more than it states: on the motion bench's dim light
    13 x more on the pixels the layer check clipped, where the network was 13 x better than the anchor.  So a layer
    check counts in proportion g = min(1, counts / layer_counts): s_T -> 1 - g (1 - s_T), and below one spike the data
    check alone stands, as in :func:`reconstruct.physics.consistency.consistency_floor`.  ``model_var`` caps sigma^2 at the spikes' own noise (the floor's
    ``combine = "min"``); ``noise_floor`` bounds it from below whatever the cap (the noise of counts below one spike,
    :func:`reconstruct.physics.consistency.count_quantum_variance`); ``gain_spread`` frees a rescaling of the reference within the sensor's gain spread (:func:`reconstruct.physics.consistency.move_excess`); None: the spread the data show, its pixel-white part only (:func:`reconstruct.physics.consistency.estimate_gain_spread`).
    ``fallback``: where the checks pull the candidate, ``"anchor"`` (the anchor) or ``"blend"`` (with a ``reference``:
    per pixel the anchor and the reference weighed by their error powers, :func:`error_blend`; the moves and the
    layer checks are then measured from that blend).
    """
    _check(zeta, I)
    dt = T.dtype
    z, Iw = zeta.to(torch.float64), I.to(torch.float64)
    s2 = bounded_noise(z, Iw, cfg.pool, model_var, "min", noise_floor).clamp_min(1e-30)
    a = physics_anchor(z, Iw, None if I_mean is None else I_mean.to(torch.float64), None if zbar_span is None else zbar_span.to(torch.float64),
                       span_ratio, cfg.pool, s2, cfg.r_pool)
    Tn, Rn = T.to(torch.float64), R.to(torch.float64)
    Tr, Rr = (a.T, a.R) if reference is None else (reference[0].to(torch.float64), reference[1].to(torch.float64))
    # the fallback from the anchor projected onto layers >= 0 (as the RWPS reference is): never farther from a true
    # layer, and bounded where the least squares runs away (zeta ~ 1 leaves T unobserved: -19 with P_T 480 measured)
    fT, fR = a.T.clamp_min(0.0), a.R.clamp_min(0.0)
    if fallback == "blend" and reference is not None:
        fT, fR = error_blend(fT, Tr, a.P_T, cfg.pool), error_blend(fR, Rr, a.P_R, cfg.pool)
    elif fallback not in ("anchor", "blend"):
        raise ValueError(f"fallback {fallback!r}: anchor or blend")
    Tn, Rn, bad = finite_or(Tn, Rn, fT, fR)  # a candidate pixel that is no number: the fallback, kept 0
    gs = estimate_gain_spread(Tn, Rn, Tr, Rr, z, Iw, s2, cfg.pool) if gain_spread is None else gain_spread
    excess = box_mean(move_excess(Tn, Rn, Tr, Rr, z, Iw, gs, cfg.pool), cfg.pool)  # RSS(candidate) - RSS(reference), less a gain error

    def frac(allow, move):
        return torch.where(move <= allow, torch.ones_like(move), allow / move.clamp_min(1e-300)).clamp(0.0, 1.0)

    s_d = frac(cfg.tol * s2, excess).masked_fill(bad, 0.0)
    dT, dR = Tn - fT, Rn - fR
    # where the anchor itself states that it knows T only to more than BLIND_T times the pixel's light (zeta ~ 1 leaves
    # T unobserved), no check can say the candidate's T is wrong, and the fallback's T is noise: the candidate's T stands
    # (the blend ran to T = 39 from a candidate's 0.64 where 1 - zeta = 5e-4 on a view's corner).  One-sided: where
    # the anchor understates its error, the floor acts as before
    light2 = box_mean((Iw.mean(-3) * 2.0) ** 2, cfg.pool)
    blind = (box_mean(a.P_T, cfg.pool) > BLIND_T**2 * light2) & ~bad
    s_T = s_R = s_d
    if cfg.layers:
        l_T = frac(cfg.tol_layer * box_mean(a.P_T_max, cfg.pool), box_mean(dT * dT, cfg.pool))
        l_R = frac(cfg.tol_layer * box_mean(a.P_R_max, cfg.pool), box_mean(dR * dR, cfg.pool))
        if counts is not None and cfg.layer_counts > 0:
            g = (box_mean(torch.broadcast_to(counts.to(torch.float64), l_T.shape), cfg.pool) / cfg.layer_counts).clamp(0.0, 1.0)
            l_T, l_R = (torch.where(g >= 1.0, x, 1.0 - g * (1.0 - x)) for x in (l_T, l_R))
        s_T, s_R = torch.minimum(s_d, l_T), torch.minimum(s_d, l_R)
    s_T = torch.where(blind, torch.ones_like(s_T), s_T)
    return AnchoredFloorResult(T=torch.where(blind, Tn, fT + s_T * dT).to(dt), R=(fR + s_R * dR).to(dt), keep_T=s_T.to(dt), keep_R=s_R.to(dt), anchor=a)
