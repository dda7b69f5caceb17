"""``polspike dataset new|build|verify`` and ``polspike bench dataset`` (thin wrappers)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import bench_app, dataset_app


@dataset_app.command("new")
def dataset_new(
    groups: int = typer.Option(..., "--groups", help="number of groups to sample"),
    seed: int = typer.Option(..., "--seed", help="sampler seed (same seed, same manifest)"),
    out: Path = typer.Option(..., "--out", help="manifest TOML to write"),
    name: Optional[str] = typer.Option(None, "--name", help="dataset name (default: the file stem)"),
    test_fraction: float = typer.Option(0.2, "--test-fraction", help="share of test groups (the last ones)"),
    width: int = typer.Option(400, "--width", help="image width in pixels"),
    height: int = typer.Option(250, "--height", help="image height in pixels"),
    duration_s: float = typer.Option(1.0, "--duration-s", help="stream length per group, seconds"),
    tier: str = typer.Option("analytic", "--tier", help="generator tier: analytic, maps, full, auto (with --tolerance)"),
    tolerance: Optional[float] = typer.Option(None, "--tolerance", help="--tier auto: largest acceptable p99 radiance error; the planner picks each group's tier and spp"),
    ranges: str = typer.Option("paper", "--ranges", help="range profile: paper (the paper's difficulty, paper.toml), paper_motion (paper + global camera motion and sensor presets), v1 (the first, easier ranges, paper_v1.toml) or objects3d (3-D object arrangements with motion, full tier)"),
    like: Optional[Path] = typer.Option(None, "--like", help="a scene TOML (e.g. calibrate-pane's pane.toml): every group gets its pane and camera fov and size (polspike/pipeline/like.py)"),
    jitter: str = typer.Option("fit", "--jitter", help="with --like: fit (jitter within the 1-sigma of the report.json beside the scene, if any) or none"),
) -> None:
    """Write a manifest whose scene parameters are drawn from the documented ranges (docs/datasets.md)."""
    from rich.console import Console

    from polinfra.atomic import write_text
    from polinfra.errors import ConfigError
    from polspike.pipeline.sampler import sample_manifest_text

    if tier not in ("analytic", "maps", "full", "auto"):
        raise ConfigError(f"--tier {tier!r} is unknown; choose analytic, maps, full or auto")
    if ranges == "objects3d":  # 3-D object arrangements: full tier only
        from polspike.pipeline.sampler_objects3d import objects3d_manifest_text

        if like is not None or tier not in ("full", "analytic") or tolerance is not None:
            raise ConfigError("--ranges objects3d renders on the full tier only; drop --like, --tier and --tolerance")
        text = objects3d_manifest_text(groups, seed, name=name or out.stem, width=width, height=height, duration_s=duration_s)
    elif like is not None:
        from polspike.pipeline.like import like_manifest_text

        text = like_manifest_text(like, groups, seed, jitter=jitter, name=name or out.stem, test_fraction=test_fraction, duration_s=duration_s, tier=tier, profile=ranges, tolerance=tolerance)
    else:
        text = sample_manifest_text(groups, seed, name=name or out.stem, test_fraction=test_fraction, width=width, height=height, duration_s=duration_s, tier=tier, profile=ranges, tolerance=tolerance)
    write_text(out, text)
    Console().print(f"[green]wrote[/] {out}: {groups} groups (seed {seed})")


def _bars(enabled: bool):
    """(context manager, BuildCallbacks): one overall bar with ETA plus one bar per running group."""
    import contextlib

    from polspike.pipeline.dataset import BuildCallbacks

    if not enabled:
        return contextlib.nullcontext(), BuildCallbacks()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    prog = Progress(TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
    overall = prog.add_task("all groups (steps)", total=None)
    tasks: dict[str, int] = {}

    def group(name: str, stage: str, done: int, total: int) -> None:
        if stage == "skipped":  # verified and kept: counted in the overall bar only
            return
        if name not in tasks:
            tasks[name] = prog.add_task(f"{name}", total=total)
        if stage == "done":  # running groups only; the overall bar keeps the count
            prog.remove_task(tasks.pop(name))
            prog.console.print(f"[green]built[/] {name}", highlight=False)
            return
        prog.update(tasks[name], completed=done, total=total, description=f"{name} [{stage}]"[:28])

    def overall_cb(done: int, total: int) -> None:
        prog.update(overall, completed=done, total=total)

    return prog, BuildCallbacks(group=group, overall=overall_cb)


@dataset_app.command("build")
def dataset_build(
    manifest: Path = typer.Argument(..., help="manifest TOML (datasets/manifests/*.toml) or a shipped name (small, paper)"),
    out: Path = typer.Option(..., "--out", help="dataset folder (groups/, dataset.json)"),
    workers: int = typer.Option(1, "--workers", help="groups built at once"),
    executor: str = typer.Option("local", "--executor", help="local (this process / a process pool) or dask"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address tcp://HOST:8786 (needs --executor dask; DIR on a shared filesystem)"),
    group: Optional[list[str]] = typer.Option(None, "--group", help="build only this group (repeatable)"),
    chunk_steps: int = typer.Option(1000, "--chunk-steps", help="spike steps per chunk (memory ~ chunk * H W / 8 bytes)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bars"),
) -> None:
    """Build (or resume) a dataset: render, simulate and store every group, with checksums."""
    from rich.console import Console

    from polspike.pipeline.dataset import build_dataset

    ctx, cbs = _bars(not quiet)
    with ctx:
        r = build_dataset(manifest, out, workers=workers, executor=executor, scheduler=scheduler, chunk_steps=chunk_steps, groups=group, callbacks=cbs)
    doc = r["dataset"]
    Console().print(
        f"[green]dataset {doc['name']}[/] in {out}: built {len(r['built'])}, skipped {len(r['skipped'])} (verified), "
        f"{len(doc['groups'])}/{doc['n_groups']} groups, {sum(g['bytes'] for g in doc['groups']) / 1e6:.1f} MB, {r['seconds']:.1f} s"
    )


@dataset_app.command("verify")
def dataset_verify(
    out: Path = typer.Argument(..., help="dataset folder"),
    fast: bool = typer.Option(False, "--fast", help="file sha256s and metadata only (skip the content checksums)"),
    partial: bool = typer.Option(False, "--partial", help="accept a build of only some groups (built with --group)"),
) -> None:
    """Re-check every checksum and metadata field; exit 2 naming the bad groups."""
    from rich.console import Console

    from polinfra.errors import DataFormatError
    from polspike.pipeline.dataset import verify_dataset

    r = verify_dataset(out, content=not fast, partial=partial)
    if not r["ok"]:
        parts = [f"{n} ({'; '.join(e)})" for n, e in r["bad"].items()]
        msg = f"{out}: {len(r['bad'])} bad group(s): {', '.join(parts)}" if parts else f"{out}:"
        if r["problems"]:
            msg += ("; " if parts else " ") + "; ".join(r["problems"])
        raise DataFormatError(msg)
    Console().print(f"ok: {r['n_groups']} groups verified in {out}")


@bench_app.command("dataset")
def bench_dataset(
    out: Path = typer.Option(Path("out/bench"), "--out", help="folder for bench_dataset.json"),
    tiers: str = typer.Option("analytic", "--tiers", help="comma-separated tiers: analytic,maps,full"),
    width: int = typer.Option(400, "--width", help="image width in pixels"),
    height: int = typer.Option(250, "--height", help="image height in pixels"),
    duration_s: float = typer.Option(0.25, "--duration-s", help="measured stream length (s); times are scaled to a 1 s group"),
    full_duration_s: float = typer.Option(0.02, "--full-duration-s", help="measured length for the full tier (path tracing per keyframe)"),
    spp: int = typer.Option(4, "--spp", help="samples per pixel of the maps/full tiers"),
    as_json: bool = typer.Option(False, "--json", help="print the JSON instead of the table"),
) -> None:
    """Seconds per 1 s group per tier, bytes per group and peak memory on this machine."""
    import json

    from rich.console import Console
    from rich.table import Table

    from polspike.pipeline.dataset_bench import run_dataset_bench

    tl = tuple(t.strip() for t in tiers.split(",") if t.strip())
    durs = {t: (full_duration_s if t == "full" else duration_s) for t in tl}
    r = run_dataset_bench(out, tiers=tl, width=width, height=height, duration_s=durs, spp=spp)
    if as_json:
        print(json.dumps(r, indent=2))
        return
    tab = Table(title=f"dataset build, {width}x{height}, {r['machine']['cpus']} CPUs (scaled to 1 s groups)")
    for c in ("tier", "measured", "s per 1 s group", "CPU s per 1 s group", "MB per 1 s group", "peak RSS MiB"):
        tab.add_column(c, justify="right")
    for row in r["rows"]:
        if "error" in row:
            tab.add_row(row["tier"], "failed", row["error"][:60], "", "", "")
            continue
        tab.add_row(row["tier"], f"{row['measured_s']:.1f} s / {row['measured_duration_s']:g} s", f"{row['s_per_1s_group']:.1f}", f"{row['cpu_s_per_1s_group']:.1f}", f"{row['bytes_per_1s_group'] / 1e6:.1f}", f"{row['peak_rss_mib']:.0f}")
    Console().print(tab)
    Console().print(f"load average {r['machine']['load_avg_1min']:.1f} on {r['machine']['cpus']} CPUs; wrote {out / 'bench_dataset.json'}")
