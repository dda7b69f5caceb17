"""``polspike validate-zeta``: rendered Stokes vs the analytic zeta of paper Eq. (2)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer


@app_typer.command("validate-zeta")
def validate_zeta_cmd(
    scene: Path = typer.Argument(..., help="scene TOML file or default scene name"),
    out: Path = typer.Option(..., "--out", help="output folder: error maps, histogram, summary.json"),
    tier: str = typer.Option("maps", "--tier", help="tier under test: analytic | maps | full | auto (the cheapest predicted to meet --tolerance)"),
    spp: Optional[int] = typer.Option(None, "--spp", help="samples per pixel [default: scene render.spp]"),
    variant: str = typer.Option("auto", "--variant", help="Mitsuba backend: auto | scalar | llvm | cuda"),
    spectral: Optional[bool] = typer.Option(None, "--spectral/--mono", help="spectral or mono rendering [default: scene]"),
    model: Optional[str] = typer.Option(None, "--model", help="analytic pane model to validate against [default: the scene's]"),
    tolerance: float = typer.Option(1e-3, "--tolerance", help="allowed p99 worst-case |zeta error| above the Monte Carlo noise floor"),
    seed: Optional[int] = typer.Option(None, "--seed", help="render seed"),
    as_json: bool = typer.Option(False, "--json", help="print summary.json to stdout"),
) -> None:
    """Cross-validate analytic zeta against a rendered tier: error maps, histogram and a verdict.

    Exit code: 0 when the verdict is "pass", 1 when it is "fail" (p99 |zeta error|
    above the noise floor exceeds --tolerance), 2 for bad input.
    """
    from generator.render import RenderOptions
    from generator.scene import load_scene
    from generator.validate import validate_zeta
    from polinfra.progress import rich_progress

    sc = load_scene(scene)
    opts = RenderOptions(tier=tier, spp=spp, variant=variant, spectral=spectral, seed=seed)
    with rich_progress(f"validate-zeta {sc.name} [{tier}]", enabled=not as_json) as cb:
        summary = validate_zeta(sc, out, opts, model=model, tolerance=tolerance, progress=cb)
    if summary.get("tier_plan"):
        tier = summary["tier_plan"]["choice"]["tier"]
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
    else:
        _print_table(sc.name, tier, tolerance, out, summary)
    if summary["verdict"] != "pass":
        raise typer.Exit(1)


def _print_table(name: str, tier: str, tolerance: float, out: Path, summary: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    tab = Table(title=f"{name}: tier {tier} vs analytic '{summary['analytic_model']}'")
    for c in ("quantity", "max", "mean", "p99"):
        tab.add_column(c)
    for k, v in summary["errors"].items():
        tab.add_row(k, f"{v['max']:.3g}", f"{v['mean']:.3g}", f"{v['p99']:.3g}")
    con = Console()
    con.print(tab)
    dep = summary.get("eq12_departure")
    if dep:  # a 3-D object scene: how far its rendered mixture departs from Eq. (1)-(2)
        from polspike.commands.dataset_inspect import _departure_line

        con.print(_departure_line(dep) + (f"; noise floor {dep['noise_floor_p99']:.3g}" if dep.get("noise_floor_p99") is not None else ""))
    colour = "green" if summary["verdict"] == "pass" else "red"
    con.print(f"noise floor (p99) {summary['noise_floor_p99']:.3g}; verdict [bold {colour}]{summary['verdict']}[/] at tolerance {tolerance:g}; maps in {out}/figures"
              + ("; exit code 1" if summary["verdict"] != "pass" else ""))
