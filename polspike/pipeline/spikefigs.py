"""Figures of a stored spike group: a raster with phi(t), and the 2K + 1 observations of one window.

Shared by ``polspike demo`` and ``polspike dataset inspect``.  Inputs are spike
group directories (``spike_sim.store`` layout); figures are written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polspike.errors import ConfigError
from polspike.plotting import image_grid, save_figure

__all__ = ["plot_spike_raster", "plot_window_frames", "brightness_pixels"]


def brightness_pixels(mean_rate: np.ndarray, n: int = 6) -> list[tuple[int, int]]:
    """``n`` pixels (row, col) spanning the quantiles of a (H, W) mean-rate image, dark to bright."""
    flat = np.argsort(mean_rate, axis=None, kind="stable")
    picks = flat[np.linspace(0, flat.size - 1, n + 2).round().astype(int)[1:-1]]
    return [tuple(int(v) for v in np.unravel_index(p, mean_rate.shape)) for p in picks]


def plot_spike_raster(
    group_dir: str | os.PathLike, png: str | os.PathLike, pixels: list[tuple[int, int]] | None = None, t0_s: float = 0.0, span_s: float = 0.02
) -> Path:
    """Spikes of a few pixels over ``[t0_s, t0_s + span_s)`` above the polarizer angle phi(t).

    Args:
        group_dir: spike group directory.
        png: output figure.
        pixels: (row, col) pixels; default six spanning dark to bright.
        t0_s, span_s: time span shown, seconds.
    """
    import matplotlib.pyplot as plt

    from spike_sim.store import open_group

    with open_group(group_dir) as g:
        rate, n_steps = g.rate_hz, g.n_steps
        n0 = int(round(t0_s * rate))
        n1 = min(n_steps, n0 + max(1, int(round(span_s * rate))))
        if not 0 <= n0 < n_steps:
            raise ConfigError(f"t0 = {t0_s} s is outside the group's 0..{n_steps / rate:.4f} s")
        spikes = g.read(n0, n1)  # (n, H, W) uint8
        phi = g.phi_true_rad[n0:n1]
    pix = pixels or brightness_pixels(spikes.mean(0))
    t_ms = (np.arange(n0, n1) + 0.5) / rate * 1e3
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(9, 4.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    for j, (r, c) in enumerate(pix):
        on = spikes[:, r, c].astype(bool)
        a0.vlines(t_ms[on], j + 0.1, j + 0.9, lw=0.6, color="k")
    a0.set_yticks(np.arange(len(pix)) + 0.5, [f"({r},{c}) {spikes[:, r, c].mean():.2f}/step" for r, c in pix], fontsize=7)
    a0.set_ylabel("pixel (row,col), rate")
    a0.set_title("spike raster (one tick = one spike, 50 us steps)")
    a1.plot(t_ms, np.degrees(np.mod(phi, np.pi)), lw=1)
    a1.set_ylabel("phi mod 180 (deg)")
    a1.set_xlabel("time (ms)")
    return save_figure(fig, png)


def plot_window_frames(group_dir: str | os.PathLike, png: str | os.PathLike, i: int | None = None, window_steps: int = 13, stride_deg: float = 31.5, n_obs: int = 7) -> Path:
    """The ``n_obs`` Eq. (3) observations I(i+k) of window ``i`` (default: the middle one) with their angles."""
    from reconstruct.groups import load_store_group
    from spike_sim.aggregate import observation_stack

    g = load_store_group(group_dir, window_steps=window_steps, stride_deg=stride_deg, n_obs=n_obs)
    K = n_obs // 2
    M = g.I.shape[0]
    if M < n_obs:
        raise ConfigError(f"{group_dir} has {M} output frames, fewer than the {n_obs} of one window; simulate a longer group")
    i = M // 2 if i is None else i
    I, phi = observation_stack(g.I, g.phi_nominal, i, K)
    vmax = float(np.percentile(I, 99.5)) or 1.0
    panels = [(f"I(i{k - K:+d}), phi = {np.degrees(phi[k]) % 180:.1f} deg", I[k], {"cmap": "gray", "vmin": 0.0, "vmax": vmax, "label": "radiance"}) for k in range(n_obs)]
    fig = image_grid(panels, ncols=4, title=f"Eq. (3) observations of window i = {i} ({window_steps} steps each, {stride_deg} deg apart)")
    return save_figure(fig, png)
