"""``polspike dataset inspect``: figures (and a video) of a group's polarization ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import dataset_app


@dataset_app.command("inspect")
def inspect_cmd(
    dir: Path = typer.Argument(..., help="dataset directory (dataset.json) or one group directory (GROUP/spikes.h5)"),
    out: Path = typer.Option(..., "--out", help="output folder for the PNG figures, inspect.json, inspect_data.npz [, video.mp4]"),
    group: Optional[str] = typer.Option(None, "--group", help="group name [default: the first group of the dataset]"),
    time: Optional[float] = typer.Option(None, "--time", help="time in the stream, seconds, snapped to the nearest output frame [default: the middle]"),
    video: bool = typer.Option(False, "--video", help="also write video.mp4: measured mixed input | GT T | GT R at the output cadence"),
    video_frames: int = typer.Option(0, "--video-frames", help="at most this many video frames (0 = the whole group)"),
    pixels: int = typer.Option(6, "--pixels", help="pixels in the spike raster"),
    dpi: int = typer.Option(110, "--dpi", help="figure resolution"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Plot theta, phi_perp, R_perp/R_par, zeta, Stokes/DoP/AoLP, the layers, a spike raster and a window's observations."""
    from rich.console import Console

    from polinfra.progress import rich_progress
    from polspike.pipeline.inspect import inspect_group

    with rich_progress("video", enabled=video and not quiet) as cb:
        s = inspect_group(dir, out, group=group, time_s=time, video=video, video_frames=video_frames, n_pixels=pixels, dpi=dpi, progress=cb)
    ch = s["checks"]
    c = Console()
    c.print(f"[green]wrote[/] {len(s['files'])} files to {out} for group {s['group']} at t = {s['time_s'] * 1e3:.2f} ms (frame {s['frame']}, phi = {s['phi_true_deg']:.1f} deg)")
    c.print(f"DoP of the mixed light in [{ch['dop_min']:.3f}, {ch['dop_max']:.3f}]; Eq. (1) vs Stokes max |diff| {ch['eq1_vs_stokes_max_abs']:.2e}")
    if ch["zeta_vs_stored_max_abs"] is not None:
        c.print(f"zeta recomputed vs stored gt/zeta: max |diff| {ch['zeta_vs_stored_max_abs']:.2e}")
    dep = s.get("eq12_departure")
    if dep:
        c.print(_departure_line(dep))


def _departure_line(dep: dict) -> str:
    """One line on how far a 3-D object scene departs from paper Eq. (1)-(2)."""
    f = lambda k, q: "n/a" if not dep.get(k) else f"{dep[k][q]:.3g}"  # noqa: E731
    return (
        f"3-D scene vs Eq. (1)-(2): DoP of T alone mean {f('dop_T', 'mean')} (p99 {f('dop_T', 'p99')}); "
        f"unpolarized-T error p99 {f('eq12_err', 'p99')} (mean {f('eq12_err', 'mean')}), polarized-T model p99 {f('polT_model_err', 'p99')}"
    )
