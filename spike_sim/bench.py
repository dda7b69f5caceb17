"""Benchmark of the spike simulator: numba kernel vs the numpy reference, same run.

Both engines simulate the FULL noise model (:data:`spike_sim.config.DEFAULT`) on
the same sensor (same fixed pattern) looking at a modulated random scene, with
the polarizer weights of :mod:`polphysics.polarizer`.  Speed is reported
in pixel-steps per second and as a ratio (machine-independent), memory as the
tracemalloc peak of Python/numpy allocations and the process peak RSS.
CPU seconds (``time.process_time``, all threads) are reported beside wall
seconds: on a shared machine pixel-steps per CPU-second is the steadier figure.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import resource
import tempfile
import time
import tracemalloc
from typing import Any

import numba
import numpy as np

from spike_sim.config import DEFAULT, SpikeSimConfig
from spike_sim.integrate_fire import make_pixel_params, noise_scalars, packed_frame_bytes, run_numba, run_numpy, step_keys

__all__ = ["run_benchmark"]


def _inputs(cfg: SpikeSimConfig, n: int, seed: int):
    rng = np.random.default_rng(seed)
    P = cfg.n_pixels
    params = make_pixel_params(cfg, seed)
    st = rng.random((2, 3, P)).astype(np.float32) * np.array([0.5, 0.1, 0.1], np.float32)[None, :, None]
    basis = (st.reshape(6, P) * params.gain[None]).astype(np.float32)
    t = np.arange(n)
    ph = 2 * np.pi * 30.0 * (t + 0.5) / cfg.rate_hz
    w = (t + 0.5) / max(n, 1)
    coef = np.stack([0.5 * (1 - w), 0.5 * (1 - w) * np.cos(2 * ph), 0.5 * (1 - w) * np.sin(2 * ph), 0.5 * w, 0.5 * w * np.cos(2 * ph), 0.5 * w * np.sin(2 * ph)], 1)
    return params, basis, coef.astype(np.float32)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_benchmark(
    width: int = 400,
    height: int = 250,
    steps: int = 4000,
    numpy_steps: int = 100,
    seed: int = 0,
    repeats: int = 3,
    full_group_s: float = 0.0,
) -> dict[str, Any]:
    """Measure both engines; optionally simulate a whole group end to end.

    Args:
        width, height: sensor size.
        steps: steps per timed numba run (best of ``repeats``, after a warm-up).
        numpy_steps: steps of the (slow) numpy reference.
        full_group_s: if > 0, also time :func:`spike_sim.simulate.simulate` of
            that many seconds to a temporary group (store + compression included).

    Returns:
        Plain dict (JSON-able) with pixel-steps/s, ratio, memory and machine info.
    """
    cfg = dataclasses.replace(DEFAULT, width=width, height=height)
    P = cfg.n_pixels
    scal = noise_scalars(cfg)
    params, basis, coef = _inputs(cfg, steps, seed)
    out = np.zeros((steps, packed_frame_bytes(P)), np.uint8)
    keys = step_keys(0, steps, seed)
    V = params.v0.copy()
    t0 = time.perf_counter()
    run_numba(basis, coef[:8], keys[:8], params, V, scal, out[:8])  # compile / load cache
    warm = time.perf_counter() - t0
    tracemalloc.start()
    best = np.inf
    best_cpu = np.inf
    for _ in range(repeats):
        V = params.v0.copy()
        t0, c0 = time.perf_counter(), time.process_time()
        run_numba(basis, coef, keys, params, V, scal, out)
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    _, nb_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rate_numba = steps * P / best
    mean_rate = float(np.unpackbits(out[: min(steps, 500)]).mean())

    pn, bn, cn = _inputs(cfg, numpy_steps, seed)
    outn = np.zeros((numpy_steps, packed_frame_bytes(P)), np.uint8)
    Vn = pn.v0.copy()
    tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    run_numpy(bn, cn, pn, Vn, scal, outn, np.random.default_rng(seed))
    tn = time.perf_counter() - t0
    tn_cpu = time.process_time() - c0
    _, np_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rate_numpy = numpy_steps * P / tn

    res: dict[str, Any] = {
        "benchmark": "spike-sim",
        "width": width,
        "height": height,
        "noise_model": "default (shot, dark+hot, fixed pattern, thermal, reset, leak, random init)",
        "numba": {"steps": steps, "seconds": best, "pixel_steps_per_s": rate_numba, "cpu_seconds": best_cpu, "pixel_steps_per_cpu_s": steps * P / best_cpu, "warmup_s": warm, "threads": numba.get_num_threads(), "tracemalloc_peak_mb": nb_peak / 1e6},
        "numpy": {"steps": numpy_steps, "seconds": tn, "pixel_steps_per_s": rate_numpy, "cpu_seconds": tn_cpu, "pixel_steps_per_cpu_s": numpy_steps * P / tn_cpu, "tracemalloc_peak_mb": np_peak / 1e6},
        "ratio_numba_over_numpy": rate_numba / rate_numpy,
        "ratio_per_cpu_second": (steps * P / best_cpu) / (numpy_steps * P / tn_cpu),
        "seconds_per_1s_group_kernel": 20000 * 400 * 250 / rate_numba,
        "mean_spike_rate": mean_rate,
        "goal": {"pixel_steps_per_s": 5e8, "ratio": 20.0},
        "peak_rss_mb": _peak_rss_mb(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "processor": platform.processor(), "load_avg": os.getloadavg()},
    }
    if full_group_s > 0:
        res["full_group"] = _full_group(cfg, full_group_s, seed)
        res["peak_rss_mb"] = _peak_rss_mb()
    return res


def _full_group(cfg: SpikeSimConfig, duration_s: float, seed: int) -> dict[str, Any]:
    from spike_sim.simulate import keyframes_from_arrays, simulate

    rng = np.random.default_rng(seed)
    K = max(2, int(duration_s * 100) + 1)
    H, W = cfg.height, cfg.width
    T = rng.random((K, H, W)).astype(np.float32) * 0.6
    R = rng.random((K, H, W)).astype(np.float32) * 0.3
    s0 = 0.5 * (T + 0.1 * R)
    lin = 0.04 * R
    st = np.stack([s0, lin, 0.0 * lin], 1)
    src = keyframes_from_arrays(np.linspace(0.0, duration_s, K), st, layers=(T, R))
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        s = simulate(src, duration_s, seed, cfg, out=os.path.join(d, "g"))
        wall = time.perf_counter() - t0
        size = sum(os.path.getsize(os.path.join(d, "g", f)) for f in os.listdir(os.path.join(d, "g")))
    return {"duration_s": duration_s, "wall_s": wall, "kernel_s": s.sim_seconds, "keyframes": K, "group_mb": size / 1e6, "mean_rate": s.mean_rate}
