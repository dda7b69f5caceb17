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
    as_json: bool = typer.Option(False, "--json", help="print JSON instead of a sentence"),
) -> None:
    """Estimate the polarizer's phase phi0 and rate from the spikes, as on the real rig, and report the error."""
    import numpy as np

    from spike_sim.calibrate import calibrate_group
    from spike_sim.store import open_group

    with open_group(group) as g:
        res = calibrate_group(g, None if target_aolp_deg is None else float(np.deg2rad(target_aolp_deg)), rate_hz)
    if as_json:
        typer.echo(json.dumps(res))
        return
    from rich.console import Console

    Console().print(
        f"{res['method']}: phi0 = {res['phi0_deg']:.3f} deg (nominal {res['nominal_phase_deg']:.3f}), rate = {res['rate_hz']:.5f} rev/s"
        f" (nominal {res['nominal_rate_hz']:.3f}); error vs true phi(t): phi0 {res['phi0_err_deg']:+.3f} deg, rms {res['rms_deg']:.3f} deg, max {res['max_abs_deg']:.3f} deg"
    )
