"""Stream a spike group from Stokes keyframes: polarizer -> integrate-and-fire -> store.

Pipeline per chunk of steps [n0, n1) (memory bounded by the chunk, not the duration):

1. :func:`polphysics.polarizer.step_keyframe_weights` gives, per step,
   closed-form weights on the keyframes' (S0, S1, S2) (polarizer integrated over
   the step, Stokes linear in time between keyframes).
2. Steps whose weights touch two keyframes (k, k+1) run through the numba kernel
   with basis = exposure * gain * (S_k, S_k+1); the rare step straddling a
   keyframe is evaluated exactly in numpy and passed as a one-term basis.
3. Packed frames go to the HDF5 group (and optionally a .dat file).

Determinism: every quantity of step n depends only on (seed, n, pixel), so the
output is bit-identical for any ``chunk_steps`` and any number of threads.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np

from polinfra.config import to_dict
from polinfra.errors import ConfigError, PolspikeWarning, ShapeError
from polphysics.polarizer import PolarizerConfig, phi_nominal, step_keyframe_weights, step_phi_edges
from spike_sim.aggregate import AggregateConfig, frame_centres
from spike_sim.config import DEFAULT, SpikeSimConfig
from spike_sim.integrate_fire import make_pixel_params, noise_scalars, packed_frame_bytes, run_numba, step_keys
from spike_sim.store import GroupWriter
from spike_sim.vidar_dat import DatWriter

__all__ = ["KeyframeSource", "keyframes_from_arrays", "keyframes_from_render", "simulate", "SimulationSummary"]

log = logging.getLogger(__name__)


@dataclasses.dataclass
class KeyframeSource:
    """Radiance over time: Stokes keyframes and (optional) ground truth.

    Attributes:
        times_s: (K,) increasing keyframe times, seconds.
        stokes: callable i -> (3, H, W) float32 Stokes in front of the polarizer.
        layers: callable i -> (T, R) GT layers (H, W) each, or None.
        maps: callable -> dict of coefficient maps, or None.
        polarizer: the scene's polarizer.
        scene_hash: content hash of the scene ("in-memory" for arrays).
        height, width: image size.
    """

    times_s: np.ndarray
    stokes: Callable[[int], np.ndarray]
    height: int
    width: int
    layers: Callable[[int], tuple[np.ndarray, np.ndarray]] | None = None
    maps: Callable[[], dict[str, np.ndarray]] | None = None
    polarizer: PolarizerConfig = dataclasses.field(default_factory=PolarizerConfig)
    scene_hash: str = "in-memory"


def keyframes_from_arrays(
    times_s,
    stokes: np.ndarray,
    layers: tuple[np.ndarray, np.ndarray] | None = None,
    maps: dict[str, np.ndarray] | None = None,
    polarizer: PolarizerConfig | None = None,
    scene_hash: str = "in-memory",
) -> KeyframeSource:
    """In-memory keyframes: ``stokes`` (K, 3, H, W); ``layers`` optional (T, R) each (K, H, W)."""
    st = np.asarray(stokes, dtype=np.float32)
    t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
    if st.ndim != 4 or st.shape[1] != 3 or st.shape[0] != t.size:
        raise ShapeError(f"stokes must be (K, 3, H, W) with K = len(times_s) = {t.size}, got {st.shape}", st.shape, "(K, 3, H, W)")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ConfigError("keyframe times must be strictly increasing")
    lay = None
    if layers is not None:
        T_, R_ = (np.asarray(a, dtype=np.float32) for a in layers)
        lay = lambda i: (T_[i], R_[i])  # noqa: E731
    return KeyframeSource(
        times_s=t,
        stokes=lambda i: st[i],
        height=st.shape[2],
        width=st.shape[3],
        layers=lay,
        maps=(lambda: maps) if maps is not None else None,
        polarizer=polarizer or PolarizerConfig(),
        scene_hash=scene_hash,
    )


def keyframes_from_render(render_dir: str | os.PathLike) -> KeyframeSource:
    """Keyframes of a render directory (``polspike render`` output), read lazily."""
    from spike_sim.renderdir import open_render

    rd = open_render(render_dir)
    has_maps = (Path(rd.path) / "maps.exr").is_file()
    return KeyframeSource(
        times_s=np.asarray(rd.times_s, dtype=np.float64),
        stokes=lambda i: np.asarray(rd.stokes(i), dtype=np.float32),
        height=rd.height,
        width=rd.width,
        layers=rd.layers,
        maps=rd.maps if has_maps else None,
        polarizer=rd.polarizer,
        scene_hash=rd.scene_hash,
    )


_TIMING_KEYS = ("group_dir", "seconds", "sim_seconds", "pixel_steps_per_s")
"""Summary fields that vary between two runs of the same inputs (wall clock, output path)."""


@dataclasses.dataclass
class SimulationSummary:
    """What :func:`simulate` did."""

    group_dir: str
    n_steps: int
    n_output_frames: int
    seconds: float
    sim_seconds: float
    pixel_steps_per_s: float
    mean_rate: float
    dat_path: str | None

    def to_dict(self) -> dict[str, Any]:
        """Plain data."""
        return dataclasses.asdict(self)


class _KeyCache:
    """Keyframe Stokes premultiplied by exposure * gain, (3, P) float32, small LRU."""

    def __init__(self, src: KeyframeSource, gain: np.ndarray):
        self.src, self.gain, self.cache = src, gain, {}

    def get(self, k: int) -> np.ndarray:
        if k not in self.cache:
            if len(self.cache) >= 4:
                self.cache.pop(min(self.cache))
            s = np.asarray(self.src.stokes(k), dtype=np.float32)
            if s.shape != (3, self.src.height, self.src.width):
                raise ShapeError(f"keyframe {k} Stokes is {s.shape}, expected (3, {self.src.height}, {self.src.width})", s.shape, "(3, H, W)")
            self.cache[k] = s.reshape(3, -1) * self.gain[None, :]
        return self.cache[k]


def _run_chunk(n0, n1, src, cfg, pol, seed, params, V, scal, keys, out) -> None:
    """Simulate steps [n0, n1) into ``out`` (n1 - n0, nbytes)."""
    dt = cfg.dt_s
    K = src.times_s.size
    k_lo, W = step_keyframe_weights(n0, n1, dt, src.times_s, pol, seed)
    nz = np.any(W != 0.0, axis=2)  # (N, 3) slots used
    # pair base: slots (0,1) -> k_lo, slots (1,2) -> k_lo+1, else straddle (-1)
    base = np.where(~nz[:, 2], k_lo, np.where(~nz[:, 0], k_lo + 1, -1))
    sk = step_keys(n0, n1, seed)
    P = params.theta.size
    i = 0
    N = n1 - n0
    while i < N:
        b = base[i]
        j = i + 1
        while j < N and base[j] == b and b >= 0:
            j += 1
        basis = np.zeros((6, P), np.float32)
        coef = np.zeros((j - i, 6), np.float32)
        if b >= 0:
            off = b - k_lo[i:j]  # 0 or 1: slot of keyframe b within each step's window
            rows = np.arange(j - i)
            basis[0:3] = keys.get(int(b))
            coef[:, 0:3] = W[i:j][rows, off]
            if b + 1 < K:
                basis[3:6] = keys.get(int(b) + 1)
                coef[:, 3:6] = W[i:j][rows, np.minimum(off + 1, 2)]
        else:  # straddling step: exact 3-keyframe sum, evaluated here
            x = np.zeros(P, np.float32)
            for slot in range(3):
                k = int(k_lo[i]) + slot
                if k < K and nz[i, slot]:
                    x += (W[i, slot].astype(np.float32)[:, None] * keys.get(k)).sum(0)
            basis[0] = x
            coef[0, 0] = 1.0
        run_numba(basis, coef, sk[i:j], params, V, scal, out[i:j])
        i = j


def simulate(
    source: KeyframeSource | str | os.PathLike,
    duration_s: float,
    seed: int,
    config: SpikeSimConfig = DEFAULT,
    out: str | os.PathLike | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk_steps: int = 1000,
    dat_path: str | os.PathLike | None = None,
    polarizer: PolarizerConfig | None = None,
    aggregate: AggregateConfig = AggregateConfig(),
    compression: str = "gzip",
    overwrite: bool = False,
    store_zeta: bool = False,
    spikes_sink: Callable[[int, np.ndarray], None] | None = None,
    store_timings: bool = True,
) -> SimulationSummary:
    """Simulate ``duration_s`` seconds of spikes behind the rotating polarizer.

    Args:
        source: a :class:`KeyframeSource` (see :func:`keyframes_from_arrays`) or a
            render directory path.
        duration_s: stream length; ``round(duration_s * rate_hz)`` steps.
        seed: sensor and noise seed (fixed pattern, noise, polarizer jitter).
        config: simulator config; its width/height must match the source.
        out: group folder (HDF5 store + group.json); None = do not store.
        progress: (done, total) steps callback.
        chunk_steps: steps per chunk (memory ~ chunk_steps * H W / 8 bytes).
        dat_path: also write a raw Vidar .dat file.
        polarizer: override the source's polarizer.
        aggregate: Eq. (3) settings that define the output times of the GT.
        compression: "gzip" or "none" for the spike dataset.
        overwrite: replace an existing group.
        store_zeta: also store paper Eq. (2) zeta at output times (float16) when maps
            exist (off by default: it follows from the stored maps and phi(i)).
        spikes_sink: optional callback (first step, packed chunk) (tests, streaming users).
        store_timings: keep the wall-clock fields (seconds, sim_seconds, pixel_steps_per_s)
            and the output path in the stored summary (``summary_json``, group.json).  False
            (dataset builds) leaves them out, so the same inputs give the same file bytes;
            the returned summary always has them.

    Returns:
        :class:`SimulationSummary`.
    """
    src = keyframes_from_render(source) if not isinstance(source, KeyframeSource) else source
    cfg = config
    if (src.height, src.width) != (cfg.height, cfg.width):
        cfg = dataclasses.replace(cfg, height=src.height, width=src.width)
        log.info("sensor size set to the source's %dx%d", src.width, src.height)
    pol = polarizer or src.polarizer
    if duration_s <= 0:
        raise ConfigError(f"duration_s = {duration_s} must be > 0")
    if chunk_steps < 1:
        raise ConfigError(f"chunk_steps = {chunk_steps} must be >= 1")
    n_steps = int(round(duration_s * cfg.rate_hz))
    dt = cfg.dt_s
    if cfg.shot_noise and cfg.photons_per_threshold < 100.0:
        warnings.warn(
            f"photons_per_threshold = {cfg.photons_per_threshold:g} gives a shot-noise ISI CV of about {1 / np.sqrt(cfg.photons_per_threshold):.2f},"
            " far above the 0.03-0.09 of real captures",
            PolspikeWarning,
            stacklevel=2,
        )
    if src.times_s[-1] < (n_steps - 1) * dt and src.times_s.size > 1:
        log.warning("keyframes end at %.4f s but the stream lasts %.4f s; the last keyframe is held", src.times_s[-1], n_steps * dt)
    P = cfg.n_pixels
    t_start = time.perf_counter()
    params = make_pixel_params(cfg, seed)
    V = params.v0.copy()
    scal = noise_scalars(cfg)
    keys = _KeyCache(src, params.gain)
    # angles per step (small: 8 bytes per step)
    mids = (np.arange(n_steps) + 0.5) * dt
    phi_nom = phi_nominal(mids, pol)
    centres, phi_i = frame_centres(phi_nom, aggregate, phi_start_rad=float(phi_nominal(0.0, pol)))
    writer = None
    if out is not None:
        writer = GroupWriter(
            out,
            cfg.height,
            cfg.width,
            cfg.rate_hz,
            n_steps,
            chunk_steps=chunk_steps,
            compression=compression,
            overwrite=overwrite,
            attrs={
                "seed": int(seed),
                "scene_hash": src.scene_hash,
                "config_json": to_dict(cfg),
                "polarizer_json": to_dict(pol),
                "aggregate_json": to_dict(aggregate),
            },
        )
    dat = DatWriter(dat_path) if dat_path is not None else None
    gt = _GtStream(writer, src, centres, dt, aggregate, store_zeta) if writer is not None else None
    ok = False
    phi_true = np.zeros(n_steps)
    total_spikes = 0
    sim_s = 0.0
    try:
        buf = np.zeros((chunk_steps, packed_frame_bytes(P)), np.uint8)
        for n0 in range(0, n_steps, chunk_steps):
            n1 = min(n_steps, n0 + chunk_steps)
            o = buf[: n1 - n0]
            t0 = time.perf_counter()
            _run_chunk(n0, n1, src, cfg, pol, seed, params, V, scal, keys, o)
            sim_s += time.perf_counter() - t0
            pa, pb = step_phi_edges(n0, n1, dt, pol, seed)
            phi_true[n0:n1] = 0.5 * (pa + pb)
            total_spikes += _popcount(o)
            if writer is not None:
                writer.write_spikes(o)
                gt.advance(n1, phi_true)
            if dat is not None:
                dat.write_packed(o, cfg.height, cfg.width)
            if spikes_sink is not None:
                spikes_sink(n0, o.copy())
            if progress is not None:
                progress(n1, n_steps)
        if writer is not None:
            writer.write_array("polarizer/phi_true_rad", phi_true)
            writer.write_array("polarizer/phi_nominal_rad", phi_nom)
            writer.write_array("time/step_mid_s", mids)
            writer.write_array("output/step_index", centres)
            writer.write_array("output/times_s", (centres + 0.5) * dt)
            writer.write_array("output/phi_nominal_rad", phi_i)
            csum = np.concatenate([[0.0], np.cumsum(phi_true)])
            h = aggregate.half
            writer.write_array("output/phi_true_rad", (csum[centres + h + 1] - csum[centres - h]) / aggregate.window_steps)
            gt.advance(n_steps, phi_true)
        ok = True
    finally:
        if dat is not None:
            dat.close(ok=ok)
        wall = time.perf_counter() - t_start
        summary = SimulationSummary(
            group_dir=str(out) if out is not None else "",
            n_steps=n_steps,
            n_output_frames=int(centres.size),
            seconds=wall,
            sim_seconds=sim_s,
            pixel_steps_per_s=n_steps * P / max(sim_s, 1e-12),
            mean_rate=total_spikes / max(1, n_steps * P),
            dat_path=str(dat_path) if dat_path is not None else None,
        )
        if writer is not None:
            if ok:
                stored = summary.to_dict()
                if not store_timings:
                    stored = {k: v for k, v in stored.items() if k not in _TIMING_KEYS}
                writer.set_attr("summary_json", stored)
                writer.close(
                    summary={
                        "seed": int(seed),
                        "scene_hash": src.scene_hash,
                        "config": to_dict(cfg),
                        "polarizer": to_dict(pol),
                        "aggregate": to_dict(aggregate),
                        "summary": stored,
                    }
                )
            else:
                writer.close(ok=False)
    log.info("simulated %d steps of %dx%d in %.2f s (%.3g pixel-steps/s in the kernel)", n_steps, cfg.width, cfg.height, summary.seconds, summary.pixel_steps_per_s)
    return summary


_POP = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)


@nb.njit(cache=True)
def _popcount_jit(flat, pop):  # pragma: no cover - jitted
    acc = 0
    for i in range(flat.size):
        acc += pop[flat[i]]
    return acc


def _popcount(packed: np.ndarray) -> int:
    return int(_popcount_jit(np.ascontiguousarray(packed).ravel(), _POP))


def _interp_layers(src: KeyframeSource, t: float) -> tuple[np.ndarray, np.ndarray]:
    kt = src.times_s
    if kt.size == 1 or t <= kt[0]:
        return src.layers(0)
    if t >= kt[-1]:
        return src.layers(kt.size - 1)
    k = int(np.searchsorted(kt, t, side="right") - 1)
    w = np.float32((t - kt[k]) / (kt[k + 1] - kt[k]))
    (T0, R0), (T1, R1) = src.layers(k), src.layers(k + 1)
    return (1 - w) * T0 + w * T1, (1 - w) * R0 + w * R1


class _GtStream:
    """Writes GT frames at output times while the stream advances (keyframes are then still cached)."""

    def __init__(self, writer: GroupWriter, src: KeyframeSource, centres: np.ndarray, dt: float, aggregate: AggregateConfig, store_zeta: bool):
        self.writer, self.src, self.c, self.dt, self.h, self.win = writer, src, centres, dt, aggregate.half, aggregate.window_steps
        self.m = 0
        M = centres.size
        self.maps = src.maps() if src.maps is not None else None
        if self.maps:
            for k, v in self.maps.items():
                writer.write_array(f"maps/{k}", np.asarray(v, dtype=np.float32))
        self.dT = self.dR = self.dz = None
        if src.layers is not None and M:
            self.dT = writer.create_frames("gt/T", M, dtype="f2")
            self.dR = writer.create_frames("gt/R", M, dtype="f2")
        if store_zeta and self.maps and {"R_perp", "R_par", "phi_perp"} <= set(self.maps) and M:
            self.dz = writer.create_frames("gt/zeta", M, dtype="f2")

    def advance(self, n_done: int, phi_true: np.ndarray) -> None:
        """Write every output frame whose window lies in the first ``n_done`` steps."""
        while self.m < self.c.size and self.c[self.m] + self.h < n_done:
            m, c = self.m, int(self.c[self.m])
            if self.dT is not None:
                T_, R_ = _interp_layers(self.src, (c + 0.5) * self.dt)
                self.writer.write_frame(self.dT, m, T_)
                self.writer.write_frame(self.dR, m, R_)
            if self.dz is not None:
                from polphysics.zeta import zeta

                phi_i = float(np.mean(phi_true[c - self.h : c + self.h + 1]))
                mp = self.maps
                self.writer.write_frame(self.dz, m, zeta(phi_i, mp["R_perp"], mp["R_par"], mp["phi_perp"]))  # Eq. (2)
            self.m += 1
