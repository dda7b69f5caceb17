"""Speed of the physics reconstruction: output frames per second at 400 x 250.

Stages timed per output frame (window of N = 7 frames):

* ``harmonic_fit``: supp. Eq. (1) fit + DoP over the window;
* ``rir``: reflection-invariant registration (mask, 6 masked phase
  correlations + sub-pixel refinement) and the warp of frames and zeta;
* ``rwps`` / ``ls``: the solver stage alone, batched over ``batch`` windows;
* ``pipeline``: harmonic fit + RIR + RWPS, one window after another.

Speed is also given as a ratio to plain LS measured in the same process, so
numbers from a loaded machine stay comparable.  CUDA is timed when present.
"""

from __future__ import annotations

import logging
import platform
import time

import numpy as np
import torch

from reconstruct.harmonic_fit import dop, harmonic_fit
from reconstruct.rir import RirConfig, estimate_shifts, warp
from reconstruct.solvers import solve

__all__ = ["bench_reconstruct"]

log = logging.getLogger(__name__)


def _timeit(fn, repeats: int, sync=lambda: None) -> float:
    fn()
    sync()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t0)
    return best


def _window(N: int, H: int, W: int, seed: int = 0):
    """One window of the closed-form synthetic set (pictures, pane maps, Poisson spike counts)."""
    from reconstruct.evaluate import EvalConfig, group_zeta
    from reconstruct.synthetic import SyntheticConfig, make_group

    g = make_group(SyntheticConfig(width=W, height=H, n_frames=N, seed=seed), 0)
    Z = group_zeta(g, EvalConfig())
    return torch.from_numpy(g.I).float(), torch.from_numpy(Z).float(), torch.from_numpy(g.phi_nominal).float()


def bench_reconstruct(width: int = 400, height: int = 250, n_obs: int = 7, batch: int = 8, repeats: int = 3, threads: int = 2, devices: tuple[str, ...] = ("cpu", "cuda"), require: bool = False) -> dict:
    """Time the reconstruction stages; returns a plain dict (JSON-ready).

    Args:
        width, height: frame size (default 400 x 250, the sensor).
        n_obs: window length N.
        batch: windows per solver call for the solver-stage throughput.
        repeats: timing repeats (best is kept).
        threads: torch CPU threads (the CPU target is 2 cores).
        devices: devices to try; missing ones are reported as skipped.
        require: raise :class:`~polinfra.errors.BackendUnavailableError` instead of skipping a missing device.

    Returns:
        {"config": ..., "results": {device: {stage: {"s_per_frame", "fps"}}}, "ratios": ...}
    """
    torch.set_num_threads(threads)
    I, Z, phi = _window(n_obs, height, width)
    out: dict = {
        "config": {"width": width, "height": height, "n_obs": n_obs, "batch": batch, "repeats": repeats, "threads": threads, "torch": torch.__version__, "machine": platform.machine()},
        "results": {},
        "skipped": {},
    }
    for dev in devices:
        if dev == "cuda" and not torch.cuda.is_available():
            if require:
                from polinfra.errors import BackendUnavailableError

                raise BackendUnavailableError("bench on cuda requested but torch sees no CUDA device; use --device cpu or auto")
            out["skipped"]["cuda"] = "no CUDA device"
            continue
        sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
        Id, Zd, Pd = I.to(dev), Z.to(dev), phi.to(dev)
        Ib = Id.expand(batch, *Id.shape).contiguous()
        Zb = Zd.expand(batch, *Zd.shape).contiguous()
        res = {}
        t = _timeit(lambda: dop(*harmonic_fit(Id, Pd)), repeats, sync)
        res["harmonic_fit"] = t
        rc = RirConfig()

        def rir():
            sh = estimate_shifts(Id, Pd, config=rc).to(Id.dtype)
            return warp(Id, sh), warp(Zd, sh)

        res["rir"] = _timeit(rir, max(1, repeats - 1), sync)
        res["ls"] = _timeit(lambda: solve("ls", Zb, Ib), repeats, sync) / batch
        res["rwps"] = _timeit(lambda: solve("rwps", Zb, Ib), repeats, sync) / batch

        def pipeline():
            dop(*harmonic_fit(Id, Pd))
            sI, sZ = rir()
            solve("rwps", sZ[None], sI[None])

        res["pipeline"] = _timeit(pipeline, max(1, repeats - 1), sync)
        out["results"][dev] = {k: {"s_per_frame": v, "fps": 1.0 / v} for k, v in res.items()}
        out["results"][dev]["ratios"] = {"rwps_over_ls_time": res["rwps"] / res["ls"], "pipeline_over_ls_time": res["pipeline"] / res["ls"]}
    return out
