"""``polspike bench area``: the area-sampled analytic tier's error and time against K, and the auto picks."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import typer

from polspike.cli import bench_app


@bench_app.command("area")
def area_cmd(
    scene: str = typer.Option("bk7_single", "--scene", help="scene name or TOML file"),
    out: Path = typer.Option(Path("out/bench/area"), "--out", help="output folder: area.json, area.md, cached oracle images (a rerun resumes)"),
    width: Optional[int] = typer.Option(None, "--width", help="image width [default: the scene's]"),
    height: Optional[int] = typer.Option(None, "--height", help="image height [default: the scene's]"),
    ks: str = typer.Option("1,2,4", "--ks", help="comma-separated rays per pixel side of the area-sampled tier"),
    oracle_k: int = typer.Option(32, "--oracle-k", help="rays per pixel side of the stratified-sampling oracle", min=2, max=64),
    tolerances: str = typer.Option("5e-3,2e-3,1e-3", "--tolerances", help="comma-separated EPS values for the auto pick"),
    full_spp: int = typer.Option(0, "--full-spp", help="instead: compare the full tier at this spp (two seeds) with the point- and area-sampled images", min=0),
) -> None:
    """Measure the area-sampled analytic tier (``--supersample K``) against a deterministic oracle of the pixel's area."""
    from rich.console import Console

    from generator.scene import load_scene
    from polinfra.atomic import ensure_dir, write_json, write_text
    from polinfra.errors import ConfigError

    try:
        kk = tuple(int(x) for x in ks.split(",") if x.strip())
        tols = tuple(float(x) for x in tolerances.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"--ks {ks!r} and --tolerances {tolerances!r} must be comma-separated numbers") from None
    if not kk or any(not 1 <= k <= 64 for k in kk) or any(not t > 0 for t in tols):
        raise ConfigError("--ks must be integers from 1 to 64 and --tolerances positive numbers")
    sc = load_scene(scene)
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=width or sc.camera.width, height=height or sc.camera.height))
    out = ensure_dir(out)
    if full_spp:
        from polspike.pipeline.tradeoff_area import full_check, full_markdown

        res = full_check(sc, full_spp, kk)
        write_json(out / "area_full.json", res)
        write_text(out / "area_full.md", full_markdown(res))
        Console().print(full_markdown(res))
        return
    from polspike.pipeline.tradeoff_area import area_markdown, run_area_bench

    res = run_area_bench(sc, out, kk, oracle_k, tols)
    write_json(out / "area.json", res)
    write_text(out / "area.md", area_markdown(res))
    Console().print(area_markdown(res))
