"""``polspike calibrate``: polarizer phase and speed from a spike group, error against the true phi(t)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer


@app_typer.command("calibrate")
def calibrate_cmd(
    group: Path = typer.Argument(..., help="spike group folder (output of `polspike simulate`)"),
    target_aolp_deg: Optional[float] = typer.Option(None, "--target-aolp-deg", help="the group films a flat target polarized at this angle (degrees); default: a glass scene, using the group's phi_perp map"),
    rate_hz: Optional[float] = typer.Option(None, "--rate-hz", help="known rotation rate in rev/s [default: estimated from the modulation]"),
    tolerance_deg: float = typer.Option(1.0, "--tolerance-deg", help="the calibration fails when the rms error of the calibrated phi(t) against the true angle exceeds this, degrees"),
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of a sentence"),
) -> None:
    """Estimate the polarizer's phase phi0 and rate from the spikes, as on the real rig, and report the error.

    Exit code: 0 when the calibration passes, 1 when it fails (rms error of the
    calibrated phi(t) against the group's true angle above --tolerance-deg), 2 for bad input.
    """
    import math

    import numpy as np

    from polinfra.errors import ConfigError
    from spike_sim.calibrate import calibrate_group
    from spike_sim.store import open_group

    if not (math.isfinite(tolerance_deg) and tolerance_deg > 0):
        raise ConfigError(f"--tolerance-deg {tolerance_deg} must be a finite number > 0")
    with open_group(group) as g:
        res = calibrate_group(g, None if target_aolp_deg is None else float(np.deg2rad(target_aolp_deg)), rate_hz)
    res["tolerance_deg"] = tolerance_deg
    res["verdict"] = "pass" if res["rms_deg"] <= tolerance_deg else "fail"
    if as_json:
        typer.echo(json.dumps(res))
    else:
        from rich.console import Console

        colour = "green" if res["verdict"] == "pass" else "red"
        Console().print(
            f"{res['method']}: phi0 = {res['phi0_deg']:.3f} deg (nominal {res['nominal_phase_deg']:.3f}), rate = {res['rate_hz']:.5f} rev/s"
            f" (nominal {res['nominal_rate_hz']:.3f}); error vs true phi(t): phi0 {res['phi0_err_deg']:+.3f} deg, rms {res['rms_deg']:.3f} deg, max {res['max_abs_deg']:.3f} deg;"
            f" verdict [bold {colour}]{res['verdict']}[/] at tolerance {tolerance_deg:g} deg rms"
        )
    if res["verdict"] != "pass":
        raise typer.Exit(1)
