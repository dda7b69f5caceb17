"""``polspike bench motion``: every method under camera pans, shake, rotation, zoom and layer motion (JSON, table, plot)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import bench_app


def _split(s: str, cast=str) -> list:
    return [cast(x.strip()) for x in s.split(",") if x.strip()]


@bench_app.command("motion")
def motion_cmd(
    out: Path = typer.Option(Path("out/bench/motion"), "--out", help="output folder: motion.json, motion.md, motion.png"),
    motions: str = typer.Option("pan,shake,rotate,zoom,layers", "--motions", help="kinds of motion, comma-separated: pan, shake, rotate, zoom, layers"),
    speeds: str = typer.Option("0,0.1,0.3,0.6,1.1,2,3", "--speeds", help="pan speeds, view widths per second, comma-separated"),
    reflections: str = typer.Option("weak,strong,dominant", "--reflections", help="reflection strengths: weak, strong, dominant"),
    lights: str = typer.Option("dim,bright", "--lights", help="light levels: dim (0.02 spikes/px/step), bright (0.3)"),
    methods: str = typer.Option("", "--methods", help="methods, comma-separated [default: all of reconstruct.evaluate.motion_bench.METHODS]"),
    width: int = typer.Option(96, "--width", help="frame width in pixels"),
    height: int = typer.Option(64, "--height", help="frame height in pixels"),
    frames: int = typer.Option(1, "--frames", help="output frames scored per cell"),
    seed: int = typer.Option(0, "--seed", help="scene seed (pictures, pane azimuth, shake, initial charges)"),
    calibrate: str = typer.Option("still", "--calibrate", help="where the self-calibrated zeta comes from: still (the same rig's still stream, once per scene and light) | cell (each cell's own moving stream)"),
    weights: Optional[Path] = typer.Option(None, "--weights", help="checkpoint file, or a shipped one by name: default | fast (the real-time network, docs/realtime.md) [default: the shipped default, reconstruct.net.checkpoint.DEFAULT_WEIGHTS]"),
    rir: str = typer.Option("window", "--rir", help="the windows' RIR shifts, estimated once per frame and shared by every method: window (per window) | chained (each frame onto the previous, reconstruct.physics.rir.ChainedRir)"),
    json_out: bool = typer.Option(False, "--json", help="print the JSON result"),
) -> None:
    """T and R PSNR / SSIM of TFP, the spike means, every physics solver and the network under motion."""
    import json

    from rich.console import Console

    from polinfra.atomic import ensure_dir, json_safe, write_json, write_text
    from polinfra.errors import ConfigError
    from polinfra.progress import rich_progress
    from reconstruct.evaluate.motion_bench import METHODS, default_cells, motion_plot, motion_table, run_motion_bench
    from reconstruct.stream.motion_scenes import MOTIONS, REFLECTION_SHARES

    try:
        sp = _split(speeds, float)
    except ValueError:
        raise ConfigError(f"--speeds {speeds!r}: comma-separated numbers (view widths per second)") from None
    mo, re_, li = _split(motions), _split(reflections), _split(lights)
    for name, got, allowed in (("--motions", mo, MOTIONS), ("--reflections", re_, tuple(REFLECTION_SHARES)), ("--lights", li, ("dim", "bright"))):
        bad = [x for x in got if x not in allowed]
        if bad or not got:
            raise ConfigError(f"{name} {','.join(bad) or '(empty)'}: choose from {', '.join(allowed)}")
    me = _split(methods) or list(METHODS)
    bad = [m for m in me if m not in METHODS]
    if bad:
        raise ConfigError(f"--methods {','.join(bad)}: choose from {', '.join(METHODS)}")
    if calibrate not in ("still", "cell"):
        raise ConfigError(f"--calibrate {calibrate!r}: choose still or cell")
    if rir not in ("window", "chained"):
        raise ConfigError(f"--rir {rir!r}: choose window or chained")
    if width < 32 or height < 32 or width % 4 or height % 4:
        raise ConfigError(f"--width {width} --height {height}: at least 32 and multiples of 4")
    if frames < 1:
        raise ConfigError(f"--frames {frames}: at least 1")
    cells = default_cells(mo, sp, re_, li)
    ensure_dir(out)
    with rich_progress("bench motion", enabled=not json_out) as cb:
        res = run_motion_bench(cells, progress=cb, width=width, height=height, frames=frames, seed=seed, methods=tuple(me), weights=weights, calibrate=calibrate, rir=rir)
    write_json(out / "motion.json", json_safe(res))  # a non-finite score (a method's NaN output) as null
    table = motion_table(res)
    write_text(out / "motion.md", table)
    motion_plot(res, out / "motion.png")
    if json_out:
        typer.echo(json.dumps(res, indent=2))
    else:
        Console().print(table)
        Console().print(f"wrote {out}/motion.json, motion.md, motion.png")
