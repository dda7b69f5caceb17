"""Training losses, paper Eq. (8)-(12).

All maps are (B, H, W) in radiance units (1.0 = brightest layer value),
per-observation tensors (B, N, H, W).  Norms are per-pixel means (the paper's
sums divided by the number of pixels), so the weights do not depend on the crop.

Reflection-dominance mask M (paper Eq. (8), "a soft mask constructed from the
synthetic mixing ratio"): with the centre-frame ground-truth zeta_c,

    rho = zeta_c R_gt / (zeta_c R_gt + (1 - zeta_c) T_gt + eps)     (reflected share of the mixed light)
    M   = m_floor + (1 - m_floor) * clip(rho / rho_ref, 0, 1)        in [m_floor, 1]

so pixels where the reflection carries a share >= rho_ref of the light get full
weight and reflection-free pixels keep weight m_floor (our documented choice:
the paper does not give the formula).
"""

from __future__ import annotations

import dataclasses

import torch

from polinfra.config import opt

__all__ = ["LossConfig", "reflection_mask", "image_grad", "loss_rec", "loss_grad", "loss_phys", "loss_excl", "ssim_map", "total_loss"]


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Weights of paper Eq. (12) and the mask / exclusion constants."""

    lambda_r: float = opt(0.5, "weight of the R term in L_rec, paper Eq. (8)", lo=0.0, hi=100.0)
    lambda_g: float = opt(0.5, "weight of L_grad, paper Eq. (12)", lo=0.0, hi=100.0)
    lambda_p: float = opt(0.1, "weight of L_phys, paper Eq. (12) (paper: 0.1)", lo=0.0, hi=100.0)
    lambda_e: float = opt(0.01, "weight of L_excl, paper Eq. (12) (paper: 0.01)", lo=0.0, hi=100.0)
    lambda_zeta: float = opt(1.0, "weight of the zeta term inside L_phys, paper Eq. (10)", lo=0.0, hi=100.0)
    lambda_ex: float = opt(4.0, "tanh scale lambda_ex of the exclusion loss, paper Eq. (11), per radiance unit per pixel", lo=0.0, hi=1e4)
    lambda_base: float = opt(0.5, "weight of L1 on the solver outputs (T^, R^), times (0.2 + 0.8 alpha): supervision shifts to the refined output as alpha drops", lo=0.0, hi=100.0)
    lambda_ssim: float = opt(0.0, "weight of 1 - SSIM(T) (skimage's 7x7 uniform-window SSIM at data range 1, the evaluation metric, on the estimate clipped to [0, 1]): a structure term beside the L1 terms (0 = off, the paper's objective)", lo=0.0, hi=100.0)
    lambda_logmse: float = opt(0.0, "weight of the mean over windows of ln(1 + MSE(T) / logmse_eps): each window's T error on the scale PSNR reads, so a bright, near noise-free window whose T is off by a little weighs as much as a dim one whose T is off by a lot (the L1 terms barely see the first); 0 = off", lo=0.0, hi=100.0)
    logmse_eps: float = opt(1e-5, "MSE at which the lambda_logmse term turns from linear to logarithmic (1e-5: 50 dB PSNR at peak 1)", lo=1e-12, hi=1.0)
    r_floor: float = opt(1.0, "weight of the R term where the reflection carries none of the light: the R term is weighted by r_floor + (1 - r_floor) clip(rho / rho_ref, 0, 1) (1 = unweighted, the paper's Eq. (8); lower values train R where the spikes identify it, not its level where they cannot)", lo=0.0, hi=1.0)
    m_floor: float = opt(0.5, "reflection mask M value where there is no reflection", lo=0.0, hi=1.0)
    rho_ref: float = opt(0.3, "reflected share of the mixed light at which M reaches 1", lo=1e-6, hi=1.0)


def reflection_mask(T_gt: torch.Tensor, R_gt: torch.Tensor, zeta_c: torch.Tensor, cfg: LossConfig = LossConfig(), floor: float | None = None) -> torch.Tensor:
    """Soft reflection-dominance mask in [floor, 1] (module docstring; floor: ``cfg.m_floor`` unless given), (B, H, W)."""
    num = zeta_c * R_gt.clamp_min(0)
    rho = num / (num + (1 - zeta_c) * T_gt.clamp_min(0) + 1e-6)
    f = cfg.m_floor if floor is None else floor
    return f + (1 - f) * (rho / cfg.rho_ref).clamp(0, 1)


def image_grad(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences (gx (..., H, W-1), gy (..., H-1, W))."""
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


def _wmean(x: torch.Tensor, m: torch.Tensor | None) -> torch.Tensor:
    return x.abs().mean() if m is None else (m * x.abs()).mean()


def loss_rec(T, R, T_gt, R_gt, M, cfg: LossConfig = LossConfig(), M_r: torch.Tensor | None = None) -> torch.Tensor:
    """L_rec = ||T - T_gt||_{1,M} + lambda_r ||R - R_gt||_{1,M_r}, paper Eq. (8) (M_r None: unweighted, as the paper)."""
    return _wmean(T - T_gt, M) + cfg.lambda_r * _wmean(R - R_gt, M_r)  # Eq. (8)


def loss_grad(T, T_gt, M) -> torch.Tensor:
    """L_grad = ||grad T - grad T_gt||_{1,M}, paper Eq. (8) (M averaged onto the difference grid)."""
    gx, gy = image_grad(T - T_gt)
    mx = 0.5 * (M[..., :, 1:] + M[..., :, :-1])
    my = 0.5 * (M[..., 1:, :] + M[..., :-1, :])
    return 0.5 * (_wmean(gx, mx) + _wmean(gy, my))  # Eq. (8)


def loss_phys(T, R, zeta_hat, I, zeta_gt, cfg: LossConfig = LossConfig()) -> torch.Tensor:
    """L_phys = mean_k ||I^_k - I_k||_1 + lambda_zeta ||zeta^ - zeta_gt||_1, paper Eq. (9)-(10).

    I^_k = 1/2 (zeta^_k R + (1 - zeta^_k) T) re-renders every observation from the
    final layers (paper Eq. (9)); the zeta term is dropped when zeta_gt is None.
    """
    I_hat = 0.5 * (zeta_hat * R.unsqueeze(1) + (1 - zeta_hat) * T.unsqueeze(1))  # Eq. (9)
    out = (I_hat - I).abs().mean()  # Eq. (10), first term
    if zeta_gt is not None:
        out = out + cfg.lambda_zeta * (zeta_hat - zeta_gt).abs().mean()
    return out


def loss_excl(T, R, cfg: LossConfig = LossConfig()) -> torch.Tensor:
    """L_excl = ||tanh(lambda_ex |grad T|) * tanh(lambda_ex |grad R|)||_1, paper Eq. (11)."""
    tx, ty = image_grad(T)
    rx, ry = image_grad(R)
    k = cfg.lambda_ex
    return 0.5 * ((torch.tanh(k * tx.abs()) * torch.tanh(k * rx.abs())).mean() + (torch.tanh(k * ty.abs()) * torch.tanh(k * ry.abs())).mean())  # Eq. (11)


SSIM_WIN = 7
"""Window of :func:`ssim_map`: skimage.metrics.structural_similarity's default (uniform 7x7)."""


def ssim_map(x: torch.Tensor, y: torch.Tensor, win: int = SSIM_WIN, data_range: float = 1.0) -> torch.Tensor:
    """SSIM map of (B, H, W) images, as skimage.metrics.structural_similarity computes it.

    Uniform ``win`` x ``win`` window, K1 = 0.01, K2 = 0.03, sample covariances (N / (N - 1));
    the map covers the "valid" interior, (B, H - win + 1, W - win + 1), whose mean is skimage's
    score (it crops (win - 1) / 2 pixels of border).  Differentiable in both arguments.
    """
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    n = win * win
    pool = lambda a: torch.nn.functional.avg_pool2d(a.unsqueeze(1), win, stride=1).squeeze(1)  # noqa: E731
    ux, uy = pool(x), pool(y)
    cov = n / (n - 1.0)
    vx = cov * (pool(x * x) - ux * ux)
    vy = cov * (pool(y * y) - uy * uy)
    vxy = cov * (pool(x * y) - ux * uy)
    return ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))


def total_loss(out, T_gt: torch.Tensor, R_gt: torch.Tensor, alpha: float, cfg: LossConfig = LossConfig()) -> tuple[torch.Tensor, dict[str, float]]:
    """Total objective, paper Eq. (12), plus the solver-output term (``lambda_base``).

    Args:
        out: :class:`reconstruct.net.network.NetOutput` (its ``I`` and ``zeta_gt`` are the RIR-aligned ones).
        T_gt, R_gt: centre-frame ground truth (B, H, W).
        alpha: current teacher-forcing ratio (scales the solver-output term).
        cfg: weights.

    Returns:
        (scalar loss, dict of the components as floats).
    """
    c = out.I.shape[1] // 2
    zc = out.zeta_gt[:, c] if out.zeta_gt is not None else out.zeta_hat[:, c].detach()
    M = reflection_mask(T_gt, R_gt, zc, cfg)
    M_r = None if cfg.r_floor >= 1.0 else reflection_mask(T_gt, R_gt, zc, cfg, floor=cfg.r_floor)
    l_rec = loss_rec(out.T, out.R, T_gt, R_gt, M, cfg, M_r)
    l_grad = loss_grad(out.T, T_gt, M)
    l_phys = loss_phys(out.T, out.R, out.zeta_hat, out.I, out.zeta_gt, cfg)
    l_excl = loss_excl(out.T, out.R, cfg)
    l_base = loss_rec(out.T_base, out.R_base, T_gt, R_gt, M, cfg, M_r)
    total = l_rec + cfg.lambda_g * l_grad + cfg.lambda_p * l_phys + cfg.lambda_e * l_excl  # Eq. (12)
    total = total + cfg.lambda_base * (0.2 + 0.8 * alpha) * l_base
    extra = {}
    if cfg.lambda_ssim > 0:
        l_ssim = 1.0 - ssim_map(out.T.clamp(0, 1), T_gt).mean()
        total = total + cfg.lambda_ssim * l_ssim
        extra["l_ssim"] = float(l_ssim.detach())
    if cfg.lambda_logmse > 0:
        mse = (out.T - T_gt).pow(2).flatten(1).mean(1)
        l_logmse = torch.log1p(mse / cfg.logmse_eps).mean()
        total = total + cfg.lambda_logmse * l_logmse
        extra["l_logmse"] = float(l_logmse.detach())
    parts = {"loss": float(total.detach()), "l_rec": float(l_rec.detach()), "l_grad": float(l_grad.detach()), "l_phys": float(l_phys.detach()), "l_excl": float(l_excl.detach()), "l_base": float(l_base.detach()), **extra}
    return total, parts
