"""``polspike render`` and ``polspike zeta``: the generator's and the physics calculator's CLI."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from polinfra.errors import ConfigError
from polspike.cli import app_typer


def _parse_frames(frames: str | None) -> tuple[int, int] | None:
    if frames is None:
        return None
    a, sep, b = frames.partition(":")
    try:
        if not sep:
            raise ValueError
        return int(a), int(b)
    except ValueError:
        raise ConfigError(f"--frames {frames!r} must look like A:B (first and one-past-last frame index)") from None


@app_typer.command("render")
def render_cmd(
    scene: Path = typer.Argument(..., help="scene TOML file, or a default scene name (near_normal, brewster, oblique_diagonal, bk7_single)"),
    out: Path = typer.Option(..., "--out", help="output render directory (created; resumable)"),
    tier: str = typer.Option("analytic", "--tier", help="analytic | maps | full (Mitsuba for maps/full) | auto (the cheapest meeting --tolerance)"),
    tolerance: Optional[float] = typer.Option(None, "--tolerance", help="--tier auto: largest acceptable p99 radiance error (worst polarizer angle), e.g. 1e-2"),
    frames: Optional[str] = typer.Option(None, "--frames", help="render only keyframes A:B"),
    fps: Optional[float] = typer.Option(None, "--fps", help="keyframes per second [default: scene render.fps]"),
    duration: Optional[float] = typer.Option(None, "--duration", help="clip length in seconds [default: scene render.duration_s]"),
    spp: Optional[int] = typer.Option(None, "--spp", help="samples per pixel for maps/full [default: scene render.spp]"),
    variant: str = typer.Option("auto", "--variant", help="Mitsuba backend: auto | scalar | llvm | cuda"),
    spectral: Optional[bool] = typer.Option(None, "--spectral/--mono", help="spectral integration with the sensor response, or mono [default: scene render.spectral]"),
    seed: Optional[int] = typer.Option(None, "--seed", help="render seed [default: scene render.seed]"),
    keyframe_hz: Optional[float] = typer.Option(None, "--keyframe-hz", help="full tier: path-traced keyframes per second (frames between are interpolated)"),
    response: str = typer.Option("cie_y", "--response", help="spectral renders: sensor response cie_y | flat | PATH.csv (columns wavelength_nm,response)"),
    bands: int = typer.Option(8, "--bands", help="spectral renders: wavelength bands over 400-700 nm", min=1, max=64),
    supersample: Optional[int] = typer.Option(None, "--supersample", help="analytic tier: 0 = pixel-centre point sample; K = the pixel's area on K x K rays (what the path tracer's pixel integrates) [default: scene render.supersample]"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Render a glass-pane scene to Stokes frames, layer ground truth and coefficient maps."""
    from rich.console import Console

    from generator.render import RenderOptions, render
    from generator.scene import load_scene
    from polinfra.progress import rich_progress

    if tolerance is not None and tier != "auto":
        raise ConfigError("--tolerance is for --tier auto; drop it or use --tier auto")
    sc = load_scene(scene)
    opts = RenderOptions(tier=tier, fps=fps, duration_s=duration, frames=_parse_frames(frames), spp=spp, variant=variant, spectral=spectral, seed=seed, keyframe_hz=keyframe_hz, response=response, n_bands=bands, supersample=supersample)
    with rich_progress(f"render {sc.name} [{tier}]", enabled=not quiet) as cb:
        meta = render(sc, out, opts, progress=cb, tolerance=tolerance)
    t = meta["timings"]
    plan = meta.get("tier_plan")
    if plan:
        c = plan["choice"]
        what = f" {c['spp']} spp" + (" spectral" if c["spectral"] else "") if c["tier"] == "full" else (" spectral" if c["spectral"] else "") + (f" --supersample {c['supersample']}" if c.get("supersample") else "")
        Console().print(f"tier auto at tolerance {plan['tolerance']:g}: {c['tier']}{what} (predicted p99 {c['predicted_p99']:.3g})")
    tier = meta["tier"]
    Console().print(f"wrote {len(meta['frames'])} frames to {out} (tier {tier}, maps {t.get('maps_s', 0):.2f} s, {t.get('per_frame_s', 0) * 1e3:.1f} ms/frame)")


@app_typer.command("zeta")
def zeta_cmd(
    n: float = typer.Option(1.5, "--n", help="relative refractive index n2/n1 (> 0; < 1 means leaving glass)"),
    theta_deg: float = typer.Option(45.0, "--theta-deg", help="incidence angle in degrees, [0, 90]"),
    phi_deg: float = typer.Option(0.0, "--phi-deg", help="polarizer angle in degrees (from image +x toward up)"),
    phi_perp_deg: float = typer.Option(0.0, "--phi-perp-deg", help="image angle of the s-direction in degrees"),
    pane: str = typer.Option("single", "--pane", help="single | thin_slab | thick_slab"),
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of a table"),
) -> None:
    """Print R_perp, R_par, T_perp, T_par and zeta (paper Eq. (2)) for one configuration."""
    import numpy as np

    from polphysics.fresnel import PANE_MODELS, pane_coefficients
    from polphysics.zeta import zeta

    if not n > 0:
        raise ConfigError(f"--n {n} must be > 0 (a refractive index)")
    if not 0.0 <= theta_deg <= 90.0:
        raise ConfigError(f"--theta-deg {theta_deg} must be in [0, 90]")
    if pane not in PANE_MODELS:
        raise ConfigError(f"--pane {pane!r}: choose one of {list(PANE_MODELS)}")
    if pane != "single" and n < 1:
        raise ConfigError(f"--n {n} < 1 is only meaningful with --pane single")
    c = pane_coefficients(np.deg2rad(theta_deg), n, pane)
    z = zeta(np.deg2rad(phi_deg), c["R_perp"], c["R_par"], np.deg2rad(phi_perp_deg))
    res = {k: float(c[k]) for k in ("R_perp", "R_par", "T_perp", "T_par")}
    res["zeta"] = float(z)
    res.update(n=n, theta_deg=theta_deg, phi_deg=phi_deg, phi_perp_deg=phi_perp_deg, pane=pane)
    if as_json:
        typer.echo(json.dumps(res))
        return
    from rich.console import Console
    from rich.table import Table

    tab = Table(title=f"{pane}, n = {n}, theta = {theta_deg} deg, phi - phi_perp = {phi_deg - phi_perp_deg} deg")
    for k in ("R_perp", "R_par", "T_perp", "T_par", "zeta"):
        tab.add_column(k)
    tab.add_row(*(f"{res[k]:.6f}" for k in ("R_perp", "R_par", "T_perp", "T_par", "zeta")))
    Console().print(tab)
