"""Where the mixing coefficients zeta come from: ground truth, physics, or a learned estimator.

* ``gt``: per-pixel pane maps R_perp, R_par, phi_perp shipped with a dataset
  group (the oracle, for evaluation), turned into zeta by paper Eq. (2).
* ``physics``: a calibrated pane geometry (camera, pane plane, index, pane
  model) -> theta(p), phi_perp(p) by :mod:`polphysics.geometry`, Fresnel
  reflectances by :mod:`polphysics.fresnel`, then paper Eq. (2).
* ``learned``: the parameter branch of the network (:func:`zeta_learned`).
* ``self``: the pane geometry estimated from the stream itself (:mod:`reconstruct.pane.selfcal`;
  the 90 deg twin of narrow glancing views resolved by the DoP cone, or where the cone holds both by
  the layers' content, R^ and T^ gradients uncorrelated under the right pane; the index and pane
  model fitted where the cone constrains them, the model also by that content test, else a thin slab
  with n = 1.5), then as ``physics``;
  falls back to ``learned`` where nothing modulates or the twin stays ambiguous.

A spike frame integrates over an aggregation window during which the polarizer
turns by ``span`` radians (0.65 ms at 30 rev/s = 7 deg).  The frame's zeta is the
window average of Eq. (2): cos 2(phi - phi_perp) is multiplied by
sinc_span = sin(span) / span (exact for constant rotation speed).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from polinfra.errors import ShapeError

__all__ = ["ZETA_SOURCES", "zeta_eq2", "PaneMaps", "zeta_from_maps", "pane_maps_from_geometry"]

ZETA_SOURCES = ("gt", "physics", "learned", "self")
"""Names accepted by the evaluation harness's ``--zeta`` option."""


def _span_factor(span_rad: float) -> float:
    return 1.0 if span_rad == 0.0 else math.sin(span_rad) / span_rad


def zeta_eq2(
    phi: torch.Tensor, R_perp: torch.Tensor, R_par: torch.Tensor, phi_perp: torch.Tensor, span_rad: float = 0.0
) -> torch.Tensor:
    """Paper Eq. (2) in torch, averaged over a polarizer sweep of ``span_rad``.

    zeta = R_perp cos^2(phi - phi_perp) + R_par sin^2(phi - phi_perp)
         = (R_perp + R_par)/2 + (R_perp - R_par)/2 cos 2(phi - phi_perp)

    Args:
        phi: polarizer angles (N,) or (..., N), radians (window centres).
        R_perp, R_par, phi_perp: maps (..., H, W).
        span_rad: polarizer rotation during one aggregation window (0 = instantaneous).

    Returns:
        zeta (..., N, H, W) in [min(R_perp, R_par), max(R_perp, R_par)].
    """
    ph = phi[..., None, None]
    mean = 0.5 * (R_perp + R_par).unsqueeze(-3)
    amp = 0.5 * (R_perp - R_par).unsqueeze(-3)
    return mean + amp * _span_factor(span_rad) * torch.cos(2.0 * (ph - phi_perp.unsqueeze(-3)))  # paper Eq. (2)


@dataclasses.dataclass(frozen=True)
class PaneMaps:
    """Per-pixel pane response: R_perp, R_par (reflectances), phi_perp (radians), each (H, W) float."""

    R_perp: np.ndarray
    R_par: np.ndarray
    phi_perp: np.ndarray

    def __post_init__(self) -> None:
        shapes = {np.shape(self.R_perp), np.shape(self.R_par), np.shape(self.phi_perp)}
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise ShapeError(f"PaneMaps needs three (H, W) maps of one shape; got {sorted(shapes)}", actual_shape=None, expected_shape="(H, W)")


def zeta_from_maps(
    maps: PaneMaps, phi: torch.Tensor | np.ndarray, span_rad: float = 0.0, *, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """Zeta (..., N, H, W) for polarizer angles phi (..., N) from pane maps, paper Eq. (2).

    Agrees with :func:`polphysics.zeta.zeta` at span_rad = 0 (tested).
    """
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
    phi_t = torch.as_tensor(phi, dtype=dtype, device=device)
    return zeta_eq2(phi_t, t(maps.R_perp), t(maps.R_par), t(maps.phi_perp), span_rad)


def pane_maps_from_geometry(camera, plane, n: float, model: str = "single", thickness_m: float = 0.0, absorption_per_m: float = 0.0) -> PaneMaps:
    """Calibrated pane geometry -> per-pixel R_perp, R_par, phi_perp (the ``physics`` source).

    Args:
        camera: :class:`polphysics.geometry.PinholeCamera` (calibrated intrinsics/pose).
        plane: :class:`polphysics.geometry.Plane` of the pane's front surface.
        n: relative refractive index of the glass.
        model: pane model, one of :data:`polphysics.fresnel.PANE_MODELS`.
        thickness_m, absorption_per_m: slab parameters.

    Returns:
        :class:`PaneMaps` with (H, W) float64 maps.
    """
    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import incidence_geometry

    geo = incidence_geometry(camera, plane)
    co = pane_coefficients(geo["theta"], n, model=model, thickness_m=thickness_m, absorption_per_m=absorption_per_m)
    return PaneMaps(R_perp=co["R_perp"], R_par=co["R_par"], phi_perp=geo["phi_perp"])


def _pad4(x: torch.Tensor, m: int = 4) -> torch.Tensor:
    H, W = x.shape[-2:]
    ph, pw = (-H) % m, (-W) % m
    return torch.nn.functional.pad(x, (0, pw, 0, ph), mode="replicate") if (ph or pw) else x

