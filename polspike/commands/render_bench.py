"""``polspike bench render``: seconds per frame of the Mitsuba tiers per backend and spp."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import bench_app


@bench_app.command("render")
def bench_render_cmd(
    out: Path = typer.Option(Path("out/bench/render"), "--out", help="output folder for render.json"),
    json_out: bool = typer.Option(False, "--json", help="print the JSON result"),
    width: int = typer.Option(400, "--width", help="frame width in pixels"),
    height: int = typer.Option(250, "--height", help="frame height in pixels"),
    spp: Optional[list[int]] = typer.Option(None, "--spp", help="samples per pixel (repeatable) [default: 4 16 64]"),
    backend: Optional[list[str]] = typer.Option(None, "--backend", help="backends to try (repeatable) [default: cuda llvm scalar]"),
    scene: str = typer.Option("brewster", "--scene", help="default scene to time"),
    repeats: int = typer.Option(2, "--repeats", help="later keyframes timed per setting"),
    no_maps: bool = typer.Option(False, "--no-maps", help="skip the maps-tier timing"),
) -> None:
    """Time full-tier keyframes and maps-tier evaluation per Mitsuba backend; LLVM/scalar ratio in the same run."""
    import json

    from rich.console import Console
    from rich.table import Table

    from generator.render_bench import run_render_bench
    from polinfra.atomic import write_json
    from polinfra.progress import rich_progress

    with rich_progress("bench render", enabled=not json_out) as cb:
        res = run_render_bench(width, height, tuple(spp or (4, 16, 64)), tuple(backend or ("cuda", "llvm", "scalar")), scene, repeats, not no_maps, progress=cb)
    write_json(out / "render.json", res)
    if json_out:
        typer.echo(json.dumps(res, indent=2))
        return
    t = Table(title=f"render benchmark ({width}x{height}, scene {scene}), seconds per frame")
    for c in ("tier", "backend", "variant", "spp", "first (incl. JIT)", "later"):
        t.add_column(c)
    for r in res["rows"]:
        t.add_row(r["tier"], r["backend"], r["variant"], str(r["spp"]), f"{r['first_s']:.3f}", f"{r['later_s']:.3f}")
    con = Console()
    con.print(t)
    for spp_k, ratio in res["scalar_over_llvm_later_s"].items():
        con.print(f"LLVM is {ratio:.1f}x faster than scalar at {spp_k} spp")
    for be, why in res["unavailable"].items():
        con.print(f"[dim]{be}: unavailable ({why})[/]")
