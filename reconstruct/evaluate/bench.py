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

from reconstruct.physics.harmonic_fit import dop, harmonic_fit
from reconstruct.physics.rir import RirConfig, estimate_shifts, warp
from reconstruct.physics.solvers import solve

__all__ = ["bench_reconstruct", "bench_reconstruct_net", "count_flops", "net_table"]

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
    from reconstruct.evaluate.harness import EvalConfig, group_zeta
    from reconstruct.stream.synthetic import SyntheticConfig, make_group

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


# ---------------------------------------------------------------------------
# The learned reconstructor: v1 against v2 in one run


def count_flops(model, height: int = 250, width: int = 400) -> float:
    """FLOPs of one output frame (one window of N frames, padded as the stream pads it), counted by
    :class:`torch.utils.flop_counter.FlopCounterMode` (a multiply-add = 2 FLOPs; convolutions, linear
    layers and matrix products; elementwise work is not counted).
    """
    from torch.utils.flop_counter import FlopCounterMode

    m = int(getattr(model, "pad_multiple", 4))
    H, W = height + (-height) % m, width + (-width) % m
    I = 0.1 + 0.3 * torch.rand(1, model.cfg.n_obs, H, W, generator=torch.Generator().manual_seed(0))
    phi = (torch.arange(model.cfg.n_obs, dtype=torch.float32) - model.cfg.n_obs // 2)[None] * 0.55
    fc = FlopCounterMode(display=False)
    from reconstruct.video.tiling import standin_inputs

    with torch.inference_mode(), fc:
        x = standin_inputs(model, I, phi)
        model(x.I, x.phi, **x.extras())
    return float(fc.get_total_flops())


def _frame_fps(model, height: int, width: int, frames: int, tile: int, precision: str = "float32", device: str = "cpu") -> float:
    from reconstruct.video.tiling import run_model_on_windows, standin_inputs

    g = np.random.default_rng(0)
    N = model.cfg.n_obs
    I = (0.1 + 0.3 * g.random((1, N, height, width))).astype(np.float32)
    phi = ((np.arange(N) - N // 2) * np.radians(31.5))[None].astype(np.float32)
    x = standin_inputs(model, I, phi)
    run_model_on_windows(model, x, device, tile, precision=precision)  # warm-up
    best = float("inf")
    cpu = float("inf")
    for _ in range(frames):
        t0, c0 = time.perf_counter(), time.process_time()
        run_model_on_windows(model, x, device, tile, precision=precision)  # returns numpy: synchronised
        best = min(best, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    _frame_fps.last_cpu_s = cpu  # CPU seconds of the best pass (all threads): robust to other processes' load
    return 1.0 / best


def _stream_fps(model, height: int, width: int, frames: int, out_dir) -> dict:
    """``polspike reconstruct`` end to end (Eq. (3) aggregation, network, video writing) on a synthetic stream."""
    from reconstruct.stream.sources import array_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    N = model.cfg.n_obs
    steps = int((frames + N + 1) * 31.5 / 360 / 30.0 * 20000) + 40
    g = np.random.default_rng(1)
    rate = g.uniform(0.05, 0.4, (1, height, width)).astype(np.float32)
    spikes = np.empty((steps, height, width), np.uint8)
    for i in range(0, steps, 64):
        n = min(64, steps - i)
        spikes[i : i + n] = g.random((n, height, width), dtype=np.float32) < rate
    c0 = time.process_time()
    s = reconstruct_stream(array_source(spikes, 0.0, 30.0), model, out_dir, ReconstructConfig(max_frames=frames))
    cpu = time.process_time() - c0  # this process's threads (the ffmpeg encoder processes are not included)
    return {"frames": s["frames"], "seconds": s["seconds"], "frames_per_second": s["frames"] / s["seconds"], "cpu_s_per_frame": cpu / max(1, s["frames"]), "tile": s["tile"], "feature_cache": s["feature_cache"], "threads": torch.get_num_threads()}


def _train_throughput(arch_cfg, train_set, steps: int, workers: int, out_dir) -> dict:
    """Wall time of ``steps`` optimizer steps of :func:`reconstruct.net.train.train` (data generation included)."""
    import dataclasses

    from reconstruct.net.train import train

    cfg = dataclasses.replace(arch_cfg, epochs=1, steps_per_epoch=steps, ckpt_every=10**6, log_every=10**6, val_every=10**6)
    t0 = time.perf_counter()
    train(cfg, train_set, None, out_dir, workers=workers)
    dt = time.perf_counter() - t0
    px = cfg.window.crop**2 * cfg.batch_size * steps
    return {"steps": steps, "workers": workers, "seconds": dt, "steps_per_second": steps / dt, "window_pixels_per_second": px / dt, "crop": cfg.window.crop, "batch": cfg.batch_size}


def bench_reconstruct_net(
    models: dict,
    *,
    height: int = 250,
    width: int = 400,
    frames: int = 2,
    threads: tuple[int, ...] = (1, 2),
    stream_frames: dict | None = None,
    train_cfgs: dict | None = None,
    train_set=None,
    train_steps: dict | None = None,
    variants: bool = True,
    compile_: bool = False,
    work_dir=None,
) -> dict:
    """Cost and speed of learned reconstructors measured in one process.

    Args:
        models: name -> model (eval mode, CPU), e.g. {"v1": ..., "v2": ...}; the first is the reference of the ratios.
        height, width: frame size (400 x 250: the sensor).
        frames: timed single-frame passes per setting (best kept).
        threads: torch thread counts for the frame rate.
        stream_frames: name -> output frames of the end-to-end ``polspike reconstruct`` run (on ``max(threads)`` threads; omit to skip).
        train_cfgs: name -> :class:`reconstruct.net.train.TrainConfig` for the training throughput (omit to skip).
        train_set: on-the-fly training windows (map-style dataset) for the training throughput.
        train_steps: name -> optimizer steps timed.
        variants: also time channels-last and bf16 autocast (and ``torch.compile`` when ``compile_``) for the models after the first.
        work_dir: scratch directory (videos, run directories).

    Returns:
        {"config", "models": {name: {...}}, "ratios": {name: {...}}} (JSON-ready).
    """
    import tempfile
    from pathlib import Path

    from reconstruct.net.network import NetConfig, count_parameters

    work = Path(work_dir or tempfile.mkdtemp(prefix="bench_net_"))
    out: dict = {"config": {"width": width, "height": height, "frames": frames, "threads": list(threads), "torch": torch.__version__, "machine": platform.machine()}, "models": {}}
    n0 = torch.get_num_threads()
    trained: dict = {}
    try:
        # training first, on one thread, the runs with a DataLoader worker before any in-process window
        # generation: the worker is forked, which GNU OpenMP (torch threads, spike_sim's numba kernel) forbids
        # once a multi-threaded region ran in this process
        torch.set_num_threads(1)
        for w in (1, 0):
            if w == 0:  # no fork after this: cap spike_sim's numba pool too (its idle OpenMP threads spin otherwise)
                try:
                    import numba

                    numba.set_num_threads(1)
                except Exception:  # pragma: no cover
                    pass
            for name in models:
                if train_cfgs and name in train_cfgs and train_set is not None:
                    steps = (train_steps or {}).get(name, 10)
                    trained.setdefault(name, {})[f"workers_{w}"] = _train_throughput(train_cfgs[name], train_set, steps, w, work / f"train_{name}_{w}")
                    log.info("%s: training %s", name, trained[name])
        for name, model in models.items():
            from reconstruct.video.tiling import auto_tile

            r: dict = {"arch": model.cfg.arch if isinstance(model.cfg, NetConfig) else "?", "parameters": count_parameters(model), "tile": auto_tile(model, "cpu")}
            torch.set_num_threads(1)
            r["gflop_per_frame"] = count_flops(model, height, width) / 1e9
            for t in threads:
                torch.set_num_threads(t)
                r[f"fps_{t}thr"] = _frame_fps(model, height, width, frames, r["tile"])
                r[f"cpu_s_per_frame_{t}thr"] = _frame_fps.last_cpu_s
                log.info("%s: %.3f frames/s on %d threads", name, r[f"fps_{t}thr"], t)
            if variants and name != next(iter(models)):  # variants of the network under test only
                t = max(threads)
                torch.set_num_threads(t)
                v = {"float32": r[f"fps_{t}thr"]}
                vc = {"float32": r[f"cpu_s_per_frame_{t}thr"]}
                v["bfloat16_autocast"] = _frame_fps(model, height, width, frames, r["tile"], "bfloat16")
                vc["bfloat16_autocast"] = _frame_fps.last_cpu_s
                model.to(memory_format=torch.channels_last)
                v["channels_last"] = _frame_fps(model, height, width, frames, r["tile"])
                vc["channels_last"] = _frame_fps.last_cpu_s
                v["channels_last_bfloat16"] = _frame_fps(model, height, width, frames, r["tile"], "bfloat16")
                vc["channels_last_bfloat16"] = _frame_fps.last_cpu_s
                model.to(memory_format=torch.contiguous_format)
                r[f"variants_cpu_s_per_frame_{t}thr"] = vc
                if compile_:
                    try:
                        cm = torch.compile(model)
                        cm.cfg = model.cfg
                        cm.pad_multiple = getattr(model, "pad_multiple", 4)
                        v["torch_compile"] = _frame_fps(cm, height, width, frames, r["tile"])
                        vc["torch_compile"] = _frame_fps.last_cpu_s
                    except Exception as exc:  # compile needs a working C++ toolchain
                        v["torch_compile"] = f"failed: {type(exc).__name__}: {str(exc).splitlines()[0][:100]}"
                r[f"variants_fps_{t}thr"] = v
            if stream_frames and name in stream_frames:
                torch.set_num_threads(max(threads))
                r["reconstruct"] = _stream_fps(model, height, width, stream_frames[name], work / f"video_{name}")
            if torch.cuda.is_available():
                model.to("cuda")
                r["fps_cuda"] = _frame_fps(model, height, width, frames, auto_tile(model, "cuda"), device="cuda")
                r["fps_cuda_bfloat16"] = _frame_fps(model, height, width, frames, auto_tile(model, "cuda"), "bfloat16", device="cuda")
                model.to("cpu")
            else:
                out.setdefault("skipped", {})["cuda"] = "no CUDA device"
            if name in trained:
                r["train_1thr"] = trained[name]
            out["models"][name] = r
    finally:
        torch.set_num_threads(n0)
    names = list(out["models"])
    ref = out["models"][names[0]]
    out["reference"] = names[0]
    out["ratios"] = {}
    for name in names[1:]:
        r = out["models"][name]
        q = {"flops_reduction": ref["gflop_per_frame"] / r["gflop_per_frame"]}
        for t in threads:
            q[f"fps_{t}thr_speedup"] = r[f"fps_{t}thr"] / ref[f"fps_{t}thr"]
            q[f"cpu_time_{t}thr_speedup"] = ref[f"cpu_s_per_frame_{t}thr"] / r[f"cpu_s_per_frame_{t}thr"]
        if "reconstruct" in r and "reconstruct" in ref:
            q["reconstruct_speedup"] = r["reconstruct"]["frames_per_second"] / ref["reconstruct"]["frames_per_second"]
        if "train_1thr" in r and "train_1thr" in ref:
            for w in (0, 1):
                q[f"train_pixels_speedup_workers_{w}"] = r["train_1thr"][f"workers_{w}"]["window_pixels_per_second"] / ref["train_1thr"]["workers_0"]["window_pixels_per_second"]
        out["ratios"][name] = q
    return out


def net_table(res: dict) -> str:
    """Markdown table of :func:`bench_reconstruct_net` results."""
    names = list(res["models"])
    thr = res["config"]["threads"]
    rows = [("parameters", lambda r: f"{r['parameters']:,}"), ("GFLOP / frame (counted)", lambda r: f"{r['gflop_per_frame']:.1f}")]
    for t in thr:
        rows.append((f"network frames/s, {t} thread{'s' if t > 1 else ''}", lambda r, t=t: f"{r[f'fps_{t}thr']:.3f}"))
        rows.append((f"network CPU-s per frame, {t} thread{'s' if t > 1 else ''}", lambda r, t=t: f"{r[f'cpu_s_per_frame_{t}thr']:.3f}"))
    rows.append((f"`polspike reconstruct` frames/s, {max(thr)} thread{'s' if max(thr) > 1 else ''}", lambda r: f"{r['reconstruct']['frames_per_second']:.3f}" if "reconstruct" in r else "-"))
    rows.append(("`polspike reconstruct` CPU-s per frame", lambda r: f"{r['reconstruct']['cpu_s_per_frame']:.3f}" if "reconstruct" in r else "-"))
    for w in (0, 1):
        rows.append((f"training steps/s (1 thread, {w} data worker{'s' if w != 1 else ''})", lambda r, w=w: f"{r['train_1thr'][f'workers_{w}']['steps_per_second']:.3f}" if "train_1thr" in r else "-"))
        rows.append((f"training window-pixels/s (1 thread, {w} data worker{'s' if w != 1 else ''})", lambda r, w=w: f"{r['train_1thr'][f'workers_{w}']['window_pixels_per_second']:,.0f}" if "train_1thr" in r else "-"))
    lines = ["| | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for label, f in rows:
        lines.append(f"| {label} | " + " | ".join(f(res["models"][n]) for n in names) + " |")
    for n, q in res.get("ratios", {}).items():
        lines.append("")
        lines.append(f"{n} vs {res['reference']} (same run): " + ", ".join(f"{k} {v:.2f}x" for k, v in q.items()))
    for n in names:
        v = next((res["models"][n][k] for k in res["models"][n] if k.startswith("variants_fps_")), None)
        vc = next((res["models"][n][k] for k in res["models"][n] if k.startswith("variants_cpu_s_")), {})
        if v:
            lines.append("")
            lines.append(f"{n} by variant, frames/s (CPU-s per frame): " + ", ".join(f"{k} {x:.3f} ({vc.get(k, float('nan')):.2f})" if isinstance(x, float) else f"{k} {x}" for k, x in v.items()))
    return "\n".join(lines) + "\n"


ENSEMBLE_METRICS = ("psnr_T", "ssim_T", "psnr_R", "ssim_R")


def bench_ensemble(groups, cfg, sizes: tuple[int, ...] = (1, 2, 4, 8), progress=None) -> dict:
    """Quality and cost of the network's test-time self-ensemble (:class:`reconstruct.net.network.SymmetryEnsemble`).

    Every size runs the network (method full, ``cfg``'s zeta) on the same ``groups`` and frames; the result gives
    T and R PSNR / SSIM (overall rows of :func:`reconstruct.evaluate.harness.evaluate_groups`), the network's seconds per
    output frame and its ratio to size 1, measured in the same run (size 1 is always run first).
    """
    import dataclasses

    from reconstruct.evaluate.harness import evaluate_groups, net_zeta_of

    sizes = tuple(dict.fromkeys((1, *sizes)))
    groups = list(groups)
    rows = []
    for j, size in enumerate(sizes):
        c = dataclasses.replace(cfg, methods="full", net_ensemble=size, figure_frames=0)
        rep = evaluate_groups(groups, c)
        nz = net_zeta_of(c)
        label = rep.config["network"]["label"] + ("" if nz == "learned" else f"@{nz}")
        o = next(r for r in rep.rows if r["group"] == "overall" and r["method"] == label)
        n = int(o["n_frames"])
        rows.append({"ensemble": size, **{k: o.get(k) for k in ENSEMBLE_METRICS}, "n_frames": n, "s_per_frame": rep.timings.get("network", 0.0) / max(n, 1)})
        if progress is not None:
            progress(j + 1, len(sizes))
    ref = rows[0]["s_per_frame"]
    for r in rows:
        r["time_ratio"] = r["s_per_frame"] / ref if ref > 0 else None
    return {"rows": rows, "config": {"n_obs": cfg.n_obs, "dt_ms": cfg.dt_ms, "zeta": cfg.zeta, "net_zeta": net_zeta_of(cfg), "max_frames": cfg.max_frames,
                                      "groups": [g.name for g in groups], "threads": torch.get_num_threads(), "machine": platform.machine()}}


def ensemble_table(res: dict) -> str:
    """Markdown table of :func:`bench_ensemble`."""
    md = "| ensemble | PSNR T | SSIM T | PSNR R | SSIM R | s / frame | time vs 1 |\n|---:|---:|---:|---:|---:|---:|---:|\n"
    f = lambda v, p: "n/a" if v is None else f"{v:.{p}f}"  # noqa: E731
    for r in res["rows"]:
        md += f"| {r['ensemble']} | {f(r['psnr_T'], 2)} | {f(r['ssim_T'], 3)} | {f(r['psnr_R'], 2)} | {f(r['ssim_R'], 3)} | {r['s_per_frame']:.3f} | {f(r['time_ratio'], 2)}x |\n"
    return md


def ensemble_figure(res: dict, path) -> None:
    """Quality against cost of :func:`bench_ensemble`: T PSNR and SSIM over the time ratio, one point per size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from polinfra.atomic import atomic_path

    rows = res["rows"]
    x = [r["time_ratio"] or 0.0 for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, key, name in ((axes[0], "psnr_T", "T PSNR (dB)"), (axes[1], "ssim_T", "T SSIM")):
        y = [r[key] if r[key] is not None else np.nan for r in rows]
        ax.plot(x, y, "o-")
        for xi, yi, r in zip(x, y, rows):
            ax.annotate(f"x{r['ensemble']}", (xi, yi), textcoords="offset points", xytext=(4, -10))
        ax.set_xlabel("network time vs ensemble 1")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    fig.suptitle(f"test-time self-ensemble ({len(res['config']['groups'])} groups, zeta {res['config']['net_zeta']})")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
