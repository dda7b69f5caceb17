"""Paper Eq. (3): spike-count frames I(i) centred at multiples of the angular stride.

``I(p, t) = (1/dt) sum_{tau = t - dt/2}^{t + dt/2} S(p, tau)``   paper Eq. (3)

Here dt is counted in simulator steps (default 13 steps = 0.65 ms at 20 kHz), so
I(i) is in spikes per step: noise-free it estimates ``exposure * <intensity>``
over the window (multiply by the rate for spikes per second).  Output frame
``i`` is centred at the step where the polarizer has turned by ``i * stride``
(31.5 deg default) from its angle at t = 0: 10800 / 31.5 = 342.9 frames per
second at 30 rev/s (supp. Eq. (17)-(18)).  phi(i) is the mean of the per-step
mid angles over the window.  The reconstructor stacks N = 2K + 1 = 7
consecutive observations (:func:`observation_stack`).

Functions take a stream (T, H, W) or a :class:`~spike_sim.store.SpikeGroup`
together with per-step angles phi(t); they do not care how the stream was made,
so they serve real captures (.dat + calibrated phi) as well.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError

__all__ = ["AggregateConfig", "frame_centres", "aggregate_stream", "aggregate_group", "observation_stack", "output_fps"]


@dataclasses.dataclass(frozen=True)
class AggregateConfig:
    """Eq. (3) aggregation parameters."""

    window_steps: int = opt(13, "window dt in simulator steps (13 = 0.65 ms at 20 kHz); odd, centred", lo=1, hi=100001)
    stride_deg: float = opt(31.5, "polarizer rotation between consecutive output frames, degrees", lo=0.01, hi=360.0)
    n_obs: int = opt(7, "observations per output frame N = 2K + 1 (odd)", lo=1, hi=101)

    def __post_init__(self) -> None:
        if self.window_steps % 2 == 0:
            raise ConfigError(f"window_steps = {self.window_steps} must be odd so the window is centred on a step; use {self.window_steps + 1}")
        if self.n_obs % 2 == 0:
            raise ConfigError(f"n_obs = {self.n_obs} must be odd (N = 2K + 1); use {self.n_obs + 1}")

    @property
    def half(self) -> int:
        """Half window in steps."""
        return self.window_steps // 2

    @property
    def K(self) -> int:
        """Observations on each side of the centre."""
        return self.n_obs // 2


def output_fps(rate_rev_s: float, stride_deg: float) -> float:
    """Output cadence: 360 f / stride (supp. Eq. (18)); 342.86 for 30 rev/s at 31.5 deg."""
    return 360.0 * rate_rev_s / stride_deg


def frame_centres(phi_step_rad: np.ndarray, cfg: AggregateConfig = AggregateConfig(), phi_start_rad: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centre steps and centre angles of the output frames that fit in the stream.

    Args:
        phi_step_rad: (T,) unwrapped mid-step polarizer angle (nominal/calibrated
            for a reconstructor, true for ground truth), increasing.
        cfg: aggregation parameters.
        phi_start_rad: angle at t = 0 (default: extrapolated from the first two steps).

    Returns:
        (centre_step (M,) int64, phi_i (M,) float64 the window-mean angle, radians).
    """
    phi = np.asarray(phi_step_rad, dtype=np.float64)
    T = phi.size
    if T < cfg.window_steps:
        return np.zeros(0, np.int64), np.zeros(0)
    if phi_start_rad is None:
        phi_start_rad = phi[0] - 0.5 * (phi[1] - phi[0]) if T > 1 else phi[0]
    turned = phi - phi_start_rad
    if np.any(np.diff(turned) <= 0):
        raise ConfigError("the polarizer angle must increase step by step to place Eq. (3) windows; check rate_hz > 0")
    stride = np.deg2rad(cfg.stride_deg)
    i_max = int(np.floor(turned[-1] / stride))
    targets = np.arange(0, i_max + 1) * stride
    # fractional step position where the mid-step angle reaches the target, rounded to a step
    pos = np.interp(targets, turned, np.arange(T, dtype=np.float64))
    c = np.rint(pos).astype(np.int64)
    ok = (c - cfg.half >= 0) & (c + cfg.half <= T - 1)
    c = c[ok]
    csum = np.concatenate([[0.0], np.cumsum(phi)])
    phi_i = (csum[c + cfg.half + 1] - csum[c - cfg.half]) / cfg.window_steps
    return c, phi_i


def aggregate_stream(spikes: np.ndarray, centres: np.ndarray, cfg: AggregateConfig = AggregateConfig(), step0: int = 0) -> np.ndarray:
    """Eq. (3) frames from an in-memory stream.

    Args:
        spikes: (T, H, W) 0/1 stream whose first step has global index ``step0``.
        centres: (M,) global centre steps (from :func:`frame_centres`).
        cfg: aggregation parameters.

    Returns:
        (M, H, W) float32, spikes per step.
    """
    if spikes.ndim != 3:
        raise ShapeError(f"spikes must be (T, H, W), got {spikes.shape}", spikes.shape, "(T, H, W)")
    c = np.asarray(centres, dtype=np.int64) - step0
    if c.size and (c.min() - cfg.half < 0 or c.max() + cfg.half >= spikes.shape[0]):
        raise ShapeError(f"windows of centres {c.min() + step0}..{c.max() + step0} +-{cfg.half} leave the stream of {spikes.shape[0]} steps", spikes.shape, "(T, H, W) covering every window")
    cs = np.zeros((spikes.shape[0] + 1,) + spikes.shape[1:], np.int32)
    np.cumsum(spikes, axis=0, out=cs[1:], dtype=np.int32)
    return ((cs[c + cfg.half + 1] - cs[c - cfg.half]) / np.float32(cfg.window_steps)).astype(np.float32)  # Eq. (3)


def aggregate_group(group, cfg: AggregateConfig = AggregateConfig(), use: str = "nominal", progress=None) -> dict[str, np.ndarray]:
    """Eq. (3) frames of a whole stored group, reading only the windows (lazy).

    Args:
        group: a :class:`~spike_sim.store.SpikeGroup`.
        cfg: aggregation parameters.
        use: "nominal" (calibrated angles, what a reconstructor knows) or "true".
        progress: optional (done, total) callback.

    Returns:
        dict with ``I`` (M, H, W) float32, ``phi_rad`` (M,), ``centre_step`` (M,),
        ``times_s`` (M,).
    """
    if use not in ("nominal", "true"):
        raise ConfigError(f"use = {use!r}; choose 'nominal' or 'true'")
    phi = group.phi_nominal_rad if use == "nominal" else group.phi_true_rad
    c, phi_i = frame_centres(phi, cfg)
    out = np.zeros((c.size, group.height, group.width), np.float32)
    for m, cc in enumerate(c):
        win = group.read(cc - cfg.half, cc + cfg.half + 1)
        out[m] = win.sum(0, dtype=np.int32) / np.float32(cfg.window_steps)  # Eq. (3)
        if progress is not None:
            progress(m + 1, c.size)
    return {"I": out, "phi_rad": phi_i, "centre_step": c, "times_s": (c + 0.5) * group.dt_s}


def observation_stack(I: np.ndarray, phi: np.ndarray, i: int, K: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The 2K + 1 observations {I(i+k), phi(i+k)}, k in [-K, K], around output frame i.

    Returns:
        ((2K+1, H, W), (2K+1,)); ShapeError when the stack leaves the sequence.
    """
    if i - K < 0 or i + K >= len(I):
        raise ShapeError(f"frame {i} needs frames {i - K}..{i + K} but the sequence has {len(I)}", (len(I),), f">= {i + K + 1} frames")
    return I[i - K : i + K + 1], np.asarray(phi)[i - K : i + K + 1]
