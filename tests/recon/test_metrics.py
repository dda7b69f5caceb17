"""Metrics wrap scikit-image; closed-form PSNR."""

from __future__ import annotations

import numpy as np
import pytest

from polinfra.errors import ShapeError
from reconstruct.evaluate.metrics import LPIPS_NA, lpips_status, psnr, ssim


def test_psnr_closed_form():
    gt = np.full((16, 16), 0.5)
    est = gt + 0.1  # MSE 0.01 -> 20 dB at data range 1
    assert abs(psnr(est, gt) - 20.0) < 1e-9
    assert psnr(gt, gt) == 100.0


def test_ssim_identity_and_clipping():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 1, (32, 32))
    assert abs(ssim(gt, gt) - 1.0) < 1e-12
    assert psnr(gt + 5.0, gt) == psnr(np.ones_like(gt), gt)  # estimates are clipped to [0, 1]


def test_shape_mismatch_and_lpips():
    with pytest.raises(ShapeError):
        psnr(np.zeros((3, 3)), np.zeros((3, 4)))
    assert lpips_status() == LPIPS_NA


def _pair(seed=1, shape=(40, 52)):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0.1, 0.9, shape)
    return gt, np.clip(gt + rng.normal(0, 0.05, shape), 0, 1)


def test_masked_scores_equal_the_whole_frame_ones_for_an_all_true_mask():
    from reconstruct.evaluate.metrics import masked_psnr, masked_ssim

    gt, est = _pair()
    full = np.ones(gt.shape, bool)
    assert masked_psnr(est, gt, full) == pytest.approx(psnr(est, gt), abs=1e-9)
    assert masked_ssim(est, gt, full) == pytest.approx(ssim(est, gt), abs=1e-12)  # skimage's mean leaves out the border too


def test_masked_psnr_closed_form_and_errors_outside_the_mask_do_not_count():
    from reconstruct.evaluate.metrics import masked_psnr, masked_ssim

    gt = np.full((30, 30), 0.5)
    mask = np.zeros(gt.shape, bool)
    mask[:, :10] = True
    est = gt.copy()
    est[:, :10] += 0.1  # MSE 0.01 inside the mask -> 20 dB
    est[:, 20:] = 1.0  # a large error confined to masked-out pixels
    assert masked_psnr(est, gt, mask) == pytest.approx(20.0, abs=1e-9)
    assert psnr(est, gt) < 12.0  # the whole frame sees it
    # SSIM: an error far (more than a window) from the masked pixels leaves their SSIM map unchanged
    g2, e2 = _pair(2, (30, 40))
    m2 = np.zeros(g2.shape, bool)
    m2[:, :12] = True
    e3 = e2.copy()
    e3[:, 25:] = 0.0
    assert masked_ssim(e3, g2, m2) == pytest.approx(masked_ssim(e2, g2, m2), abs=1e-12)
    assert ssim(e3, g2) < ssim(e2, g2) - 0.1
    assert masked_psnr(est, gt, np.zeros(gt.shape, bool)) is None and masked_ssim(est, gt, np.zeros(gt.shape, bool)) is None
    with pytest.raises(ShapeError):
        masked_psnr(est, gt, mask[:5])
