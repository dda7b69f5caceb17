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
    planner: bool = typer.Option(False, "--planner", help="check --tier auto: the planner's grid (analytic, maps, full 4/16/64 spp), predictions vs measurements and the picks at --tolerances (planner.md)"),
    tolerances: str = typer.Option("5e-2,2e-2,1e-2,1e-3", "--tolerances", help="--planner: comma-separated EPS values whose auto picks are rendered and measured"),
    max_pick_spp: int = typer.Option(256, "--max-pick-spp", help="--planner: render and measure full-tier picks up to this spp", min=1),
    sampled: int = typer.Option(0, "--sampled", help="also measure N scenes drawn by the dataset sampler (--sampled-profile, --sampled-seed)", min=0),
    sampled_seed: int = typer.Option(1, "--sampled-seed", help="sampler seed of --sampled"),
    sampled_profile: str = typer.Option("paper", "--sampled-profile", help="sampler profile of --sampled: paper | v1 | objects3d"),
    json_out: bool = typer.Option(False, "--json", help="print the JSON result"),
) -> None:
    """Measure the speed/accuracy trade of tiers, spp, mono/spectral, backend, keyframe rate."""
    import json

    from rich.console import Console

    from generator.scene import default_scenes, load_scene
    from polinfra.atomic import write_json, write_text
    from polinfra.errors import ConfigError
    from polinfra.progress import rich_progress
    from polspike.pipeline.tradeoff import Candidate, default_candidates, run_tradeoff

    names = scenes if scenes is not None else ([] if sampled else default_scenes())
    scs = []
    for n in names:
        s = load_scene(n)
        scs.append(dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=width, height=height)))
    if sampled:
        from polspike.pipeline.sampler_objects3d import sampled_scenes

        scs += sampled_scenes(sampled, sampled_seed, width, height, profile=sampled_profile)
    try:
        tols = tuple(float(x) for x in tolerances.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"--tolerances {tolerances!r} must be comma-separated numbers") from None
    if any(not t > 0 for t in tols):
        raise ConfigError(f"--tolerances {tolerances!r}: every tolerance must be > 0")
    ref = Candidate(f"reference full {ref_spp}spp spectral llvm", "full", ref_spp, spectral=True, variant="llvm")
    if planner:
        from polspike.pipeline.tradeoff import planner_candidates

        cands = planner_candidates(spectral=any(s.pane.glass is not None for s in scs))
    else:
        cands = default_candidates(quick)
    refs: dict = {}
    with rich_progress("bench tradeoff", enabled=not json_out) as cb:
        res = run_tradeoff(scs, out, cands, ref=ref, progress=cb, refs=refs, keyframe_rates_hz=() if planner else (25.0, 50.0, 100.0, 200.0))
    if planner:
        import numpy as np

        from polspike.pipeline.tradeoff_planner import check_planner, planner_markdown

        np.savez_compressed(out / "references.npz", **{f"{k}__S": v[0] for k, v in refs.items()}, **{f"{k}__resolution": np.float64(v[1]) for k, v in refs.items()})

        chk = check_planner(scs, res["rows"], refs, tols, max_pick_spp=max_pick_spp)
        write_json(out / "planner.json", chk)
        write_text(out / "planner.md", planner_markdown(chk))
        res["planner"] = chk
    if json_out:
        typer.echo(json.dumps(res, indent=2))
    else:
        Console().print((out / "tradeoff.md").read_text())
        if planner:
            Console().print((out / "planner.md").read_text())
        Console().print(f"wrote {out}/tradeoff.json, tradeoff.md, pareto.png" + (", planner.json, planner.md" if planner else ""))
