"""calibrate-pane's content test: where the cone leaves n or the pane model open, the layers solved under each hypothesis should be independent."""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from polinfra.errors import ConfigError
from reconstruct.pane.calibrate_config import CalibratePaneConfig
from reconstruct.pane.glass import index_grid

log = logging.getLogger(__name__)


CONTENT_N_GRID = index_grid(1.40, 2.00, 0.02)
"""Index grid of the content test (common glasses; a best index at either end is not used; why this range:
:data:`reconstruct.pane.glass.INDEX_GRID`)."""


CONTENT_PART_HALF_TURNS = 3
"""Half turns of the polarizer per time part of the content test when ``content_parts`` is 0 (0.05 s at 30 rev/s):
parts much longer than that blur the moving layers (an eval_fresh_val build at 0.2 s, every solver within 0.3 dB:
11 of 16 with 2 parts of 0.1 s, 12 of 16 with 4 of 0.05 s; docs/calibrate_pane.md, round 5)."""


def _one_sigma_geometries(x: np.ndarray, cov: np.ndarray, wrt: tuple[int, ...]) -> list[np.ndarray]:
    """The geometry ``x`` moved by one standard deviation along each principal direction of a fit's covariance
    (``cov`` over the parameters ``wrt``, as :class:`reconstruct.pane.geometry_fit.GeometryFit` carries them): where an index read at ``x`` is re-read to propagate the
    geometry's uncertainty into it.
    """
    ev, evec = np.linalg.eigh(np.asarray(cov, np.float64))
    out = []
    for lam, v in zip(ev, evec.T):
        xp = np.asarray(x, np.float64).copy()
        xp[list(wrt)] += math.sqrt(max(float(lam), 0.0)) * v
        out.append(xp)
    return out


def content_n_sigma_from_geometry(pm, x: np.ndarray, cov: np.ndarray, wrt: tuple[int, ...], model: str, n_hat: float, step: int = 4) -> float:
    """1-sigma of a content-test index from the geometry's uncertainty.  The content test finds the zeta under
    which the layers do not leak into each other, i.e. the reflection's DoP (R_perp - R_par) / (R_perp + R_par)
    per pixel (the leak is alpha = A - A' B / B', docs/calibrate_pane.md); so for each principal direction
    of the geometry's covariance, the geometry moved by one standard deviation, the index whose DoP map best matches
    the fitted one (least squares over the view, every ``step``-th pixel) is the shifted reading.  Returns the
    root sum of squares of the shifts.
    """
    from polphysics.fresnel import pane_coefficients

    key = "thin_slab" if model == "thick_slab" else model

    def dop(theta: np.ndarray, n: float) -> np.ndarray:
        co = pane_coefficients(theta, float(n), model=key)
        return (co["R_perp"] - co["R_par"]) / np.maximum(co["R_perp"] + co["R_par"], 1e-12)

    d0 = dop(pm.maps(x)["theta"][::step, ::step], n_hat)
    grid = n_hat + np.arange(-0.2, 0.2001, 0.0025)
    shifts = []
    for xp in _one_sigma_geometries(x, cov, wrt):
        th = pm.maps(xp)["theta"][::step, ::step]
        cost = [float(np.mean((dop(th, g) - d0) ** 2)) for g in grid]
        shifts.append(float(grid[int(np.argmin(cost))] - n_hat))
    return float(np.sqrt(np.sum(np.square(shifts))))


CONTENT_SPLIT_PARTS = 4
"""``content_pixels = "auto"`` splits the pixels where the content test has at least this many time parts.  The
split removes the fixed pattern's pull on the index but halves each layer's pixels; with 2 parts (0.1 s) the spread
costs more than the bias (validation builds, every solver within 0.3 dB: same 18, split 17 of 28), with 4 (0.2 s)
the other way round (stress regimes and eval_fresh_val's scenes built at 0.2 s: same 25, split 28 of 34;
docs/calibrate_pane.md, round 6)."""


def content_pixels_for(pixels: str, parts: int) -> str:
    """The content test's pixel mode for ``content_pixels`` = ``pixels`` and ``parts`` time parts."""
    if pixels == "auto":
        return "split" if parts >= CONTENT_SPLIT_PARTS else "same"
    return pixels


def content_parts_for(phi: np.ndarray, frames: int, parts: int = 0) -> int:
    """Time parts of the content test for a span of ``frames`` frames at polarizer angles ``phi``: ``parts`` when
    given, else one per :data:`CONTENT_PART_HALF_TURNS` half turns (rounded), at least 2.
    """
    from reconstruct.physics.harmonic_fit import half_turn_frames

    if parts:
        return int(parts)
    chunks = int(frames) // max(1, half_turn_frames(np.asarray(phi, np.float64)))
    return max(2, int(round(chunks / CONTENT_PART_HALF_TURNS)))


def content_glass(I: np.ndarray, phi: np.ndarray, theta: np.ndarray, phi_perp: np.ndarray, gain: float, models: tuple[str, ...],
                  cfg: CalibratePaneConfig, fixed_n: float | None = None, n_grid: np.ndarray | None = None, parts: list | None = None) -> dict:
    """Pane model and index from the layers' content (gradient exclusion, :mod:`reconstruct.physics.exclusion`).

    For every hypothesis (model, n) the span's time parts are solved in closed form (paper Eq. (1)-(2)) and the
    gradients of R^ of one part and T^ of another are correlated per tile (``content_tiles`` per axis); the score is
    the mean squared tile correlation (a wrong zeta leaks one layer's texture into the other: module docstring of
    reconstruct.physics.exclusion).  The best hypothesis is the least score.  A model is claimed when the other model's best
    score is higher by ``content_z`` standard errors of the paired per-tile differences; n when every index more
    than ``max_n_sigma`` away is rejected in the same way.  Featureless layers leave every score at the noise level
    and nothing is claimed.  Returns the scores, the choice and the two verdicts.
    """
    from polphysics.fresnel import pane_coefficients
    from reconstruct.physics.exclusion import (
        cross_gradient_sums,
        label_correlations,
        part_harmonics,
        rotate_parts,
    )

    t0 = time.perf_counter()
    H, W = theta.shape
    K = cfg.content_tiles
    yy, xx = np.mgrid[0:H, 0:W]
    tiles = (yy * K // H) * K + (xx * K // W)
    if parts is None:  # ``parts``: the time parts' (a0, c) given directly (docs/calibrate_pane_report.py: noiseless parts)
        try:
            parts = part_harmonics(I, phi, content_parts_for(phi, I.shape[0], cfg.content_parts))
        except ConfigError as e:
            return {"ok": False, "why": str(e)}
    pixels = content_pixels_for(cfg.content_pixels, len(parts))
    turned = rotate_parts(parts, phi_perp)  # the same for every hypothesis
    grid = np.array([fixed_n]) if fixed_n else (CONTENT_N_GRID if n_grid is None else n_grid)
    ct = {}
    for model in models:
        rows = []
        for n in grid:
            co = pane_coefficients(theta, float(n), model=model)
            A = 0.5 * (co["R_perp"] + co["R_par"])
            B = 0.5 * (co["R_perp"] - co["R_par"])
            rows.append(label_correlations(cross_gradient_sums(turned, None, A, B, gain, sigma=cfg.content_sigma_px, pixels=pixels), tiles, K * K, power=cfg.content_power))
        ct[model] = np.array(rows)  # (n, tiles)
    ok = np.all(np.isfinite(np.concatenate(list(ct.values()))), axis=0)
    if ok.sum() < 4:
        return {"ok": False, "why": f"only {int(ok.sum())} tiles carry gradients: nothing to score"}
    sq = {m: v[:, ok] ** 2 for m, v in ct.items()}
    score = {m: v.mean(1) for m, v in sq.items()}
    best_model = min(models, key=lambda m: float(score[m].min()))
    i_best = int(np.argmin(score[best_model]))
    ref = sq[best_model][i_best]
    T_ = int(ok.sum())

    def zdiff(other: np.ndarray) -> float:
        d = other - ref
        se = float(np.std(d, ddof=1) / math.sqrt(T_))
        return float(d.mean() / se) if se > 0 else float("inf")

    out = {"ok": True, "tiles": T_, "parts": len(parts), "pixels": pixels, "n_grid": grid.tolist(), "score": {m: v.tolist() for m, v in score.items()},
           "correlation_global_best": float(np.nanmean(ct[best_model][i_best][ok])), "best_model": best_model, "best_n": float(grid[i_best]),
           "best_score": float(score[best_model][i_best])}
    if len(models) > 1:
        other = [m for m in models if m != best_model][0]
        j = int(np.argmin(score[other]))
        zm = zdiff(sq[other][j])
        out["model"] = {"identified": bool(zm >= cfg.content_z), "value": best_model, "z": zm, "other": other, "other_n": float(grid[j]), "other_score": float(score[other][j]),
                        "why": f"layers' gradients least correlated under {best_model} (n {grid[i_best]:.2f}: score {score[best_model][i_best]:.4f}); "
                               f"best {other} (n {grid[j]:.2f}) scores {score[other][j]:.4f}, {zm:.1f} standard errors higher over {T_} tiles (need {cfg.content_z:g})"}
    if not fixed_n and grid.size > 1:
        far = np.abs(grid - grid[i_best]) > cfg.max_n_sigma + 1e-9
        zs = np.array([zdiff(sq[best_model][k]) if far[k] else 0.0 for k in range(grid.size)])  # within the tolerance: accepted
        accepted = grid[(zs < cfg.content_z)]
        lo, hi = float(accepted.min()), float(accepted.max())
        inside = float(grid[0]) < grid[i_best] < float(grid[-1])
        out["n"] = {"identified": bool(far.any() and np.all(zs[far] >= cfg.content_z) and inside), "value": float(grid[i_best]), "accepted_range": [lo, hi],
                    "why": f"indices {lo:.2f}-{hi:.2f} of {best_model} score within {cfg.content_z:g} standard errors of the best ({grid[i_best]:.2f})"
                           + ("" if inside else "; the best index is at the end of the grid")}
    out["seconds"] = time.perf_counter() - t0
    return out
