"""Physics solvers for the stacked mixing system, supp. Eq. (3)-(15).

Per pixel, a window of N = 2K+1 observations gives (supp. Eq. (3)-(5))

    A x ~= b,   A_k = [zeta_k, 1 - zeta_k],   b_k = 2 I(i+k),   x = [R, T].

Every solver here reduces to the weighted ridge normal equations (supp. Eq. (9))

    (A^T W A + lambda' I) x = A^T W b,     lambda' = lambda * sum_k w_k,

solved in closed form per pixel (2x2 adjugate / determinant): no per-pixel
Python loop, batched over any leading dimensions, any device, differentiable.

Scaling of lambda (documented choice): supp. Eq. (7) is written for the raw
weights; we multiply lambda by sum_k w_k, i.e. the data term is the weighted
*mean* squared residual.  Then lambda is dimensionless, independent of N and of
the scale of w (uniform weights and softmax weights give the same solution).

Solvers (all share :func:`solve_weighted_ridge`):

* ``ls``: plain least squares (lambda = 0 plus the numerical floor below).
* ``ridge``: a fixed lambda (:attr:`SolverConfig.ridge_lambda`).
* ``irls``: least squares followed by ``irls_iters`` Huber reweightings,
  supp. Eq. (10)-(11).
* ``rwps``: reliability weights w in [0, 1], per-pixel lambda from Conf,
  supp. Eq. (8), then the same IRLS reweighting (supp. Sec. 8: "IRLS on top
  of RWPS").

Conf (supp. Eq. (12)-(15)) is det(M) of the weighted moment matrix.  Since
det(M) = sum_{j<k} w_j w_k (zeta_j - zeta_k)^2 = (sum w)^2 Var_w(zeta), we
normalise it as

    d = 4 det(M) / (sum_k w_k)^2 = 4 Var_w(zeta)      in [0, 1]
    Conf = d (1 + kappa) / (d + kappa)                 in [0, 1]

(d = 1 only when half the weight sits at zeta = 0 and half at zeta = 1).
kappa is the value of d at which Conf = 1/(2) (1 + kappa) ~ 0.5; the default
kappa = 0.01 puts Conf = 0.5 at a zeta standard deviation of 0.05, the middle
of what glass produces (R_perp - R_par from 0 to ~0.3).  Conf is per pixel,
invariant to the scale of w, monotone in det(M) and smooth.

Adaptive Conf (``SolverConfig.lambda_map = "adaptive"``, the physics default
:data:`PHYSICS_SOLVER_CONFIG`).  The fixed Conf above reads the conditioning only: a pane
with a clearly modulated zeta gets Conf ~ 1 and lambda_low = 0.01 even when the spikes are so few
that the answer is noise, and a weak but clean modulation gets the prior even where the data could
speak.  What supp. Eq. (7)-(15) intend (little regularisation where the modulation is strong and
well conditioned, the prior where the system is near-singular) is a statement about the reflection
estimate's signal-to-noise ratio, so the adaptive Conf measures exactly that per pixel
(:func:`adaptive_confidence`): from a first weighted least-squares solve, the residual variance
sigma^2 of one observation, the variance of the reflection estimate v_R = sigma^2 S_tt / det(M)
(it grows without bound as det(M) of supp. Eq. (15) -> 0), the signal power
s_R^2 = <R_ls^2> - <v_R> (pooled over a ``noise_pool`` box), q = s_R^2 / <v_R>, and

    Conf = q / (q + snr_kappa),     lambda = lambda_low Conf + lambda_high (1 - Conf)   (Eq. (8))

so lambda -> lambda_low where the reflection is measured well and -> lambda_high (the prior
toward small R, T: a TFP-like answer) where it is not.  The reliability weights are the same
Poisson inverse-variance weights, but their first-pass prediction is solved with lambda_high (a
near-singular noisy window otherwise turns its swings into weights), and the Huber passes after
the solve are ``rwps_irls_iters``.  The constants (``snr_kappa``, ``lambda_low``,
``lambda_high``, ``rwps_irls_iters``) are fitted on training groups only by
``polspike fit-rwps`` (:mod:`reconstruct.evaluate.rwps_fit`; README, "RWPS that adapts").

Pooled prior (``rwps_prior = "pooled"``, the physics default).  A prior toward R = T is wrong
where R << T (stress.toml's weak-reflection level) and toward R = T = 0 (ridge) where R ~ T.  The
pooled prior pulls R - T toward D0, the neighbourhood's own estimate of it
(:func:`pooled_difference_prior`): the per-pixel LS differences R_ls - T_ls averaged over a
``prior_pool`` box, each pixel weighted by its conditioning det(M) / sum(w) (the precision of the
difference, supp. Eq. (15)), and shrunk toward 0 (R = T) by d / (d + ``prior_kappa``) where the box
itself is near-singular (d = the box mean of 4 Var_w(zeta): near-singular differences are biased,
not just noisy, and pooling does not remove a bias).  Conf then measures how well the pixel's own
data fix R - T against the prior's error: q = s_D^2 / v_D, s_D^2 the spread of R - T around D0
(noise removed), v_D = sigma^2 sum(w) / det(M) the variance of R_ls - T_ls; Conf = q / (q +
``snr_kappa``), lambda by Eq. (8), prior term lambda (R - T - D0)^2.  The default
``lambda_map = "fixed"`` keeps the original behaviour, so a checkpoint whose stored SolverConfig
predates the field reproduces bit for bit.

Numerical floor: the 2x2 system gets lambda' + eps * tr(M) + tiny on its
diagonal, eps = 1e-12 (float64) or 1e-7 (float32).  With all zeta equal or all
weights zero the result is finite (no NaN, no inf): the near minimum-norm
solution, or 0 when every weight is zero.
"""

from __future__ import annotations

import dataclasses

import torch

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError

__all__ = ["SOLVERS", "PHYSICS_SOLVER_CONFIG", "adaptive_confidence", "pooled_difference_prior", "SolverConfig", "SolverResult", "moments", "confidence", "lambda_from_conf", "solve_weighted_ridge", "weighted_sums", "huber_factor", "solve", "poisson_reliability"]

SOLVERS = ("ls", "ridge", "irls", "rwps")
"""Solver names accepted by :func:`solve`."""


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Parameters of the physics solvers (dimensionless unless stated)."""

    ridge_lambda: float = opt(3e-2, "lambda of the fixed-lambda ridge solver (times sum of weights)", lo=0.0, hi=1e6)
    lambda_low: float = opt(1e-2, "RWPS lambda at Conf = 1, supp. Eq. (8)", lo=0.0, hi=1e6)
    lambda_high: float = opt(1e-1, "RWPS lambda at Conf = 0, supp. Eq. (8); must exceed lambda_low", lo=0.0, hi=1e6)
    conf_kappa: float = opt(0.01, "Conf normalisation: value of 4 Var_w(zeta) giving Conf ~ 0.5", lo=1e-9, hi=1.0)
    irls_iters: int = opt(3, "Huber reweighting iterations after the first solve, supp. Sec. 8", lo=0, hi=100)
    huber_c: float = opt(2.0, "Huber threshold delta in units of the per-pixel robust residual scale", lo=1e-3, hi=100.0)
    # defaults tuned on the closed-form synthetic set (reconstruct/README.md, "Solver defaults")
    huber_floor: float = opt(1e-3, "absolute floor on delta, in units of b (2 I)", lo=0.0, hi=1e6)
    # Conf -> lambda mapping of rwps; "fixed" is the original one, kept as the default so that every
    # stored SolverConfig (checkpoints) and SolverConfig() reproduce exactly.
    lambda_map: str = opt("fixed", "rwps Conf -> lambda: fixed (Conf from 4 Var_w(zeta) alone) or adaptive (noise-aware Conf, module docstring)", choices=("fixed", "adaptive"))
    snr_kappa: float = opt(1.0, "adaptive: value of the conditioning SNR q at which Conf = 1/2", lo=1e-9, hi=1e9)
    rwps_irls_iters: int = opt(-1, "Huber reweighting iterations of rwps (-1: irls_iters, the original behaviour)", lo=-1, hi=100)
    rwps_prior: str = opt("zero", "adaptive rwps prior: zero (lambda (R^2 + T^2), as ridge), equal (lambda (R - T)^2, toward the window mean) or pooled (lambda (R - T - D0)^2, D0 the locally pooled R - T; module docstring)", choices=("zero", "equal", "pooled"))
    noise_pool: int = opt(5, "adaptive: side (pixels) of the box over which the residual noise and signal power are pooled", lo=1, hi=101)
    prior_pool: int = opt(31, "pooled prior: side (pixels) of the box over which R - T is pooled into the prior mean D0", lo=1, hi=1001)
    prior_kappa: float = opt(0.003, "pooled prior: box mean of 4 Var_w(zeta) at which D0 keeps half its value (toward R = T below)", lo=0.0, hi=1.0)


@dataclasses.dataclass
class SolverResult:
    """Solver output: layers (..., H, W), Conf (..., H, W), final weights (..., N, H, W)."""

    R: torch.Tensor
    T: torch.Tensor
    conf: torch.Tensor
    weights: torch.Tensor
    lam: torch.Tensor


PHYSICS_SOLVER_CONFIG = SolverConfig(lambda_map="adaptive", lambda_low=0.0, lambda_high=0.3, snr_kappa=0.03, rwps_irls_iters=0, rwps_prior="pooled", prior_pool=31, prior_kappa=0.001)
"""Solver parameters of the physics-only paths (evaluation, ``polspike reconstruct --method``):
adaptive RWPS with the constants fitted on training groups (``polspike fit-rwps``, README)."""


def _eps(dtype: torch.dtype) -> float:
    return 1e-12 if dtype == torch.float64 else 1e-7


def moments(zeta: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted moments S_rr, S_rt, S_tt (supp. Eq. (14)) and sum w, over the window axis -3."""
    a = zeta
    bt = 1.0 - zeta
    S_rr = (w * a * a).sum(-3)  # supp. Eq. (14)
    S_rt = (w * a * bt).sum(-3)
    S_tt = (w * bt * bt).sum(-3)
    return S_rr, S_rt, S_tt, w.sum(-3)


def confidence(zeta: torch.Tensor, w: torch.Tensor | None = None, kappa: float = 0.01) -> torch.Tensor:
    """Solver confidence in [0, 1] from det of the weighted moment matrix, supp. Eq. (12)-(15).

    Args:
        zeta: mixing coefficients (..., N, H, W) in [0, 1].
        w: weights broadcastable to zeta (default 1).
        kappa: normalisation constant (module docstring).

    Returns:
        Conf (..., H, W) = d (1 + kappa) / (d + kappa), d = 4 det(M) / (sum w)^2.
    """
    w = torch.ones_like(zeta) if w is None else torch.broadcast_to(w.to(zeta.dtype), zeta.shape)
    S_rr, S_rt, S_tt, sw = moments(zeta, w)
    det = (S_rr * S_tt - S_rt * S_rt).clamp_min(0.0)  # supp. Eq. (15)
    tiny = torch.finfo(zeta.dtype).tiny ** 0.5
    d = (4.0 * det / (sw * sw + tiny)).clamp(0.0, 1.0)
    return d * (1.0 + kappa) / (d + kappa)


def _box(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over a k x k box (edge-aware: padding does not count) of (..., H, W), as two 1-D passes (rows, then
    columns; the valid part of a box is a product of row and column ranges, so this is the 2-D mean): every element
    the float sum of its window's values in increasing index, divided by their count, as ``avg_pool2d`` with
    ``count_include_pad=False`` computes it (bit for bit, tests/recon/test_solver_exact.py), by k shifted additions of
    whole maps instead of a scalar loop per pixel.
    """
    if k <= 1:
        return x
    return _box_pass(_box_pass(x, k, -2), k, -1)


def _box_pass(x: torch.Tensor, k: int, dim: int) -> torch.Tensor:
    """The edge-aware 1-D mean over k values along ``dim`` (-2 or -1) of (..., H, W); window of i: i - k // 2 .. i - k // 2 + k - 1.

    Zero-padded shifted copies added in increasing index: out-of-range terms add +0.0, which leaves a float sum as it is.
    """
    n, h = x.shape[dim], k // 2
    xp = torch.nn.functional.pad(x, (h, k - 1 - h) if dim == -1 else (0, 0, h, k - 1 - h))
    acc = torch.zeros_like(x)
    for d in range(k):
        acc += xp.narrow(dim, d, n)
    i = torch.arange(n, device=x.device)
    count = ((i - h + k).clamp(max=n) - (i - h).clamp(min=0)).to(x.dtype)
    return acc / (count[:, None] if dim == -2 else count)


def _ls_noise(zeta: torch.Tensor, b: torch.Tensor, w: torch.Tensor, pool: int, sums: tuple[torch.Tensor, ...] | None = None):
    """The weighted least-squares solve and its residual noise, shared by the adaptive Conf and the pooled prior:
    (S_rr, S_rt, S_tt, sum w, det M, tiny, R_ls, T_ls, sigma^2 box-averaged over ``pool`` pixels).  ``sums``: the
    window sums of :func:`weighted_sums` when the caller has them.
    """
    sums = weighted_sums(zeta, b, w) if sums is None else sums
    S_rr, S_rt, S_tt, sw = sums[:4]
    tiny = torch.finfo(zeta.dtype).tiny ** 0.5
    det = (S_rr * S_tt - S_rt * S_rt).clamp_min(0.0)
    n_eff = sw * sw / ((w * w).sum(-3) + tiny)
    R, T = solve_weighted_ridge(zeta, b, w, 0.0, sums=sums)
    r = b - (zeta * R.unsqueeze(-3) + (1.0 - zeta) * T.unsqueeze(-3))
    dof = (n_eff - 2.0).clamp_min(0.5)
    sigma2 = _box((w * r * r).sum(-3) / (sw + tiny) * n_eff / dof, pool)
    return S_rr, S_rt, S_tt, sw, det, tiny, R, T, sigma2


def adaptive_confidence(zeta: torch.Tensor, b: torch.Tensor, w: torch.Tensor, snr_kappa: float = 1.0, pool: int = 5, sums: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
    """Noise-aware Conf in [0, 1) (``lambda_map = "adaptive"``; module docstring, "Adaptive Conf").

    An empirical-Bayes signal-to-noise ratio of the reflection estimate: a first weighted
    least-squares solve gives R_ls and the residual variance sigma^2 of one observation
    (N_eff / (N_eff - 2) corrected, N_eff = (sum w)^2 / sum w^2); R_ls's variance is
    v_R = sigma^2 S_tt / det(M) (the (R, R) entry of sigma^2 M^-1, supp. Eq. (14)-(15)), which blows
    up as the system turns singular; the signal power is s_R^2 = max(<R_ls^2> - <v_R>, 0), both
    pooled over a ``pool`` x ``pool`` box (<.>).  q = s_R^2 / <v_R> and Conf = q / (q + snr_kappa):
    strong, well-conditioned modulation with a visible reflection -> Conf -> 1 (little
    regularisation); near-singular or noise-dominated -> Conf -> 0 (the prior).

    Args:
        zeta, b, w: (..., N, H, W) mixing coefficients, right sides (2 I) and weights.
        snr_kappa: q at which Conf = 1/2.
        pool: box side in pixels.
        sums: optional :func:`weighted_sums` of (zeta, b, w), computed here when omitted.

    Returns:
        Conf (..., H, W).
    """
    S_rr, S_rt, S_tt, sw, det, tiny, R, T, sigma2 = _ls_noise(zeta, b, w, pool, sums)
    v_R = (sigma2 * S_tt / (det + _eps(zeta.dtype) * S_tt * S_tt + tiny)).clamp_max(1e12)
    v_pool = _box(v_R, pool)
    s2 = (_box(R * R, pool) - v_pool).clamp_min(0.0)
    q = s2 / (v_pool + tiny)
    return q / (q + snr_kappa)


def pooled_difference_prior(
    zeta: torch.Tensor, b: torch.Tensor, w: torch.Tensor, pool: int = 31, kappa0: float = 0.003, noise_pool: int = 5, sums: tuple[torch.Tensor, ...] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Prior mean D0 of R - T and the SNR q of the difference (``rwps_prior = "pooled"``; module docstring).

    A first weighted least-squares solve gives D = R_ls - T_ls per pixel and its variance
    v_D = sigma^2 [1, -1] M^-1 [1, -1]^T = sigma^2 sum(w) / det(M) (since S_rr + 2 S_rt + S_tt = sum w;
    sigma^2 as in :func:`adaptive_confidence`).  Over a ``pool`` x ``pool`` box (<.>), each pixel
    weighted by its conditioning u = det(M) / sum(w) (the precision of D up to sigma^2, supp. Eq. (15)):

        D0 = <u D> / <u>                                         the pooled difference
        s_D^2 = max(<u (D - D0)^2> - <u v_D>, 0) / <u>            its spread around D0 (noise removed)
        D0 <- D0 d / (d + kappa0),   d = <4 det(M) / sum(w)^2>    toward R = T where the box itself is near-singular
        q = s_D^2 / v_D                                           how well this pixel's data measure D

    Args:
        zeta, b, w: (..., N, H, W) mixing coefficients, right sides (2 I) and weights.
        pool: box side in pixels of the pooled prior.
        kappa0: box-mean conditioning 4 Var_w(zeta) at which D0 keeps half its value.
        noise_pool: box side of the residual-noise estimate.
        sums: optional :func:`weighted_sums` of (zeta, b, w), computed here when omitted.

    Returns:
        (D0, q), each (..., H, W).
    """
    S_rr, S_rt, S_tt, sw, det, tiny, R, T, sigma2 = _ls_noise(zeta, b, w, noise_pool, sums)
    v_D = (sigma2 * sw / (det + _eps(zeta.dtype) * sw * sw + tiny)).clamp_max(1e12)
    D = R - T
    u = det / (sw + tiny)
    bu = _box(u, pool) + tiny
    D0 = _box(u * D, pool) / bu
    s2 = ((_box(u * (D - D0) ** 2, pool) - _box(u * v_D, pool)) / bu).clamp_min(0.0)
    d = _box(4.0 * det / (sw * sw + tiny), pool)
    D0 = D0 * d / (d + kappa0 + tiny)
    return D0, s2 / (v_D + tiny)


def lambda_from_conf(conf: torch.Tensor, lambda_low: float, lambda_high: float) -> torch.Tensor:
    """Per-pixel ridge strength, supp. Eq. (8): lambda_low Conf + lambda_high (1 - Conf)."""
    return lambda_low * conf + lambda_high * (1.0 - conf)  # supp. Eq. (8)


def weighted_sums(zeta: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The window sums of the weighted normal equations, over the window axis -3: (S_rr, S_rt, S_tt, sum w) of
    :func:`moments` and the right sides r_R = sum w zeta b, r_T = sum w (1 - zeta) b (supp. Eq. (9)).  One solve's
    least-squares pass and its final ridge solve share them (same zeta, b and weights).
    """
    S_rr, S_rt, S_tt, sw = moments(zeta, w)
    r_R = (w * zeta * b).sum(-3)
    r_T = (w * (1.0 - zeta) * b).sum(-3)
    return S_rr, S_rt, S_tt, sw, r_R, r_T


def solve_weighted_ridge(
    zeta: torch.Tensor, b: torch.Tensor, w: torch.Tensor, lam: torch.Tensor | float = 0.0, prior: str = "zero", prior_mean: torch.Tensor | None = None,
    sums: tuple[torch.Tensor, ...] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form (A^T W A + lambda sum(w) I)^{-1} A^T W b per pixel, supp. Eq. (9).

    Args:
        zeta: (..., N, H, W) mixing coefficients.
        b: (..., N, H, W) right sides, b_k = 2 I(i+k).
        w: (..., N, H, W) non-negative weights.
        lam: scalar or (..., H, W) dimensionless ridge strength.
        prior: ``zero`` (lambda (R^2 + T^2), supp. Eq. (7)) or ``equal`` (lambda (R - T)^2: only
            the difference is pulled, toward R = T, so a near-singular window returns the window
            mean 2 <I> (TFP) instead of shrinking the well-determined mean level).
        prior_mean: with ``prior = "equal"``, the prior pulls R - T toward this (..., H, W) value
            instead of 0: lambda (R - T - D0)^2 (``rwps_prior = "pooled"``).
        sums: optional :func:`weighted_sums` of (zeta, b, w), computed here when omitted.

    Returns:
        (R, T), each (..., H, W).
    """
    S_rr, S_rt, S_tt, sw, r_R, r_T = weighted_sums(zeta, b, w) if sums is None else sums
    if prior_mean is not None and prior == "equal":
        r_R = r_R + lam * sw * prior_mean
        r_T = r_T - lam * sw * prior_mean
    tr = S_rr + S_tt
    tiny = torch.finfo(zeta.dtype).tiny ** 0.25  # its square (the 2x2 determinant) stays a normal number
    floor = _eps(zeta.dtype) * tr + tiny
    if prior == "equal":
        m11 = S_rr + lam * sw + floor
        m22 = S_tt + lam * sw + floor
        m12 = S_rt - lam * sw
    else:
        diag = lam * sw + floor
        m11 = S_rr + diag
        m22 = S_tt + diag
        m12 = S_rt
    det = m11 * m22 - m12 * m12  # > 0
    R = (m22 * r_R - m12 * r_T) / det  # supp. Eq. (9), 2x2 adjugate
    T = (m11 * r_T - m12 * r_R) / det
    return R, T


def huber_factor(r: torch.Tensor, delta: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Huber-style factor q = min(1, delta / (|r| + eps)), supp. Eq. (11)."""
    return torch.clamp(delta / (r.abs() + eps), max=1.0)  # supp. Eq. (11)


def _robust_scale(r: torch.Tensor) -> torch.Tensor:
    """Per-pixel residual scale 1.4826 * median_k |r_k| over the window axis -3."""
    return 1.4826 * r.abs().median(dim=-3).values


def poisson_reliability(zeta: torch.Tensor, I: torch.Tensor, floor: float = 0.05, first_lambda: float = 0.0) -> torch.Tensor:
    """Classical reliability weights in (0, 1] for spike-count frames (used when no learned w is given).

    A spike count's variance grows with its expected rate (Poisson), so frame k
    gets the inverse-variance weight relative to the window's least-exposed frame,
    w_k = (min_j p_j + c) / (p_k + c).  The expected rate p_k is the smooth
    first-pass prediction zeta_k R + (1 - zeta_k) T of an unweighted least-squares
    solve (never the raw count, whose zeros would get all the weight);
    c = floor * mean_k p_k keeps dark pixels near w = 1.

    Args:
        zeta: (..., N, H, W) mixing coefficients.
        I: (..., N, H, W) observations.
        floor: relative offset c.
        first_lambda: ridge strength of the first pass (0: plain least squares, the original;
            the adaptive mapping uses its ``lambda_high`` so that a near-singular, noisy window
            does not turn its swings into weights).

    Returns:
        weights (..., N, H, W) in (0, 1].
    """
    R, T = solve_weighted_ridge(zeta, 2.0 * I, torch.ones_like(I), first_lambda)
    p = (zeta * R.unsqueeze(-3) + (1.0 - zeta) * T.unsqueeze(-3)).clamp_min(0.0)
    c = floor * p.mean(dim=-3, keepdim=True) + torch.finfo(I.dtype).tiny ** 0.5
    return (p.min(dim=-3, keepdim=True).values + c) / (p + c)


def solve(
    method: str,
    zeta: torch.Tensor,
    I: torch.Tensor,
    weights: torch.Tensor | None = None,
    config: SolverConfig = SolverConfig(),
) -> SolverResult:
    """Recover (R, T) from a window of observations with one of :data:`SOLVERS`.

    Args:
        method: ``ls``, ``ridge``, ``irls`` or ``rwps``.
        zeta: (..., N, H, W) mixing coefficients in [0, 1] (paper Eq. (2)).
        I: (..., N, H, W) observations I(i+k) in radiance units (paper Eq. (1):
            I = 1/2 (zeta R + (1 - zeta) T)); b = 2 I, supp. Eq. (3).
        weights: reliability weights in [0, 1] broadcastable to I (rwps only;
            default :func:`poisson_reliability` of I); ignored by other solvers.
        config: solver parameters.

    Returns:
        :class:`SolverResult` with R, T, Conf (computed with the initial weights),
        the final effective weights and lambda.
    """
    if method not in SOLVERS:
        raise ConfigError(f"unknown solver {method!r}; choose one of {list(SOLVERS)}")
    if zeta.shape != I.shape and torch.broadcast_shapes(zeta.shape, I.shape) != I.shape:
        raise ShapeError(f"zeta {tuple(zeta.shape)} must broadcast to I {tuple(I.shape)}", actual_shape=tuple(zeta.shape), expected_shape=tuple(I.shape))
    if I.dim() < 3:
        raise ShapeError(f"I must be (..., N, H, W); got {tuple(I.shape)}", actual_shape=tuple(I.shape), expected_shape="(..., N, H, W)")
    zeta = torch.broadcast_to(zeta.to(I.dtype), I.shape)
    b = 2.0 * I  # supp. Eq. (3)
    if method == "rwps":
        first = config.lambda_high if config.lambda_map == "adaptive" else 0.0
        w0 = poisson_reliability(zeta, I, first_lambda=first) if weights is None else torch.broadcast_to(weights.to(I.dtype), I.shape).clamp(0.0, 1.0)
    else:
        w0 = torch.ones_like(I)
    D0 = None
    sums = weighted_sums(zeta, b, w0) if (method == "rwps" and config.lambda_map == "adaptive") else None  # the noise pass's and the final solve's
    if method == "rwps" and config.lambda_map == "adaptive" and config.rwps_prior == "pooled":
        D0, q = pooled_difference_prior(zeta, b, w0, config.prior_pool, config.prior_kappa, config.noise_pool, sums)
        conf = q / (q + config.snr_kappa)
    elif method == "rwps" and config.lambda_map == "adaptive":
        conf = adaptive_confidence(zeta, b, w0, config.snr_kappa, config.noise_pool, sums)
    else:
        conf = confidence(zeta, w0, config.conf_kappa)
    if method == "rwps":
        lam = lambda_from_conf(conf, config.lambda_low, config.lambda_high)
    elif method == "ridge":
        lam = torch.full_like(conf, config.ridge_lambda)
    else:
        lam = torch.zeros_like(conf)
    prior = "equal" if (method == "rwps" and config.lambda_map == "adaptive" and config.rwps_prior in ("equal", "pooled")) else "zero"
    R, T = solve_weighted_ridge(zeta, b, w0, lam, prior, D0, sums)
    w = w0
    if method in ("irls", "rwps"):
        iters = config.rwps_irls_iters if (method == "rwps" and config.rwps_irls_iters >= 0) else config.irls_iters
        for _ in range(iters):
            r = b - (zeta * R.unsqueeze(-3) + (1.0 - zeta) * T.unsqueeze(-3))  # supp. Eq. (10)
            delta = (config.huber_c * _robust_scale(r)).clamp_min(config.huber_floor).unsqueeze(-3)
            w = w0 * huber_factor(r, delta)  # supp. Eq. (11): w^(j+1) = w q^(j)
            R, T = solve_weighted_ridge(zeta, b, w, lam, prior, D0)
    return SolverResult(R=R, T=T, conf=conf, weights=w, lam=lam)
