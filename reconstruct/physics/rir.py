"""Reflection-Invariant Registration (RIR), supp. Sec. 6.

Within a window of N frames the reflection layer flickers with the polarizer
(it is strongly polarized), the transmission barely does.  Registering raw
frames therefore locks onto the flickering reflection.  RIR instead:

1. fits the per-pixel harmonic model (supp. Eq. (1)) and its DoP (supp. Eq. (2));
2. keeps low-DoP, well-exposed pixels (:func:`registration_mask`);
3. estimates the translation of each frame to the centre frame by masked
   phase correlation (scikit-image's ``phase_cross_correlation`` with
   ``reference_mask``/``moving_mask``, Padfield 2010), which is whole-pixel
   only (run on 2x2 block means for speed), then refines it to sub-pixel precision by a masked Gauss-Newton
   (Lucas-Kanade) fit of translation plus gain/offset on the same pixels;
4. warps frames *and* the per-frame coefficient maps (zeta) with one
   differentiable bilinear warp (:func:`warp`, ``grid_sample``).

Shift convention: ``shift = (dy, dx)`` in pixels is the translation that,
applied to frame k, registers it onto the centre frame:
``warp(I_k, shift)(y, x) = I_k(y - dy, x - dx)``, the same convention as
``skimage.registration.phase_cross_correlation``.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch
import torch.nn.functional as F

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError
from reconstruct.physics.harmonic_fit import dop, harmonic_fit

__all__ = ["RIR_SD_SCALE", "RirConfig", "registration_mask", "warp", "estimate_shifts", "steady_shifts", "align_window", "ChainedRir"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RirConfig:
    """Parameters of reflection-invariant registration."""

    dop_max: float = opt(0.12, "pixels with DoP above this are excluded (reflection-dominated)", lo=0.0, hi=10.0)
    exposure_lo: float = opt(0.05, "exclude pixels darker than this fraction of the 99th-percentile a0", lo=0.0, hi=1.0)
    exposure_hi: float = opt(0.98, "exclude pixels brighter than this fraction of the max a0 (saturation)", lo=0.0, hi=1.0)
    mask_sigma_px: float = opt(2.0, "Gaussian smoothing of frames before the DoP fit (noisy spike frames), pixels", lo=0.0, hi=50.0)
    min_fraction: float = opt(0.05, "if fewer pixels pass, keep this fraction of well-exposed pixels with the lowest DoP", lo=0.0, hi=1.0)
    smooth_sigma_px: float = opt(1.0, "Gaussian pre-smoothing of frames before registration, pixels (0 = none)", lo=0.0, hi=20.0)
    refine_iters: int = opt(8, "Gauss-Newton sub-pixel refinement iterations (0 = whole-pixel only)", lo=0, hi=100)
    max_shift_px: float = opt(16.0, "shifts larger than this are treated as failed registrations and set to 0", lo=0.0, hi=1e4)
    erode_px: int = opt(4, "erosion of the mask for sub-pixel refinement, pixels", lo=0, hi=100)
    coarse_factor: int = opt(2, "block size of the whole-pixel masked phase correlation (1 = full resolution)", lo=1, hi=16)
    refine_points: int = opt(20000, "at most this many mask pixels in the sub-pixel refinement", lo=16, hi=10**8)
    overlap_ratio: float = opt(0.3, "minimum overlap for skimage's masked correlation", lo=0.0, hi=1.0)
    steady: bool = opt(True, "hold a window's shifts to one constant velocity where its registrations are noise (steady_shifts): where at least half the frames are precise they keep their shifts and the others get their velocity's; otherwise the velocity fitted to all, shrunk toward rest by its standard error. False: every registration as it is (a failed one 0)")
    steady_px: float = opt(0.2, "a frame is precise where its stated precision (the refinement's sd times RIR_SD_SCALE) is within this many pixels (steady)", lo=0.0, hi=100.0)


def registration_mask(I: torch.Tensor, phi: torch.Tensor, config: RirConfig = RirConfig()) -> torch.Tensor:
    """Low-DoP, well-exposed pixels of a window.

    Frames are smoothed (``mask_sigma_px``) before the per-pixel harmonic fit so
    that spike noise does not inflate the DoP of every pixel.

    Args:
        I: frames (N, H, W).
        phi: angles (N,) radians.

    Returns:
        bool mask (H, W) on the CPU.
    """
    with torch.no_grad():
        if config.mask_sigma_px > 0:
            I = torch.from_numpy(np.stack([_smooth(f, config.mask_sigma_px) for f in I.detach().cpu().double().numpy()]))
            phi = phi.detach().cpu().double()
        a0, ac, as_ = harmonic_fit(I, phi)
        p = dop(a0, ac, as_, eps=1e-6 * float(a0.abs().max().clamp_min(1e-30)))
        ref = _quantile(a0.flatten().float(), 0.99).to(a0.dtype)
        well = (a0 >= config.exposure_lo * ref) & (a0 <= config.exposure_hi * a0.max())
        mask = well & (p <= config.dop_max)
        need = int(config.min_fraction * mask.numel())
        if int(mask.sum()) < need and int(well.sum()) > 0:
            pw = torch.where(well, p, torch.full_like(p, float("inf")))
            k = min(need, int(well.sum()))
            thr = torch.kthvalue(pw.flatten(), k).values
            mask = well & (pw <= thr)
    return mask


def _quantile(x: torch.Tensor, q: float, dim: int | None = None) -> torch.Tensor:
    """``torch.quantile(x, q, dim)`` of a tensor without NaN (linear interpolation between the two order statistics
    around rank q (n - 1), by ``torch.lerp`` as torch does) from two selections instead of a sort; ``dim`` None: of
    all its values.
    """
    if dim is None:
        x, dim = x.flatten(), 0
    n = x.shape[dim]
    pos = q * (n - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, n - 1)
    a = torch.kthvalue(x, lo + 1, dim=dim).values
    b = torch.kthvalue(x, hi + 1, dim=dim).values if hi != lo else a
    return torch.lerp(a, b, torch.tensor(pos - lo, dtype=x.dtype))


def warp(x: torch.Tensor, shifts: torch.Tensor) -> torch.Tensor:
    """Differentiable sub-pixel translation of images, ``out(y, x) = in(y - dy, x - dx)``.

    Args:
        x: images (..., N, H, W) (frames or per-frame coefficient maps).
        shifts: (..., N, 2) as (dy, dx) in pixels, broadcast over the leading dims.

    Returns:
        warped images, same shape as x (bilinear, border values replicated).
    """
    if x.dim() < 3 or shifts.shape[-1] != 2:
        raise ShapeError(f"warp needs x (..., N, H, W) and shifts (..., N, 2); got {tuple(x.shape)} and {tuple(shifts.shape)}", actual_shape=tuple(shifts.shape), expected_shape="(..., N, 2)")
    H, W = x.shape[-2:]
    shifts = torch.broadcast_to(shifts.to(x.dtype), x.shape[:-2] + (2,))
    flat = x.reshape(-1, 1, H, W)
    s = shifts.reshape(-1, 2)
    ys = (2.0 * torch.arange(H, dtype=x.dtype, device=x.device) + 1.0) / H - 1.0
    xs = (2.0 * torch.arange(W, dtype=x.dtype, device=x.device) + 1.0) / W - 1.0
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    gx = gx[None] - (2.0 * s[:, 1] / W)[:, None, None]
    gy = gy[None] - (2.0 * s[:, 0] / H)[:, None, None]
    grid = torch.stack([gx, gy], dim=-1)
    out = F.grid_sample(flat, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out.reshape(x.shape)


def _smooth(img: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return img
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(img, sigma)


def _block_mean(img: np.ndarray, f: int) -> np.ndarray:
    H, W = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    return img[:H, :W].reshape(H // f, f, W // f, f).mean(axis=(1, 3))


def _block_sum_mean(img: np.ndarray, f: int) -> np.ndarray:
    """:func:`_block_mean` by strided sums (equal up to the order of the additions; a few times faster)."""
    H, W = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    rows = img[0:H:f, :W].copy()
    for k in range(1, f):
        rows += img[k:H:f, :W]
    out = rows[:, 0:W:f].copy()
    for k in range(1, f):
        out += rows[:, k:W:f]
    return out / (f * f)


def _gradient_stack(img: np.ndarray) -> torch.Tensor:
    """:func:`_with_gradient` by numpy (the same central differences, one-sided at the borders)."""
    gy, gx = np.gradient(img)
    return torch.from_numpy(np.stack([img, gy, gx]))


def _erode(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0:
        return mask
    from scipy.ndimage import binary_erosion

    return binary_erosion(mask, iterations=px, border_value=0)


def _sample(img: torch.Tensor, yx: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of images (C, H, W) at pixel positions yx (P, 2) -> (C, P), border-replicated."""
    H, W = img.shape[-2:]
    gx = (2.0 * yx[:, 1] + 1.0) / W - 1.0
    gy = (2.0 * yx[:, 0] + 1.0) / H - 1.0
    grid = torch.stack([gx, gy], -1)[None, None]
    return F.grid_sample(img[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0]


def _refine(ref: torch.Tensor, mov: torch.Tensor, mask: torch.Tensor, s0: torch.Tensor, iters: int, max_points: int = 20000) -> torch.Tensor:
    """Masked Gauss-Newton on normalised intensities: min_s sum_mask (n(warp(mov, s)) - n(ref))^2, from s0 -> (s, the
    fit's stated sd of a component, :func:`_stated_sd`; inf where the mask holds too few pixels).

    Works on the mask's pixels only (at most ``max_points``, evenly strided):
    the moving image and its gradients are sampled there with the same
    bilinear interpolation as :func:`warp`.  float64 (H, W) inputs.
    """
    pts = _mask_points(mask, max_points).to(ref.dtype)
    if pts.shape[0] < 16:
        return s0, float("inf")
    r_ref, stack = ref[pts[:, 0].long(), pts[:, 1].long()], _with_gradient(mov)
    s = _gauss_newton(r_ref, stack, pts, s0, iters)
    return s, _stated_sd(r_ref, stack, pts, s)


def _mask_points(mask: torch.Tensor, max_points: int) -> torch.Tensor:
    """(P, 2) (y, x) of the mask's pixels, at most ``max_points`` (evenly strided)."""
    pts = mask.nonzero()
    if pts.shape[0] > max_points:
        pts = pts[:: int(np.ceil(pts.shape[0] / max_points))]
    return pts


def _with_gradient(img: torch.Tensor) -> torch.Tensor:
    gy, gx = torch.gradient(img)
    return torch.stack([img, gy, gx])


def _normalised(x: torch.Tensor) -> torch.Tensor:
    """Zero mean, unit variance over the mask's points."""
    return (x - x.mean()) / x.std().clamp_min(1e-30)


def _linearised(r_ref: torch.Tensor, stack: torch.Tensor, pts: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The normalised fit at ``s``: residual r (P,), Jacobian A (P, 2) and A'A with a tiny ridge, for the normalised
    reference values ``r_ref`` at ``pts`` and the moving image with its gradient ``stack`` (3, H, W).
    """
    J, Jy, Jx = _sample(stack, pts - s)  # warp(mov, s)(p) = mov(p - s) and its gradient there
    # photometric normalisation on the mask (zero mean, unit variance): the polarizer changes
    # each frame's gain a little; normalising (rather than fitting a gain) keeps the step well
    # scaled when the frames are noisy
    sd = J.std().clamp_min(1e-30)
    r = r_ref - (J - J.mean()) / sd
    # warp(mov, s + d) ~= J - grad J . d   =>   r ~= -(Jy dy + Jx dx) / sd
    A = -torch.stack([Jy, Jx], -1) / sd  # (P, 2)
    Hm = A.T @ A
    return r, A, Hm + (1e-9 * Hm.diagonal().sum() + 1e-30) * torch.eye(2, dtype=Hm.dtype)


def _gauss_newton(r_ref: torch.Tensor, stack: torch.Tensor, pts: torch.Tensor, s0: torch.Tensor, iters: int) -> torch.Tensor:
    """The iterations of :func:`_refine`: reference values at ``pts``, the moving image with its gradient (3, H, W)."""
    s = s0.clone()
    r_ref = _normalised(r_ref)
    for _ in range(iters):
        r, A, Hm = _linearised(r_ref, stack, pts, s)
        d = torch.linalg.solve(Hm, A.T @ r).clamp(-0.5, 0.5)
        s = s + d
        if float(d.abs().max()) < 1e-4:
            break
    return s


def _stated_sd(r_ref: torch.Tensor, stack: torch.Tensor, pts: torch.Tensor, s: torch.Tensor) -> float:
    """The Gauss-Newton fit's own sd of a shift component at ``s`` (pixels): sqrt(<r^2> tr (A'A)^-1 / 2), the residual
    r and Jacobian A of :func:`_gauss_newton` there.  It counts the mask's pixels as independent; the pre-smoothing
    correlates their noise, so the shifts scatter about RIR_SD_SCALE times more (measured, :func:`steady_shifts`).
    """
    r, _, Hm = _linearised(_normalised(r_ref), stack, pts, s)
    return float((float((r * r).mean()) * torch.linalg.inv(Hm).diagonal().sum() / 2.0) ** 0.5)


def estimate_shifts(
    I: torch.Tensor, phi: torch.Tensor, center: int | None = None, mask: torch.Tensor | None = None, config: RirConfig = RirConfig()
) -> torch.Tensor:
    """Translation of every frame of a window onto its centre frame (sub-pixel).

    Args:
        I: frames (N, H, W) (any device; registration runs on CPU in float64).
        phi: angles (N,) radians.
        center: index of the reference frame (default N // 2).
        mask: bool (H, W) registration mask (default :func:`registration_mask`).

    Returns:
        shifts (N, 2) as (dy, dx) pixels, float64, on I's device; the centre row is 0.
    """
    from skimage.registration import phase_cross_correlation

    if I.dim() != 3:
        raise ShapeError(f"estimate_shifts needs one window (N, H, W); got {tuple(I.shape)}", actual_shape=tuple(I.shape), expected_shape="(N, H, W)")
    N = I.shape[0]
    c = N // 2 if center is None else center
    if mask is None:
        mask = registration_mask(I, phi, config)
    frames = I.detach().to("cpu", torch.float64).numpy()
    m_np = mask.detach().cpu().numpy().astype(bool)
    sm = [_smooth(f, config.smooth_sigma_px) for f in frames]
    ref_t = torch.from_numpy(sm[c])
    if config.coarse_factor > 1:
        co = [_block_mean(f, config.coarse_factor) for f in sm]
        m_co = _block_mean(m_np.astype(np.float64), config.coarse_factor) > 0.99
    # the refinement samples neighbours (bilinear warp, finite-difference gradients, smoothing):
    # erode its mask so no excluded (reflection) pixel or image border leaks in
    m_t = torch.from_numpy(_erode(m_np, config.erode_px))
    out = torch.zeros(N, 2, dtype=torch.float64)
    valid = torch.zeros(N, dtype=torch.bool)
    sd = torch.full((N,), float("nan"), dtype=torch.float64)  # the refinement's stated sd per frame (nan: none)
    for k in range(N):
        if k == c or not m_np.any():
            continue
        f = config.coarse_factor
        if f > 1:  # whole-pixel search on a block-averaged copy; the refinement recovers full resolution
            shift = f * phase_cross_correlation(co[c], co[k], reference_mask=m_co, moving_mask=m_co, overlap_ratio=config.overlap_ratio)[0]
        else:
            shift = phase_cross_correlation(sm[c], sm[k], reference_mask=m_np, moving_mask=m_np, overlap_ratio=config.overlap_ratio)[0]
        s0 = torch.as_tensor(np.asarray(shift, dtype=np.float64))
        if config.refine_iters > 0:
            s0, sd[k] = _refine(ref_t, torch.from_numpy(sm[k]), m_t, s0, config.refine_iters, config.refine_points)
        if not torch.isfinite(s0).all() or float(s0.abs().max()) > config.max_shift_px:
            log.debug("frame %d: registration failed (shift %s), using 0", k, s0.tolist())
            s0 = torch.zeros(2, dtype=torch.float64)
        else:
            valid[k] = True
        out[k] = s0
    return (steady_shifts(out, c, valid, config.steady_px, sd=sd if bool(torch.isfinite(sd[valid]).all()) else None) if config.steady else out).to(I.device)


RIR_SD_SCALE = 3.0
"""How many times the Gauss-Newton fit's stated sd the registered shifts scatter by (:func:`_stated_sd` counts the
pre-smoothed mask's pixels as independent): 2.7-4.9 measured on the RIR test stack at noise 0.003-0.04, about 4 on a
dim paper-profile stream (0.023 spikes per pixel per step, 85 mask pixels)."""


def steady_shifts(shifts: torch.Tensor, center: int, valid: torch.Tensor | None = None, steady_px: float = 0.2,
                  inlier_px: float = 0.5, sd: torch.Tensor | None = None) -> torch.Tensor:
    """A window's registered ``shifts`` (N, 2) onto frame ``center``, held to one constant velocity where the
    registrations are noise: the frames lie equally spaced in time (18 ms for the 7 windows), over which a pan, a
    shake or a layer's motion is close to steady, while a registration of noise-limited frames (dim light: a third of
    a spike per pixel per window) scatters by a pixel or more about any velocity.

    A frame is precise where it lies within ``inlier_px`` of the median slope of the ``valid`` frames (a failed or
    wrong registration does not pull it) and its own stated precision, the refinement's sd (``sd`` (N,),
    :func:`_stated_sd`) times RIR_SD_SCALE, is within ``steady_px``; without ``sd`` (an estimator that states none),
    where the frames within ``inlier_px`` scatter about their refitted velocity by at most ``steady_px`` rms.  Where at
    least half the frames besides the centre are precise, they keep their shifts as registered (a shake's curve
    too) and every other frame gets the velocity fitted to them, v t.  Otherwise the registrations are noise: the
    shifts are the least-squares v t over all valid frames with v shrunk by its standard error se^2 = r^2 / sum t^2
    (r^2 the frames' scatter about v per component), v (1 - 2 se^2 / |v|^2)^+ (its power less the noise's): a
    still scene's noise gives shifts near 0, not a velocity that would move the long span.
    """
    s = shifts.to(torch.float64)
    N = s.shape[0]
    t = torch.arange(N, dtype=torch.float64) - float(center)
    use = (t != 0) if valid is None else (valid.to(torch.bool) & (t != 0))
    if int(use.sum()) == 0:
        return torch.zeros_like(s)

    def fit(m):
        tm = t[m]
        stt = float((tm * tm).sum())
        v = (tm[:, None] * s[m]).sum(0) / stt
        res = s[m] - tm[:, None] * v[None, :]
        dof = 2 * int(m.sum()) - 2
        return v, (float((res * res).sum()) / dof if dof > 0 else 0.0), stt

    v_med = (s[use] / t[use][:, None]).median(0).values
    precise = use & (torch.linalg.vector_norm(s - t[:, None] * v_med[None, :], dim=1) <= inlier_px)
    if sd is not None:
        precise &= RIR_SD_SCALE * torch.nan_to_num(sd.to(torch.float64), nan=float("inf")) <= steady_px
    if 2 * int(precise.sum()) >= N - 1:
        v, r2, _ = fit(precise)
        if sd is not None or r2 <= steady_px * steady_px:
            return torch.where((precise | (t == 0))[:, None], s, t[:, None] * v[None, :])
    v, r2, stt = fit(use)
    v2 = float((v * v).sum())
    return t[:, None] * (v * (max(0.0, 1.0 - 2.0 * (r2 / stt) / v2) if v2 > 0 else 0.0))[None, :]


def align_window(
    I: torch.Tensor, phi: torch.Tensor, coeffs: torch.Tensor | None = None, config: RirConfig = RirConfig()
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """RIR on one window: estimate shifts and warp frames and per-frame maps alike.

    Args:
        I: frames (N, H, W).
        phi: angles (N,) radians.
        coeffs: optional per-frame maps (N, H, W) or (C, N, H, W) (e.g. zeta) warped with the same shifts.

    Returns:
        (aligned I, aligned coeffs or None, shifts (N, 2)).
    """
    shifts = estimate_shifts(I, phi, config=config)
    sI = warp(I, shifts.to(I.dtype))
    sc = None if coeffs is None else warp(coeffs, shifts.to(coeffs.dtype))
    return sI, sc, shifts


class ChainedRir:
    """RIR for a stream whose motion is global: each new frame is registered once, onto the frame before it, and a
    window's shifts are differences of the running sums (translations add), instead of six masked phase
    correlations per window.

    Per new frame: the frames are smoothed (``smooth_sigma_px``) and block-averaged by ``factor``; the
    shift onto the previous frame is a masked Gauss-Newton fit (the refinement of :func:`estimate_shifts`),
    coarse to fine (block sizes ``4 factor``, then ``factor``, then full resolution on at most ``points`` mask
    pixels), from zero: inter-frame motion at the output cadence is small (a few pixels at most).  The
    registration mask (:func:`registration_mask`, low-DoP well-exposed pixels) is computed on the block-averaged
    window every ``mask_every`` windows and kept in between (it follows the scene, which moves slowly).

    With ``finest`` > 1 the fit stops at blocks of that size (the full-resolution level is skipped: the frame is
    block-averaged first and smoothed there with ``smooth_sigma_px / finest``), about 4 x cheaper per frame; the
    error this costs against a known translation is measured in docs/realtime.md.

    Args:
        config: RIR parameters (mask thresholds, smoothing, iterations, max shift).
        finest: block size of the finest level (1 = full resolution; at most ``factor``).
        fused: the Gauss-Newton iterations as one numba loop (:mod:`reconstruct.physics.fused_rir`, the same fit)
            instead of torch calls.
    """

    def __init__(self, config: RirConfig = RirConfig(), factor: int = 2, mask_every: int = 8, points: int = 4000, finest: int = 1, fused: bool = True):
        self.config, self.factor, self.mask_every, self.points, self.fused = config, int(factor), int(mask_every), int(points), bool(fused)
        if finest not in (1, self.factor):
            raise ConfigError(f"finest level must be 1 or the block factor {self.factor}; got {finest}")
        self.finest = int(finest)
        self.levels = tuple(lv for lv in (4 * self.factor, self.factor, 1) if lv >= self.finest)
        self.q: dict[int, np.ndarray] = {}  # running sum of the frame-to-frame shifts
        self.prev: tuple[int, dict] | None = None  # (frame index, its pyramid)
        self.pts: dict[int, torch.Tensor] | None = None  # mask points per level
        self.windows = 0

    def _mask(self, I, phi: torch.Tensor) -> None:
        I = I.detach().cpu() if torch.is_tensor(I) else torch.from_numpy(np.stack([np.asarray(x) for x in I]))
        f = self.factor
        cfg = dataclasses.replace(self.config, mask_sigma_px=self.config.mask_sigma_px / f)
        if self.fused:  # the same steps by the compiled kernels (block means, smoothing, erosion)
            from reconstruct.physics.fused_rir import block_mean_fused, erode_fused, smooth_fused

            co = torch.from_numpy(smooth_fused(block_mean_fused(I.detach().cpu().numpy(), f), cfg.mask_sigma_px))
            m = registration_mask(co, phi.detach().cpu().double(), dataclasses.replace(cfg, mask_sigma_px=0.0)).numpy()
            bm, er = block_mean_fused, erode_fused
        else:
            co = torch.from_numpy(np.stack([_block_mean(x, f) for x in I.detach().cpu().double().numpy()]))
            m = registration_mask(co, phi, cfg).numpy()
            bm, er = _block_mean, _erode
        full = np.zeros(I.shape[-2:], bool)
        full[: m.shape[0] * f, : m.shape[1] * f] = np.repeat(np.repeat(m, f, 0), f, 1)
        self.pts = {}
        lv_w = {}
        for lv in self.levels:
            m = bm(full.astype(np.float64), lv) > 0.99 if lv > 1 else full
            lv_w[lv] = m.shape[1]
            m = er(m, max(1, self.config.erode_px // lv))
            self.pts[lv] = _mask_points(torch.from_numpy(m), self.points).double()
        self.pts_np = {lv: (p.numpy(), (p[:, 0] * lv_w[lv] + p[:, 1]).long().numpy()) for lv, p in self.pts.items()}  # flat indices

    def _pyramid(self, frame: np.ndarray) -> dict:
        f0 = self.finest
        if self.fused:
            from reconstruct.physics.fused_rir import pyramid_fused

            return pyramid_fused(frame, self.config.smooth_sigma_px / f0, f0, self.levels)
        if f0 > 1:
            sm = _smooth(_block_sum_mean(frame, f0), self.config.smooth_sigma_px / f0)
            return {lv: _gradient_stack(_block_sum_mean(sm, lv // f0) if lv > f0 else sm) for lv in self.levels}
        sm = _smooth(frame, self.config.smooth_sigma_px)
        return {lv: _gradient_stack(_block_sum_mean(sm, lv) if lv > 1 else sm) for lv in self.levels}

    def _pair(self, ref: dict, mov: dict) -> torch.Tensor:
        s = torch.zeros(2, dtype=torch.float64)
        for lv in self.levels:
            pts = self.pts[lv]
            if pts.shape[0] < 16:
                continue
            r = ref[lv][0][pts[:, 0].long(), pts[:, 1].long()]
            s = lv * _gauss_newton(r, mov[lv], pts, s / lv, max(self.config.refine_iters, 1))
        if not torch.isfinite(s).all() or float(s.abs().max()) > self.config.max_shift_px:
            return torch.zeros(2, dtype=torch.float64)
        return s

    def _pair_np(self, ref: dict, mov: dict) -> np.ndarray:
        """:meth:`_pair` on numpy levels (:func:`reconstruct.physics.fused_rir.pyramid_fused`), the numba fit."""
        from reconstruct.physics.fused_rir import gauss_newton_fused

        s = np.zeros(2)
        for lv in self.levels:
            pts, flat = self.pts_np[lv]
            if pts.shape[0] < 16:
                continue
            s = lv * gauss_newton_fused(np.take(ref[lv][0], flat), mov[lv], pts, s / lv, max(self.config.refine_iters, 1))
        if not np.isfinite(s).all() or float(np.abs(s).max()) > self.config.max_shift_px:
            return np.zeros(2)
        return s

    def window_shifts(self, I, phi: torch.Tensor, index: np.ndarray) -> torch.Tensor:
        """Shifts (N, 2) registering each frame of the window onto its centre; ``index`` (N,) the frames' indices in
        the stream, consecutive.  ``I``: the frames, (N, H, W) tensor or a sequence of N (H, W) arrays (views of a
        ring of frames, not copied: only the frame new to the chain is read, and the mask's window every
        ``mask_every`` windows).
        """
        N = len(I)
        if self.pts is None or self.windows % self.mask_every == 0:
            self._mask(I, phi)
        self.windows += 1
        for k in range(N):
            j = int(index[k])
            if j in self.q:
                continue
            fr = I[k].detach().cpu().numpy() if torch.is_tensor(I[k]) else np.asarray(I[k])
            sm = self._pyramid(fr if self.fused else fr.astype(np.float64))
            if self.prev is None or self.prev[0] != j - 1:
                self.q[j] = np.zeros(2)
            else:
                self.q[j] = self.q[j - 1] + (self._pair_np(self.prev[1], sm) if self.fused else self._pair(self.prev[1], sm).numpy())
            self.prev = (j, sm)
        lo = int(index[0])
        for j in [j for j in self.q if j < lo]:
            del self.q[j]
        c = N // 2
        qc = self.q[int(index[c])]
        out = torch.from_numpy(np.stack([self.q[int(j)] - qc for j in index]))
        if self.config.steady:  # held to one velocity as estimate_shifts' are (the chain's errors add up like a walk)
            out = steady_shifts(out, c, None, self.config.steady_px)
        return out.to(I.device) if torch.is_tensor(I) else out
