"""``polspike calibrate-pane`` and ``polspike bench calibrate-pane`` (thin wrappers over polspike.pipeline.calibrate_pane)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer, bench_app


@app_typer.command("calibrate-pane")
def calibrate_pane_cmd(
    input: Path = typer.Argument(..., help="a spike group directory (GROUP/spikes.h5) or a raw Vidar .dat file"),
    out: Path = typer.Option(..., "--out", help="output folder: pane.toml, maps.exr, report.json, figures"),
    height: Optional[int] = typer.Option(None, "--height", help=".dat: frame height H"),
    width: Optional[int] = typer.Option(None, "--width", help=".dat: frame width W"),
    phi0_deg: Optional[float] = typer.Option(None, "--phi0-deg", help=".dat: polarizer angle at t = 0 (calibration), degrees"),
    rev_per_s: Optional[float] = typer.Option(None, "--rev-per-s", help=".dat: polarizer rotation rate (calibration), rev/s"),
    rate_hz: float = typer.Option(20000.0, "--rate-hz", help=".dat: camera steps per second"),
    fov_deg: Optional[float] = typer.Option(None, "--fov-deg", help="known horizontal field of view, degrees (default: fitted)"),
    pane_model: str = typer.Option("auto", "--pane-model", help="auto (fit where the data constrain it), single, thin_slab or thick_slab"),
    n: Optional[float] = typer.Option(None, "--n", help="known refractive index (default: fitted where the data constrain it)"),
    glass: Optional[str] = typer.Option(None, "--glass", help="known named glass (e.g. bk7); its index at 550 nm is kept fixed"),
    span_s: float = typer.Option(0.1, "--span-s", help="length of the stream used, seconds (the pane must not move)"),
    window_steps: int = typer.Option(13, "--window-steps", help="Eq. (3) window in camera steps"),
) -> None:
    """Fit the pane (orientation, index, model) and the field of view to a recording by differentiating the maps tier."""
    from rich.console import Console

    from polinfra.errors import ConfigError
    from polspike.pipeline.calibrate_pane import calibrate_input
    from polspike.pipeline.pane_outputs import write_outputs
    from reconstruct.pane.calibrate_config import PANE_CHOICES, CalibratePaneConfig

    if pane_model not in PANE_CHOICES:
        raise ConfigError(f"--pane-model {pane_model!r}: choose one of {', '.join(PANE_CHOICES)}")
    if n is not None and glass is not None:
        raise ConfigError("give --n or --glass, not both")
    if n is not None and not (1.0 < n < 4.0):
        raise ConfigError(f"--n {n} is not a glass index; use 1 < n < 4")
    if glass is not None:
        from polphysics.fresnel import GLASSES

        if glass.upper() not in {k.upper() for k in GLASSES}:
            raise ConfigError(f"--glass {glass!r} is unknown; choose one of {sorted(GLASSES)}")
    if fov_deg is not None and not (1.0 <= fov_deg <= 150.0):
        raise ConfigError(f"--fov-deg {fov_deg} is out of range (1-150)")
    if not (0.005 <= span_s <= 100.0):
        raise ConfigError(f"--span-s {span_s} is out of range (0.005-100 s)")
    if window_steps < 1 or window_steps % 2 == 0:
        raise ConfigError(f"--window-steps {window_steps} must be a positive odd number")
    cfg = CalibratePaneConfig(span_s=span_s, window_steps=window_steps, fov_deg=fov_deg or 0.0, n=n or 0.0, glass=glass, pane_model=pane_model)
    con = Console()
    res, base, W, H = calibrate_input(input, cfg, height=height, width=width, phi0_deg=phi0_deg, rev_per_s=rev_per_s, rate_hz=rate_hz,
                                      progress=lambda stage: con.print(f"[dim]{stage}...[/]"))
    rep = write_outputs(out, res, base_scene=base, width=W, height=H)
    if not res["ok"]:
        con.print(f"[yellow]not calibrated[/]: {rep['reason']} (report: {out / 'report.json'})")
        raise typer.Exit(1)
    p, u, ident = rep["params"], rep["uncertainty_1sigma"], rep["identifiability"]

    def verdict(k):
        v = ident[k]["identified"]
        if v is None:
            return "given"
        if v:
            return "fitted" + (" from the layers' content" if ident[k].get("by") == "content" else "")
        return "NOT identified: " + ("the content test's best guess" if "content test's best guess" in ident[k]["why"] else "prior kept")

    kept = rep["geometry"].get("fov_kept")
    how = {"self_calibration": "kept from the self-calibration: the fit with it free ran into a degenerate view",
           "twin_profile": "the 90 deg twin's, from its fov profile judged by the modulation depths",
           "feasibility": "the widest view in which every modulating block sees the pane in front: the fit with it free ran to an edge-on pane"}
    fov_txt = (f"fov {p['fov_deg']:.2f} deg ({how.get(kept['by'], kept['by'])}; NOT identified: give --fov-deg if known)" if kept else
               f"fov {p['fov_deg']:.2f} +- {u['fov_deg']:.2f} deg ({'given' if ident['fov']['identified'] is None else 'fitted' if ident['fov']['identified'] else 'NOT identified: give --fov-deg if known'})")
    con.print(f"tilt {p['tilt_deg']:.2f} +- {u['tilt_deg']:.2f} deg, azimuth {p['azimuth_deg']:.2f} +- {u['azimuth_deg']:.2f} deg, {fov_txt}")
    con.print(f"theta +- {u['theta_deg_median']:.2f} deg{' at that fov' if kept else ''}, phi_perp +- {u['phi_perp_deg_median']:.2f} deg (median 1 sigma); "
              f"orientation residual {rep['geometry']['orientation_residual_deg_median']:.2f} deg")
    if rep.get("twin", {}).get("chosen") == "twin":
        con.print(f"90 deg twin taken: {rep['twin']['why']}")
    con.print(f"n {p['n']:.4f} ({verdict('n')}), model {p['model']} ({verdict('model')}); thickness and reflectance scale not identified")
    if not rep["pane_toml"]["written"]:
        con.print(f"[yellow]no pane.toml[/]: {rep['pane_toml']['why']}; reconstruct with --pane {out} still uses the maps")
    con.print(f"[green]wrote[/] {out}: {', '.join(rep['files'])} in {rep['timings_s']['total_s']:.1f} s")


@bench_app.command("calibrate-pane")
def bench_calibrate_pane(
    out: Path = typer.Option(Path("out/bench"), "--out", help="folder for bench_calibrate_pane.json"),
    width: int = typer.Option(400, "--width", help="image width in pixels"),
    height: int = typer.Option(250, "--height", help="image height in pixels"),
    span_s: float = typer.Option(0.1, "--span-s", help="stream span fitted, seconds"),
    spans: str = typer.Option("", "--spans", help="comma-separated spans (seconds) to measure the span knob at as well: seconds and errors per span, e.g. 0.05,0.1,0.2"),
    as_json: bool = typer.Option(False, "--json", help="print the JSON instead of the table"),
) -> None:
    """Seconds for one full calibrate-pane fit of a span (goal: 0.1 s at 400 x 250 in <= 2 min on 2 cores), beside the self-calibration alone."""
    import json

    from rich.console import Console
    from rich.table import Table

    from polinfra.errors import ConfigError
    from polspike.pipeline.calibrate_pane import run_bench

    try:
        sweep = tuple(float(v) for v in spans.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"--spans {spans!r}: give comma-separated seconds, e.g. 0.05,0.1,0.2") from None
    if any(not 0.02 <= v <= 10.0 for v in sweep):
        raise ConfigError(f"--spans {spans!r}: each span must be 0.02-10 s (two half turns of the polarizer at least)")
    r = run_bench(out, width=width, height=height, span_s=span_s, spans=sweep)
    if as_json:
        print(json.dumps(r, indent=2))
        return
    tab = Table(title=f"calibrate-pane, {width}x{height}, {span_s:g} s span, {r['machine']['cpus']} CPUs")
    for c in ("stage", "seconds", "x self-calibration"):
        tab.add_column(c, justify="right")
    for row in r["rows"]:
        tab.add_row(row["stage"], f"{row['s']:.2f}", f"{row['ratio']:.2f}")
    Console().print(tab)
    Console().print(f"goal <= 120 s: {'met' if r['total_s'] <= 120 else 'NOT met'} ({r['total_s']:.1f} s); load average {r['machine']['load_avg_1min']:.1f}; "
                    f"tilt error {r['accuracy'].get('tilt_err_deg', float('nan')):.2f} deg; wrote {out / 'bench_calibrate_pane.json'}")
    if r["span_sweep"]:
        tab = Table(title="the span knob: the same pane and layers fitted over each span")
        for c in ("span s", "seconds", "x self-calibration", "theta err", "theta 1-sigma", "phi_perp err", "tilt err", "n (err, claimed)", "model (right, claimed)"):
            tab.add_column(c, justify="right")
        for w in r["span_sweep"]:
            if not w["ok"]:
                tab.add_row(f"{w['span_s']:g}", f"{w['s']:.2f}", f"{w['ratio']:.2f}", "refused", "", "", "", "", "")
                continue
            tab.add_row(f"{w['span_s']:g}", f"{w['s']:.2f}", f"{w['ratio']:.2f}", f"{w['theta_err_deg_median']:.3f}", f"{w['theta_sigma_deg_median']:.3f}",
                        f"{w['phi_perp_err_deg_median']:.3f}", f"{w['tilt_err_deg']:.3f}", f"{w['n']:.3f} ({w['n_err']:.3f}, {'yes' if w['n_identified'] else 'no'})",
                        f"{w['model']} ({'yes' if w['model_right'] else 'no'}, {'yes' if w['model_identified'] else 'no'})")
        Console().print(tab)
