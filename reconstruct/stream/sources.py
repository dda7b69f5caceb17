"""Spike sources: a .dat file, an in-memory array or a stored group, read in chunks with the polarizer angle per step."""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from polinfra.errors import ConfigError, DataFormatError

log = logging.getLogger(__name__)


@dataclasses.dataclass
class SpikeSource:
    """A spike stream: chunk iterator, per-step polarizer angles and metadata.

    Attributes:
        chunks: callable returning an iterator of (first step, (n, H, W) uint8 spikes).
        phi_step_rad: (T,) mid-step polarizer angle, unwrapped, radians.
        height, width, rate_hz (steps per second), polarizer_rev_s, name.
        exposure: thresholds per step per unit radiance, when the source knows it.
    """

    chunks: Callable[[], Iterator[tuple[int, np.ndarray]]]
    phi_step_rad: np.ndarray
    height: int
    width: int
    rate_hz: float
    polarizer_rev_s: float
    name: str
    exposure: float | None = None

    def window_span_rad(self, window_steps: int) -> float:
        """Polarizer rotation during one Eq. (3) window of ``window_steps`` steps, radians (zeta is averaged over it)."""
        return 2 * math.pi * self.polarizer_rev_s * window_steps / self.rate_hz


def dat_source(path: str | os.PathLike, height: int, width: int, phi0_rad: float, rev_per_s: float, rate_hz: float = 20000.0, chunk_steps: int = 2000) -> SpikeSource:
    """A raw Vidar ``.dat`` with the polarizer calibrated as phi(t) = phi0 + 2 pi f t (t at mid-step)."""
    from spike_sim.vidar_dat import dat_frame_count, iter_dat

    n = dat_frame_count(path, height, width)
    t = (np.arange(n) + 0.5) / rate_hz
    phi = phi0_rad + 2 * math.pi * rev_per_s * t

    def chunks():
        s = 0
        for c in iter_dat(path, height, width, chunk_frames=chunk_steps):
            yield s, c
            s += c.shape[0]

    return SpikeSource(chunks, phi, height, width, rate_hz, rev_per_s, Path(path).name)


def array_source(spikes: np.ndarray, phi0_rad: float, rev_per_s: float, rate_hz: float = 20000.0, name: str = "array", chunk_steps: int = 2000) -> SpikeSource:
    """An in-memory (T, H, W) 0/1 stream (e.g. a real .npz capture) with a calibrated polarizer."""
    sp = np.asarray(spikes)
    if sp.ndim != 3:
        raise DataFormatError(f"spike array must be (T, H, W); got shape {sp.shape}")
    t = (np.arange(sp.shape[0]) + 0.5) / rate_hz
    phi = phi0_rad + 2 * math.pi * rev_per_s * t
    return SpikeSource(lambda: ((s, sp[s : s + chunk_steps]) for s in range(0, sp.shape[0], chunk_steps)), phi, sp.shape[1], sp.shape[2], rate_hz, rev_per_s, name)


def group_source(path: str | os.PathLike, chunk_steps: int = 2000) -> SpikeSource:
    """A stored spike group (``polspike simulate`` output); nominal (calibrated) angles, its exposure."""
    from spike_sim.store import open_group

    g = open_group(path)
    cfg = g.json_attr("config_json") or {}
    pol = g.json_attr("polarizer_json") or {}
    return SpikeSource(
        lambda: g.iter_chunks(chunk_steps), g.phi_nominal_rad, g.height, g.width, g.rate_hz, float(pol.get("rate_hz", 30.0)), Path(path).name,
        exposure=float(cfg["exposure"]) if "exposure" in cfg else None,
    )


def frames_exposure(source, exposure: float | None = None) -> float:
    """The exposure :func:`span_frames` divides by: the one given, else the source's, else 1 (a raw stream of unknown
    scale: radiance = spikes per step).  Frames times it are spikes per step whatever it is, so saturation tests on
    them hold.
    """
    return exposure if exposure is not None else (source.exposure or 1.0)


def span_frames(source, span_s: float, window_steps: int = 13, exposure: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The first ``span_s`` of a spike stream as back-to-back Eq. (3) frames: I (M, H, W) float32 radiance, phi (M,) radians."""
    steps_needed = max(window_steps * 3, int(round(span_s * source.rate_hz)))
    steps_needed = min(steps_needed, int(source.phi_step_rad.size))
    ex = frames_exposure(source, exposure)
    bufs, have = [], 0
    for _, chunk in source.chunks():
        bufs.append(np.asarray(chunk))
        have += chunk.shape[0]
        if have >= steps_needed:
            break
    sp = np.concatenate(bufs)[:steps_needed] if bufs else np.zeros((0, source.height, source.width), np.uint8)
    M = sp.shape[0] // window_steps
    if M < 3:
        raise StreamTooShortError(f"{source.name}: self-calibration needs at least {3 * window_steps} steps; the stream has {sp.shape[0]}")
    counts = sp[: M * window_steps].reshape(M, window_steps, source.height, source.width).sum(1, dtype=np.int32)
    I = counts.astype(np.float32) / np.float32(window_steps * ex)  # Eq. (3), radiance units
    phi = source.phi_step_rad[: M * window_steps].reshape(M, window_steps).mean(1)
    return I, phi


class StreamTooShortError(ConfigError):
    """The stream is shorter than the self-calibration needs (half a polarizer turn of frames): a caller with
    another zeta source (the network's learned zeta) falls back to it; one without says so (exit 2).
    """
