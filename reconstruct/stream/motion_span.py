"""The long spike span, motion-compensated: its parts aligned to the centre before they are summed.

A pan of v pixels/s smears a plain span of L steps (20 kHz) into a box of v L / 20000 pixels: the 17.5 ms span at one
view width per second (400 px/s) by 7 px.  Here the span is cut into ``n_sub`` consecutive parts (50 steps each for
the 350-step span: about 27 deg of polarizer at 30 rev/s, blur v 50 / 20000 px), each part's spike sums (weighted by
1, cos 2 phi_t, sin 2 phi_t: the mean and the first harmonic, :func:`reconstruct.stream.groups.span_harmonic`) are
moved onto the part that holds the span's centre step by reflection-invariant registration
(:func:`reconstruct.physics.rir.estimate_shifts`: the transmission's low-DoP pixels, so the flicker of the polarized
reflection does not steer it; the parts' angles cover about half a turn, as the 7 windows do), and the moved sums are
added.  Shifts below ``min_shift_px`` are taken as none (a still scene keeps its span exactly: no resampling blur).

Two layers can move differently; registration follows the transmission, so a reflection that moves otherwise stays
smeared in the compensated span as in the plain one: what a method reads from the span is checked against the N
windows by the data-consistency floor (:mod:`reconstruct.physics.consistency`).
"""

from __future__ import annotations

import numpy as np
import torch

from polinfra.errors import ShapeError
from reconstruct.physics.rir import RirConfig, estimate_shifts, warp
from reconstruct.stream.groups import harmonic_design, span_harmonic, span_part_edges

__all__ = ["SPAN_RIR", "SPAN_PARTS", "SPAN_AUTO_PX", "compensated_span", "compensate_part_sums", "part_shifts_from_windows", "window_velocity", "auto_part_shifts",
           "span_part_sums", "register_parts", "auto_span_shifts"]

SPAN_RIR = RirConfig(dop_max=1.0, coarse_factor=1)
"""Registration of the span's parts: every well-exposed pixel (``dop_max`` 1) and whole-pixel search at full
resolution.  Across parts 50 steps apart a pan changes each pixel more than the polarizer does, and the per-pixel
harmonic fit behind RIR's low-DoP mask reads that change as polarization: with the windows' mask (DoP <= 0.12) the
moving texture itself is left out and the outer parts, 3 px away at 400 px/s, register wrongly (measured on the
synthetic pan of tests/recon/test_motion_span.py)."""


SPAN_PARTS = 7
"""Parts of the 350-step span: 50 steps each (about 27 deg of polarizer at 30 rev/s)."""

SPAN_AUTO_PX = 1.0
"""``--span auto``: the plain span's smear (pixels over the whole span, at the windows' fitted velocity) from which the
span's parts are moved (:func:`auto_part_shifts`)."""

SPAN_AUTO_SPIKES = 1.0
"""``--span auto``: windows with fewer spikes per pixel than this on average are noise-limited (a 13-step window in
0.02 spikes/px/step holds 0.26; at 0.3, 3.9): their registration fails (no shift) and the span's parts are registered
instead (:func:`auto_span_shifts`)."""

SPAN_AUTO_INLIERS = 4
"""``--span auto``: windows besides the centre (of 6) whose shifts must lie within 0.5 px of the fitted velocity for the
span's parts to be moved: in dim light (0.02 spikes/px/step at 96 x 64) the per-window registration of a still scene
scatters by up to 2 px, and a velocity fitted to that moved the span and cost the network 2 dB."""


def compensated_span(spikes: np.ndarray, phi: np.ndarray, exposure: float, n_sub: int = SPAN_PARTS, harmonic: bool = True, min_shift_px: float = 0.3,
                     rir: RirConfig = SPAN_RIR, shifts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The span's mean (and first harmonic) with its parts registered to the centre part.

    Args:
        spikes: (L, H, W) spikes of the span's steps (0/1 or counts).
        phi: (L,) the steps' polarizer angles, radians.
        exposure: thresholds per step per unit radiance (the result is in radiance units).
        n_sub: parts the span is cut into (1: the plain span).
        harmonic: also the first harmonic (b, c) of the moved spikes.
        min_shift_px: shifts of smaller magnitude are set to 0.
        rir: registration parameters (:data:`SPAN_RIR`).
        shifts: (n_sub, 2) the parts' shifts where known (e.g. :func:`part_shifts_from_windows`): no registration of the parts.

    Returns:
        (I_mean (H, W) float32, I_harm (2, H, W) float32 or None, shifts (n_sub, 2) as (dy, dx) applied to each part).
    """
    sp = np.asarray(spikes)
    ph = np.asarray(phi, np.float64)
    if sp.ndim != 3 or ph.shape != sp.shape[:1]:
        raise ShapeError(f"spikes must be (L, H, W) with phi (L,); got {sp.shape} and {ph.shape}", actual_shape=ph.shape, expected_shape=sp.shape[:1])
    sums, parts = span_part_sums(sp, ph, n_sub)
    return compensate_part_sums(sums, parts, ph, exposure, harmonic, min_shift_px, rir, shifts)


def span_part_sums(spikes: np.ndarray, phi: np.ndarray, n_sub: int = SPAN_PARTS) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The spike sums (n_sub, 3, H, W: weighted by 1, cos 2 phi, sin 2 phi) of the span's ``n_sub`` parts, and the parts."""
    sp = np.asarray(spikes)
    ph = np.asarray(phi, np.float64)
    parts = span_part_edges(sp.shape[0], n_sub)
    return np.stack([np.tensordot(harmonic_design(ph[a:b]), sp[a:b].astype(np.float64), axes=(1, 0)) for a, b in parts]), parts


def _span_times(parts: list[tuple[int, int]]) -> tuple[int, int, np.ndarray]:
    """The span of consecutive ``parts`` ([lo, hi) step ranges): its length in steps, its centre step, and each part's
    middle step counted from that centre (n,).
    """
    lo, hi = parts[0][0], parts[-1][1]
    c = lo + (hi - lo) // 2
    return hi - lo, c, np.array([0.5 * (a + b - 1) for a, b in parts]) - c


def register_parts(sums: np.ndarray, parts: list[tuple[int, int]], phi: np.ndarray, rir: RirConfig = SPAN_RIR) -> np.ndarray:
    """Each part's shift (n, 2) onto the part holding the span's centre step, by registering the parts' means
    (:func:`reconstruct.physics.rir.estimate_shifts` with ``rir``); ``phi`` the per-step angles ``parts`` index.
    """
    ph = np.asarray(phi, np.float64)
    c = _span_times(parts)[1]
    means = torch.from_numpy(np.asarray(sums, np.float64)[:, 0] / np.array([max(b - a, 1) for a, b in parts], np.float64)[:, None, None])
    angles = torch.tensor([ph[a:b].mean() for a, b in parts], dtype=torch.float64)
    centre = next(i for i, (a, b) in enumerate(parts) if a <= c < b)
    return estimate_shifts(means, angles, center=centre, config=rir).cpu().numpy()


def auto_span_shifts(window_shifts: np.ndarray, window_centres: np.ndarray, sums: np.ndarray, parts: list[tuple[int, int]], phi: np.ndarray,
                     spikes_per_window: float, smear_px: float = SPAN_AUTO_PX, min_inliers: int = SPAN_AUTO_INLIERS,
                     min_spikes: float = SPAN_AUTO_SPIKES) -> tuple[np.ndarray, str]:
    """``--span auto`` for one window -> (the parts' shifts (n, 2), which source: ``rir``, ``parts`` or ``plain``).

    1. At least ``min_inliers`` windows follow one velocity and it smears the span by ``smear_px`` or more: the parts
       move by it (``rir``, :func:`auto_part_shifts`; no registration of their own).
    2. Else, where the windows hold ``min_spikes`` or more spikes per pixel on average (``spikes_per_window``): the
       plain span (their registration is trusted, and says still or slow: every spike kept, no resampling).
    3. Else the windows are noise-limited (dim light: a failed registration returns no shift, which reads as still):
       the parts' own registration (:func:`register_parts`, 50 steps each, ~4x the spikes), as one velocity fitted to
       the parts the same way, where at least ``min_inliers`` parts follow it and it smears the span by ``smear_px``
       (``parts``); else the plain span.
    """
    n = len(parts)
    sh = auto_part_shifts(window_shifts, window_centres, parts, smear_px, min_inliers)
    if sh is not None:
        return sh, "rir"
    if spikes_per_window >= min_spikes or n < 3:
        return np.zeros((n, 2)), "plain"
    L, _, mid = _span_times(parts)
    vel, p_in = window_velocity(register_parts(sums, parts, phi), mid)
    if p_in >= min_inliers and float(np.hypot(*vel)) * L >= smear_px:
        return mid[:, None] * vel[None, :], "parts"
    return np.zeros((n, 2)), "plain"


def part_shifts_from_windows(window_shifts: np.ndarray, window_centres: np.ndarray, parts: list[tuple[int, int]], inlier_px: float = 0.5) -> np.ndarray:
    """Each part's shift onto the span's centre from the N windows' RIR shifts onto their centre window
    (``window_shifts`` (N, 2) as (dy, dx), at steps ``window_centres`` (N,)), as one constant velocity over the span:
    the median of the windows' slopes, refitted by least squares on the windows within ``inlier_px`` of it (a window
    whose registration failed, e.g. the outer ones of a fast pan where the low-DoP mask leaves the moving texture out,
    does not pull it).  The 7 windows cover +-171 steps and the 7 parts +-150: no registration of the span's own.
    """
    _, c, mid = _span_times(parts)
    return mid[:, None] * window_velocity(window_shifts, np.asarray(window_centres, np.float64) - c, inlier_px)[0][None, :]


def window_velocity(window_shifts: np.ndarray, t: np.ndarray, inlier_px: float = 0.5) -> tuple[np.ndarray, int]:
    """The image velocity (dy, dx) in pixels per step that the N windows' RIR shifts onto their centre (``window_shifts``
    (N, 2)) give, the windows at steps ``t`` (N,) from the centre: the median of the windows' slopes, refitted by least
    squares on the windows within ``inlier_px`` of it (:func:`part_shifts_from_windows`); and the number of those windows.
    """
    ws = np.asarray(window_shifts, np.float64)
    t = np.asarray(t, np.float64)
    far = np.abs(t) > 0.5
    vel = np.median(ws[far] / t[far, None], axis=0) if far.any() else np.zeros(2)
    ok = far & (np.hypot(*(ws - t[:, None] * vel).T) <= inlier_px)
    if ok.any():
        vel = (t[ok, None] * ws[ok]).sum(0) / (t[ok] ** 2).sum()
    return vel, int(ok.sum())


def auto_part_shifts(window_shifts: np.ndarray, window_centres: np.ndarray, parts: list[tuple[int, int]], smear_px: float = SPAN_AUTO_PX,
                     min_inliers: int = SPAN_AUTO_INLIERS) -> np.ndarray | None:
    """``--span auto`` for one window: the parts' shifts of :func:`part_shifts_from_windows` where the fitted velocity
    would smear the plain span by at least ``smear_px`` pixels (|v| times the span's steps: a fast pan, whose windows
    register) and at least ``min_inliers`` windows besides the centre follow it, else None: the plain span (a slow or
    still scene keeps every spike without resampling; noise-limited windows, whose shifts scatter, do not move it).
    """
    L, c, mid = _span_times(parts)
    vel, n_in = window_velocity(window_shifts, np.asarray(window_centres, np.float64) - c)
    if float(np.hypot(*vel)) * L < smear_px or n_in < min_inliers:
        return None
    return mid[:, None] * vel[None, :]  # part_shifts_from_windows, on the velocity just fitted


def compensate_part_sums(sums: np.ndarray, parts: list[tuple[int, int]], phi: np.ndarray, exposure: float, harmonic: bool = True,
                         min_shift_px: float = 0.3, rir: RirConfig = SPAN_RIR, shifts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """:func:`compensated_span` from the parts' spike sums ``sums`` (n, 3, H, W: weighted by 1, cos 2 phi, sin 2 phi) over
    the consecutive step ranges ``parts`` ([lo, hi), indices into ``phi``, the per-step angles; the streaming
    reconstructor keeps these sums, :meth:`reconstruct.stream.groups.SpikeMeanSums.part_sums`).
    """
    ph = np.asarray(phi, np.float64)
    sums = np.array(sums, np.float64)
    lo, hi = parts[0][0], parts[-1][1]
    L = hi - lo
    given = shifts is not None
    shifts = np.array(shifts, np.float64) if given else np.zeros((len(parts), 2))
    if len(parts) >= 3:
        if not given:
            shifts = register_parts(sums, parts, ph, rir)
        shifts[np.hypot(shifts[:, 0], shifts[:, 1]) < min_shift_px] = 0.0
        moved = np.flatnonzero(np.abs(shifts).sum(1) > 0)
        if moved.size:
            t = torch.from_numpy(sums[moved])  # (m, 3, H, W): each part's three sums moved by its shift
            sh = torch.from_numpy(shifts[moved])[:, None].expand(-1, 3, -1)
            sums[moved] = warp(t, sh).numpy()
    total = sums.sum(0)
    I_mean = (total[0] / (L * float(exposure))).astype(np.float32)
    I_harm = span_harmonic(total, ph[lo:hi], float(exposure)) if harmonic else None
    return I_mean, I_harm, shifts
