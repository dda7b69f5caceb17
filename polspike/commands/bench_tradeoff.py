"""``polspike bench tradeoff``: cost vs error of every fidelity knob, against a reference in the same run."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import typer

from polspike.cli import bench_app


@bench_app.command("tradeoff")
def tradeoff_cmd(
    out: Path = typer.Option(Path("out/bench/tradeoff"), "--out", help="output folder: tradeoff.json, tradeoff.md, pareto.png"),
    scenes: Optional[list[str]] = typer.Option(None, "--scene", help="scene(s) to measure [default: every default scene]"),
    width: int = typer.Option(400, "--width", help="image width in pixels for the measurement"),
    height: int = typer.Option(250, "--height", help="image height in pixels"),
    ref_spp: int = typer.Option(256, "--ref-spp", help="samples per pixel of the full-tier reference"),
    quick: bool = typer.Option(False, "--quick", help="reduced candidate grid (for tests)"),
    json_out: bool = typer.Option(False, "--json", help="print the JSON result"),
) -> None:
    """Measure the speed/accuracy trade of tiers, spp, mono/spectral, backend, keyframe rate."""
    import json

    from rich.console import Console

    from generator.scene import default_scenes, load_scene
    from polspike.pipeline.tradeoff import Candidate, default_candidates, run_tradeoff
    from polinfra.progress import rich_progress

    names = scenes or default_scenes()
    scs = []
    for n in names:
        s = load_scene(n)
        scs.append(dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=width, height=height)))
    ref = Candidate(f"reference full {ref_spp}spp spectral llvm", "full", ref_spp, spectral=True, variant="llvm")
    with rich_progress("bench tradeoff", enabled=not json_out) as cb:
        res = run_tradeoff(scs, out, default_candidates(quick), ref=ref, progress=cb)
    if json_out:
        typer.echo(json.dumps(res, indent=2))
    else:
        Console().print((out / "tradeoff.md").read_text())
        Console().print(f"wrote {out}/tradeoff.json, tradeoff.md, pareto.png")
