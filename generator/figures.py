"""Figures of a rendered scene: pane geometry, coefficient and zeta maps, mixed frames."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polinfra.plotting import image_grid, save_figure
from polphysics.stokes import aolp, dop, polarizer_intensity
from polphysics.zeta import zeta

__all__ = ["plot_maps", "plot_mixed_frames"]


def plot_maps(maps: dict[str, np.ndarray], path: str | os.PathLike, title: str = "") -> Path:
    """theta, phi_perp, R_perp, R_par and zeta at four polarizer angles (paper Eq. (2))."""
    th = np.rad2deg(maps["theta"])
    pp = np.rad2deg(maps["phi_perp"])
    panels = [
        ("incidence angle theta", th, {"cmap": "viridis", "label": "deg"}),
        ("s-direction phi_perp", pp, {"cmap": "twilight", "vmin": 0, "vmax": 180, "label": "deg (image, CCW from +x)"}),
        ("R_perp", maps["R_perp"], {"cmap": "magma", "label": "reflectance"}),
        ("R_par", maps["R_par"], {"cmap": "magma", "label": "reflectance"}),
    ]
    vmax = float(np.max(maps["R_perp"]))
    for phi_deg in (0, 45, 90, 135):
        z = zeta(np.deg2rad(phi_deg), maps["R_perp"], maps["R_par"], maps["phi_perp"])
        panels.append((f"zeta at phi = {phi_deg} deg", z, {"cmap": "magma", "vmin": 0, "vmax": vmax, "label": "reflected fraction"}))
    return save_figure(image_grid(panels, ncols=4, title=title or "pane response (paper Eq. (2))"), path)


def plot_mixed_frames(stokes: np.ndarray, T: np.ndarray, R: np.ndarray, path: str | os.PathLike, phis_deg=(0, 45, 90, 135), title: str = "") -> Path:
    """Mixed intensity I(phi) behind the polarizer at several angles, with DoP, AoLP and the GT layers."""
    s0, s1, s2 = stokes
    panels = [("T layer (ground truth)", T, {"vmin": 0, "vmax": 1, "label": "radiance"}), ("R layer (ground truth)", R, {"vmin": 0, "vmax": 1, "label": "radiance"})]
    panels.append(("DoP of mixed light", dop(s0, s1, s2), {"cmap": "inferno", "vmin": 0, "vmax": 1, "label": "degree"}))
    panels.append(("AoLP of mixed light", np.rad2deg(aolp(s1, s2)), {"cmap": "twilight", "vmin": 0, "vmax": 180, "label": "deg"}))
    hi = float(np.percentile(s0, 99.5)) * 0.5 + 1e-9
    for p in phis_deg:
        panels.append((f"I(phi = {p} deg)", polarizer_intensity(s0, s1, s2, np.deg2rad(p)), {"vmin": 0, "vmax": hi, "label": "radiance"}))
    return save_figure(image_grid(panels, ncols=4, title=title or "mixed frame behind the rotating polarizer"), path)
