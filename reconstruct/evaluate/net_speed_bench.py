"""``polspike bench net-speed``: the network path's CPU cost with the inference speed-ups, against the default path in one run.

On a closed-form pane stream (:mod:`reconstruct.stream.pane_stream`, a .dat with T panning at 20 px/s) the shipped
network runs through the streaming path (:func:`reconstruct.video.stream.reconstruct_stream`: RIR estimated once per
window, the long span as ``polspike reconstruct`` builds it by default (``--span auto``), the network with its solves
and data floor, EXR frames written) on the pane's true maps (no
self-calibration), on one torch thread by default, once per variant: ``default`` (the reference), ``fast``
(:func:`reconstruct.net.inference.accelerate` with ``fast``) and, when asked, ``compile`` and ``fast+compile``.  Each
variant's model runs a warm-up of one batch first (numba kernels load, ``torch.compile`` compiles: its time is
reported apart), then the timed frames.  Per variant: CPU seconds per frame by stage (the stream's
``cpu_s_per_frame``), frames per CPU second and per wall second, the ratio to the default's frames per CPU second, and
the largest change of T and R against the default's frames (the tolerance the speed-up keeps).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["NET_SPEED_VARIANTS", "bench_net_speed", "net_speed_markdown"]

log = logging.getLogger(__name__)

NET_SPEED_VARIANTS = {"default": {}, "fast": {"fast": True}, "compile": {"compile_": True}, "fast+compile": {"fast": True, "compile_": True},
                      "fast+bf16": {"fast": True, "bf16": True}, "fast+bf16+compile": {"fast": True, "bf16": True, "compile_": True}}
"""Variants by name: the keyword arguments of :func:`reconstruct.net.inference.accelerate`."""


def _frames(d: Path) -> dict[str, np.ndarray]:
    from polinfra.exr import read_exr

    files = sorted((d / "frames").glob("*.exr"))
    got = [read_exr(f, ["T", "R"]) for f in files]
    return {k: np.stack([g[k] for g in got]) for k in ("T", "R")} if got else {}


def _psnr(x: np.ndarray, ref: np.ndarray) -> float:
    """PSNR of ``x`` against ``ref`` (peak: the reference's 99.9th percentile), dB."""
    x, ref = x.astype(np.float64), ref.astype(np.float64)
    mse = float(np.mean((x - ref) ** 2))
    peak = float(np.percentile(ref, 99.9))
    return float("inf") if mse == 0 else 10.0 * math.log10(max(peak, 1e-12) ** 2 / mse)


def bench_net_speed(width: int = 400, height: int = 250, frames: int = 12, variants: tuple[str, ...] = ("default", "fast"), threads: int = 1, rir: str = "window",
                    workdir: str | None = None, progress=None, weights: tuple[str, ...] = ("default",)) -> dict[str, Any]:
    """Measure the variants (module docstring); ``frames`` even (two windows per forward pass); the first variant is the reference.

    ``weights``: checkpoints or names of shipped ones (:func:`reconstruct.net.checkpoint.resolve_weights`); each runs
    every variant, rows named ``variant`` for one checkpoint, else ``weights:variant``; the first row is the reference.
    Rows of another checkpoint than the reference's give the PSNR of their T and R against the reference's frames
    (``psnr_vs_reference``: how far the other network's output lies) instead of a float tolerance.

    Returns:
        {"config", "variants": {name: {...}}, "reference"} (JSON-ready).
    """
    import torch

    from reconstruct.net.checkpoint import load_model, resolve_weights
    from reconstruct.net.inference import accelerate
    from reconstruct.net.net_zeta import MapsZetaNet
    from reconstruct.physics.zeta import PaneMaps
    from reconstruct.stream.pane_stream import PaneStreamConfig, pane_stream_maps, write_pane_dat
    from reconstruct.stream.sources import dat_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    cfg = PaneStreamConfig(width=width, height=height, exposure=2.0, motion_px_s=(0.0, 20.0))
    tick = progress or (lambda s: None)
    n0 = torch.get_num_threads()
    res: dict[str, Any] = {"config": {"width": width, "height": height, "frames": frames, "threads": threads, "rir": rir, "weights": [resolve_weights(w).name for w in weights],
                                      "torch": torch.__version__, "stream": dataclasses.asdict(cfg), "load_avg_start": os.getloadavg()}, "variants": {}}
    fps_out = 360.0 * cfg.rev_per_s / 31.5
    seconds = (frames + 2 + 8) / fps_out + 0.03  # the timed frames, the warm-up's, the window's 6 more and the 17.5 ms span
    m = pane_stream_maps(cfg)
    maps = PaneMaps(m["R_perp"], m["R_par"], m["phi_perp"])
    span = 2 * math.pi * cfg.rev_per_s * 13 / cfg.rate_hz
    ref = None
    rows = [(w, v, v if len(weights) == 1 else f"{w}:{v}") for w in weights for v in variants]
    try:
        with tempfile.TemporaryDirectory(dir=workdir) as d:
            d = Path(d)
            tick(f"write a {seconds:.3f} s stream")
            dat = write_pane_dat(d / "s.dat", cfg, seconds)
            for wname, vname, name in rows:
                net = load_model(wname, "cpu", use_rir=True, floor=True)[0]
                stats = accelerate(net, **NET_SPEED_VARIANTS[vname])
                model = MapsZetaNet(net, maps, span)
                run = lambda n, out: reconstruct_stream(dat_source(dat, height, width, cfg.phi0_rad, cfg.rev_per_s, cfg.rate_hz), model, out,  # noqa: E731
                                                        ReconstructConfig(video=False, frames="exr", exposure=cfg.exposure, max_frames=n, threads=threads, rir=rir, span="auto"))
                tick(f"{name}: warm-up")
                w0, c0 = time.perf_counter(), time.process_time()
                run(2, d / f"w_{name}")
                warm = {"wall_s": time.perf_counter() - w0, "cpu_s": time.process_time() - c0}
                tick(f"{name}: {frames} frames")
                s = run(frames, d / f"o_{name}")
                row = {"cpu_s_per_frame": s["cpu_s_per_frame"], "frames_per_cpu_s": 1.0 / s["cpu_s_per_frame"]["total"], "frames_per_wall_s": s["frames_per_second_processed"],
                       "warm_up": warm, "compile": dict(stats.summary()), "load_avg": os.getloadavg()}
                got = _frames(d / f"o_{name}")
                row["weights"], row["variant"] = wname, vname
                if ref is None:
                    ref = got
                else:
                    first = res["variants"][rows[0][2]]
                    row["ratio_cpu"] = row["frames_per_cpu_s"] / first["frames_per_cpu_s"]
                    row["ratio_model_cpu"] = first["cpu_s_per_frame"]["model"] / row["cpu_s_per_frame"]["model"]
                    row["ratio_wall"] = row["frames_per_wall_s"] / first["frames_per_wall_s"]
                    if wname == rows[0][0]:  # the same network sped up: how far its floats move
                        row["max_abs_change"] = {k: float(np.abs(got[k].astype(np.float64) - ref[k]).max()) for k in ("T", "R")}
                    if got and ref:  # how far the output lies from the reference's (another network's, or bfloat16's rounding)
                        row["psnr_vs_reference"] = {k: _psnr(got[k], ref[k]) for k in ("T", "R")}
                res["variants"][name] = row
                log.info("%s: %.3f frames per CPU second", name, row["frames_per_cpu_s"])
    finally:
        torch.set_num_threads(n0)
    res["reference"] = rows[0][2]
    res["config"]["load_avg_end"] = os.getloadavg()
    return res


def net_speed_markdown(res: dict[str, Any]) -> str:
    """Markdown table of :func:`bench_net_speed`."""
    c = res["config"]
    lines = [f"Network path at {c['width']} x {c['height']}, {c['frames']} frames, {c['threads']} torch thread(s), --rir {c['rir']} ({', '.join(c['weights'])}); "
             f"load average {c['load_avg_start'][0]:.1f} -> {c['load_avg_end'][0]:.1f}", "",
             "| row | RIR | span | model | total CPU s / frame | frames / CPU s | frames / s (wall) | x reference (CPU) | x reference (wall) | model x reference | "
             "max abs dT | max abs dR | T, R PSNR vs reference (dB) | warm-up (compile) CPU s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in res["variants"].items():
        cs = r["cpu_s_per_frame"]
        ch = r.get("max_abs_change", {})
        pv = r.get("psnr_vs_reference")
        pvs = "-" if pv is None else f"{pv['T']:.1f}, {pv['R']:.1f}"
        f = lambda v, nd=3: "-" if v is None else f"{v:.{nd}f}"  # noqa: E731
        e = lambda v: "-" if v is None else f"{v:.1e}"  # noqa: E731
        lines.append(f"| {name} | {f(cs['rir'])} | {f(cs['span'])} | {f(cs['model'])} | {f(cs['total'])} | {f(r['frames_per_cpu_s'])} | {f(r['frames_per_wall_s'])} | "
                     f"{f(r.get('ratio_cpu'), 2)} | {f(r.get('ratio_wall'), 2)} | {f(r.get('ratio_model_cpu'), 2)} | {e(ch.get('T'))} | {e(ch.get('R'))} | "
                     f"{pvs} | {f(r['warm_up']['cpu_s'], 1)} |")
    return "\n".join(lines) + "\n"
