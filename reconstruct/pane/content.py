"""The content test: two layers that a right zeta separates share no edges; the crossed gradient correlation of the separated layers."""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

from reconstruct.pane.cone import CONE_MODELS, _span_factor_of
from reconstruct.physics.exclusion import cross_gradient_sums
from reconstruct.physics.harmonic_fit import half_turn_frames, harmonic_fit

log = logging.getLogger(__name__)


CONTENT_SIGMA_PX = 2.0
"""Gaussian smoothing (pixels) of the solved layers before their gradients are correlated (:func:`layer_gradient_correlation`):
keeps the texture, damps the per-pixel spike noise (measured on the stress set: 1.5-2 px separate the families alike)."""


CONTENT_TILES = 3
"""The content score is the RMS of the layer-gradient correlation over CONTENT_TILES x CONTENT_TILES tiles of the view."""


CONTENT_THETA_MAX_DEG = 82.0
"""Pixels a hypothesis sees beyond this incidence are left out of the content test: there the pane reflects about as much as
it transmits (A >= 0.5 for n = 1.5), and a 90 deg twin's solve turns into a layer swap (T' ~ R, R' ~ T) that is as
uncorrelated as the truth (module docstring).  Hypotheses with under a quarter of their pixels below it are not scored."""


def _content_parts(I: np.ndarray, phi: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The span cut into consecutive parts of at least half a polarizer turn (as many as fit, every frame used), each
    as its harmonic mean a0 and modulation c = ac + i as (supp. Eq. (1) fitted over the part); [] when fewer than two
    fit.  Their spike noise is independent (disjoint spikes), so correlating one part's R^ with the next one's T^
    carries no noise term (consecutive frames are not independent: integrate-and-fire makes a pixel's consecutive
    counts anticorrelated), and adjacent parts keep the layers' motion between the two small.
    """
    I = np.asarray(I, np.float64)
    phi = np.asarray(phi, np.float64)
    L = half_turn_frames(phi)
    C = I.shape[0] // L
    if C < 2:
        return []
    b = np.linspace(0, I.shape[0], C + 1).astype(int)
    out = []
    for j in range(C):
        a0, ac, as_ = (t.numpy() for t in harmonic_fit(torch.from_numpy(I[b[j]:b[j + 1]]), torch.from_numpy(phi[b[j]:b[j + 1]])))  # supp. Eq. (1)
        out.append((a0, ac + 1j * as_))
    return out


def layer_gradient_correlation(parts, phi_perp: np.ndarray, theta: np.ndarray, n: float, model: str, span_factor: float = 1.0,
                               sigma: float = CONTENT_SIGMA_PX, theta_max_deg: float = CONTENT_THETA_MAX_DEG, tiles: int = CONTENT_TILES) -> dict:
    """Normalised correlation of the gradients of R^ and T^ solved under one pane hypothesis (module docstring, "content").

    Per chunk (``parts``, :func:`_content_parts`), paper Eq. (1)-(2) invert in closed form: the modulation along phi_perp is
    m = B sinc (R - T) / 2 and the mean a0 = (T + A (R - T)) / 2, so D = 2 m / (B sinc), T^ = 2 a0 - A D, R^ = T^ + D
    (A, B the mean and half difference of R_perp, R_par for ``n`` and ``model``).  Each layer is smoothed by ``sigma``
    pixels and differenced along x and y; the correlation is the mean over adjacent chunks of (gR_j gT_j+1 + gR_j+1 gT_j) / 2
    over sqrt(mean power of gR x mean power of gT), over pixel pairs the hypothesis sees below ``theta_max_deg``.  Independent layers give about 0;
    a pane read as its 90 deg twin where T dominates gives R^ ~ T + (T - R) and T^ ~ T: strongly positive.

    Returns ``corr`` (the whole view) and ``rms``: the root mean square of the correlation over ``tiles`` x ``tiles``
    tiles.  A wrong scale or DoP shape leaks T into R^ by (1 - B / B') T, which changes with theta across the view, so
    a wrong (tilt, model) pair can zero the whole view's correlation but not every tile's; ``rms`` is the score.
    Both NaN when fewer than a quarter of the pixels qualify (a tile with fewer than 16 pairs is skipped).
    """
    from polphysics.fresnel import pane_coefficients

    nan = {"corr": float("nan"), "rms": float("nan")}
    if len(parts) < 2:
        return nan
    co = pane_coefficients(theta, n, model=model)
    A = 0.5 * (co["R_perp"] + co["R_par"])
    B = 0.5 * (co["R_perp"] - co["R_par"]) * span_factor
    ok = np.degrees(theta) <= theta_max_deg
    okx, oky = ok[:-1, :-1] & ok[:-1, 1:], ok[:-1, :-1] & ok[1:, :-1]
    if 0.5 * (okx.mean() + oky.mean()) < 0.25:
        return nan
    sums = cross_gradient_sums(parts, phi_perp, A, B, sigma=sigma, mask=ok, pairs="adjacent", pixels=CONTENT_PIXELS)  # reconstruct.physics.exclusion
    cross, pr, pt = sums["cross"], sums["pr"], sums["pt"]
    cnt = okx.astype(int) + oky.astype(int)

    def corr(sl):
        den = math.sqrt(max(float(pr[sl].sum()) * float(pt[sl].sum()), 1e-300))
        return float(cross[sl].sum()) / den

    h, w = cross.shape
    per_tile = [corr((slice(i * h // tiles, (i + 1) * h // tiles), slice(j * w // tiles, (j + 1) * w // tiles)))
                for i in range(tiles) for j in range(tiles)
                if cnt[i * h // tiles:(i + 1) * h // tiles, j * w // tiles:(j + 1) * w // tiles].sum() >= 16]
    return {"corr": corr(slice(None)), "rms": float(np.sqrt(np.mean(np.square(per_tile)))) if per_tile else float("nan")}


CONTENT_PIXELS = "same"
"""Pixels of the content test (reconstruct.physics.exclusion.cross_gradient_sums).  ``split`` would take R^ and T^ from the two
sets of a checkerboard, so that the sensor's static fixed pattern, common to both layers at a pixel, drops out; the
thresholds below were set with the pattern in, and with ``split`` the network's self-zeta validation moved little
(v7, 3 frames: eval_fresh_val T 33.60 -> 33.60, R 24.15 -> 23.94; eval_paper_val T 35.07 -> 35.03, R 22.63 -> 23.43),
so ``same`` stays."""


CONTENT_MODEL_MARGIN = 0.05
"""Content test: a pane model is claimed when its tile-RMS correlation beats the other model's by this much ..."""


CONTENT_INDEPENDENT = 0.25
"""... and is at most this (the layers come out nearly independent under it: the chance correlation of independent
textures is 0.1-0.25 on 100-200 px views).  Both chosen on the stress set (docs/selfcal.md, "Pane model from the
content"): every claim made there is right; a fast, dim, strong-reflection slab scores 0.34 / 0.45 (single / slab)
and would be read as a single pane by the margin alone."""


def _content_claims_model(best: float, second: float) -> bool:
    return bool(best <= CONTENT_INDEPENDENT and second - best > CONTENT_MODEL_MARGIN)


def content_model(I: np.ndarray, phi: np.ndarray, phi_perp: np.ndarray, theta: np.ndarray, n: float, models=CONE_MODELS) -> dict:
    """The pane model by the layers' content at a fixed geometry (module docstring, "content"): the tile-RMS layer-gradient
    correlation (:func:`layer_gradient_correlation`) under each model; the best is claimed by :func:`_content_claims_model`.
    A wrong model's scale leaks T into R^ by (1 - B / B') T.  Returns ``scores``, ``model`` (or None) and ``identified``.
    """
    halves = _content_parts(I, phi)
    sf = _span_factor_of(phi)
    sc = {mo: layer_gradient_correlation(halves, phi_perp, theta, n, mo, sf)["rms"] for mo in models}
    fin = sorted((v, k) for k, v in sc.items() if np.isfinite(v))
    ok = len(fin) > 1 and _content_claims_model(fin[0][0], fin[1][0])
    return {"scores": sc, "model": fin[0][1] if ok else None, "identified": ok}
