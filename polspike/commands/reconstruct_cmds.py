"""``polspike evaluate`` (physics solvers and baselines on a test split) and ``polspike bench reconstruct``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer, bench_app


@app_typer.command("evaluate")
def evaluate_cmd(
    dataset: str = typer.Argument(..., help="dataset directory (dataset.json + group stores), one group directory, or 'synthetic[:SEED]' (closed-form set made in-process)"),
    split: str = typer.Option("test", "--split", help="split listed in dataset.json"),
    method: str = typer.Option("ls,ridge,irls,rwps", "--method", help="comma-separated methods: ls, ridge, irls, rwps (physics solvers), full (the network of --checkpoint)"),
    zeta: str = typer.Option("gt", "--zeta", help="zeta source of the solvers: gt (group pane maps), physics (Fresnel from the calibrated pane), learned (network parameter branch), self (pane fitted to the stream; also the network's unless --net-zeta)"),
    out: Path = typer.Option(Path("out/evaluate"), "--out", help="output folder (results.csv/.md/.json, figure.png, config.json)"),
    n_obs: int = typer.Option(7, "--n-obs", help="observations per output frame N = 2K + 1"),
    dt_ms: float = typer.Option(0.65, "--dt-ms", help="aggregation window, milliseconds (odd number of steps)"),
    stride_deg: float = typer.Option(31.5, "--stride-deg", help="polarizer rotation between output frames, degrees"),
    rir: bool = typer.Option(True, "--rir/--no-rir", help="reflection-invariant registration of each window (full: the without-RIR ablation)"),
    floor: bool = typer.Option(True, "--floor/--no-floor", help="full: the network's data-consistency floor, as polspike reconstruct runs it (--no-floor: the refinement's output as it is)"),
    floor_anchor: Optional[str] = typer.Option(None, "--floor-anchor", help="full with the floor: what it falls back to where the data check fails: blend (per pixel the RWPS and the best closed-form physics, weighed by their error powers) | rwps (the physics-only RWPS) | best (the best closed-form physics alone) [default: the checkpoint's, blend]"),
    gain_spread: str = typer.Option("", "--gain-spread", help="full with the floor: its allowance for the sensor's per-pixel gain spread: auto (each group's own sensor) | estimate (from the windows, its pixel-white part) | a relative sd from 0 to 0.5 [default: auto]"),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="network checkpoint for --method full / --zeta learned (a file, or default | fast) [default: the shipped reconstruct/weights default, reconstruct.net.checkpoint.DEFAULT_WEIGHTS]"),
    no_attention: bool = typer.Option(False, "--no-attention", help="full: the checkpoint is the without-angle-attention ablation (trained so)"),
    no_conf: bool = typer.Option(False, "--no-conf", help="full: the without-Conf ablation (trained so, else a test-time ablation)"),
    net_tile: int = typer.Option(256, "--net-tile", help="full: network tile size in pixels (0 = whole frame)"),
    bf16: bool = typer.Option(False, "--bf16", help="full: the network's learned layers in bfloat16 where the CPU has AMX or AVX-512 BF16 (as polspike reconstruct --bf16), to measure its quality change"),
    max_frames: int = typer.Option(0, "--max-frames", help="at most this many output frames per group (0 = all)"),
    pane_n: float = typer.Option(1.5, "--pane-n", help="physics zeta: calibrated refractive index"),
    pane_model: str = typer.Option("single", "--pane-model", help="physics zeta: single, thin_slab or thick_slab"),
    dtype: str = typer.Option("float32", "--dtype", help="solver dtype: float32 or float64"),
    device: str = typer.Option("cpu", "--device", help="torch device for the solvers and the network: cpu, cuda or auto"),
    self_fov: str = typer.Option("scene", "--self-fov", help="self zeta: the field of view the self-calibration is given: scene (the group's) or fitted (withheld, fitted from the spikes as for a .dat without --fov-deg)"),
    sweep: bool = typer.Option(False, "--sweep", help="also run the window analysis (N in 5,7,9 x dt in 0.30,0.65,1.10 ms; supp. Table 1)"),
    by_regime: bool = typer.Option(False, "--by-regime", help="stress table: every solver with each zeta of --regime-zetas, baselines and the network (unless --no-net), one row per regime level of the group names (datasets/manifests/stress.toml)"),
    regime_zetas: str = typer.Option("gt,learned", "--regime-zetas", help="--by-regime: comma-separated zeta sources (gt, physics, learned, self)"),
    net: bool = typer.Option(True, "--net/--no-net", help="--by-regime: include the network (full) column"),
    net_zeta: str = typer.Option("", "--net-zeta", help="full: zeta of the network's solver and refinement: learned (its own), self, gt, physics or none (zeta = 0) [default: self with --zeta self, else learned]"),
    net_fallback: str = typer.Option("auto", "--net-fallback", help="full with net zeta self: the zeta where a group does not self-calibrate: auto (learned where >= 5 % of pixels still modulate, else none) | none (zeta = 0, T is the whole light) | learned"),
    net_ensemble: int = typer.Option(1, "--net-ensemble", help="full: average the network over 1, 2, 4 or 8 mirror / transpose symmetries of each window (test-time self-ensemble; that many forward passes)"),
    net_zetas: str = typer.Option("learned", "--net-zetas", help="--by-regime: comma-separated zeta sources of the network columns (learned -> net, self -> net@self, none -> net@none)"),
    lambda_map: str = typer.Option("adaptive", "--lambda-map", help="rwps Conf -> lambda: adaptive (fitted physics default) or fixed (the original mapping)"),
    anchor: str = typer.Option("none", "--anchor", help="mean: also score every method anchored to the 17.5 ms spike mean (rows and columns '+mean'; T = 2 I_mean - zbar (R^ - T^)) and the physics of the whole span's first harmonic (row 'span'); none: off"),
    synthetic_groups: int = typer.Option(4, "--synthetic-groups", help="synthetic: number of groups"),
    synthetic_frames: int = typer.Option(20, "--synthetic-frames", help="synthetic: frames per group"),
    synthetic_noise: str = typer.Option("poisson", "--synthetic-noise", help="synthetic: poisson, integrate_fire or none"),
    synthetic_size: str = typer.Option("200x125", "--synthetic-size", help="synthetic: WxH"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    executor: str = typer.Option("local", "--executor", help="local (the groups one after another in this process) or dask (one task per group on a Dask cluster; the same tables)"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address tcp://HOST:8786 (implies --executor dask; the workers must see the dataset, e.g. on a shared filesystem) [default with --executor dask: a local cluster of --workers processes]"),
    workers: int = typer.Option(2, "--workers", help="--executor dask without --scheduler: worker processes of the local cluster (one thread each)"),
) -> None:
    """Score the physics solvers and/or the network (with TFP / best-frame baselines) on every test group: PSNR/SSIM of T and R."""
    from rich.console import Console

    from polinfra.config import from_dict
    from polinfra.errors import ConfigError
    from polinfra.progress import rich_progress
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups, load_groups, markdown_table, write_report
    from reconstruct.evaluate.paper_table import sweep_markdown, window_sweep
    from reconstruct.net.checkpoint import floor_overrides
    from reconstruct.stream.synthetic import SyntheticConfig

    floor_overrides(floor, floor_anchor, gain_spread)  # a bad --floor-anchor or --gain-spread: one line, before any work
    cfg = from_dict(
        EvalConfig,
        {"n_obs": n_obs, "dt_ms": dt_ms, "stride_deg": stride_deg, "methods": method, "zeta": zeta, "rir": rir, "max_frames": max_frames, "pane_n": pane_n, "pane_model": pane_model, "dtype": dtype, "device": device,
         "checkpoint": str(checkpoint or ""), "no_attention": no_attention, "no_conf": no_conf, "net_tile": net_tile, "bf16": bf16, "net_zeta": net_zeta, "net_fallback": net_fallback, "net_ensemble": net_ensemble, "anchor": anchor, "self_fov": self_fov, "floor": floor, "floor_anchor": floor_anchor or "", "gain_spread": gain_spread},
        where="command line",
    )
    try:
        w, h = (int(x) for x in synthetic_size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--synthetic-size {synthetic_size!r} is not WxH; write e.g. 200x125") from None
    syn = from_dict(SyntheticConfig, {"n_groups": synthetic_groups, "n_frames": synthetic_frames, "noise": synthetic_noise, "width": w, "height": h}, where="command line")
    con = Console()
    if executor not in ("local", "dask"):
        raise ConfigError(f"--executor {executor!r} is unknown; choose local or dask")
    dask = executor == "dask" or bool(scheduler)
    if dask and by_regime:
        raise ConfigError("--by-regime runs in this process; drop --executor dask / --scheduler")
    if not dask:
        with rich_progress("load groups", enabled=not quiet) as cb:
            groups = load_groups(dataset, split, cfg, syn, progress=cb)
    from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, SolverConfig

    if lambda_map not in ("adaptive", "fixed"):
        raise ConfigError(f"--lambda-map {lambda_map!r}: choose adaptive or fixed")
    solver_cfg = PHYSICS_SOLVER_CONFIG if lambda_map == "adaptive" else SolverConfig()
    if by_regime:
        from polinfra.atomic import write_json, write_text
        from reconstruct.evaluate.regimes import evaluate_by_regime, regime_markdown, regime_report

        zs = [z.strip() for z in regime_zetas.split(",") if z.strip()]
        nzs = [z.strip() for z in net_zetas.split(",") if z.strip()]
        with rich_progress("evaluate by regime", enabled=not quiet) as cb:
            res = evaluate_by_regime(groups, cfg, zs, network=net, solver_cfg=solver_cfg, progress=cb, net_zetas=nzs)
        res["checkpoint"] = str(checkpoint) if checkpoint else "shipped default"
        write_json(out / "by_regime.json", res)
        write_text(out / "by_regime.md", f"# Stress set per regime level ({dataset}, split {split}; network: {res['checkpoint']})\n\n" + regime_report(res))
        Console().print("PSNR of T (dB)\n" + regime_markdown(res) + "\nPSNR of R (dB)\n" + regime_markdown(res, "rows_R") + "\nPSNR of R where the reflection is >= 20 % of the light (dB)\n" + regime_markdown(res, "rows_R_share"))
        Console().print(f"[green]wrote[/] {out / 'by_regime.md'}, {out / 'by_regime.json'}")
        return
    with rich_progress("evaluate", enabled=not quiet) as cb:
        if dask:
            from reconstruct.evaluate.harness import group_loaders
            from reconstruct.evaluate.parallel import evaluate_groups_dask

            report = evaluate_groups_dask(group_loaders(dataset, split, cfg, syn), cfg, solver_cfg, scheduler=scheduler, workers=workers, progress=cb)
        else:
            report = evaluate_groups(groups, cfg, solver_cfg, progress=cb)
    paths = write_report(report, out)
    con.print(markdown_table(report, overall_only=True))
    if sweep:
        from polinfra.atomic import write_json, write_text

        rows = window_sweep(None, dataset, split, cfg, synthetic=syn, solver_cfg=solver_cfg)
        if not rows:  # an empty table would read as a result
            raise ConfigError("--sweep: no group is long enough for the sweep's windows (N up to 9 at dt up to 1.10 ms): no output frame; use longer groups (synthetic: --synthetic-frames 20)")
        write_json(out / "window_sweep.json", rows)
        write_text(out / "window_sweep.md", "# Window analysis (supp. Table 1)\n\n" + sweep_markdown(rows))
        con.print(sweep_markdown(rows))
    con.print(f"[green]wrote[/] {', '.join(str(p) for p in paths.values())}")


@app_typer.command("evaluate-paper")
def evaluate_paper_cmd(
    dataset: str = typer.Argument(..., help="dataset directory with a test split (e.g. out/datasets/eval_paper), one group directory, or 'synthetic[:SEED]'"),
    full: list[Path] = typer.Option([], "--full", help="checkpoint of the full network (repeat for seeds: the column is their mean) [default: the shipped default]"),
    no_rir: list[Path] = typer.Option([], "--no-rir", help="checkpoint(s) trained without RIR [default: --full with RIR off at test time]"),
    no_attention: list[Path] = typer.Option([], "--no-attention", help="checkpoint(s) trained without angle attention [default: column omitted]"),
    no_conf: list[Path] = typer.Option([], "--no-conf", help="checkpoint(s) trained without Conf [default: --full with Conf zeroed at test time]"),
    solvers: str = typer.Option("ls,ridge,irls,rwps", "--solvers", help="supp. Table 3 solvers, comma-separated ('' = skip the table)"),
    zeta: str = typer.Option("self", "--zeta", help="zeta of the physics RWPS column: self (fitted to each group's stream), gt, physics or learned"),
    net_zeta: str = typer.Option("self", "--net-zeta", help="zeta of every network column: self (the pane fitted to each group's stream; where it refuses, zeta = 0 or the learned zeta as reconstruct.net.net_zeta.fallback_for decides: how polspike reconstruct runs the network) or learned (its own), gt, physics, none"),
    split: str = typer.Option("test", "--split", help="split listed in dataset.json"),
    out: Path = typer.Option(Path("out/evaluate_paper"), "--out", help="output folder (paper_table.md/.csv/.json)"),
    n_obs: int = typer.Option(7, "--n-obs", help="observations per output frame N"),
    dt_ms: float = typer.Option(0.65, "--dt-ms", help="aggregation window, milliseconds"),
    max_frames: int = typer.Option(0, "--max-frames", help="at most this many output frames per group (0 = all)"),
    net_tile: int = typer.Option(256, "--net-tile", help="network tile size in pixels (0 = whole frame)"),
    net_ensemble: int = typer.Option(1, "--net-ensemble", help="average every network column over 1, 2, 4 or 8 mirror / transpose symmetries of each window (test-time self-ensemble; that many forward passes)"),
    device: str = typer.Option("cpu", "--device", help="cpu, cuda or auto"),
    threads: int = typer.Option(0, "--threads", help="torch CPU threads (0 = torch default)"),
    floor: bool = typer.Option(True, "--floor/--no-floor", help="every network column: the network's data-consistency floor, as polspike reconstruct runs it (--no-floor: the refinement's output as it is)"),
    floor_anchor: Optional[str] = typer.Option(None, "--floor-anchor", help="with the floor: what it falls back to where the data check fails: blend (per pixel the RWPS and the best closed-form physics, weighed by their error powers) | rwps (the physics-only RWPS) | best (the best closed-form physics alone) [default: the checkpoint's, blend]"),
    gain_spread: str = typer.Option("", "--gain-spread", help="full with the floor: its allowance for the sensor's per-pixel gain spread: auto (each group's own sensor) | estimate (from the windows, its pixel-white part) | a relative sd from 0 to 0.5 [default: auto]"),
    synthetic_groups: int = typer.Option(4, "--synthetic-groups", help="synthetic: number of groups"),
    synthetic_size: str = typer.Option("200x125", "--synthetic-size", help="synthetic: WxH"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """The test split in the paper's layout: Table 1 (Ours and the three ablations, mean over the given seeds, with TFP and physics RWPS) and supp. Table 3 (solver-only / final per solver)."""
    import csv
    import io

    import torch
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.config import from_dict
    from polinfra.errors import CheckpointError
    from polinfra.progress import rich_progress
    from reconstruct.evaluate.harness import EvalConfig, load_groups
    from reconstruct.evaluate.paper_table import paper_csv, paper_markdown, paper_tables
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS

    if threads > 0:
        torch.set_num_threads(threads)
    for p in [*full, *no_rir, *no_attention, *no_conf]:
        if not p.is_file():
            raise CheckpointError(f"checkpoint not found: {p}")
    from polinfra.errors import ConfigError
    from reconstruct.net.checkpoint import floor_overrides
    from reconstruct.stream.synthetic import SyntheticConfig

    floor_overrides(floor, floor_anchor, gain_spread)  # a bad --floor-anchor or --gain-spread: one line, before any work
    cfg = from_dict(EvalConfig, {"n_obs": n_obs, "dt_ms": dt_ms, "zeta": zeta, "max_frames": max_frames, "net_tile": net_tile, "net_ensemble": net_ensemble, "device": device, "floor": floor, "floor_anchor": floor_anchor or "", "gain_spread": gain_spread}, where="command line")
    try:
        w, h = (int(x) for x in synthetic_size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--synthetic-size {synthetic_size!r} is not WxH; write e.g. 200x125") from None
    syn = from_dict(SyntheticConfig, {"n_groups": synthetic_groups, "width": w, "height": h}, where="command line")
    with rich_progress("load groups", enabled=not quiet) as cb:
        groups = load_groups(dataset, split, cfg, syn, progress=cb)
    cks = {"full": [str(p) for p in (full or [DEFAULT_WEIGHTS])], "no_rir": [str(p) for p in no_rir], "no_attention": [str(p) for p in no_attention], "no_conf": [str(p) for p in no_conf]}
    sv = [s.strip() for s in solvers.split(",") if s.strip()]
    with rich_progress("paper tables", enabled=not quiet) as cb:
        res = paper_tables(groups, cks, cfg, solvers=sv, progress=cb, net_zeta=net_zeta)
    res["config"]["dataset"], res["config"]["split"] = dataset, split
    md = paper_markdown(res)
    buf = io.StringIO()
    csv.writer(buf).writerows([["n/a" if v is None else v for v in row] for row in paper_csv(res)])
    write_text(out / "paper_table.md", md)
    write_text(out / "paper_table.csv", buf.getvalue())
    write_json(out / "paper_table.json", res)
    con = Console()
    con.print(md)
    con.print(f"[green]wrote[/] {out / 'paper_table.md'}, {out / 'paper_table.csv'}, {out / 'paper_table.json'}")


@app_typer.command("evaluate-real")
def evaluate_real_cmd(
    folder: Optional[Path] = typer.Argument(None, help="folder of the real recordings [default: ../shared/data/real_spikes beside the project]"),
    out: Path = typer.Option(Path("out/evaluate_real"), "--out", help="output folder (real.md/.csv/.json, real.png, runs/)"),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="network checkpoint [default: the shipped reconstruct/weights default]"),
    max_frames: int = typer.Option(3, "--max-frames", help="output frames per recording (bounded run)"),
    crop: int = typer.Option(0, "--crop", help="centre crop side in pixels (0 = whole frames)"),
    zeta: Optional[str] = typer.Option(None, "--zeta", help="the network's zeta: self, learned or none [default: reconstruct.net.net_zeta.NET_DEFAULT_ZETA, self: the pane fitted to each recording; where it does not calibrate, zeta = 0 or the learned zeta (reconstruct.net.net_zeta.fallback_for)]"),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda"),
    threads: int = typer.Option(0, "--threads", help="torch CPU threads (0 = torch default)"),
    ensemble: int = typer.Option(1, "--ensemble", help="the network averaged over 1, 2, 4 or 8 mirror / transpose symmetries (test-time self-ensemble, as polspike reconstruct --ensemble)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Reconstruct each real recording (no polarizer) on a few frames: no crash, no NaN, PSNR of T against the TFP image and the spike mean; table + figure.

    Exit code 1 when a recording crashes or gives NaN (the table says which).
    """
    import csv
    import io

    import torch
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.errors import CheckpointError, ConfigError
    from polinfra.progress import rich_progress
    from polspike.pipeline.real_eval import default_real_dir, evaluate_real, real_markdown
    from reconstruct.net.net_zeta import NET_DEFAULT_ZETA, NET_ZETA_SOURCES

    if threads > 0:
        torch.set_num_threads(threads)
    zeta = zeta or NET_DEFAULT_ZETA
    if zeta not in NET_ZETA_SOURCES:
        raise ConfigError(f"--zeta {zeta!r}: choose {', '.join(NET_ZETA_SOURCES)}")
    if max_frames < 1:
        raise ConfigError(f"--max-frames {max_frames}: must be >= 1 (a bounded run)")
    from reconstruct.net.network import check_ensemble_size

    check_ensemble_size(ensemble, "--ensemble")
    folder = folder or default_real_dir()
    if not folder.is_dir():
        raise ConfigError(f"real recordings folder {folder} not found")
    if checkpoint is not None and not checkpoint.is_file():
        raise CheckpointError(f"checkpoint not found: {checkpoint}")
    with rich_progress("real recordings", enabled=not quiet) as cb:
        res = evaluate_real(out, folder, weights=checkpoint, max_frames=max_frames, crop=crop, zeta=zeta, device=device, progress=cb, ensemble=ensemble)
    if not res["rows"]:
        raise ConfigError(f"no known recording in {folder} (expected {', '.join(r.file for r in __import__('polspike.pipeline.real_eval', fromlist=['RECORDINGS']).RECORDINGS)})")
    md = real_markdown(res)
    cols = ["recording", "status", "size", "steps", "frames", "nan_frames", "exposure", "rev_per_s", "psnr_tfp", "psnr_mean", "psnr_tfp_vs_mean", "corr_tfp", "corr_mean"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
    w.writeheader()
    w.writerows(res["rows"])
    write_text(out / "real.md", "# Real recordings (no polarizer)\n\n" + md)
    write_text(out / "real.csv", buf.getvalue())
    write_json(out / "real.json", res)
    con = Console()
    con.print(md)
    con.print(f"[green]wrote[/] {out / 'real.md'}, {out / 'real.csv'}, {out / 'real.json'}, {out / 'real.png'}")
    if not all(r.get("finite") for r in res["rows"]):
        raise typer.Exit(1)


@bench_app.command("ensemble")
def bench_ensemble_cmd(
    dataset: str = typer.Argument(..., help="dataset directory (dataset.json + group stores), e.g. out/datasets/eval_paper_val, or 'synthetic[:SEED]'"),
    split: str = typer.Option("test", "--split", help="split listed in dataset.json"),
    sizes: str = typer.Option("1,2,4,8", "--sizes", help="comma-separated ensemble sizes (1, 2, 4, 8); 1 is always run, as the reference"),
    zeta: str = typer.Option("self", "--zeta", help="the network's zeta: self (fitted to each group's stream, as polspike reconstruct) | learned | gt"),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="network checkpoint [default: the shipped default]"),
    max_frames: int = typer.Option(3, "--max-frames", help="output frames per group (0 = all)"),
    threads: int = typer.Option(1, "--threads", help="torch CPU threads"),
    out: Path = typer.Option(Path("out/bench/ensemble"), "--out", help="output folder (ensemble.json, ensemble.md, ensemble.png)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """The network's test-time self-ensemble: T / R quality and network time per output frame for each size, time as a ratio to size 1 in the same run."""
    import torch
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.config import from_dict
    from polinfra.errors import ConfigError
    from polinfra.progress import rich_progress
    from reconstruct.evaluate.bench import bench_ensemble, ensemble_figure, ensemble_table
    from reconstruct.evaluate.harness import EvalConfig, load_groups
    from reconstruct.net.network import check_ensemble_size
    from reconstruct.stream.synthetic import SyntheticConfig

    try:
        sz = tuple(int(x) for x in sizes.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"--sizes {sizes!r}: write comma-separated integers, e.g. 1,2,4,8") from None
    if not sz:
        raise ConfigError(f"--sizes {sizes!r}: give at least one size, e.g. 1,2,4,8")
    for x in sz:
        check_ensemble_size(x, "--sizes:")
    if zeta not in ("self", "learned", "gt"):
        raise ConfigError(f"--zeta {zeta!r}: choose self, learned or gt")
    if threads > 0:
        torch.set_num_threads(threads)
    cfg = from_dict(EvalConfig, {"zeta": zeta, "net_zeta": zeta, "rir": False, "max_frames": max_frames, "checkpoint": str(checkpoint or "")}, where="command line")
    with rich_progress("load groups", enabled=not quiet) as cb:
        groups = load_groups(dataset, split, cfg, SyntheticConfig(), progress=cb)
    with rich_progress("ensemble sizes", enabled=not quiet) as cb:
        res = bench_ensemble(groups, cfg, sz, progress=cb)
    res["config"]["dataset"], res["config"]["split"] = dataset, split
    md = ensemble_table(res)
    write_json(out / "ensemble.json", res)
    write_text(out / "ensemble.md", md)
    ensemble_figure(res, out / "ensemble.png")
    con = Console()
    con.print(md)
    con.print(f"[green]wrote[/] {out / 'ensemble.json'}, {out / 'ensemble.md'}, {out / 'ensemble.png'}")


@bench_app.command("exposure")
def bench_exposure_cmd(
    datasets: list[Path] = typer.Argument(..., help="built dataset directories (groups/ with stored exposures), e.g. out/datasets/fit_paper out/datasets/eval_paper out/datasets/stress"),
    out: Path = typer.Option(Path("out/bench/exposure"), "--out", help="output folder (exposure.json, exposure.md)"),
    max_steps: int = typer.Option(4000, "--max-steps", help="steps of each group the estimate reads (as polspike reconstruct: 4000)"),
) -> None:
    """Exposure estimated from the spikes (reconstruct/stream/exposure.py) vs the exposure each group was simulated with: log error per dataset."""
    import numpy as np
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.errors import ConfigError
    from reconstruct.stream.exposure import REFERENCE_RADIANCE, exposure_errors

    res, md = {}, ["| dataset | groups | mean ln(est / true) | std | max abs | worst factor | within x1.5 | geometric mean of the 99.9th pct radiance |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for d in datasets:
        gdir = d / "groups"
        if not gdir.is_dir():
            raise ConfigError(f"{d}: no groups/ folder (a built dataset directory is expected)")
        rows = exposure_errors(sorted(p for p in gdir.iterdir() if p.is_dir()), max_steps)
        if not rows:
            raise ConfigError(f"{d}: no group with a stored exposure")
        le = np.array([r["log_error"] for r in rows])
        q = np.exp(np.mean(np.log([r["quantile_radiance"] for r in rows])))
        res[str(d)] = {"rows": rows, "mean_log_error": float(le.mean()), "std_log_error": float(le.std()), "max_abs_log_error": float(np.abs(le).max()),
                       "within_1_5": float(np.mean(np.abs(le) <= np.log(1.5))), "geomean_quantile_radiance": float(q)}
        r = res[str(d)]
        md.append(f"| {d} | {len(rows)} | {r['mean_log_error']:+.3f} | {r['std_log_error']:.3f} | {r['max_abs_log_error']:.3f} | {np.exp(r['max_abs_log_error']):.2f} | {100 * r['within_1_5']:.0f} % | {q:.4f} |")
    text = "\n".join(md) + f"\n\nREFERENCE_RADIANCE = {REFERENCE_RADIANCE} (the geometric mean of the 99.9th percentile radiance of the paper.toml train groups, out/datasets/fit_paper).\n"
    write_json(out / "exposure.json", res)
    write_text(out / "exposure.md", text)
    Console().print(text)


@bench_app.command("reconstruct")
def bench_reconstruct_cmd(
    out: Path = typer.Option(Path("out/bench/reconstruct"), "--out", help="output folder for reconstruct.json and reconstruct.md"),
    json_out: bool = typer.Option(False, "--json", help="print the JSON result"),
    width: int = typer.Option(400, "--width", help="frame width in pixels"),
    height: int = typer.Option(250, "--height", help="frame height in pixels"),
    batch: int = typer.Option(8, "--batch", help="windows per solver call (solver-stage throughput)"),
    repeats: int = typer.Option(3, "--repeats", help="timed repetitions per device (the best is reported)"),
    threads: int = typer.Option(2, "--threads", help="torch CPU threads"),
    device: str = typer.Option("auto", "--device", help="auto (CPU, plus CUDA when present), cpu, or cuda"),
) -> None:
    """Output frames/s of harmonic fit + RIR + RWPS, and of the solver stage alone, vs plain LS (CPU; CUDA if present)."""
    import json

    from rich.console import Console
    from rich.table import Table

    from polinfra.atomic import write_json, write_text
    from polinfra.errors import ConfigError
    from reconstruct.evaluate.bench import bench_reconstruct

    devices = {"auto": ("cpu", "cuda"), "cpu": ("cpu",), "cuda": ("cuda",)}.get(device)
    if devices is None:
        raise ConfigError(f"--device {device!r}: choose auto, cpu or cuda")
    res = bench_reconstruct(width=width, height=height, batch=batch, repeats=repeats, threads=threads, devices=devices, require=device == "cuda")
    tab = Table(title=f"reconstruct at {width}x{height}, N = 7")
    for c in ("device", "stage", "ms / frame", "frames / s"):
        tab.add_column(c)
    md = "| device | stage | ms / frame | frames / s |\n|---|---|---:|---:|\n"
    for dev, stages in res["results"].items():
        for st, v in stages.items():
            if st == "ratios":
                continue
            tab.add_row(dev, st, f"{1e3 * v['s_per_frame']:.2f}", f"{v['fps']:.1f}")
            md += f"| {dev} | {st} | {1e3 * v['s_per_frame']:.2f} | {v['fps']:.1f} |\n"
        r = stages["ratios"]
        md += f"\n{dev}: RWPS / LS time = {r['rwps_over_ls_time']:.2f}; pipeline / LS time = {r['pipeline_over_ls_time']:.1f}\n"
    write_json(out / "reconstruct.json", res)
    write_text(out / "reconstruct.md", md)
    con = Console()
    con.print(tab)
    for dev, stages in res["results"].items():
        r = stages["ratios"]
        con.print(f"{dev}: RWPS / LS time {r['rwps_over_ls_time']:.2f}, pipeline / LS time {r['pipeline_over_ls_time']:.1f}")
    for dev, why in res["skipped"].items():
        con.print(f"{dev}: skipped ({why})")
    if json_out:
        print(json.dumps(res, indent=2))


@app_typer.command("fit-rwps")
def fit_rwps_cmd(
    dataset: str = typer.Argument(..., help="built dataset directory whose TRAINING groups fit the constants (e.g. out/datasets/fit_paper)"),
    split: str = typer.Option("train", "--split", help="split to fit on (train: never fit on test groups)"),
    out: Path = typer.Option(Path("out/fit_rwps"), "--out", help="output folder (fit.json, fit.md)"),
    max_frames: int = typer.Option(3, "--max-frames", help="output frames per group"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Fit the adaptive RWPS constants (snr_kappa, lambda_low, lambda_high) on training groups with the true zeta (reconstruct/evaluate/rwps_fit.py)."""
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.errors import ConfigError
    from polinfra.progress import rich_progress
    from reconstruct.evaluate.harness import EvalConfig, load_groups
    from reconstruct.evaluate.rwps_fit import GRID, aligned_windows, fit_markdown, fit_rwps

    if split == "test":
        raise ConfigError("fit-rwps fits on training groups; --split test would leak the test split into the constants")
    cfg = EvalConfig(max_frames=max_frames, zeta="gt")
    with rich_progress("load groups", enabled=not quiet) as cb:
        groups = load_groups(dataset, split, cfg, progress=cb)
    win = aligned_windows(groups, cfg)
    with rich_progress("grid", enabled=not quiet) as cb:
        res = fit_rwps(win, progress=cb)
    res["dataset"], res["split"], res["max_frames"], res["grid"] = dataset, split, max_frames, GRID
    md = fit_markdown(res)
    write_json(out / "fit.json", res)
    write_text(out / "fit.md", f"# RWPS fit on {dataset} ({split}, {len(res['groups'])} groups, {max_frames} frames each)\n\nbest: {res['best']}\n\n" + md)
    con = Console()
    con.print(md)
    con.print(f"best: {res['best']} (objective {res['objective']:.3f} dB)")
