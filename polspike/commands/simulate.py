"""``polspike simulate`` (render dir -> spike group) and ``polspike bench spike-sim``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer, bench_app


def load_sim_config(path: Optional[Path], preset_name: str):
    """Preset, overridden by a TOML file's ``[spike_sim]`` table (or top-level keys); plus ``[aggregate]``."""
    from polinfra.config import from_dict, load_toml, to_dict
    from spike_sim.aggregate import AggregateConfig
    from spike_sim.config import SpikeSimConfig, preset

    base = preset(preset_name)
    if path is None:
        return base, AggregateConfig()
    data = load_toml(path)
    agg = from_dict(AggregateConfig, data.pop("aggregate", {}), where=str(path), prefix="aggregate.")
    sim = data.pop("spike_sim", None)
    prefix = "spike_sim."
    if sim is None:
        sim, prefix = data, ""
    elif data:
        from polinfra.errors import ConfigError

        raise ConfigError(f"{path}: unknown key {sorted(data)[0]}; accepted tables: spike_sim, aggregate")
    merged = {**to_dict(base), **sim}
    return from_dict(SpikeSimConfig, merged, where=str(path), prefix=prefix), agg


@app_typer.command("simulate")
def simulate_cmd(
    render_dir: Path = typer.Argument(..., help="render directory (output of `polspike render`)"),
    out: Path = typer.Option(..., "--out", help="output group folder (spikes.h5 + group.json)"),
    duration: float = typer.Option(1.0, "--duration", help="stream length in seconds"),
    seed: int = typer.Option(0, "--seed", help="sensor/noise seed (same seed, same bits, any chunking)"),
    dat: Optional[Path] = typer.Option(None, "--dat", help="also write a raw Vidar .dat file (SpikeCV / spikezoo layout)"),
    config: Optional[Path] = typer.Option(None, "--config", help="TOML with a [spike_sim] table (and optional [aggregate])"),
    preset: str = typer.Option("default", "--preset", help="base noise preset: ideal, default, noisy"),
    chunk_steps: int = typer.Option(1000, "--chunk-steps", help="steps per chunk (memory ~ chunk * H W / 8 bytes)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing group"),
    compression: str = typer.Option("gzip", "--compression", help="spike dataset compression: gzip (deflate 1, ~30 % smaller) or none (fastest)"),
    store_zeta: bool = typer.Option(False, "--store-zeta", help="also store paper Eq. (2) zeta at each output time (float16, gt/zeta; needs maps.exr)"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Simulate the spike camera behind the rotating polarizer for a rendered scene."""
    from rich.console import Console

    from polinfra.progress import rich_progress
    from spike_sim.simulate import simulate

    cfg, agg = load_sim_config(config, preset)
    with rich_progress("simulate", enabled=not quiet) as cb:
        s = simulate(render_dir, duration, seed, cfg, out=out, progress=cb, chunk_steps=chunk_steps, dat_path=dat, aggregate=agg, overwrite=overwrite, compression=compression, store_zeta=store_zeta)
    Console().print(
        f"[green]wrote[/] {out}: {s.n_steps} steps, {s.n_output_frames} Eq. (3) output frames, mean rate {s.mean_rate:.4f} spikes/step,"
        f" {s.seconds:.1f} s ({s.pixel_steps_per_s:.3g} pixel-steps/s in the kernel)" + (f"; .dat {dat}" if dat else "")
    )


@bench_app.command("spike-sim")
def bench_spike_sim_cmd(
    out: Path = typer.Option(Path("out/bench/spike-sim"), "--out", help="output folder for spike_sim.json"),
    json_out: bool = typer.Option(False, "--json", help="print the JSON result"),
    steps: int = typer.Option(4000, "--steps", help="steps per timed numba run"),
    numpy_steps: int = typer.Option(100, "--numpy-steps", help="steps of the numpy reference"),
    width: int = typer.Option(400, "--width", help="sensor width in pixels"),
    height: int = typer.Option(250, "--height", help="sensor height in pixels"),
    full_group: float = typer.Option(0.0, "--full-group", help="also simulate a group of this many seconds end to end"),
) -> None:
    """Pixel-steps/s of the numba simulator (full noise) vs the numpy reference, ratio and memory."""
    import json

    from rich.console import Console
    from rich.table import Table

    from polinfra.atomic import write_json
    from spike_sim.bench import run_benchmark

    res = run_benchmark(width, height, steps, numpy_steps, full_group_s=full_group)
    write_json(out / "spike_sim.json", res)
    if json_out:
        typer.echo(json.dumps(res, indent=2))
        return
    t = Table(title=f"spike-sim benchmark ({width}x{height}, full noise, {res['numba']['threads']} threads)")
    for c in ("engine", "pixel-steps/s (wall)", "pixel-steps/CPU-s", "s per 1 s group", "tracemalloc peak MB"):
        t.add_column(c)
    for k in ("numba", "numpy"):
        r = res[k]
        t.add_row(k, f"{r['pixel_steps_per_s']:.3g}", f"{r['pixel_steps_per_cpu_s']:.3g}", f"{2e9 / r['pixel_steps_per_s']:.1f}", f"{r['tracemalloc_peak_mb']:.1f}")
    con = Console()
    con.print(t)
    con.print(f"ratio numba/numpy = {res['ratio_numba_over_numpy']:.1f}x wall, {res['ratio_per_cpu_second']:.1f}x per CPU-second (goal >= 20x); goal 5e8 pixel-steps/s")
    con.print(f"peak RSS {res['peak_rss_mb']:.0f} MB; load average {res['machine']['load_avg'][0]:.1f} on {res['machine']['cpus']} CPUs")
    if "full_group" in res:
        fg = res["full_group"]
        con.print(f"full {fg['duration_s']} s group: {fg['wall_s']:.1f} s wall ({fg['kernel_s']:.1f} s kernel), {fg['group_mb']:.0f} MB")
    con.print(f"wrote {out / 'spike_sim.json'}")
