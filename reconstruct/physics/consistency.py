"""The data-consistency floor: a (T, R) must predict the N observations no worse than the physics does, within noise.

Paper Eq. (1)-(2) in the solvers' units: b_k = 2 I_k = zeta_k R + (1 - zeta_k) T, k = 1..N, for the N (RIR-aligned)
windows of one output frame.  Any estimate x = (T, R) of a pixel has the residual

    RSS(x) = sum_k (b_k - zeta_k R - (1 - zeta_k) T)^2.

For the physics core's answer x_p (a solver on the same zeta and windows) and a candidate x_n (e.g. the network's
refined output), d = x_n - x_p, write a = sum_k (A_k d)^2 and c = sum_k r_k (A_k d), r the physics residual,
A_k = [1 - zeta_k, zeta_k].  Along the segment x(s) = x_p + s d the excess residual is exactly

    E(s) = RSS(x(s)) - RSS(x_p) = a s^2 - 2 c s.

**The noise it is weighed against.**  Were x_p the unweighted least-squares solution (c = 0) and the observations
independent with variance sigma^2 each, the truth itself would show E = (x* - x_ls)' A'A (x* - x_ls) ~ sigma^2
chi^2_2: mean 2 sigma^2, 95 % below 5.99 sigma^2.  sigma^2 is measured, not assumed: the least-squares residual
variance RSS_ls / (N - 2) averaged over a ``pool`` x ``pool`` box (:func:`observation_noise`; the same estimate as the
adaptive RWPS's, :mod:`reconstruct.physics.solvers`), so it holds the spikes' Poisson / quantization noise and
whatever the model leaves (an imperfect self-calibrated zeta, residual misalignment) alike.  Where the spike model's
noise is known (exposure and window length, :func:`reconstruct.physics.identifiability.window_mean_variance`),
``model_var`` either bounds sigma^2 from below (``combine = "max"``) or caps it (``"min"``: the residual then counts
only as far as the spikes' noise explains it, so misalignment or a wrong zeta does not widen the allowance).  Under
either, ``noise_floor`` holds: the noise of counts below one spike per window (:func:`count_quantum_variance`), which a
dim pool's residual (its counts all 0, fitted exactly) cannot show.

**The floor** (:func:`consistency_floor`) keeps the fraction

    s = min(1, tol sigma^2 / <E(1)>)          (s = 1 where <E(1)> <= tol sigma^2)

of the candidate's move, x = x_p + s d, <.> a ``pool`` x ``pool`` box mean (the test is made on a neighbourhood, so a
systematic disagreement stands out of the per-pixel chi-square noise and s varies smoothly).  Why this s: in the metric
of the data the physics' own error has power P ~ 2 sigma^2 (2 dof) and, the candidate's error tau^2 being independent
of it, the move has power E = P + tau^2; the blend (1 - s) x_p + s x_n has error (1 - s)^2 P + s^2 tau^2.  With
``tol = 4`` (= 2 P / sigma^2) that error is exactly min(tau^2, P): where tau^2 <= P, s = 1 and the candidate stands;
where tau^2 > P, s = 2 P / (P + tau^2) and (1 - s)^2 P + s^2 tau^2 = P (P (tau^2 - P)^2 + 4 P^2 tau^2 =
P (P + tau^2)^2).  So the floored output's error is, in expectation, that of the better of the physics and the
candidate, whatever the candidate (``tol = 2`` is the minimum-error blend for a known tau^2, but
it shrinks a candidate as good as the truth whenever the pooled excess fluctuates above its mean: measured on the
motion bench's dim light, 2 dB lost against the unfloored network).  A candidate the observations
allow (its excess within the noise) passes unchanged; one that contradicts them (a level taken from a long span that
a pan smeared, R carrying T's texture, a garbage correction) is pulled back to the physics, the more the further it
strays: its distance from x_p in the metric of the data is s sqrt(a) = tol sigma^2 sqrt(a) / <a - 2c>, which tends
to 0 as the candidate's error grows (for x_p the least-squares solution, c = 0, it is tol sigma^2 / sqrt(a) per pixel
with pool = 1).  The excess is measured in the metric A'A, so the move is free along the direction the N windows do
not determine (R - T where zeta barely modulates: the span's and the refinement's business) and checked along the
one they do (the level).  ``mode = "hard"`` keeps x_p wherever <E(1)> exceeds the allowance (no blend).
"""

from __future__ import annotations

import dataclasses

import torch

from polinfra.config import opt
from polinfra.errors import ShapeError
from reconstruct.physics.solvers import _box

__all__ = ["FloorConfig", "FloorResult", "observation_noise", "bounded_noise", "count_quantum_variance", "spike_noise_bounds", "window_counts", "move_excess", "gain_rescale", "estimate_gain_spread", "consistency_floor", "box_mean", "finite_or"]


@dataclasses.dataclass(frozen=True)
class FloorConfig:
    """Parameters of the data-consistency floor (module docstring)."""

    tol: float = opt(4.0, "allowed excess residual over the physics', in noise variances of one observation (4 = twice the physics' own error power, 2 dof: the floored error is min(the candidate's, the physics'), module docstring)", lo=0.0, hi=1e6)
    pool: int = opt(5, "side (pixels) of the box over which the noise variance and the excess are averaged (1 = per pixel)", lo=1, hi=101)
    mode: str = opt("shrink", "shrink: keep the fraction min(1, tol sigma^2 / excess) of the candidate's move | hard: the physics wherever the excess exceeds tol sigma^2", choices=("shrink", "hard"))


@dataclasses.dataclass
class FloorResult:
    """The floored layers (..., H, W), the kept fraction s of the candidate's move from the physics (1 = unchanged,
    0 = the physics), the candidate's box-mean excess residual in noise variances <E(1)> / sigma^2, and sigma^2.
    """

    T: torch.Tensor
    R: torch.Tensor
    keep: torch.Tensor
    excess: torch.Tensor
    sigma2: torch.Tensor


def _check(zeta: torch.Tensor, I: torch.Tensor) -> None:
    if I.dim() < 3 or zeta.shape != I.shape:
        raise ShapeError(f"zeta and I must be (..., N, H, W) of one shape; got {tuple(zeta.shape)} and {tuple(I.shape)}", actual_shape=tuple(zeta.shape), expected_shape=tuple(I.shape))


def box_mean(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean of (..., H, W) maps over a k x k box (stride 1, borders averaged over the pixels inside): ``avg_pool2d``
    with ``count_include_pad=False``, bit for bit, as the solvers' two 1-D passes (half its cost in float64).
    """
    return _box(x, k)


def bounded_noise(zeta: torch.Tensor, I: torch.Tensor, pool: int, model_var: torch.Tensor | None = None, combine: str = "max",
                  noise_floor: torch.Tensor | float | None = None) -> torch.Tensor:
    """sigma^2 of one observation (..., H, W) as the floors weigh it: :func:`observation_noise` over ``pool``, then the
    spike model's ``model_var`` (box-averaged over ``pool``) as a lower bound (``combine = "max"``) or a cap (``"min"``),
    then at least ``noise_floor`` (:func:`count_quantum_variance`) whatever the rest says.
    """
    sigma2 = observation_noise(zeta, I, pool)
    if model_var is not None:
        if combine not in ("max", "min"):
            raise ValueError(f"combine {combine!r}: max or min")
        mv = box_mean(torch.broadcast_to(model_var.to(sigma2.dtype), sigma2.shape), pool)
        sigma2 = torch.maximum(sigma2, mv) if combine == "max" else torch.minimum(sigma2, mv)
    if noise_floor is not None:
        sigma2 = torch.maximum(sigma2, torch.as_tensor(noise_floor, dtype=sigma2.dtype, device=sigma2.device))
    return sigma2


def count_quantum_variance(level, exposure, steps: int):
    """sigma^2 of one observation b = 2 I that a window of ``steps`` steps shows as no residual, for the light ``level``
    (radiance units, e.g. the long span's spike mean; a number or a tensor) at ``exposure`` thresholds per step per unit
    radiance: where the expected count m = level x steps x exposure is below one spike, a window counts 0 or 1 and errs
    by m (1 - m) spike^2 (an integrate-and-fire pixel from a residue spread over one threshold; a Poisson one by m), one
    spike being 2 / (steps exposure) in b.  A dim pool of windows whose counts are all 0 is fitted exactly, so its
    residual says there is no noise at all; this is the noise that is there all the same.  From one spike per window
    up the counts vary and the residual shows their noise: 0 there.
    """
    q = 2.0 / (float(steps) * exposure)
    m = level * float(steps) * exposure
    m = m.clamp(0.0, 1.0) if hasattr(m, "clamp") else min(max(float(m), 0.0), 1.0)
    return q * q * m * (1.0 - m)


def _per_image(exposure, I: torch.Tensor):
    """``exposure`` (a number, or (B,) one per image) shaped to broadcast over (B, H, W) maps of ``I`` (B, N, H, W)."""
    return torch.as_tensor(exposure, dtype=I.dtype, device=I.device).reshape(-1, 1, 1) if torch.is_tensor(exposure) else float(exposure)


def window_counts(I: torch.Tensor, exposure, steps: int = 13) -> torch.Tensor | None:
    """Expected spikes per pixel in one window of ``steps`` steps, (B, H, W), from windows ``I`` (B, N, H, W) in
    radiance units at ``exposure`` thresholds per step per unit radiance (a number or (B,)); None where it is unknown.
    """
    if exposure is None:
        return None
    e = _per_image(exposure, I)
    return I.mean(1).clamp_min(0.0) * e * float(steps)


def _rescale(p, q, T_ref, e_ref, n: float, sz, szz):
    """Alpha = <A d, u> / |u|^2 and |u|^2, u = A x_ref = T_ref + zeta_k e_ref the reference's predicted observations and
    A_k d = p + zeta_k q the move's, from the windows' moments sum zeta (``sz``) and sum zeta^2 (``szz``) over N = ``n``.
    """
    sdu = n * p * T_ref + (p * e_ref + q * T_ref) * sz + q * e_ref * szz
    suu = n * T_ref * T_ref + 2.0 * T_ref * e_ref * sz + e_ref * e_ref * szz
    return sdu / suu.clamp_min(torch.finfo(suu.dtype).tiny ** 0.5), suu


def gain_rescale(T: torch.Tensor, R: torch.Tensor, T_ref: torch.Tensor, R_ref: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rescaling of the reference that the candidate's move holds, in the metric of the data, and the reference's
    predicted signal power: (alpha, |A x_ref|^2), each (..., H, W), for windows ``I`` and ``zeta`` (..., N, H, W).
    """
    _check(zeta, I)
    e_ref = R_ref - T_ref
    p = T - T_ref
    return _rescale(p, (R - R_ref) - p, T_ref, e_ref, float(zeta.shape[-3]), zeta.sum(-3), (zeta * zeta).sum(-3))


def estimate_gain_spread(T: torch.Tensor, R: torch.Tensor, T_ref: torch.Tensor, R_ref: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor,
                         sigma2: torch.Tensor, pool: int = 5, max_noise: float = 0.05, min_pixels: int = 256, cap: float = 0.15) -> torch.Tensor:
    """The sensor's per-pixel photo-gain spread (relative sd) as the data show it, one per image: (..., 1, 1).

    A gain error rescales a pixel's N observations alike (:func:`move_excess`), so between a fit to the windows (the
    reference) and layers free of the sensor's pattern (a candidate that is close to the truth) the per-pixel rescaling
    alpha (:func:`gain_rescale`) is the pattern, plus the windows' noise in it, sigma^2 / |A x_ref|^2, plus the
    candidate's own error.  The pattern is white from pixel to pixel, the candidate's error mostly is not: alpha less
    its ``pool`` box mean keeps the pattern (times sqrt(1 - 1 / pool^2)) and drops a smooth error.  On the pixels whose
    alpha the noise blurs by less than ``max_noise`` (sd; bright light), the spread is the robust sd of that white part
    (1.4826 x its median absolute value) with the median noise taken off in quadrature; 0 where fewer than
    ``min_pixels`` pixels qualify (dim light, where the windows' noise hides any pattern and the allowance would not
    matter), and at most ``cap``.  ``sigma2``: the noise variance of one observation (..., H, W), as the floor weighs it.
    """
    alpha, suu = gain_rescale(T, R, T_ref, R_ref, zeta, I)
    white = alpha - box_mean(alpha, pool)
    v = sigma2.to(alpha.dtype) / suu.clamp_min(torch.finfo(suu.dtype).tiny ** 0.5)
    lead = alpha.shape[:-2]
    w2, v2, u2 = (torch.broadcast_to(x, alpha.shape).reshape(-1, alpha.shape[-2] * alpha.shape[-1]) for x in (white, v, suu))
    out = torch.zeros(w2.shape[0], dtype=alpha.dtype, device=alpha.device)
    shrink = 1.0 - 1.0 / float(pool * pool)
    for i in range(w2.shape[0]):
        sel = (v2[i] < max_noise * max_noise) & torch.isfinite(w2[i]) & (u2[i] > 0)
        if int(sel.sum()) < min_pixels:
            continue
        var = (1.4826 * w2[i][sel].abs().median()) ** 2 / shrink - v2[i][sel].median()
        out[i] = var.clamp_min(0.0).sqrt().clamp_max(cap)
    return out.reshape(*lead, 1, 1)


def move_excess(T: torch.Tensor, R: torch.Tensor, T_ref: torch.Tensor, R_ref: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor,
                gain_spread: float | torch.Tensor = 0.0, white_pool: int = 0) -> torch.Tensor:
    """RSS(T, R) - RSS(T_ref, R_ref) on the windows ``I`` (..., N, H, W) on ``zeta``, per pixel (..., H, W), less what
    a photo-gain error explains: a pixel's gain g scales its N observations alike, so the true layers differ from a
    fit by the factor 1 + g, along the reference itself.  The candidate's move d = x - x_ref loses its component along
    x_ref in the metric of the data, alpha = <A d, A x_ref> / |A x_ref|^2 (:func:`gain_rescale`), as far as
    |alpha| <= 3 ``gain_spread`` (three sd of the sensor's spread: the pooled check carries a pixel beyond it into its
    neighbours; a number, or a tensor that broadcasts over (..., H, W), e.g. one per image), before the excess is
    taken: a candidate that is the reference rescaled within the spread passes, any other move is measured in full.
    ``white_pool`` > 1 (the floors' setting) frees alpha as a fixed pattern can make it: its part that is white at that
    scale (alpha less its ``white_pool`` box mean m) within 3 spreads and with at most twice the pattern's variance
    over the box (scaled down where its box mean square is larger: a candidate's error that is no pattern, e.g. a
    constant added to T, has a white part that follows the scene's texture and can be far larger), and m itself
    within 3 spreads / ``white_pool`` only: a sensor's pattern is independent from pixel to pixel, so its box mean
    over 25 pixels is a fifth of it, while a candidate's own brightness error over a neighbourhood (a smooth
    rescaling of the reference) is measured beyond that (a 10 % rescaling of a view behind a 5.8 % pattern: 6.5 % of
    it counted).

    In closed form from the windows' moments over N (no (..., N, H, W) temporaries): A_k d = p + zeta_k q with
    p = T - T_ref, q = (R - R_ref) - p, and the reference's residual r_k = b_k - T_ref - zeta_k (R_ref - T_ref), so the
    excess sum (A_k d)^2 - 2 r_k A_k d needs only sum zeta, sum zeta^2, sum b and sum zeta b; the gain's direction
    A x_ref = T_ref + zeta_k (R_ref - T_ref) is of the same form.
    """
    _check(zeta, I)
    n = float(zeta.shape[-3])
    b = 2.0 * I
    sz, szz, sb, szb = zeta.sum(-3), (zeta * zeta).sum(-3), b.sum(-3), (zeta * b).sum(-3)
    e_ref = R_ref - T_ref
    sr = sb - n * T_ref - sz * e_ref  # sum_k r_k
    szr = szb - sz * T_ref - szz * e_ref  # sum_k zeta_k r_k
    p = T - T_ref
    q = (R - R_ref) - p
    if torch.is_tensor(gain_spread) or gain_spread > 0:
        alpha, _ = _rescale(p, q, T_ref, e_ref, n, sz, szz)
        lim = 3.0 * torch.as_tensor(gain_spread, dtype=alpha.dtype, device=alpha.device)
        if white_pool > 1:  # the white part within 3 sd, with at most a pattern's power per box; its box mean within 3 sd of a mean of white_pool^2 pixels
            m = box_mean(alpha, white_pool)
            w = alpha - m
            cap = 2.0 * (lim / 3.0) ** 2  # twice the pattern's variance: a box of the truth's pattern stays below it but for chi-square's tail
            w = w * (cap / box_mean(w * w, white_pool).clamp_min(torch.finfo(w.dtype).tiny)).clamp(max=1.0).sqrt()
            alpha = torch.maximum(torch.minimum(w, lim), -lim) + torch.maximum(torch.minimum(m, lim / white_pool), -lim / white_pool)
        else:
            alpha = torch.maximum(torch.minimum(alpha, lim), -lim)
        p, q = p - alpha * T_ref, q - alpha * e_ref  # A (d - alpha x_ref), A being linear
    return n * p * p + 2.0 * p * q * sz + q * q * szz - 2.0 * (p * sr + q * szr)


def spike_noise_bounds(I: torch.Tensor, exposure, I_mean: torch.Tensor | None = None, steps: int = 13, pool: int = 5):
    """The spike model's bounds on sigma^2 of b = 2 I for windows ``I`` (B, N, H, W) of ``steps`` steps at ``exposure``
    (None: unknown -> (None, None)): the Poisson variance 4 I / (exposure steps) of the windows' mean light (a cap,
    ``combine = "min"``) and the noise of counts under one spike (:func:`count_quantum_variance`, box-averaged over
    ``pool``) at the brighter of the windows' mean and the long span's ``I_mean`` (B, H, W), which sees light the
    windows' zeros do not (a lower bound, ``noise_floor``).
    """
    if exposure is None:
        return None, None
    e = _per_image(exposure, I)
    level = I.mean(1).clamp_min(0.0)
    cap = 4.0 * level / (e * float(steps)) + 1e-12
    if I_mean is not None:
        level = torch.maximum(level, I_mean.to(I.dtype).clamp_min(0.0))
    return cap, box_mean(count_quantum_variance(level, e, steps), pool)


def observation_noise(zeta: torch.Tensor, I: torch.Tensor, pool: int = 5) -> torch.Tensor:
    """sigma^2 of one observation b_k = 2 I_k, (..., H, W): the unweighted least-squares residual RSS / (N - 2),
    box-averaged over ``pool`` (zeta that does not modulate, std over the N below 1e-4: the residual about the window
    mean, N - 1 dof).  In closed form: b_k = T + zeta_k (R - T) is a line in zeta_k, so least squares leaves the
    residual r_k = (b_k - <b>) - (zeta_k - <zeta>) D with D = sum (zeta_k - <zeta>)(b_k - <b>) / sum (zeta_k - <zeta>)^2.
    """
    _check(zeta, I)
    b = 2.0 * I
    N = I.shape[-3]
    dz = zeta - zeta.mean(-3, keepdim=True)
    db = b - b.mean(-3, keepdim=True)
    szz = (dz * dz).sum(-3, keepdim=True)
    modulates = szz > max(N - 1, 1) * 1e-8  # the windows' zeta std above 1e-4: the 2 x 2 system is not singular
    D = torch.where(modulates, (dz * db).sum(-3, keepdim=True) / szz.clamp_min(torch.finfo(szz.dtype).tiny ** 0.5), torch.zeros_like(szz))
    r = db - dz * D
    rss = (r * r).sum(-3)
    dof = torch.where(modulates.squeeze(-3), torch.full_like(rss, max(N - 2, 1)), torch.full_like(rss, max(N - 1, 1)))
    return box_mean(rss / dof, pool)


def finite_or(T: torch.Tensor, R: torch.Tensor, T_f: torch.Tensor, R_f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A candidate's pixels that are no number (NaN or inf in T or R: a network that overflowed) replaced by the
    fallback's -> (T, R, those pixels): a floor then keeps 0 of the candidate there, and no NaN spreads through its pools.
    """
    bad = ~(torch.isfinite(T) & torch.isfinite(R))
    return torch.where(bad, T_f, T), torch.where(bad, R_f, R), bad


def consistency_floor(T: torch.Tensor, R: torch.Tensor, T_p: torch.Tensor, R_p: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor,
                      cfg: FloorConfig = FloorConfig(), model_var: torch.Tensor | None = None, combine: str = "max",
                      noise_floor: torch.Tensor | float | None = None, gain_spread: float | None = 0.0) -> FloorResult:
    """Floor a candidate (T, R) at the physics (T_p, R_p) by the N observations ``I`` (..., N, H, W) on ``zeta``.

    Args:
        T, R: the candidate layers (..., H, W) (e.g. the network's refined output).
        T_p, R_p: the physics core's layers on the same zeta and (aligned) windows.
        zeta: (..., N, H, W) mixing coefficients (paper Eq. (2)) of the windows.
        I: (..., N, H, W) the windows in radiance units (paper Eq. (1): I = 1/2 (zeta R + (1 - zeta) T)).
        cfg: :class:`FloorConfig`.
        model_var: optional (..., H, W) or broadcastable sigma^2 of b = 2 I from the spike model.
        combine: "max" (``model_var`` a lower bound on sigma^2) or "min" (a cap).
        noise_floor: optional sigma^2 that holds whatever the residual and ``model_var`` say (broadcastable to
            (..., H, W)): the noise of counts below one spike (:func:`count_quantum_variance`), which no residual of
            windows that all count 0 can show.
        gain_spread: the sensor's relative photo-gain spread: a move along the physics itself within two of it is
            free (:func:`move_excess`); None: the spread the data show, its pixel-white part only
            (:func:`estimate_gain_spread`).

    Returns:
        :class:`FloorResult` (module docstring).
    """
    _check(zeta, I)
    zeta, I = zeta.to(T.dtype), I.to(T.dtype)
    T, R, bad = finite_or(T, R, T_p, R_p)  # a candidate pixel that is no number: the physics, kept 0
    sigma2 = bounded_noise(zeta, I, cfg.pool, model_var, combine, noise_floor).clamp_min(torch.finfo(T.dtype).tiny ** 0.5)
    dT, dR = T - T_p, R - R_p
    allow = cfg.tol * sigma2
    gs = estimate_gain_spread(T, R, T_p, R_p, zeta, I, sigma2, cfg.pool) if gain_spread is None else gain_spread
    e1 = box_mean(move_excess(T, R, T_p, R_p, zeta, I, gs, cfg.pool), cfg.pool)
    ok = e1 <= allow
    if cfg.mode == "hard":
        s = ok.to(T.dtype)
    else:
        s = torch.where(ok, torch.ones_like(e1), allow / e1.clamp_min(torch.finfo(T.dtype).tiny ** 0.5)).clamp(0.0, 1.0)
    s = s.masked_fill(bad, 0.0)
    return FloorResult(T=T_p + s * dT, R=R_p + s * dR, keep=s, excess=e1 / sigma2, sigma2=sigma2)
