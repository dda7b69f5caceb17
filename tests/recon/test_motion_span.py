"""The motion-compensated long span (reconstruct/stream/motion_span.py) on a synthetic pan.

Oracle: a pan of v px/s smears a plain span of L steps (20 kHz) into a box of v L / 20000 px, whose 10-90 % edge
rise is 0.8 v L / 20000 px; the compensated span's parts are L / 7 steps long, a box 7 times shorter.
"""

from __future__ import annotations

import numpy as np
import pytest

from reconstruct.stream.groups import span_part_edges
from reconstruct.stream.motion_span import compensated_span

RATE = 20000.0


def _pan(v: float, L: int = 350, H: int = 64, W: int = 96, exposure: float = 2.0, seed: int = 0):
    """Integrate-and-fire spikes of a step edge (all rows) and a texture (top half) panning at v px/s behind a weak
    pane (zeta modulated by the polarizer at 30 rev/s; no reflection); the true layer at the centre step.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    t = np.arange(L) / RATE
    phi = 0.4 + 2 * np.pi * 30.0 * t
    acc = rng.uniform(0.0, 1.0, (H, W))
    spikes = np.zeros((L, H, W), np.uint8)

    def layer(dx):
        xs = x - dx
        tex = np.where(y < H // 2, 0.12 * np.sin(0.9 * xs + 0.4 * y) * np.cos(0.6 * y - 0.3 * xs), 0.0)
        return 0.4 + 0.25 * np.tanh((xs - W / 2) / 0.4) + tex

    for i in range(L):
        z = 0.1 + 0.05 * np.cos(2 * (phi[i] - 0.3))
        I = 0.5 * (1 - z) * layer(v * (t[i] - t[L // 2]))
        acc += exposure * I
        s = np.floor(acc)
        acc -= s
        spikes[i] = s.astype(np.uint8)
    return spikes, phi, layer(0.0)


def _edge_width(img: np.ndarray) -> float:
    """10-90 % rise (px) of the row-mean profile of the bottom half across the step edge (linear interpolation)."""
    p = img[img.shape[0] // 2 + 2 :].mean(0)
    lo, hi = np.median(p[:20]), np.median(p[-20:])
    q = (p - lo) / (hi - lo)
    xs = np.arange(q.size, dtype=np.float64)
    c = q.size // 2
    seg, xseg = q[c - 20 : c + 20], xs[c - 20 : c + 20]
    x10, x90 = np.interp(0.1, seg, xseg), np.interp(0.9, seg, xseg)  # monotone within the edge's neighbourhood
    return float(x90 - x10)


def test_span_parts_cover_the_span():
    parts = span_part_edges(350, 7)
    assert parts[0][0] == 0 and parts[-1][1] == 350 and all(b == c for (_, b), (c, _) in zip(parts[:-1], parts[1:]))
    assert max(b - a for a, b in parts) - min(b - a for a, b in parts) <= 1


@pytest.mark.parametrize("v", [400.0, 800.0])
def test_compensated_span_is_sharp_where_the_plain_span_is_blurred(v):
    L = 350
    spikes, phi, truth = _pan(v, L)
    plain, _, _ = compensated_span(spikes, phi, 2.0, n_sub=1, harmonic=False)
    comp, harm, shifts = compensated_span(spikes, phi, 2.0, n_sub=7)
    box = v * L / RATE  # the plain span's smear, px
    w_true, w_plain, w_comp = _edge_width(truth), _edge_width(plain), _edge_width(comp)
    assert w_plain == pytest.approx(np.hypot(0.8 * box, w_true), rel=0.25)  # closed form of the box blur
    assert w_comp < max(0.35 * w_plain, w_true + 0.2 * box)
    # the parts' shifts follow the pan: part j's centre lies (j - 3) L / 7 steps from the span's centre
    want = -v * (np.array([(a + b) / 2 for a, b in span_part_edges(L, 7)]) - L / 2) / RATE
    np.testing.assert_allclose(shifts[:, 1], want, atol=0.35)
    assert harm is not None and harm.shape == (2, *comp.shape)


def test_still_scene_keeps_the_plain_span_exactly():
    spikes, phi, _ = _pan(0.0, 350)
    plain, hp, _ = compensated_span(spikes, phi, 2.0, n_sub=1)
    comp, hc, shifts = compensated_span(spikes, phi, 2.0, n_sub=7)
    assert np.all(shifts == 0)
    np.testing.assert_allclose(comp, plain, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(hc, hp, rtol=1e-5, atol=1e-6)


def test_streamed_part_sums_give_the_compensated_span_of_the_spikes():
    """The streaming reconstructor's running sums (SpikeMeanSums with 7 parts, fed in uneven chunks) give the same
    compensated span as the spikes themselves (compensated_span), and it is sharper than the streamed plain span.
    """
    from reconstruct.stream.groups import SpikeMeanSums
    from reconstruct.stream.motion_span import SPAN_PARTS, compensate_part_sums

    L, pad = 350, 40
    spikes, phi, _ = _pan(400.0, L=L + 2 * pad)
    c = pad + L // 2  # the span of the frame centred here is [pad, pad + L + 1) clipped: 351 steps as the stream's
    ps = SpikeMeanSums(np.array([c]), L, spikes.shape[0], spikes.shape[1:], phi, n_sub=SPAN_PARTS)
    for a in range(0, spikes.shape[0], 97):
        ps.feed(a, spikes[a : a + 97])
    sums, parts = ps.part_sums(0)
    lo, hi = parts[0][0], parts[-1][1]
    assert (lo, hi) == (c - L // 2, c + L // 2 + 1) and len(parts) == SPAN_PARTS
    got_m, got_h, got_s = compensate_part_sums(sums, parts, phi, 2.0)
    ref_m, ref_h, ref_s = compensated_span(spikes[lo:hi], phi[lo:hi], 2.0)
    np.testing.assert_allclose(got_s, ref_s, atol=1e-6)
    assert np.abs(ref_s).max() > 1.0  # a 400 px/s pan: the outer parts moved by ~3 px
    np.testing.assert_allclose(got_m, ref_m, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got_h, ref_h, rtol=1e-4, atol=1e-5)
    assert _edge_width(got_m) < 0.5 * _edge_width(ps.mean(0, 2.0))


def test_part_shifts_from_the_windows_rir_match_the_registered_parts():
    """On a 400 px/s pan the 7 windows' RIR shifts (13-step windows 57 steps apart), read as one velocity over the
    span, give the parts' shifts within 0.3 px of their own registration and of the closed form, even where the outer
    windows fail to register, and the span built with them is as sharp.  Held to one velocity (the default), the
    windows that registered keep their shifts and the outer ones get the pan's.
    """
    import torch

    from reconstruct.physics.rir import RirConfig, estimate_shifts
    from reconstruct.stream.groups import harmonic_design
    from reconstruct.stream.motion_span import compensate_part_sums, part_shifts_from_windows

    L, pad, v = 350, 40, 400.0
    spikes, phi, _ = _pan(v, L=L + 2 * pad)
    c = pad + L // 2
    wc = c + 57 * np.arange(-3, 4)
    I = np.stack([spikes[k - 6 : k + 7].mean(0) / 2.0 for k in wc])
    It, pt = torch.from_numpy(I).double(), torch.from_numpy(phi[wc]).double()
    wsh = estimate_shifts(It, pt, config=RirConfig(steady=False)).numpy()  # the registrations as they are
    good = np.abs(wsh[:, 1] - v * (c - wc) / RATE) < 0.3  # the windows that follow the pan (the closed form)
    assert good.sum() >= 4 and not good.all()  # the outer windows' registration fails here (the mask leaves the texture out)
    held = estimate_shifts(It, pt).numpy()  # steady (the default): the failed windows get the others' velocity
    np.testing.assert_allclose(held[:, 1], v * (c - wc) / RATE, atol=0.3)
    np.testing.assert_allclose(held[good], wsh[good], atol=0.02)  # a precise registration keeps its shift
    lo, hi = c - L // 2, c + L // 2 + 1
    parts = [(lo + a, lo + b) for a, b in span_part_edges(hi - lo, 7)]
    sh = part_shifts_from_windows(wsh, wc, parts)
    _, _, reg = compensated_span(spikes[lo:hi], phi[lo:hi], 2.0)
    np.testing.assert_allclose(sh, reg, atol=0.3)
    np.testing.assert_allclose(sh[:, 1], [v * (c - 0.5 * (a + b - 1)) / RATE for a, b in parts], atol=0.3)
    sums = np.stack([np.tensordot(harmonic_design(phi[a:b]), spikes[a:b].astype(np.float64), axes=(1, 0)) for a, b in parts])
    m_rir, _, used = compensate_part_sums(sums, parts, phi, 2.0, shifts=sh)
    m_reg, _, _ = compensated_span(spikes[lo:hi], phi[lo:hi], 2.0)
    assert np.abs(used).max() > 1.0 and _edge_width(m_rir) < 1.2 * _edge_width(m_reg) + 0.2


def test_auto_span_takes_the_windows_velocity_the_parts_own_or_the_plain_span():
    """``--span auto``: windows that follow one velocity move the parts by it (``rir``); noise-limited windows (below
    one spike per pixel) whose shifts scatter, or fail to zero, leave it to the parts' own registration, which on a
    400 px/s pan gives the closed form's shifts within 0.3 px (``parts``) and on a still scene leaves the span plain;
    windows with spikes enough that find no motion keep it plain.
    """
    from reconstruct.stream.motion_span import auto_span_shifts, span_part_sums

    L = 351
    wc = L // 2 + 57 * np.arange(-3, 4)
    scattered = np.array([[1.92, 1.05], [2.3, 1.59], [-0.11, -0.17], [0, 0], [-0.05, -0.35], [1.88, -0.7], [2.08, 1.83]])
    for v in (400.0, 0.0):
        spikes, phi, _ = _pan(v, L=L)
        sums, parts = span_part_sums(spikes, phi)
        mids = np.array([0.5 * (a + b - 1) for a, b in parts]) - L // 2
        truth = np.stack([np.zeros(7), -v * mids / RATE], 1)  # the part at step t moved back by v t
        for ws in (scattered, np.zeros((7, 2))):
            sh, how = auto_span_shifts(ws, wc, sums, parts, phi, spikes_per_window=0.3)
            if v:
                assert how == "parts"
                np.testing.assert_allclose(sh, truth, atol=0.3)
            else:
                assert how == "plain" and not sh.any()
            sh, how = auto_span_shifts(ws, wc, sums, parts, phi, spikes_per_window=3.0)
            assert how == "plain" and not sh.any()
        lin = np.stack([np.zeros(7), -v * (wc - L // 2) / RATE], 1)  # windows that register, at the same pan
        sh, how = auto_span_shifts(lin, wc, sums, parts, phi, spikes_per_window=3.0)
        assert how == ("rir" if v else "plain")
        np.testing.assert_allclose(sh, truth, atol=1e-6)
