"""RIR: masked registration recovers sub-pixel shifts that a strongly polarized reflection hides from naive phase correlation."""

from __future__ import annotations

import numpy as np
import torch
from skimage.registration import phase_cross_correlation

from reconstruct.physics.rir import align_window, estimate_shifts, registration_mask, warp

from ._synth import periodic_texture


def _stack(N=7, H=96, W=128, noise=0.003, seed=0):
    """T moves by known sub-pixel shifts; a bright, static, strongly polarized R covers the left half."""
    rng = np.random.default_rng(seed)
    true = np.array([[0.3 * (k - N // 2), -0.45 * (k - N // 2)] for k in range(N)])
    phi = np.deg2rad(31.5) * np.arange(N)
    R = 2.0 + 0.8 * periodic_texture(np.random.default_rng(2), H, W, fmax=0.05)
    left = np.zeros((H, W))
    left[:, : W // 2] = 1.0
    frames = []
    for k in range(N):
        # T_k is T translated by -true[k]; warping it by true[k] registers it onto the centre frame
        T = 0.5 + 0.08 * periodic_texture(np.random.default_rng(1), H, W, shift=-true[k])
        zeta = left * (0.45 * np.cos(phi[k] - 0.3) ** 2 + 0.02) + (1 - left) * 0.03  # paper Eq. (2) with R_par ~ 0
        I = 0.5 * (zeta * R + (1 - zeta) * T)  # paper Eq. (1)
        frames.append(I + rng.normal(0.0, noise, I.shape))
    return np.array(frames), phi, true


def test_masked_registration_recovers_subpixel_shifts_naive_is_fooled():
    frames, phi, true = _stack()
    I = torch.from_numpy(frames)
    naive = np.array([phase_cross_correlation(frames[3], f, upsample_factor=20)[0] for f in frames])
    est = estimate_shifts(I, torch.from_numpy(phi)).numpy()
    err_naive = np.abs(naive - true).max()
    err = np.abs(est - true).max()
    assert err_naive > 0.3, f"the test stack should fool naive phase correlation (max error {err_naive})"
    assert err < 0.05, f"RIR shifts {est.tolist()} vs true {true.tolist()} (max error {err})"


def test_mask_excludes_polarized_reflection():
    frames, phi, _ = _stack()
    m = registration_mask(torch.from_numpy(frames), torch.from_numpy(phi)).numpy()
    W = frames.shape[-1]
    assert m[:, : W // 2].mean() < 0.1
    assert m[:, W // 2 :].mean() > 0.9


def test_warp_integer_shift_matches_roll_and_is_differentiable():
    g = torch.Generator().manual_seed(5)
    x = torch.rand(2, 3, 12, 16, dtype=torch.float64, generator=g)
    s = torch.tensor([[1.0, -2.0]] * 3, dtype=torch.float64)
    out = warp(x, s)
    ref = torch.roll(x, shifts=(1, -2), dims=(-2, -1))
    assert torch.allclose(out[..., 2:-2, 3:-3], ref[..., 2:-2, 3:-3], atol=1e-12)
    xs = torch.rand(1, 2, 6, 7, dtype=torch.float64, generator=g).requires_grad_(True)
    ss = torch.tensor([[0.3, -0.2], [0.1, 0.4]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: warp(a, b), (xs, ss), atol=1e-6)


def test_align_window_registers_frames_and_coefficient_maps_by_the_known_shift():
    """A known sub-pixel motion is recovered and undone on the frames AND on per-frame maps that move
    with the scene (map k = a smooth pattern translated like T_k): after alignment every map equals the
    untranslated pattern, and the T-only half of every frame matches the centre frame.
    """
    frames, phi, true = _stack()
    N, H, W = frames.shape
    moving = np.array([periodic_texture(np.random.default_rng(5), H, W, shift=-true[k], fmax=0.05) for k in range(N)])
    still = periodic_texture(np.random.default_rng(5), H, W, fmax=0.05)
    sI, sc, shifts = align_window(torch.from_numpy(frames), torch.from_numpy(phi), torch.from_numpy(moving))
    assert np.abs(shifts.numpy() - true).max() < 0.05
    inner = (slice(None), slice(4, -4), slice(4, -4))
    before, after = np.abs(moving - still)[inner], np.abs(sc.numpy() - still)[inner]
    assert after.mean() < 0.1 * before.mean() and after.max() < 0.05, (before.mean(), after.mean(), after.max())
    right = (slice(None), slice(4, -4), slice(W // 2 + 4, -4))  # T-only half (weak, static reflection)
    f_before, f_after = np.abs(frames - frames[N // 2])[right].mean(), np.abs(sI.numpy() - sI.numpy()[N // 2])[right].mean()
    assert f_after < 0.3 * f_before, (f_before, f_after)


def test_steady_shifts_keep_a_clean_registration_and_fill_a_failed_frame():
    """Shifts within 0.2 px rms of one velocity are kept as registered (a slight acceleration survives); a frame whose
    registration failed (set to 0, not valid) gets the velocity's v t.
    """
    from reconstruct.physics.rir import steady_shifts

    t = torch.arange(7, dtype=torch.float64) - 3
    s = torch.stack([0.4 * t + 0.01 * t * t, -0.7 * t], 1)
    assert torch.equal(steady_shifts(s, 3), s)
    failed = s.clone()
    failed[0] = 0.0
    valid = torch.ones(7, dtype=torch.bool)
    valid[0] = False
    out = steady_shifts(failed, 3, valid)
    assert torch.equal(out[1:], s[1:])
    assert torch.allclose(out[0], torch.tensor([-1.2, 2.1], dtype=torch.float64), atol=0.05)


def test_steady_shifts_of_noise_shrink_to_rest_and_of_a_noisy_pan_keep_its_velocity():
    """Registrations of noise (sd 0.8 px, no motion) end 3 x closer to the truth (0) in rms over 200 draws; a 1 px per
    frame pan under the same scatter keeps its velocity within 10 % on average, and its shifts end closer to the truth
    than the raw registrations.
    """
    from reconstruct.physics.rir import steady_shifts

    gen = torch.Generator().manual_seed(0)
    t = torch.arange(7, dtype=torch.float64) - 3
    pan = torch.stack([1.0 * t, 0.0 * t], 1)
    err_raw = {"rest": 0.0, "pan": 0.0}
    err_out = dict(err_raw)
    slopes = []
    for _ in range(200):
        noise = 0.8 * torch.randn(7, 2, generator=gen, dtype=torch.float64)
        noise[3] = 0.0
        for key, truth in (("rest", torch.zeros(7, 2, dtype=torch.float64)), ("pan", pan)):
            out = steady_shifts(truth + noise, 3)
            err_raw[key] += float(((noise) ** 2).mean())
            err_out[key] += float(((out - truth) ** 2).mean())
            if key == "pan":
                slopes.append(float(out[6, 0] - out[0, 0]) / 6.0)
    assert err_out["rest"] < err_raw["rest"] / 9.0, (err_out, err_raw)
    assert err_out["pan"] < err_raw["pan"] / 2.0, (err_out, err_raw)
    assert abs(np.mean(slopes) - 1.0) < 0.1
