"""Image quality metrics for layer reconstructions (library implementations).

PSNR and SSIM come from :mod:`skimage.metrics` on (H, W) float64 images with
``data_range = 1`` (radiance 1.0 = brightest layer value).  Estimates are
clipped to [0, data_range] before scoring (a reconstruction outside the
displayable range is scored as it would be shown).  LPIPS needs pretrained
backbone weights that cannot be downloaded here; its column reports
:data:`LPIPS_NA` unless a local implementation and weights are importable.
"""

from __future__ import annotations

import numpy as np

from polinfra.errors import ShapeError

__all__ = ["psnr", "ssim", "masked_psnr", "masked_ssim", "masked_score", "lpips_status", "LPIPS_NA", "score"]

LPIPS_NA = "n/a (no local weights)"


def _prep(est, gt, data_range: float) -> tuple[np.ndarray, np.ndarray]:
    e = np.asarray(est, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if e.shape != g.shape or e.ndim != 2:
        raise ShapeError(f"metrics need two (H, W) images of one shape; got {e.shape} and {g.shape}", actual_shape=e.shape, expected_shape=g.shape)
    return np.clip(e, 0.0, data_range), g


def psnr(est, gt, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (skimage.metrics.peak_signal_noise_ratio); inf-safe (capped at 100 dB); NaN where
    the estimate has a non-finite pixel (never the cap: ``min(100, nan)`` is 100).
    """
    from skimage.metrics import peak_signal_noise_ratio

    if not np.isfinite(np.asarray(est, dtype=np.float64)).all():
        return float("nan")
    e, g = _prep(est, gt, data_range)
    if np.array_equal(e, g):
        return 100.0
    return float(min(100.0, peak_signal_noise_ratio(g, e, data_range=data_range)))


def _win(shape) -> int:
    return max(min(7, min(shape) - (1 - min(shape) % 2)), 3)


def ssim(est, gt, data_range: float = 1.0) -> float:
    """Structural similarity (skimage.metrics.structural_similarity, default 7x7 window)."""
    from skimage.metrics import structural_similarity

    e, g = _prep(est, gt, data_range)
    return float(structural_similarity(g, e, data_range=data_range, win_size=_win(g.shape)))


def _mask(mask, shape) -> np.ndarray:
    m = np.asarray(mask, dtype=bool)
    if m.shape != shape:
        raise ShapeError(f"the mask must have the images' shape {shape}; got {m.shape}", actual_shape=m.shape, expected_shape=shape)
    return m


def masked_psnr(est, gt, mask, data_range: float = 1.0) -> float | None:
    """PSNR in dB of the pixels where ``mask`` is true: 10 log10(range^2 / MSE over them), the estimate
    clipped as in :func:`psnr` (capped at 100 dB); None for an empty mask.
    """
    e, g = _prep(est, gt, data_range)
    m = _mask(mask, g.shape)
    if not m.any():
        return None
    mse = float(np.mean((e[m] - g[m]) ** 2))
    return 100.0 if mse == 0 else float(min(100.0, 10.0 * np.log10(data_range**2 / mse)))


def masked_ssim(est, gt, mask, data_range: float = 1.0) -> float | None:
    """Mean of the SSIM map (skimage ``full=True``, the window of :func:`ssim`) over the pixels where
    ``mask`` is true, leaving out the border of half a window as skimage's own mean does (so an all-true
    mask gives :func:`ssim` exactly); None when no such pixel remains.
    """
    from skimage.metrics import structural_similarity

    e, g = _prep(est, gt, data_range)
    m = _mask(mask, g.shape).copy()
    win = _win(g.shape)
    _, smap = structural_similarity(g, e, data_range=data_range, win_size=win, full=True)
    pad = (win - 1) // 2
    if pad:
        m[:pad], m[-pad:], m[:, :pad], m[:, -pad:] = False, False, False, False
    return float(np.mean(smap[m], dtype=np.float64)) if m.any() else None


def masked_score(est, gt, mask, data_range: float = 1.0) -> dict[str, float | None]:
    """{"psnr", "ssim"} of :func:`masked_psnr` / :func:`masked_ssim`."""
    return {"psnr": masked_psnr(est, gt, mask, data_range), "ssim": masked_ssim(est, gt, mask, data_range)}


def lpips_status() -> str:
    """Why LPIPS is or is not reported (no network access: weights must be local)."""
    try:
        import lpips  # noqa: F401
    except ImportError:
        return LPIPS_NA
    return LPIPS_NA  # the package downloads backbone weights on first use; none are cached here


def score(est, gt, data_range: float = 1.0) -> dict[str, float]:
    """{"psnr": dB, "ssim": [-1, 1]} of one (H, W) estimate against its ground truth."""
    return {"psnr": psnr(est, gt, data_range), "ssim": ssim(est, gt, data_range)}
