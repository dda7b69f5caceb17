"""Metrics wrap scikit-image; closed-form PSNR."""

from __future__ import annotations

import numpy as np
import pytest

from polinfra.errors import ShapeError
from reconstruct.metrics import LPIPS_NA, lpips_status, psnr, ssim


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
