"""``polspike bench realtime``: does the physics path keep up with the camera?

On a closed-form pane stream (:mod:`reconstruct.stream.pane_stream`, written as .dat files of two lengths) the
same physics model runs through the live path (:func:`reconstruct.video.live.reconstruct_live`) and the general
streaming path (:func:`reconstruct.video.stream.reconstruct_stream`, the reference) in one run.  Marginal
throughput is taken between the two lengths, so start-up cancels.  Each figure is given in wall-clock time and
in CPU time (the process's threads plus its encoder children): on a shared, loaded machine the wall clock
measures the neighbours as much as the code, the CPU time does not.

Each live-path setting runs once on the short recording before it is timed (the numba kernels load or compile on
their first call).  Real-time factor = seconds of recording per second of processing (>= 1 keeps up with the camera).  Per stage
(live path): read, aggregate, zeta, RIR, solve, write, encode, and the self-calibration (once, on the first
0.1 s).  Memory: a long stream (default 60 s, one second of packed spikes repeated: 30 whole polarizer turns, so
the phase is continuous) made on the fly and run through the live path in a child process, peak RSS beside a
short run's.  Latency: a child process appends a recording to a .dat at real time while the live path follows it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["bench_realtime", "realtime_markdown"]

log = logging.getLogger(__name__)

CAMERA_FPS = 360.0 * 30.0 / 31.5  # output cadence at 30 rev/s and 31.5 deg


def _cpu() -> float:
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def _model(method: str, rir: bool, maps, span: float):
    from reconstruct.video.physics import PhysicsModel

    return PhysicsModel(method, 7, maps=maps, span_rad=span, rir=rir)


LIVE_VARIANTS = {
    "torch": {"solver": "torch", "video_quality": "high", "rir_finest": 1, "preview": True},
    "high-video": {"video_quality": "high", "preview": True},
    "preview": {"preview": True},
    "coarse-rir": {"rir_finest": 2},
    "threads2": {"threads": 2},
    "gray-video": {"video_codec": "h264-gray"},
    "y4m": {"video_codec": "y4m"},
    "serial": {"pipeline": False},
    "unshared": {"share_pixels": False},
}
"""Live-path settings the bench can run beside the defaults: ``torch`` = the torch solvers, the torch RIR fit and the
CRF-10 videos with the preview (the live path before its fused kernels), ``high-video`` = CRF-10 videos with the
preview, ``preview`` = the defaults plus preview.mp4 (the three videos of the path before), ``coarse-rir`` = the RIR
fit stopping at 2 x 2 blocks, ``threads2`` = the fused RWPS passes on two numba threads, ``gray-video`` = 4:0:0 H.264
videos, ``y4m`` = raw 8-bit .y4m videos (no encoder process), ``serial`` = the fused rwps stages one after the other on
the stream's thread (no solve thread; rwps only), ``unshared`` = the solve thread makes every pixel row of its window
(the stream's thread waits instead of taking the rows left; rwps only)."""


def _run(path: str, dat: Path, cfg, model, out: Path, video: bool) -> dict[str, Any]:
    from reconstruct.stream.packed import PackedDat
    from reconstruct.stream.sources import dat_source
    from reconstruct.video.live import LiveConfig, StageTimes, reconstruct_live
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    w0, c0 = time.perf_counter(), _cpu()
    times = None
    if path.startswith("live"):
        times = StageTimes()
        over = LIVE_VARIANTS[path.split(":")[1]] if ":" in path else {}
        s = reconstruct_live(PackedDat(dat, cfg.height, cfg.width), model, out, LiveConfig(video=video, **over), phi0_rad=cfg.phi0_rad, rev_per_s=cfg.rev_per_s,
                             rate_hz=cfg.rate_hz, exposure=cfg.exposure, times=times)
    else:
        src = dat_source(dat, cfg.height, cfg.width, cfg.phi0_rad, cfg.rev_per_s, cfg.rate_hz)
        s = reconstruct_stream(src, model, out, ReconstructConfig(video=video, exposure=cfg.exposure))
    return {"frames": s["frames"], "pipeline": s.get("pipeline"), "wall_s": time.perf_counter() - w0, "cpu_s": _cpu() - c0, "stages": None if times is None else {"wall": times.wall, "cpu": times.cpu}}


def _marginal(short: dict, long: dict) -> dict[str, float]:
    df = long["frames"] - short["frames"]
    dw, dc = long["wall_s"] - short["wall_s"], long["cpu_s"] - short["cpu_s"]
    return {"frames": df, "fps_wall": df / dw if dw > 0 else None, "fps_cpu": df / dc if dc > 0 else None}


def _child_rss(seconds: float, width: int, height: int, video: bool) -> dict[str, Any]:
    """Run the live path on ``seconds`` of a looped on-the-fly stream in a child process; its peak RSS and times."""
    code = f"""
import json, math, resource, sys, time
from reconstruct.stream.pane_stream import PaneStreamConfig, pane_stream_maps, pane_stream_packed
from reconstruct.stream.packed import PackedChunks
from reconstruct.physics.zeta import PaneMaps
from reconstruct.video.physics import PhysicsModel
from reconstruct.video.live import LiveConfig, reconstruct_live
import numpy as np, tempfile
cfg = PaneStreamConfig(width={width}, height={height}, exposure=2.0)
block = np.concatenate(list(pane_stream_packed(cfg, int(cfg.rate_hz), 200)))  # 1 s = 30 whole turns
steps = int(round({seconds} * cfg.rate_hz))
def chunks():
    s = 0
    while s < steps:
        m = min(1000, steps - s)
        a = s % block.shape[0]
        yield block[a:a + m] if a + m <= block.shape[0] else np.concatenate([block[a:], block[:a + m - block.shape[0]]])
        s += m
import os, threading
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
run = {{"start": rss(), "max": 0.0}}
done = threading.Event()
def sample():
    while not done.wait(0.05):
        run["max"] = max(run["max"], rss())
threading.Thread(target=sample, daemon=True).start()
mp = pane_stream_maps(cfg)
model = PhysicsModel("ls", 7, maps=PaneMaps(R_perp=mp["R_perp"], R_par=mp["R_par"], phi_perp=mp["phi_perp"]), span_rad=2 * math.pi * 30 * 13 / 20000, rir=False)
t0 = time.perf_counter(); c0 = time.process_time()
with tempfile.TemporaryDirectory() as d:
    s = reconstruct_live(PackedChunks(chunks(), cfg.height, cfg.width, steps), model, d, LiveConfig(video={video}), phi0_rad=cfg.phi0_rad, rev_per_s=30.0, rate_hz=cfg.rate_hz, exposure=cfg.exposure)
done.set()
print(json.dumps({{"seconds": {seconds}, "frames": s["frames"], "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "run_rss_start_mb": run["start"], "run_rss_max_mb": max(run["max"], rss()), "run_rss_end_mb": rss(),
                  "rss_before_mb": rss0 / 1024, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}}))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)})
    if r.returncode != 0:
        raise RuntimeError(f"memory run failed: {r.stderr[-1500:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _latency(dat: Path, cfg, model, seconds: float, chunk_steps: int) -> dict[str, Any]:
    """A child copies ``dat`` into a new file at real time, ``chunk_steps`` at a time; the live path follows it."""
    from reconstruct.stream.packed import PackedDat
    from reconstruct.video.live import LiveConfig, reconstruct_live

    fb = cfg.height * cfg.width // 8
    with tempfile.TemporaryDirectory() as d:
        dst = Path(d) / "growing.dat"
        code = (f"import time\nsrc = open({str(dat)!r}, 'rb'); dst = open({str(dst)!r}, 'ab', buffering=0)\nt0 = time.perf_counter(); n = 0\n"
                f"while n < {int(seconds * cfg.rate_hz)}:\n    b = src.read({chunk_steps * fb})\n    if not b: break\n    dst.write(b); n += len(b) // {fb}\n"
                f"    lag = n / {cfg.rate_hz} - (time.perf_counter() - t0)\n    if lag > 0: time.sleep(lag)\n")
        w = subprocess.Popen([sys.executable, "-c", code])
        try:
            s = reconstruct_live(PackedDat(dst, cfg.height, cfg.width, stored_w=cfg.width), model, Path(d) / "out", LiveConfig(idle_s=1.0, video=True),
                                 phi0_rad=cfg.phi0_rad, rev_per_s=cfg.rev_per_s, rate_hz=cfg.rate_hz, exposure=cfg.exposure, follow=True)
        finally:
            w.wait()
    return {"seconds": seconds, "chunk_steps": chunk_steps, "frames": s["frames"], **s["latency_s"]}


def bench_realtime(width: int = 400, height: int = 250, short_s: float = 0.25, long_s: float = 1.0, memory_s: float = 60.0, latency_s: float = 1.0,
                   methods: tuple[str, ...] = ("ls", "rwps+rir"), reference: bool = True, video: bool = True, workdir: str | None = None, progress=None,
                   variants: tuple[str, ...] = ("torch",)) -> dict[str, Any]:
    """Measure the live path against the streaming path (module docstring).

    Args:
        width, height: frame size.
        short_s, long_s: the two recording lengths of the marginal throughput.
        memory_s: length of the constant-memory run (0 = skip); a 5 s run gives the comparison.
        latency_s: length of the followed recording (0 = skip).
        methods: ``ls`` (no RIR) and/or ``rwps+rir`` (RIR on), also ``rwps``, ``ls+rir``.
        reference: also run today's streaming path.
        video: write the MP4s (the encode stage).
        variants: live-path settings run beside the defaults (:data:`LIVE_VARIANTS`), each a ratio.
    """
    from reconstruct.pane.source import calibrate_stream
    from reconstruct.physics.zeta import PaneMaps
    from reconstruct.stream.packed import PackedDat, packed_source
    from reconstruct.stream.pane_stream import PaneStreamConfig, write_pane_dat
    from reconstruct.video.live import LiveConfig

    # a pan of 20 px/s for RIR to follow (0.06 px per output frame); static where no method registers
    cfg = PaneStreamConfig(width=width, height=height, exposure=2.0, motion_px_s=(0.0, 20.0) if any(m.endswith("+rir") for m in methods) else (0.0, 0.0))
    res: dict[str, Any] = {"config": {"width": width, "height": height, "short_s": short_s, "long_s": long_s, "camera_fps": CAMERA_FPS, "video": video,
                                      "stream": dataclasses.asdict(cfg), "cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg(),
                                      "variants": {v: LIVE_VARIANTS[v] for v in variants}, "pipeline_default": LiveConfig().pipeline}, "methods": {}}
    tick = (lambda s: progress(s)) if progress else (lambda s: None)
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        d = Path(d)
        dats = {}
        for tag, secs in (("short", short_s), ("long", long_s)):
            tick(f"write {secs} s stream")
            dats[tag] = write_pane_dat(d / f"{tag}.dat", cfg, secs)
        tick("self-calibration")
        src = packed_source(PackedDat(dats["long"], height, width), int(0.2 * cfg.rate_hz), cfg.phi0_rad, cfg.rev_per_s, cfg.rate_hz, "bench")
        src = dataclasses.replace(src, exposure=cfg.exposure)
        w0, c0 = time.perf_counter(), time.process_time()
        sc = calibrate_stream(src, None, 13, cfg.exposure, None, None, None)
        res["selfcal"] = {"wall_s": time.perf_counter() - w0, "cpu_s": time.process_time() - c0, "ok": bool(sc.ok), "span_s": 0.1}
        if not sc.ok:
            raise RuntimeError(f"the bench stream did not self-calibrate: {sc.reason}")
        maps: PaneMaps = sc.maps
        span = 2 * math.pi * cfg.rev_per_s * 13 / cfg.rate_hz
        for m in methods:
            method, rir = m.split("+")[0], m.endswith("+rir")
            row: dict[str, Any] = {}
            paths = ("live", *(f"live:{v}" for v in variants if not (v == "coarse-rir" and not rir) and not (v in ("threads2", "serial") and method != "rwps")), *(("stream",) if reference else ()))
            for path in paths:
                if path.startswith("live"):  # warm-up: the numba kernels load (or compile) on their first call
                    _run(path, dats["short"], cfg, _model(method, rir, maps, span), d / f"w_{m}_{path.replace(':', '_')}", video)
                runs = {}
                for tag in ("short", "long"):
                    tick(f"{m} {path} {tag}")
                    runs[tag] = _run(path, dats[tag], cfg, _model(method, rir, maps, span), d / f"o_{m}_{path.replace(':', '_')}_{tag}", video)
                row[path] = {"runs": runs, "marginal": _marginal(runs["short"], runs["long"]), "load_avg": os.getloadavg()}
            new = row["live"]["marginal"]
            row["ratio"] = {}
            for path in paths[1:]:
                ref = row[path]["marginal"]
                if None not in (new["fps_wall"], new["fps_cpu"], ref["fps_wall"], ref["fps_cpu"]):
                    row["ratio"][path] = {"wall": new["fps_wall"] / ref["fps_wall"], "cpu": new["fps_cpu"] / ref["fps_cpu"]}
            if "stream" in row["ratio"]:
                row["speedup_wall"], row["speedup_cpu"] = row["ratio"]["stream"]["wall"], row["ratio"]["stream"]["cpu"]
            st = row["live"]["runs"]["long"]["stages"]
            secs = long_s
            row["stage_ms_per_frame_cpu"] = {}  # marginal between the two lengths: one-off costs cancel
            for path in [p for p in paths if p.startswith("live")]:
                a, b = row[path]["runs"]["short"], row[path]["runs"]["long"]
                df = b["frames"] - a["frames"]
                if df > 0:
                    row["stage_ms_per_frame_cpu"][path] = {k: 1e3 * (b["stages"]["cpu"][k] - a["stages"]["cpu"].get(k, 0.0)) / df for k in b["stages"]["cpu"]}
            row["stages_rtf_cpu"] = {k: secs / v if v > 1e-9 else None for k, v in st["cpu"].items()}
            row["stages_rtf_wall"] = {k: secs / v if v > 1e-9 else None for k, v in st["wall"].items()}
            res["methods"][m] = row
        if latency_s > 0:
            tick("latency at real time")
            res["latency"] = _latency(dats["long"], cfg, _model("ls", False, maps, span), min(latency_s, long_s), 200)
    if memory_s > 0:
        tick(f"memory: {memory_s} s stream")
        res["memory"] = {"short": _child_rss(min(5.0, memory_s), width, height, False), "long": _child_rss(memory_s, width, height, False)}
    res["config"]["load_avg_end"] = os.getloadavg()
    return res


def _f(v, nd: int = 1) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def realtime_markdown(res: dict[str, Any]) -> str:
    c = res["config"]
    keys = sorted({k for row in res["methods"].values() for k in row["stages_rtf_cpu"]})
    L = [f"Live path vs the streaming path at {c['width']} x {c['height']}, marginal throughput between {c['short_s']} s and {c['long_s']} s recordings "
         f"(camera: {c['camera_fps']:.1f} frames/s; load average {c['load_avg_start'][0]:.1f} at the start on {c['cpu_count']} cores).", "",
         "| method | path | frames | frames/s (wall) | frames/s (CPU) | real-time factor (CPU) | load average after |", "|---|---|---:|---:|---:|---:|---:|"]
    for m, row in res["methods"].items():
        for path in [p for p in row if p == "live" or p.startswith("live:") or p == "stream"]:
            mg = row[path]["marginal"]
            fr = f"{row[path]['runs']['short']['frames']} -> {row[path]['runs']['long']['frames']}"
            la = row[path].get("load_avg")
            L.append(f"| {m} | {path} | {fr} | {_f(mg['fps_wall'])} | {_f(mg['fps_cpu'])} | {_f(mg['fps_cpu'] and mg['fps_cpu'] / c['camera_fps'], 2)} | {_f(la and la[0])} |")
        for path, r in row.get("ratio", {}).items():
            L.append(f"| {m} | live / {path} | | {r['wall']:.1f} x | {r['cpu']:.1f} x | | |")
    L += ["", f"Self-calibration (once, first 0.1 s): {res['selfcal']['wall_s']:.1f} s wall, {res['selfcal']['cpu_s']:.1f} s CPU.", "",
          "Real-time factor per stage of the live path (seconds of recording per second of the stage, CPU time; encode = the background thread, without the x264 children):", "",
          "| method | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for m, row in res["methods"].items():
        L.append(f"| {m} | " + " | ".join(_f(row["stages_rtf_cpu"].get(k)) for k in keys) + " |")
    L += ["", "CPU milliseconds per output frame per stage, marginal between the two lengths (encode = the background thread; the x264 "
          "processes are only in the totals above):", "", "| method | path | " + " | ".join(keys) + " |", "|---|---|" + "---:|" * len(keys)]
    for m, row in res["methods"].items():
        for path, st in row.get("stage_ms_per_frame_cpu", {}).items():
            L.append(f"| {m} | {path} | " + " | ".join(_f(st.get(k), 2) for k in keys) + " |")
    if "latency" in res:
        la = res["latency"]
        L += ["", f"--follow at real time ({la['seconds']} s written in chunks of {la['chunk_steps']} steps): latency median {1e3 * la['median']:.0f} ms, "
              f"p95 {1e3 * la['p95']:.0f} ms, max {1e3 * la['max']:.0f} ms over {la['frames']} frames."]
    if "memory" in res:
        ms, ml = res["memory"]["short"], res["memory"]["long"]
        L += ["", "Memory (live ls, no video, one second of packed spikes made once and repeated on the fly; RSS sampled every 50 ms during the run):", "",
              "| recording | frames | RSS at the start | largest RSS during the run | RSS at the end | frames per CPU second |", "|---:|---:|---:|---:|---:|---:|"]
        for m in (ms, ml):
            L.append(f"| {m['seconds']:g} s | {m['frames']} | {m['run_rss_start_mb']:.0f} MB | {m['run_rss_max_mb']:.0f} MB | {m['run_rss_end_mb']:.0f} MB | {m['frames'] / m['cpu_s']:.0f} |")
    return "\n".join(L) + "\n"
