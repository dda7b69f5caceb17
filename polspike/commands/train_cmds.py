"""``polspike train`` and ``polspike reconstruct``: the learned reconstructor's CLI.

The CLI is the one place that wires the generator's layer content into
``reconstruct``'s on-the-fly window source (``reconstruct`` never imports
``generator``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polinfra.errors import ConfigError
from polspike.cli import app_typer


def on_the_fly_sets(cfg):
    """(train set, validation set) of on-the-fly windows: generator analytic tier + spike_sim, disjoint scenes and content."""
    from polspike.pipeline.train_windows import window_sets

    return window_sets(cfg.window, cfg.train_items, cfg.val_items, cfg.seed, cfg.train_scenes, cfg.test_scenes, cfg.scene_seed, cfg.manifest, cfg.val_manifest, cfg.val_split, cfg.mix_manifests)

ARCH_BASE_PRESETS = {"v1": "v1_base.toml", "v2": "v2_lowres_branch.toml"}
"""The training preset each architecture was first trained with (its data and window settings)."""


def _limit_numba_threads(threads: int) -> None:
    """Cap spike_sim's parallel numba kernel at ``threads`` too: with more, its idle OpenMP threads
    spin between windows and take the CPU the training step needs (measured: 0.59 -> 0.39 CPU-s per
    in-process step on one thread).  This starts numba's OpenMP pool, after which GNU OpenMP forbids
    forking: call it only when no DataLoader worker will be forked later.
    """
    try:
        import numba

        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    except Exception:  # pragma: no cover - numba is a spike_sim dependency; never fatal here
        pass


@app_typer.command("train")
def train_cmd(
    config: Optional[Path] = typer.Argument(None, help="training TOML ([net], [loss], [solver], [window] tables; TrainConfig keys) [default: built-in defaults]"),
    out: Path = typer.Option(..., "--out", help="run directory (last.pt, log.csv, curves.png); an existing run is resumed"),
    data: Optional[Path] = typer.Option(None, "--data", help="built dataset directory (stored windows); omit to generate windows on the fly"),
    minutes: Optional[float] = typer.Option(None, "--minutes", help="stop after this many minutes (checkpointed; rerun to continue)"),
    device: Optional[str] = typer.Option(None, "--device", help="auto | cpu | cuda [default: config device]"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    threads: int = typer.Option(0, "--threads", help="torch CPU threads (0 = torch default); use 1 on a shared machine: oversubscribed threads run ~20x slower"),
    workers: int = typer.Option(1, "--workers", help="processes building batches ahead of the optimizer (0 = in the training process); the trajectory does not depend on it"),
    nproc: int = typer.Option(1, "--nproc", help="data-parallel training processes on this machine (torchrun --standalone; gloo on CPU, nccl on CUDA): each takes batch_size / N windows of every step, so N must divide batch_size; the global batch and the learning rate stay the config's. Several machines: start torchrun yourself (docs/scaling_out.md)"),
) -> None:
    """Train the reconstructor (paper Sec. 3.4 curriculum); resumable, deterministic for a seed on CPU."""
    import dataclasses

    from reconstruct.net.distributed import check_world, world_from_env

    ranks = world_from_env()
    if nproc < 1:
        check_world(nproc, 1)
    if nproc > 1 and ranks.active:
        raise ConfigError(f"--nproc {nproc} inside a torchrun launch: the processes are torchrun's (--nproc-per-node); drop --nproc")
    if nproc > 1:
        from polinfra.config import from_dict, load_toml
        from polspike.pipeline.train_launch import launch_local
        from reconstruct.net.train import TrainConfig

        check_world(nproc, (from_dict(TrainConfig, load_toml(config), where=str(config)) if config else TrainConfig()).batch_size)
        args = [*([str(config)] if config else []), "--out", str(out), *(["--data", str(data)] if data else []), *(["--minutes", str(minutes)] if minutes is not None else []),
                *(["--device", device] if device else []), *(["--quiet"] if quiet else []), "--threads", str(threads), "--workers", str(workers)]
        raise typer.Exit(launch_local(nproc, args))

    import torch

    if threads > 0:
        torch.set_num_threads(threads)
        if workers <= 0:  # windows generated in this process (starting numba's pool would forbid forking a worker)
            _limit_numba_threads(threads)

    from rich.console import Console

    from polinfra.config import from_dict, load_toml
    from polinfra.progress import rich_progress
    from reconstruct.net.distributed import init_ranks, shutdown
    from reconstruct.net.train import TrainConfig, train

    cfg = from_dict(TrainConfig, load_toml(config), where=str(config)) if config else TrainConfig()
    if device:
        cfg = dataclasses.replace(cfg, device=device)
    if ranks.active:
        check_world(ranks.world, cfg.batch_size, "world size")
        init_ranks(ranks, cfg.device)
        quiet = quiet or not ranks.is_writer
    if data is None:
        train_set, val_set = on_the_fly_sets(cfg)
        src = f"on-the-fly windows ({('scenes of ' + ', '.join((cfg.manifest, *cfg.mix_manifests))) if cfg.manifest else f'{cfg.train_scenes} train / {cfg.test_scenes} validation sampled scenes'}, generator analytic tier + spike_sim)"
    else:
        from reconstruct.net.windows import open_window_datasets

        train_set, val_set = open_window_datasets(data, cfg)
        src = f"stored windows in {data}"
    try:
        with rich_progress("train", enabled=not quiet) as cb:
            res = train(cfg, train_set, val_set, out, progress=cb, max_seconds=None if minutes is None else 60.0 * minutes, workers=max(0, workers), ranks=ranks)
    finally:
        shutdown(ranks)
    if not ranks.is_writer:
        return
    c = Console()
    c.print(f"data: {src}" + (f"; {ranks.world} data-parallel processes, {cfg.batch_size // ranks.world} windows each per step" if ranks.active else ""))
    c.print(f"PolSpikeNet: {res['param_count']:,} trainable parameters; step {res['step']}/{res['total_steps']}")
    m = res["metrics"]
    if m:
        c.print(f"validation PSNR of T: full {m['psnr_T']:.2f} dB, RWPS (learned zeta) {m['psnr_T_base']:.2f} dB, RWPS (GT zeta) {m['psnr_T_oracle']:.2f} dB")
    c.print(f"run directory: {out}")


def _write_selfcal_maps(out: Path, model, info: dict | None) -> str | None:
    """OUT/maps.exr: the pane maps the self-calibration fitted (R_perp, R_par, phi_perp, as calibrate-pane writes them),
    so that ``--pane OUT`` runs another reconstruction of the setup on the same zeta without calibrating again.
    Returns the file's name, or None when nothing was self-calibrated.
    """
    maps = getattr(model, "maps", None)
    if maps is None or info is None or not (info.get("selfcal") or {}).get("ok"):
        return None
    import numpy as np

    from polinfra.atomic import ensure_dir
    from polinfra.exr import write_exr

    ch = {k: np.asarray(getattr(maps, k), np.float32) for k in ("R_perp", "R_par", "phi_perp")}
    write_exr(ensure_dir(out) / "maps.exr", ch, attrs={"source": "polspike reconstruct --zeta self", "tier": "self-calibrated pane maps"})
    return "maps.exr"


@app_typer.command("reconstruct")
def reconstruct_cmd(
    input: Path = typer.Argument(..., help="a spike group directory (polspike simulate) or a raw Vidar .dat file"),
    out: Path = typer.Option(..., "--out", help="output directory: T.mp4, R.mp4 [, preview.mp4], reconstruct.json [, frames/]"),
    height: Optional[int] = typer.Option(None, "--height", help=".dat: frame height H"),
    width: Optional[int] = typer.Option(None, "--width", help=".dat: frame width W"),
    phi0_deg: Optional[float] = typer.Option(None, "--phi0-deg", help=".dat: polarizer angle at t = 0 (calibration), degrees"),
    rev_per_s: Optional[float] = typer.Option(None, "--rev-per-s", help=".dat: polarizer rotation rate (calibration), rev/s"),
    rate_hz: float = typer.Option(20000.0, "--rate-hz", help=".dat: camera steps per second"),
    exposure: Optional[float] = typer.Option(None, "--exposure", help="thresholds per step per unit radiance [default: a group's stored exposure; a .dat's estimated from its firing rates (reconstruct/stream/exposure.py)]"),
    window_steps: int = typer.Option(13, "--window-steps", help="Eq. (3) window in steps (13 = 0.65 ms)"),
    stride_deg: float = typer.Option(31.5, "--stride-deg", help="polarizer rotation between output frames (31.5 deg -> 342.9 FPS at 30 rev/s)"),
    frames: str = typer.Option("none", "--frames", help="also write frames: none | png | exr"),
    weights: Optional[Path] = typer.Option(None, "--weights", help="checkpoint file, or a shipped one by name: default | fast (the real-time network, docs/realtime.md) [default: the shipped reconstruct/weights default, reconstruct.net.checkpoint.DEFAULT_WEIGHTS]"),
    rir_shifts: str = typer.Option("window", "--rir", help="how each window's RIR shifts are estimated (once, for the network and the span): window (6 masked phase correlations and a Gauss-Newton refinement per window, as the network was trained) | chained (each frame registered once onto the previous one, reconstruct.physics.rir.ChainedRir: ~15x cheaper; docs/motion.md)"),
    no_rir: bool = typer.Option(False, "--no-rir", help="no RIR alignment of the windows (a checkpoint trained without it, run as trained) [default: RIR before the solver and the network, also for a checkpoint trained without it]"),
    floor: bool = typer.Option(True, "--floor/--no-floor", help="the network's data-consistency floor: its (T, R) must predict the 7 aligned windows within the noise of the physics-only RWPS's fit, else it is pulled back toward the physics (--floor-anchor; reconstruct/physics/consistency.py)"),
    floor_anchor: Optional[str] = typer.Option(None, "--floor-anchor", help="what the floor falls back to where the data check fails: blend (per pixel the RWPS and the best closed-form physics weighed by their error powers; on a self-calibrated or given zeta) | rwps (the physics-only RWPS) | best (per pixel the best closed-form physics alone: least squares, the spike mean or a blend, reconstruct/physics/anchor.py) [default: the checkpoint's, blend]"),
    floor_layers: Optional[bool] = typer.Option(None, "--floor-layers/--no-floor-layers", help="with --floor-anchor best or blend: also judge T and R by their own move from the anchor against its stated error (docs/motion.md) [default: the checkpoint's, off]"),
    gain_spread: Optional[str] = typer.Option(None, "--gain-spread", help="the floor's allowance for the sensor's per-pixel gain spread: auto (a stored group's own, its simulator's fixed pattern; 0 for a .dat) | estimate (from the windows, its pixel-white part) | a relative sd from 0 to 0.5 [default: auto]"),
    max_frames: int = typer.Option(0, "--max-frames", help="stop after this many output frames (0 = all)"),
    device: str = typer.Option("auto", "--device", help="auto | cpu | cuda"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    method: str = typer.Option("net", "--method", help="net (the network) | ls | ridge | irls | rwps (a physics solver alone: no checkpoint unless --zeta learned)"),
    anchor: str = typer.Option("none", "--anchor", help="physics methods: mean = anchor each frame to the 17.5 ms spike mean (T = 2 I_mean - zbar (R - T): the level from ~27x more spikes, only R - T from the 7 windows; motion blurs the mean) | none"),
    zeta: Optional[str] = typer.Option(None, "--zeta", help="self (pane fitted to the stream) | learned (the network's parameter branch) | none (the network on zeta = 0: no separable reflection, T is the whole light) | physics | gt (physics methods, group stores only) [default: self (reconstruct.net.net_zeta.NET_DEFAULT_ZETA)]"),
    zeta_fallback: str = typer.Option("auto", "--zeta-fallback", help="the network's zeta where --zeta self cannot calibrate the stream: auto (learned where >= 5 % of pixels still modulate, e.g. under a camera pan, else none) | none (zeta = 0: T is the whole light) | learned"),
    precision: str = typer.Option("float32", "--precision", help="float32 | bfloat16 (autocast of the network; the solver stays float32)"),
    pane_n: Optional[float] = typer.Option(None, "--pane-n", help="the pane's refractive index where known (e.g. from polspike calibrate-pane) [default: --zeta self fits it where the spikes constrain it, else 1.5; --zeta physics: 1.5]"),
    pane_model: str = typer.Option("auto", "--pane-model", help="the pane model where known: single, thin_slab or thick_slab [default auto: --zeta self fits it where the spikes constrain it, else thin_slab; --zeta physics: single]"),
    fov_deg: Optional[float] = typer.Option(None, "--fov-deg", help="--zeta self: the camera's horizontal field of view in degrees where the lens is known [default: a group's scene fov; a .dat: fitted from the spikes, which on narrow views trades against the pane's tilt (docs/selfcal.md)]"),
    pane: Optional[Path] = typer.Option(None, "--pane", help="zeta from pane maps instead of --zeta: the output directory (or maps.exr) of polspike calibrate-pane, e.g. fitted once on a long static recording and used for every recording of the setup, or of an earlier polspike reconstruct whose --zeta self calibrated (its maps.exr: the same pane without calibrating again)"),
    ensemble: int = typer.Option(1, "--ensemble", help="the network averaged over 1, 2, 4 or 8 mirror / transpose symmetries of each window (test-time self-ensemble: that many forward passes, no feature cache; measured by polspike bench ensemble)"),
    follow: bool = typer.Option(False, "--follow", help=".dat: the file is still being written (a camera): output frames as their spikes arrive, the latency on stderr and in reconstruct.json; Ctrl-C stops with every output complete (physics methods on pane maps)"),
    follow_idle: float = typer.Option(5.0, "--follow-idle", help="--follow: stop when the file has not grown for this many seconds (0 = only Ctrl-C stops)"),
    path: str = typer.Option("auto", "--path", help="live (packed reads, fused solver, background encoding: the real-time path; physics methods on pane maps over a .dat) | stream (the general streaming path) | auto (live where it applies)"),
    span: str = typer.Option("auto", "--span", help="the network's long span: plain (every spike of the 17.5 ms around the frame) | compensated (its 7 parts registered onto the centre part first: for a moving camera; reconstruct/stream/motion_span.py) | rir (the parts moved by the windows' RIR shifts interpolated in time: no registration of its own) | auto (per window: rir where the windows follow one velocity that smears the span by 1 px or more, the parts' own registration where the windows are noise-limited, else plain; docs/motion.md)"),
    video_quality: str = typer.Option("fast", "--video-quality", help="live path videos: fast (x264 CRF 23, less encoder CPU) | high (CRF 10, as the streaming path)"),
    video_codec: str = typer.Option("h264", "--video-codec", help="live path videos: h264 (T.mp4, R.mp4, plays everywhere) | h264-gray (4:0:0 .mp4: less encoder CPU; ffmpeg, mpv, VLC, not browsers) | y4m (raw 8-bit T.y4m, R.y4m: no encoder CPU, 100 kB per 400 x 250 frame)"),
    threads: int = typer.Option(0, "--threads", help="torch threads of the streaming path on the CPU [default 0 = auto: the cores idle when the run starts (1-minute load average), at least 1; the live path runs its solver on one]"),
    preview: Optional[bool] = typer.Option(None, "--preview/--no-preview", help="also write preview.mp4 (input | T | R side by side; more encoder CPU than T.mp4 and R.mp4 together) [default: the streaming path yes, the live path no: it keeps up with the camera]"),
    fast: bool = typer.Option(False, "--fast", help="the network's convolutions in channels-last memory format: about 1.9x on them on the CPU, T and R within float32 rounding of the default (reconstruct/net/inference.py)"),
    compile_: bool = typer.Option(False, "--compile", help="torch.compile (inductor) of the network's forward pass: needs a C++ compiler, else runs eagerly with a warning; the first batch compiles (minutes on 2 cores; reconstruct.json 'compile'), T and R within float32 rounding of the default (reconstruct/net/inference.py)"),
    bf16: bool = typer.Option(False, "--bf16", help="the network's learned layers in bfloat16 where the CPU computes it natively (AMX or AVX-512 BF16; elsewhere float32 with a warning), the physics around them as before: 1.2-1.3x end to end on 2 cores, the test split's PSNR unchanged to 0.01 dB (docs/realtime.md)"),
) -> None:
    """Turn a spike group or a .dat into reflection-free T and R video at the output cadence (~343 FPS)."""
    import dataclasses
    import math

    import torch
    from rich.console import Console

    from polinfra.progress import rich_progress
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
    from reconstruct.pane.selfcal import SelfCalConfig
    from reconstruct.stream.sources import dat_source, group_source
    from reconstruct.video.physics import PHYSICS_METHODS, STREAM_ZETA_SOURCES
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    if method not in ("net", *PHYSICS_METHODS):
        raise ConfigError(f"--method {method!r}: choose net or one of {', '.join(PHYSICS_METHODS)}")
    if (fast or compile_ or bf16) and method != "net":
        raise ConfigError(f"{'--fast' if fast else '--compile' if compile_ else '--bf16'} speeds up the network (--method net); a physics solver has no convolutions")
    if zeta is not None and zeta not in (*STREAM_ZETA_SOURCES, "none"):
        raise ConfigError(f"--zeta {zeta!r}: choose one of {', '.join(STREAM_ZETA_SOURCES)}, none")
    from reconstruct.net.net_zeta import NET_FALLBACKS, NET_ZETA_SOURCES

    if method == "net" and zeta not in (None, *NET_ZETA_SOURCES):
        raise ConfigError(f"--zeta {zeta} needs a physics --method (ls, ridge, irls, rwps); the network takes --zeta {', '.join(NET_ZETA_SOURCES)}")
    if method != "net" and zeta == "none":
        raise ConfigError("--zeta none is for the network (--method net): a physics solver cannot separate anything on zeta = 0")
    if zeta_fallback not in NET_FALLBACKS:
        raise ConfigError(f"--zeta-fallback {zeta_fallback!r}: choose {', '.join(NET_FALLBACKS)}")
    if zeta in ("gt", "physics") and input.suffix.lower() == ".dat":
        raise ConfigError(f"--zeta {zeta} needs a stored group's pane maps; a raw .dat has none: use --zeta self or learned")
    if anchor not in ("none", "mean"):
        raise ConfigError(f"--anchor {anchor!r}: choose none or mean")
    if anchor == "mean" and method == "net":
        raise ConfigError("--anchor mean is for the physics methods (ls, ridge, irls, rwps); a use_mean network anchors itself")
    dev = "cuda" if device == "auto" and torch.cuda.is_available() else ("cpu" if device == "auto" else device)
    if precision not in ("float32", "bfloat16"):
        raise ConfigError(f"--precision {precision!r}: choose float32 or bfloat16")
    from reconstruct.net.network import check_ensemble_size

    check_ensemble_size(ensemble, "--ensemble")
    if ensemble > 1 and method != "net":
        raise ConfigError("--ensemble is for the network (--method net); a physics solver is per pixel, mirrors change nothing")
    if pane_model not in ("auto", "single", "thin_slab", "thick_slab"):
        raise ConfigError(f"--pane-model {pane_model!r}: choose auto, single, thin_slab or thick_slab")
    if pane_n is not None and not 1.0 < pane_n <= 4.0:
        raise ConfigError(f"--pane-n {pane_n}: a pane's refractive index lies in (1, 4]")
    if exposure is not None and not exposure > 0:
        raise ConfigError(f"--exposure {exposure}: must be > 0 (thresholds per step per unit radiance)")
    if fov_deg is not None:
        if not 1.0 <= fov_deg <= 170.0:
            raise ConfigError(f"--fov-deg {fov_deg}: a camera's horizontal field of view in degrees, 1 to 170")
        if pane is not None or zeta not in (None, "self"):
            raise ConfigError("--fov-deg is for the self-calibration (--zeta self, the default); " + ("--pane's maps already hold the geometry" if pane is not None else f"--zeta {zeta} does not fit the pane") + ": drop --fov-deg")
    selfcal = None if fov_deg is None else SelfCalConfig(fov_deg=float(fov_deg))
    if pane is not None:
        if zeta is not None:
            raise ConfigError(f"--pane gives zeta (the calibrated maps): drop --zeta {zeta}")
        if pane_n is not None or pane_model != "auto":
            raise ConfigError("--pane fixes the index and the pane model (they are in its maps): drop --pane-n / --pane-model")
    if span not in ("plain", "compensated", "rir", "auto"):
        raise ConfigError(f"--span {span!r}: choose plain, compensated, rir or auto")
    if rir_shifts not in ("window", "chained"):
        raise ConfigError(f"--rir {rir_shifts!r}: choose window or chained (--no-rir turns RIR off)")
    rir = not no_rir
    if threads < 0:
        raise ConfigError(f"--threads {threads}: a number of threads >= 1, or 0 for auto")
    if dev == "cpu":  # the self-calibration and the stream alike: no more threads than idle cores (reconstruct.video.stream.cpu_threads)
        from reconstruct.video.stream import cpu_threads

        threads = cpu_threads(threads)
        torch.set_num_threads(threads)
    cfg = ReconstructConfig(window_steps=window_steps, stride_deg=stride_deg, exposure=exposure or 1.0, frames=frames, max_frames=max_frames, precision=precision,
                            preview=True if preview is None else preview, threads=threads, span=span, rir=rir_shifts)
    if path not in ("auto", "live", "stream"):
        raise ConfigError(f"--path {path!r}: choose auto, live or stream")
    if video_quality not in ("fast", "high"):
        raise ConfigError(f"--video-quality {video_quality!r}: choose fast or high")
    if video_codec not in ("h264", "h264-gray", "y4m"):
        raise ConfigError(f"--video-codec {video_codec!r}: choose h264, h264-gray or y4m")
    is_dat = input.suffix.lower() == ".dat"
    if (follow or path == "live") and (not is_dat or method == "net" or anchor != "none"):
        raise ConfigError(f"{'--follow' if follow else '--path live'} runs a physics solver (--method ls, ridge, irls, rwps) on pane maps over a .dat, without --anchor mean")
    if video_codec != "h264" and (not is_dat or method == "net" or anchor != "none" or path == "stream"):
        raise ConfigError(f"--video-codec {video_codec} is an option of the live path (physics methods on pane maps over a .dat); the streaming path writes H.264")
    if follow and path == "stream":
        raise ConfigError("--follow runs on the live path: drop --path stream")
    if follow_idle < 0:
        raise ConfigError(f"--follow-idle {follow_idle}: seconds >= 0")
    reader = None
    if is_dat:
        missing = [n for n, v in (("--height", height), ("--width", width), ("--phi0-deg", phi0_deg), ("--rev-per-s", rev_per_s)) if v is None]
        if missing:
            raise ConfigError(f"a .dat input needs {', '.join(missing)} (frame size and polarizer calibration)")
        if follow:
            from polspike.commands.live_cmd import wait_for_dat
            from reconstruct.stream.packed import packed_source

            start = max(4000, int(round(0.2 * rate_hz)))  # the exposure estimate's steps (and the self-calibration's 0.1 s)
            reader = wait_for_dat(input, height, width, start, follow_idle)
            src = packed_source(reader, start, math.radians(phi0_deg), rev_per_s, rate_hz, input.name)
        else:
            src = dat_source(input, height, width, math.radians(phi0_deg), rev_per_s, rate_hz, cfg.chunk_steps)
    elif input.is_dir():
        src = group_source(input, cfg.chunk_steps)
    else:
        raise ConfigError(f"input {input} is neither a .dat file nor a spike group directory")
    from reconstruct.net.checkpoint import floor_overrides, resolve_weights

    fa = floor_overrides(True, floor_anchor, gain_spread, floor_layers)  # a bad --floor-anchor or --gain-spread: one line
    load = lambda: load_model(weights or DEFAULT_WEIGHTS, dev, use_rir=rir, floor=floor, **fa)[0]  # noqa: E731
    net_model = load() if method == "net" else None  # a bad checkpoint is reported before the stream is read
    if net_model is not None and (fast or compile_ or bf16):
        from reconstruct.net.inference import accelerate

        stats = accelerate(net_model, fast=fast, compile_=compile_, bf16=bf16)
        speed = {"fast": fast, "bf16": stats.bf16, "compile": stats.summary()}
    else:
        speed = {}
    gs_used = None if net_model is None else net_model.cfg.floor_gain_spread
    from reconstruct.net.network import GAIN_SPREAD_AUTO

    if gs_used == GAIN_SPREAD_AUTO:  # a stored group's own sensor, 0 for a .dat
        from reconstruct.net.checkpoint import set_stream_gain_spread
        from spike_sim.config import pixel_gain_spread
        from spike_sim.store import open_group

        gs_used = 0.0
        if input.is_dir():
            with open_group(input) as g:
                gs_used = pixel_gain_spread(g.json_attr("config_json") or {"fixed_pattern": False})
        set_stream_gain_spread(net_model, gs_used)
    anchor_used = net_model.cfg.floor_anchor if net_model is not None else None
    layers_used = bool(net_model.cfg.floor_layers) if net_model is not None and anchor_used in ("best", "blend") else None
    if net_model is not None and ensemble > 1:
        from reconstruct.net.network import SymmetryEnsemble

        net_model = SymmetryEnsemble(net_model, ensemble).eval()
    exposure_info = {"exposure_source": "stored in the group" if src.exposure is not None and exposure is None else "--exposure"}
    if exposure is not None:
        src = dataclasses.replace(src, exposure=None)  # --exposure forces the value, also over a group's stored one
    elif src.exposure is None:
        from reconstruct.stream.exposure import estimate_source_exposure

        est = estimate_source_exposure(src)
        cfg = dataclasses.replace(cfg, exposure=est.exposure)
        exposure_info = {"exposure_source": "estimated", "exposure_estimate": est.summary()}
    info = None
    if pane is not None:
        from reconstruct.video.physics import PhysicsModel, calibrated_pane_maps

        maps = calibrated_pane_maps(pane, src.height, src.width)
        span = src.window_span_rad(window_steps)
        info = {"zeta": f"pane ({pane})", "selfcal": None}
        if method == "net":
            from reconstruct.net.net_zeta import MapsZetaNet

            model = MapsZetaNet(net_model, maps, span)
        else:
            model = PhysicsModel(method, maps=maps, span_rad=span, rir=rir, anchor=anchor)
    elif method == "net":
        from reconstruct.net.net_zeta import NET_DEFAULT_ZETA

        model = net_model
        zeta = zeta or NET_DEFAULT_ZETA
        if zeta in ("self", "none"):
            from reconstruct.net.net_zeta import build_net_zeta_model

            model, info = build_net_zeta_model(model, zeta, src, group_dir=None if input.suffix.lower() == ".dat" else input, window_steps=window_steps,
                                               exposure=None if src.exposure is not None else cfg.exposure, fallback=zeta_fallback, pane_n=pane_n, pane_model=pane_model, selfcal=selfcal)
            if str(info["zeta"]).startswith("none"):
                # zeta = 0: the physics core is the windows' plain mean, no separation to hold the network to
                from reconstruct.net.network import NetConfig

                for m in net_model.modules():
                    if isinstance(getattr(m, "cfg", None), NetConfig):
                        m.cfg = dataclasses.replace(m.cfg, floor=False)
                floor = False
    else:
        from reconstruct.video.physics import build_physics_model

        model, info = build_physics_model(method, zeta or "self", src, group_dir=None if input.suffix.lower() == ".dat" else input, window_steps=window_steps,
                                          exposure=None if src.exposure is not None else cfg.exposure, rir=rir, load_learned=load, anchor=anchor,
                                          pane_n=pane_n, pane_model=pane_model, selfcal=selfcal)
    maps_out = _write_selfcal_maps(out, model, info)
    meta = {**exposure_info, "method": method, "weights": str(resolve_weights(weights)) if net_model is not None else None, "anchor": anchor, "ensemble": ensemble, "rir": rir, "floor": floor if method == "net" else None, "floor_anchor": anchor_used if floor else None, "floor_layers": layers_used if floor else None, "floor_gain_spread": gs_used if floor else None, "span": span if method == "net" else None, "zeta": info["zeta"] if info is not None else "learned", **speed}
    live = is_dat and path != "stream" and method != "net" and getattr(model, "maps", None) is not None and anchor == "none" and dev == "cpu"
    if not live and (follow or path == "live" or video_codec != "h264"):  # what the checks above could not know: maps, device
        what = "--follow" if follow else "--path live" if path == "live" else f"--video-codec {video_codec} (an option of the live path)"
        raise ConfigError(f"{what} needs pane maps (zeta {info['zeta'] if info else 'learned'} is not) on the CPU")
    if live:
        from polspike.commands.live_cmd import run_live
        from reconstruct.stream.packed import PackedDat
        from reconstruct.video.live import LiveConfig

        lcfg = LiveConfig(window_steps=window_steps, stride_deg=stride_deg, frames=frames, max_frames=max_frames, idle_s=follow_idle, video_quality=video_quality,
                          video_codec=video_codec, preview=bool(preview))
        reader = reader or PackedDat(input, height, width)
        s = run_live(reader, model, out, lcfg, phi0_rad=math.radians(phi0_deg), rev_per_s=rev_per_s, rate_hz=rate_hz,
                     exposure=src.exposure if src.exposure is not None else cfg.exposure, name=input.name, follow=follow, meta=meta, quiet=quiet)
        s["tfp_corr_mean"] = None
    else:
        with rich_progress("reconstruct", enabled=not quiet) as cb:
            s = reconstruct_stream(src, model, out, cfg, device=dev, progress=cb, meta=meta)
    c = Console()
    if info is not None:
        from polinfra.atomic import write_json

        write_json(out / ("zeta.json" if method == "net" else "physics.json"), {"method": method, **info, "pane_maps": maps_out})
        sc = info["selfcal"]
        if sc and sc["ok"]:
            c.print(f"{method} on self-calibrated zeta: pane tilt {sc['tilt_deg']:.1f} deg, azimuth {sc['azimuth_deg']:.1f} deg, fov {sc['fov_deg']:.1f} deg{' (fitted: give --fov-deg if the lens is known)' if sc['fov_fitted'] else ''}, {sc['model']} n {sc['n']:g}")
        else:
            c.print(f"{method} on zeta: {info['zeta']}" + (f" ({sc['reason']})" if sc else ""))
    if exposure_info["exposure_source"] == "estimated":
        e = exposure_info["exposure_estimate"]
        c.print(f"exposure estimated from the stream: {e['exposure']:.4g} thresholds per step per unit radiance ({e['quantile']:g}th percentile rate {e['rate_quantile']:.4f} spikes/step{'; saturated: a lower bound' if e['saturated'] else ''}); force one with --exposure")
    c.print(f"{s['frames']} frames at {s['fps']:.1f} FPS from {s['input']} ({s['size'][1]}x{s['size'][0]}); NaN frames: {s['nan_frames']}")
    if s["tfp_corr_mean"] is not None:
        c.print(f"correlation of T with the plain TFP image: {s['tfp_corr_mean']:.3f}")
    c.print(f"wrote {', '.join(s['outputs']) or 'no video'} to {out} ({s['seconds']:.1f} s)")


def heldout_mean_steps() -> int:
    """Steps of the long spike mean a ``use_mean`` network is given in the held-out windows (as trained: the default
    sensor's rate, 350 at 20 kHz).
    """
    from reconstruct.stream.groups import spike_mean_steps
    from spike_sim.config import preset

    return spike_mean_steps(preset("default").rate_hz)


def heldout_wide_steps() -> int:
    """Steps of the wide window a network with ``wide_input`` is given in the held-out windows (as trained: the default
    sensor's rate, 30 rev/s, 31.5 deg; 57 at 20 kHz).
    """
    from reconstruct.stream.groups import wide_window_steps
    from spike_sim.config import preset

    return wide_window_steps(preset("default").rate_hz, 30.0, 31.5)


def heldout_inputs(model) -> dict:
    """The long-span keywords of :func:`heldout_test_set` a network takes (``mean_steps``, ``wide_steps``)."""
    need = model.cfg.inputs
    return {"mean_steps": heldout_mean_steps() if "I_mean" in need else 0, "wide_steps": heldout_wide_steps() if "I_wide" in need else 0}


def heldout_test_set(crop: int = 64, items: int = 96, seed: int = 20_000, manifest: str = "", scenes: int = 10, scene_seed: int = 0, light: str = "range", mean_steps: int = 0, wide_steps: int = 0):
    """The model card's test set: on-the-fly windows of the test groups of ``manifest`` (else of ``scenes`` sampled test scenes).

    ``light``: "range" = the exposure drawn from the default range (the shipped v1/v2 scores), "group" = each manifest
    group's own sensor and light level (paper.toml's dim-to-bright range).  ``mean_steps``: also the long spike mean
    (a ``use_mean`` network's input); ``wide_steps``: also the wide windows (a network with ``wide_input``).
    """
    from polinfra.errors import ConfigError
    from polspike.pipeline.train_windows import GeneratorWindows, manifest_scenes, scene_pool
    from reconstruct.net.onthefly import OnTheFlyWindows, WindowConfig

    if light not in ("range", "group"):
        raise ConfigError(f"light = {light!r}: choose range or group")
    if light == "group":
        if not manifest:
            raise ConfigError("light = group takes each manifest group's sensor: give a manifest")
        sc, sims = manifest_scenes(manifest, "test", with_sensor=True)
        w = WindowConfig(crop=crop, sim_preset="group", exposure_source="group", mean_steps=mean_steps, wide_steps=wide_steps)
        return OnTheFlyWindows(GeneratorWindows(sc, w, sims=sims), length=items, seed=seed)
    sc = manifest_scenes(manifest, "test") if manifest else scene_pool(scenes, scene_seed, "test")
    return OnTheFlyWindows(GeneratorWindows(sc, WindowConfig(crop=crop, mean_steps=mean_steps, wide_steps=wide_steps)), length=items, seed=seed)


@app_typer.command("evaluate-checkpoint")
def evaluate_checkpoint_cmd(
    weights: Optional[Path] = typer.Argument(None, help="checkpoint [default: the shipped reconstruct/weights default, reconstruct.net.checkpoint.DEFAULT_WEIGHTS]"),
    out: Optional[Path] = typer.Option(None, "--out", help="write scores.json and scores.md here"),
    items: int = typer.Option(96, "--items", help="test windows"),
    crop: int = typer.Option(64, "--crop", help="test crop side (multiple of 4)"),
    seed: int = typer.Option(20_000, "--seed", help="test-set seed (window positions, crops, sensor noise)"),
    manifest: str = typer.Option("datasets/manifests/paper_v1.toml", "--manifest", help="windows of this manifest's test groups (default: the shipped checkpoints' split; '' = sampled test scenes)"),
    rir: Optional[bool] = typer.Option(None, "--rir/--no-rir", help="RIR alignment [default: as trained]"),
    device: str = typer.Option("auto", "--device", help="auto | cpu | cuda"),
    threads: int = typer.Option(0, "--threads", help="torch CPU threads (0 = torch default)"),
    solver: Optional[str] = typer.Option(None, "--solver", help="ls | ridge | irls | rwps: physics solver before the same refinement (supp. Table 3) [default: as trained]"),
    light: str = typer.Option("range", "--light", help="range: exposures from the default range (the shipped v1/v2 scores); group: each manifest group's own sensor and light level"),
) -> None:
    """PSNR / SSIM of T on the held-out synthetic test set: full network, RWPS-only (learned zeta, w), RWPS with GT zeta, TFP."""
    import torch
    from rich.console import Console
    from rich.table import Table

    from polinfra.atomic import ensure_dir, write_json, write_text
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
    from reconstruct.net.train import evaluate_model

    if threads > 0:
        torch.set_num_threads(threads)
    dev = "cuda" if device == "auto" and torch.cuda.is_available() else ("cpu" if device == "auto" else device)
    over = ({} if rir is None else {"use_rir": rir}) | ({} if solver is None else {"solver_method": solver})
    model, data = load_model(weights or DEFAULT_WEIGHTS, dev, **over)
    ds = heldout_test_set(crop, items, seed, manifest, light=light, **heldout_inputs(model))
    m = evaluate_model(model, ds, batch_size=8, device=dev, ssim=True)
    rows = [
        ("T: full network", "T"), ("T: RWPS-only, learned zeta and w (T^)", "T_base"), ("T: RWPS, ground-truth zeta (oracle)", "T_oracle"), ("T: TFP, 2 x window mean", "T_tfp"),
        ("R: full network", "R"), ("R: RWPS-only, learned zeta and w (R^)", "R_base"), ("R: RWPS, ground-truth zeta (oracle)", "R_oracle"),
    ]
    tab = Table(title=f"test split ({manifest or 'sampled test scenes'}): {items} windows of {crop}x{crop}, seed {seed}")
    tab.add_column("method")
    tab.add_column("PSNR (dB)", justify="right")
    tab.add_column("SSIM", justify="right")
    md = ["| method | PSNR (dB) | SSIM |", "|---|---:|---:|"]
    for name, k in rows:
        tab.add_row(name, f"{m[f'psnr_{k}']:.2f}", f"{m[f'ssim_{k}']:.3f}")
        md.append(f"| {name} | {m[f'psnr_{k}']:.2f} | {m[f'ssim_{k}']:.3f} |")
    if "psnrrefl_T" in m:
        md.append("")
        md.append(f"Reflection-affected pixels only (reflected share >= 0.2: {100 * m['refl_fraction']:.1f} % of the pixels), PSNR of T (dB):")
        md.append("")
        md.append("| full network | RWPS-only | RWPS, GT zeta | TFP |")
        md.append("|---:|---:|---:|---:|")
        md.append(f"| {m['psnrrefl_T']:.2f} | {m['psnrrefl_T_base']:.2f} | {m['psnrrefl_T_oracle']:.2f} | {m['psnrrefl_T_tfp']:.2f} |")
        tab.add_row(f"T on reflection-affected pixels ({100 * m['refl_fraction']:.1f} %): full / RWPS-only / oracle / TFP",
                    f"{m['psnrrefl_T']:.2f} / {m['psnrrefl_T_base']:.2f} / {m['psnrrefl_T_oracle']:.2f} / {m['psnrrefl_T_tfp']:.2f}", "")
    Console().print(tab)
    if out:
        ensure_dir(out)
        write_json(out / "scores.json", {"weights": str(weights or DEFAULT_WEIGHTS), "manifest": manifest, "items": items, "crop": crop, "seed": seed, "step": data.get("step"), "rir": bool(model.cfg.use_rir), "solver": model.cfg.solver_method, "metrics": m})
        write_text(out / "scores.md", "\n".join(md) + "\n")


from polspike.cli import bench_app  # noqa: E402


@bench_app.command("reconstruct-net")
def bench_reconstruct_net_cmd(
    weights: Optional[Path] = typer.Option(None, "--weights", help="checkpoint of the network under test [default: the shipped default checkpoint]"),
    reference: Optional[Path] = typer.Option(None, "--reference", help="reference checkpoint measured in the same run [default: reconstruct/weights/polspike_v1.pt]"),
    height: int = typer.Option(250, "--height", help="frame height H, pixels"),
    width: int = typer.Option(400, "--width", help="frame width W, pixels"),
    frames: int = typer.Option(2, "--frames", help="timed output frames per setting (best kept)"),
    stream_frames: int = typer.Option(12, "--stream-frames", help="output frames of the end-to-end `polspike reconstruct` run of the network under test (the reference runs 2); 0 = skip"),
    train_steps: int = typer.Option(20, "--train-steps", help="timed training steps of the network under test (the reference runs a third as many, at least 4); 0 = skip"),
    variants: bool = typer.Option(True, "--variants/--no-variants", help="also time channels-last and bf16 autocast"),
    compile_: bool = typer.Option(False, "--compile", help="also time torch.compile (needs a C++ compiler; minutes of compile time)"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="write the results here as JSON (and the table beside it as .md)"),
    threads: int = typer.Option(2, "--threads", help="frame rates are timed on 1 and on this many torch threads (1 = one thread only)"),
) -> None:
    """Reference (v1) and new network in one run: GFLOP per frame, parameters, frames/s on 1 and 2 threads, `polspike reconstruct` frames/s, training throughput."""
    import dataclasses

    import torch

    torch.set_num_threads(1)  # before any torch work: the training part forks a DataLoader worker (GNU OpenMP forbids fork after a parallel region)
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.config import from_dict, load_toml
    from reconstruct.evaluate.bench import bench_reconstruct_net, net_table
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, V1_WEIGHTS, load_model
    from reconstruct.net.train import TrainConfig

    ref_path, new_path = reference or V1_WEIGHTS, weights or DEFAULT_WEIGHTS
    models, train_cfgs = {}, {}
    for label, path in (("reference", ref_path), ("new", new_path)):
        model, data = load_model(path, "cpu", use_rir=False)
        name = f"{model.cfg.arch} ({Path(path).name})"
        models[name] = model
        base = from_dict(TrainConfig, load_toml(Path(__file__).resolve().parents[2] / "reconstruct" / "configs" / ARCH_BASE_PRESETS[model.cfg.arch]))
        # the items a network reads: the long spike mean / wide windows where its config takes them
        train_cfgs[name] = dataclasses.replace(base, net=model.cfg, seed=0, window=dataclasses.replace(base.window, **heldout_inputs(model)))
    names = list(models)
    train_set = None
    if train_steps > 0:
        train_set, _ = on_the_fly_sets(train_cfgs[names[-1]])  # the network under test's items (a superset of v1's)
        for j in range(len(train_set.source.scenes)):  # build every scene's maps once, before timing (workers fork with them)
            train_set.source._scene(j)
    res = bench_reconstruct_net(
        models, height=height, width=width, frames=frames, threads=(1,) if threads <= 1 else (1, threads),
        stream_frames=({names[0]: 2, names[1]: stream_frames} if stream_frames > 0 else None),
        train_cfgs=train_cfgs if train_steps > 0 else None, train_set=train_set,
        train_steps={names[0]: max(4, train_steps // 3), names[1]: train_steps}, variants=variants, compile_=compile_,
    )
    table = net_table(res)
    Console().print(table)
    if json_out:
        write_json(json_out, res)
        write_text(Path(json_out).with_suffix(".md"), table)


@bench_app.command("train-ddp")
def bench_train_ddp_cmd(
    out: Path = typer.Option(Path("out/bench_train_ddp"), "--out", help="working directory of the benchmark runs"),
    steps: int = typer.Option(40, "--steps", help="training steps per setting"),
    warmup: int = typer.Option(5, "--warmup", help="steps left out of the timing"),
    batch: int = typer.Option(8, "--batch", help="global batch (windows per step, every setting)"),
    crop: int = typer.Option(32, "--crop", help="window side (multiple of 4)"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="write the results here as JSON (and the table beside it as .md) [default: OUT/bench_train_ddp.json]"),
) -> None:
    """Training throughput of 2 data-parallel processes against 1 process (1 and 2 threads), at equal global batch, in one run."""
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polspike.pipeline.train_bench import bench_train_ddp, ddp_table

    res = bench_train_ddp(out, steps=steps, warmup=warmup, batch=batch, crop=crop)
    table = ddp_table(res)
    Console().print(table)
    jp = json_out or out / "bench_train_ddp.json"
    write_json(jp, res)
    write_text(Path(jp).with_suffix(".md"), table)
