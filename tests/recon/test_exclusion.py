"""reconstruct.physics.exclusion: closed-form layer solve under a zeta hypothesis and the crossed gradient correlation.

Oracles: paper Eq. (1)-(2) written out here (window sinc included) and the algebra of the module docstring
(a zeta scaled by k gives T' = T and R' = T + (R - T) / k); independent textures are uncorrelated.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

from reconstruct.physics.exclusion import cross_gradient_sums, label_correlations, part_harmonics, solve_layers


def _tex(seed, H=64, W=96, s=1.5):
    f = gaussian_filter(np.random.default_rng(seed).standard_normal((H, W)), s)
    return f / f.std()


def _frames(R, T, A, B, phi_perp, M=52, span=0.1225, noise=0.0, seed=0):
    """Eq. (3) frames of static layers: back-to-back windows sweeping ``span`` rad each (window-mean zeta, Eq. (2))."""
    rng = np.random.default_rng(seed)
    phi = 0.3 + span * np.arange(M)
    sinc = math.sin(span) / span
    I = []
    for p in phi:
        z = A + B * sinc * np.cos(2 * (p - phi_perp))
        L = 0.5 * (z * R + (1 - z) * T)
        I.append(L + noise * rng.standard_normal(L.shape))
    return np.asarray(I), phi, sinc


def test_solve_inverts_eq1_and_a_scaled_zeta_leaks_t_into_r():
    H, W = 32, 48
    rng = np.random.default_rng(1)
    R = 1.0 + 0.3 * _tex(2, H, W)
    T = 0.5 + 0.1 * _tex(3, H, W)
    A = rng.uniform(0.05, 0.2, (H, W))
    B = rng.uniform(0.02, 0.04, (H, W)) * np.sign(rng.uniform(-1, 1, (H, W)))
    pp = rng.uniform(0, math.pi, (H, W))
    I, phi, g = _frames(R, T, A, B, pp)
    (a0, c), = part_harmonics(I, phi, 1)
    R1, T1 = solve_layers(a0, c, pp, A, B, g)
    np.testing.assert_allclose(R1, R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(T1, T, rtol=0, atol=1e-9)
    k = 1.8
    R2, T2 = solve_layers(a0, c, pp, k * A, k * B, g)
    np.testing.assert_allclose(T2, T, atol=1e-9)  # a pure scale error leaves T alone ...
    np.testing.assert_allclose(R2, T + (R - T) / k, atol=1e-9)  # ... and mixes T's texture into R


def test_crossed_correlation_is_near_zero_at_the_truth_and_signed_by_the_scale_error():
    H, W = 64, 96
    R = 1.0 + 0.3 * _tex(4)
    T = 0.5 + 0.15 * _tex(5)
    A = np.full((H, W), 0.12)
    B = np.full((H, W), 0.05)
    pp = np.full((H, W), 0.4)
    I, phi, g = _frames(R, T, A, B, pp, noise=0.01)
    parts = part_harmonics(I, phi, 2)
    one = np.zeros((H, W), int)
    c = {k: label_correlations(cross_gradient_sums(parts, pp, k * A, k * B, g), one, 1)[0] for k in (0.6, 1.0, 1.6)}
    assert abs(c[1.0]) < 0.1  # independent textures, independent noise across parts
    for k in (0.6, 1.6):
        # the noise-free oracle: gradients of T and of R' = T + (R - T) / k (k > 1: positive leak, k < 1: negative)
        gr = np.gradient(gaussian_filter(T + (R - T) / k, 2.0))
        gt = np.gradient(gaussian_filter(T, 2.0))
        pred = sum(float(np.sum(a * b)) for a, b in zip(gr, gt)) / math.sqrt(sum(float(np.sum(a * a)) for a in gr) * sum(float(np.sum(b * b)) for b in gt))
        assert abs(c[k] - pred) < 0.06 and abs(pred) > 0.2 and np.sign(pred) == np.sign(k - 1), (k, c[k], pred)


def test_cross_part_power_removes_the_noise_from_the_normalisation():
    """Two time parts of the same static layers with independent noise: the crossed products of R' with R' (and T'
    with T') hold the content's gradient power only, so ``power="cross"`` gives the correlation of the noise-free
    layers, while ``power="same"`` shrinks it by the noise (oracle: the correlation computed on the noise-free solve).
    """
    H, W = 64, 96
    rng = np.random.default_rng(7)
    R = 1.0 + 0.3 * _tex(11, H, W)
    T = 0.6 + 0.2 * (0.6 * _tex(11, H, W) + 0.8 * _tex(12, H, W))  # shares R's texture: correlated gradients
    A = np.full((H, W), 0.12)
    B = np.full((H, W), 0.08)
    pp = np.full((H, W), 0.4)
    a0 = 0.5 * (T + A * (R - T))
    c = 0.5 * B * (R - T) * np.exp(2j * pp)
    one = np.zeros((H, W), int)
    clean = label_correlations(cross_gradient_sums([(a0, c), (a0, c)], pp, A, B, sigma=1.0), one, 1)[0]
    noisy = [(a0 + 0.03 * rng.standard_normal((H, W)), c + 0.02 * (rng.standard_normal((H, W)) + 1j * rng.standard_normal((H, W)))) for _ in range(2)]
    sums = cross_gradient_sums(noisy, pp, A, B, sigma=1.0)
    same = label_correlations(sums, one, 1, power="same")[0]
    cross = label_correlations(sums, one, 1, power="cross")[0]
    assert clean > 0.3
    assert abs(cross - clean) < 0.05 * clean
    assert same < 0.8 * clean


def test_split_pixels_drop_the_fixed_pattern_that_same_pixels_read_as_correlation():
    """The sensor's fixed pattern, a static per-pixel gain (7 %, as the default sensor's threshold and gain
    mismatch), multiplies R' and T' alike in every time part, so crossing the parts keeps it: taken from the same
    pixels, the layers' gradient correlation at the true zeta moves up by the gain's own gradient power; with R'
    from one checkerboard set and T' from the other the gain's values are independent and the correlation stays
    where the gain-free layers put it.  Without a gain the two agree (the split keeps the content's correlation).
    Oracle: the same solve of the gain-free harmonics.
    """
    H, W = 96, 128
    A, B, pp = np.full((H, W), 0.12), np.full((H, W), 0.08), np.full((H, W), 0.4)
    one = np.zeros((H, W), int)
    for seed in range(3):
        R = 1.0 + 0.05 * _tex(21 + seed, H, W, s=4)  # low-contrast layers: the fixed pattern's gradients count
        T = 0.6 + 0.03 * _tex(40 + seed, H, W, s=4)
        gain = 1.0 + 0.07 * np.random.default_rng(23 + seed).standard_normal((H, W))
        a0, c = 0.5 * (T + A * (R - T)), 0.5 * B * (R - T) * np.exp(2j * pp)

        def corr(g, pixels):
            return float(label_correlations(cross_gradient_sums([(g * a0, g * c)] * 2, pp, A, B, sigma=2.0, pixels=pixels), one, 1)[0])

        free_same, free_split = corr(1.0, "same"), corr(1.0, "split")
        assert abs(free_split - free_same) < 0.01
        assert corr(gain, "same") - free_same > 0.1, seed
        assert abs(corr(gain, "split") - free_split) < 0.04, seed


def test_split_pixels_leave_masked_pixels_out_and_refuse_unknown_names():
    """A masked-out region holds garbage (huge values): with the mask, the split sums over the rest equal those of
    the same layers without the garbage (nothing leaks in through the normalised convolution), and no gradient pair
    touching the mask counts.
    """
    import pytest

    from polinfra.errors import ConfigError

    H, W = 48, 64
    R, T = 1.0 + 0.3 * _tex(31, H, W, s=3), 0.6 + 0.2 * _tex(32, H, W, s=3)
    A, B, pp = np.full((H, W), 0.12), np.full((H, W), 0.08), np.full((H, W), 0.4)
    a0, c = 0.5 * (T + A * (R - T)), 0.5 * B * (R - T) * np.exp(2j * pp)
    mask = np.ones((H, W), bool)
    mask[:, 40:] = False
    bad = np.where(mask, a0, 1e6), np.where(mask, c, 1e6)
    s_bad = cross_gradient_sums([bad] * 2, pp, A, B, sigma=2.0, pixels="split", mask=mask)
    s_ok = cross_gradient_sums([(a0, c)] * 2, pp, A, B, sigma=2.0, pixels="split", mask=mask)
    for k in ("cross", "pr", "pt"):
        np.testing.assert_allclose(s_bad[k], s_ok[k], rtol=1e-9, atol=1e-12)
        assert np.all(s_bad[k][:, 40:] == 0.0)
    assert np.sum(s_ok["pr"]) > 0
    parts = [(np.ones((H, W)), np.zeros((H, W), complex))] * 2
    with pytest.raises(ConfigError, match="pixels"):
        cross_gradient_sums(parts, pp, A, B, pixels="odd")


def test_the_part_pair_sums_equal_the_explicit_double_sum_over_distinct_parts():
    """cross, pr_x and pt_x sum over every ordered pair of distinct time parts; they are formed in O(P) as the
    product of the part sums less the p = q terms.  Oracle: the explicit double loop over p != q of the per-part
    gradients (same: R'_p . T'_q; split: the mean of set 0 of one with set 1 of the other, both ways), for 2, 3 and 5
    noisy parts, with and without a mask.
    """
    from reconstruct.physics.exclusion import _checkerboard, _grad, _set_grad, solve_layers

    H, W, sigma = 40, 56, 1.5
    rng = np.random.default_rng(7)
    A, B, pp = 0.12 + 0.02 * _tex(1, H, W, s=3), 0.08 + 0.01 * _tex(2, H, W, s=3), 0.4 + 0.1 * _tex(3, H, W, s=3)
    mask = np.ones((H, W), bool)
    mask[5:12, 30:44] = False
    for P in (2, 3, 5):
        parts = [(0.5 + 0.05 * rng.standard_normal((H, W)), 0.04 * (rng.standard_normal((H, W)) + 1j * rng.standard_normal((H, W)))) for _ in range(P)]
        for pixels in ("same", "split"):
            for m in (None, mask):
                got = cross_gradient_sums(parts, pp, A, B, sigma=sigma, pixels=pixels, mask=m)
                sets = _checkerboard((H, W))
                if m is not None:
                    sets = tuple(S & m for S in sets)
                okx = oky = None
                if m is not None:
                    okx, oky = m[:-1, :-1] & m[:-1, 1:], m[:-1, :-1] & m[1:, :-1]
                g = []
                for a0, c in parts:
                    R, T = solve_layers(a0, c, pp, A, B, 1.0, None if pixels == "split" else m)
                    d = {}
                    for k, x in (("R", R), ("T", T)):
                        if pixels == "split":
                            two = [_set_grad(x, S, sigma) for S in sets]
                        else:
                            two = [_grad(x, sigma)] * 2
                        if m is not None:
                            two = [(np.where(okx, u[0], 0.0), np.where(oky, u[1], 0.0)) for u in two]
                        d[k] = two
                    g.append(d)
                dot = lambda u, v: u[0] * v[0] + u[1] * v[1]  # noqa: E731
                mix = lambda u, v: 0.5 * (dot(u[0], v[1]) + dot(u[1], v[0]))  # noqa: E731
                n = P * (P - 1)
                want = {"cross": sum(mix(g[p]["R"], g[q]["T"]) for p in range(P) for q in range(P) if p != q) / n,
                        "pr_x": sum(mix(g[p]["R"], g[q]["R"]) for p in range(P) for q in range(P) if p != q) / n,
                        "pt_x": sum(mix(g[p]["T"], g[q]["T"]) for p in range(P) for q in range(P) if p != q) / n}
                for k, v in want.items():
                    np.testing.assert_allclose(got[k], v, rtol=1e-9, atol=1e-12 * float(np.abs(v).max()), err_msg=f"{k} P={P} {pixels} mask={m is not None}")
