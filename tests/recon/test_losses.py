"""Losses, paper Eq. (8)-(12), against hand-computed values."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from reconstruct.net.losses import LossConfig, image_grad, loss_excl, loss_grad, loss_phys, loss_rec, reflection_mask, total_loss


def test_rec_is_weighted_l1():
    T = torch.zeros(1, 2, 2)
    Tg = torch.ones(1, 2, 2)
    M = torch.tensor([[[1.0, 0.5], [0.5, 0.5]]])
    cfg = LossConfig(lambda_r=0.25)
    got = loss_rec(T, T + 2, Tg, T, M, cfg)
    assert math.isclose(float(got), (1 + 0.5 * 3) / 4 + 0.25 * 2, rel_tol=1e-6)


def test_mask_range_and_monotone():
    cfg = LossConfig(m_floor=0.5, rho_ref=0.3)
    T = torch.ones(1, 1, 3)
    R = torch.tensor([[[0.0, 1.0, 10.0]]])
    M = reflection_mask(T, R, torch.full_like(T, 0.1), cfg)
    assert math.isclose(float(M[0, 0, 0]), 0.5, abs_tol=1e-6)  # no reflection -> floor
    assert math.isclose(float(M[0, 0, 2]), 1.0, abs_tol=1e-6)  # reflection share 0.53 > rho_ref -> 1
    assert 0.5 < float(M[0, 0, 1]) < 1.0


def test_grad_loss_zero_for_offset_and_positive_for_edges():
    T = torch.rand(1, 8, 8, generator=torch.Generator().manual_seed(0))
    M = torch.ones_like(T)
    assert float(loss_grad(T + 0.3, T, M)) < 1e-7  # constant offset has no gradient error
    edge = T.clone()
    edge[..., 4:] += 1
    assert float(loss_grad(edge, T, M)) > 0.01


def test_phys_zero_for_consistent_layers():
    """Eq. (9)-(10): exact layers and zeta re-render the observations exactly."""
    g = torch.Generator().manual_seed(0)
    T, R = torch.rand(2, 6, 6, generator=g), torch.rand(2, 6, 6, generator=g)
    z = 0.05 + 0.2 * torch.rand(2, 7, 6, 6, generator=g)
    I = 0.5 * (z * R[:, None] + (1 - z) * T[:, None])
    assert float(loss_phys(T, R, z, I, z)) < 1e-7
    assert math.isclose(float(loss_phys(T, R, z + 0.1, I, z, LossConfig(lambda_zeta=1.0))) - float(loss_phys(T, R, z + 0.1, I, None)), 0.1, rel_tol=1e-4)


def test_exclusion_tanh_form():
    """Eq. (11): zero when one layer is flat; equals tanh(k a) tanh(k b) for two ramps."""
    x = torch.arange(5.0).view(1, 1, 5).expand(1, 5, 5)
    cfg = LossConfig(lambda_ex=2.0)
    assert float(loss_excl(0.1 * x, torch.ones(1, 5, 5), cfg)) == 0.0
    got = float(loss_excl(0.1 * x, 0.2 * x, cfg))
    assert math.isclose(got, 0.5 * math.tanh(0.2) * math.tanh(0.4), rel_tol=1e-5)  # only x-gradients are non-zero
    gx, gy = image_grad(x)
    assert gx.shape == (1, 5, 4) and gy.shape == (1, 4, 5)


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.0])
def test_total_is_eq12_plus_base_term(alpha):
    """Total = paper Eq. (12) + lambda_base (0.2 + 0.8 alpha) L_rec(T^, R^): the solver-output term is non-zero
    for solver outputs that differ from the truth, counted in the total and back-propagated to T^.
    """
    g = torch.Generator().manual_seed(1)
    B, N, H, W = 2, 7, 8, 8
    T, R = torch.rand(B, H, W, generator=g), torch.rand(B, H, W, generator=g)
    z = 0.1 * torch.ones(B, N, H, W)
    I = 0.5 * (z * R[:, None] + (1 - z) * T[:, None])
    T_base = (T + 0.2).requires_grad_(True)  # the solver's T^ is off by 0.2
    out = SimpleNamespace(T=T + 0.1, R=R, T_base=T_base, R_base=R, zeta_hat=z, zeta_gt=z, I=I)
    cfg = LossConfig(lambda_base=0.5)
    tot, parts = total_loss(out, T, R, alpha, cfg)
    # oracle for the base term: the reconstruction term of a network whose refined output IS the solver output
    _, as_refined = total_loss(SimpleNamespace(T=T + 0.2, R=R, T_base=T, R_base=R, zeta_hat=z, zeta_gt=z, I=I), T, R, alpha, cfg)
    assert parts["l_base"] > 0.05 and math.isclose(parts["l_base"], as_refined["l_rec"], rel_tol=1e-6)
    eq12 = parts["l_rec"] + cfg.lambda_g * parts["l_grad"] + cfg.lambda_p * parts["l_phys"] + cfg.lambda_e * parts["l_excl"]
    assert math.isclose(float(tot.detach()), eq12 + 0.5 * (0.2 + 0.8 * alpha) * parts["l_base"], rel_tol=1e-6)
    tot.backward()
    assert float(T_base.grad.abs().sum()) > 0
    off, _ = total_loss(out, T, R, alpha, LossConfig(lambda_base=0.0))
    assert math.isclose(float(off.detach()), eq12, rel_tol=1e-6)


def test_ssim_map_mean_is_the_evaluation_ssim():
    """Oracle: skimage.metrics.structural_similarity (the metric evaluate reports), on random and structured pairs."""
    from skimage.metrics import structural_similarity

    from reconstruct.net.losses import ssim_map

    g = torch.Generator().manual_seed(3)
    y = torch.rand(2, 40, 33, generator=g, dtype=torch.float64)
    x = (0.7 * y + 0.3 * torch.rand(2, 40, 33, generator=g, dtype=torch.float64)).clamp(0, 1)
    m = ssim_map(x, y)
    assert m.shape == (2, 34, 27)
    for b in range(2):
        ref = structural_similarity(y[b].numpy(), x[b].numpy(), data_range=1.0)
        assert abs(float(m[b].mean()) - ref) < 1e-9
    assert abs(float(ssim_map(y, y).mean()) - 1.0) < 1e-12  # identical images


def test_ssim_term_is_off_by_default_and_pulls_toward_the_structure():
    """lambda_ssim = 0 leaves the paper's objective unchanged; > 0 adds 1 - SSIM(T), which a gradient step lowers."""
    from reconstruct.net.losses import LossConfig, ssim_map

    g = torch.Generator().manual_seed(4)
    gt = torch.rand(1, 24, 24, generator=g)
    est = (gt + 0.2 * torch.randn(1, 24, 24, generator=g)).clamp(0, 1).requires_grad_(True)
    assert LossConfig().lambda_ssim == 0.0
    l0 = 1 - ssim_map(est.clamp(0, 1), gt).mean()
    l0.backward()
    with torch.no_grad():
        est2 = est - 0.05 * est.grad / est.grad.abs().max()
    assert float(1 - ssim_map(est2.clamp(0, 1), gt).mean()) < float(l0)


def test_r_floor_weights_the_r_term_by_the_reflected_share():
    """r_floor < 1: the R term of L_rec is the L1 weighted by r_floor + (1 - r_floor) clip(rho / rho_ref, 0, 1)
    (closed form on three pixels: no reflection, share 0.1, share 0.53); r_floor = 1 is the paper's unweighted term.
    """
    T = torch.ones(1, 1, 3)
    R = torch.tensor([[[0.0, 1.0, 10.0]]])
    zc = torch.full_like(T, 0.1)
    err = torch.tensor([[[0.3, 0.2, 0.1]]])
    rho = torch.tensor([0.0, 0.1 / (0.1 + 0.9), 1.0 / (1.0 + 0.9)])
    cfg = LossConfig(lambda_r=1.0, r_floor=0.2, rho_ref=0.3)
    w = 0.2 + 0.8 * (rho / 0.3).clamp(0, 1)
    M_r = reflection_mask(T, R, zc, cfg, floor=cfg.r_floor)
    assert torch.allclose(M_r[0, 0], w, atol=1e-5)
    got = loss_rec(T, R + err, T, R, torch.ones_like(T), cfg, M_r)
    assert math.isclose(float(got), float((w * err[0, 0]).mean()), rel_tol=1e-5)
    z = zc[:, None].expand(1, 7, 1, 3)
    I = 0.5 * (z * R[:, None] + (1 - z) * T[:, None])
    out = SimpleNamespace(T=T, R=R + err, T_base=T, R_base=R, zeta_hat=z, zeta_gt=z, I=I)
    _, p1 = total_loss(out, T, R, 0.0, LossConfig(lambda_r=1.0))
    _, p2 = total_loss(out, T, R, 0.0, cfg)
    assert math.isclose(p1["l_rec"], float(err.mean()), rel_tol=1e-5) and math.isclose(p2["l_rec"], float(got), rel_tol=1e-5)


@pytest.mark.parametrize("alpha", [1.0, 0.0])
def test_total_equals_eq12_written_out_in_numpy(alpha):
    """Paper Eq. (8)-(12) written out again here in float64 numpy, from the paper's formulas and the module's
    documented choices (per-pixel means; M = m_floor + (1 - m_floor) clip(rho / rho_ref, 0, 1) with the centre-frame
    true zeta; the gradient terms' M averaged onto the forward-difference grid and x / y halves averaged), plus the
    solver-output term lambda_base (0.2 + 0.8 alpha) L_rec(T^, R^); every weight off its default so a swapped or
    dropped weight shows, and the predicted zeta away from the true one so both L_phys terms count.
    """
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(11)
    B, N, H, W = 2, 7, 9, 10
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    Tg, Rg, T, R, Tb, Rb = (rnd(B, H, W) for _ in range(6))
    zg, zh, I = 0.5 * rnd(B, N, H, W), 0.5 * rnd(B, N, H, W), 0.5 * rnd(B, N, H, W)
    cfg = LossConfig(lambda_r=0.3, lambda_g=0.7, lambda_p=0.2, lambda_e=0.05, lambda_zeta=1.5, lambda_ex=3.0, lambda_base=0.4, m_floor=0.4, rho_ref=0.25)
    tot, _ = total_loss(SimpleNamespace(T=T, R=R, T_base=Tb, R_base=Rb, zeta_hat=zh, zeta_gt=zg, I=I), Tg, Rg, alpha, cfg)

    Tg, Rg, T, R, Tb, Rb, zg, zh, I = (x.numpy() for x in (Tg, Rg, T, R, Tb, Rb, zg, zh, I))
    zc = zg[:, N // 2]
    rho = zc * Rg / (zc * Rg + (1 - zc) * Tg + 1e-6)
    M = 0.4 + 0.6 * np.clip(rho / 0.25, 0, 1)

    def rec(t, r):  # Eq. (8), first part
        return np.mean(M * np.abs(t - Tg)) + 0.3 * np.mean(np.abs(r - Rg))

    d = T - Tg  # Eq. (8), second part
    l_grad = 0.5 * (np.mean(0.5 * (M[..., 1:] + M[..., :-1]) * np.abs(d[..., 1:] - d[..., :-1]))
                    + np.mean(0.5 * (M[:, 1:] + M[:, :-1]) * np.abs(d[:, 1:] - d[:, :-1])))
    I_hat = 0.5 * (zh * R[:, None] + (1 - zh) * T[:, None])  # Eq. (9)
    l_phys = np.mean(np.abs(I_hat - I)) + 1.5 * np.mean(np.abs(zh - zg))  # Eq. (10)
    th = lambda x, ax: np.tanh(3.0 * np.abs(np.diff(x, axis=ax)))  # noqa: E731
    l_excl = 0.5 * (np.mean(th(T, 2) * th(R, 2)) + np.mean(th(T, 1) * th(R, 1)))  # Eq. (11)
    eq12 = rec(T, R) + 0.7 * l_grad + 0.2 * l_phys + 0.05 * l_excl  # Eq. (12)
    want = eq12 + 0.4 * (0.2 + 0.8 * alpha) * rec(Tb, Rb)
    assert float(tot) == pytest.approx(want, rel=1e-12)


def test_logmse_term_weighs_each_windows_error_on_the_psnr_scale():
    """lambda_logmse: the term is the mean over windows of ln(1 + MSE(T) / eps), closed form on two windows; it is
    off by default; and, unlike L1, its pull on a window grows as that window's error shrinks (the gradient per unit
    error is 2 / (N (MSE + eps))), so a near-perfect bright window is not drowned by a noisy dim one.
    """
    T = torch.zeros(2, 4, 4)
    err = torch.zeros(2, 4, 4)
    err[0] += 0.003  # a bright, clean window: MSE 9e-6
    err[1] += 0.1  # a dim, noisy one: MSE 1e-2
    R = torch.zeros_like(T)
    z = torch.full((2, 7, 4, 4), 0.1)
    out = SimpleNamespace(T=(T + err).requires_grad_(True), R=R, T_base=T, R_base=R, zeta_hat=z, zeta_gt=z, I=0.5 * (1 - z) * T[:, None])
    assert LossConfig().lambda_logmse == 0.0
    _, p0 = total_loss(out, T, R, 0.0, LossConfig())
    assert "l_logmse" not in p0
    cfg = LossConfig(lambda_logmse=0.5, logmse_eps=1e-5)
    tot, p = total_loss(out, T, R, 0.0, cfg)
    want = (math.log1p(9e-6 / 1e-5) + math.log1p(1e-2 / 1e-5)) / 2
    assert math.isclose(p["l_logmse"], want, rel_tol=1e-4)
    assert math.isclose(p["loss"] - p0["loss"], 0.5 * want, rel_tol=1e-4)
    (g,) = torch.autograd.grad(0.5 * torch.log1p((out.T - T).pow(2).flatten(1).mean(1) / 1e-5).mean(), out.T)
    per_unit = g.flatten(1).mean(1) / err.flatten(1).mean(1)  # gradient per unit of error, per window
    assert float(per_unit[0]) > 100 * float(per_unit[1])
