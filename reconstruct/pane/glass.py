"""The glass: index and pane model (single interface or thin slab) from the cone scores, with a prior where the data do not decide."""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


INDEX_GRID = np.round(np.arange(1.30, 2.2001, 0.01), 4)
"""The refractive indices any pane fit tries: every 0.01 from 1.30 to 2.20 (below crown glass to dense flint).  Each
fit reads a range of it through :func:`index_grid`; the ranges and steps differ, each for a reason given where it is
used:

- the self-calibration's cone (:data:`reconstruct.pane.cone.CONE_N_GRID`): 1.40-1.70 every 0.05.  It scores every
  hypothesis on every stream that ``--zeta self`` calibrates, and it claims an index only when the indices within
  its margin form an interval inside the range (:func:`fit_glass`); a range ending at 1.70 keeps that claim to the
  common glasses it was measured on (docs/selfcal.md);
- calibrate-pane's edge fit (:data:`reconstruct.pane.edges.N_GRID`): 1.30-2.20 every 0.02, the start of a
  Gauss-Newton refinement of n bounded by the same range, so it spans every glass the maps tier renders;
- calibrate-pane's content test (:data:`reconstruct.pane.content_glass.CONTENT_N_GRID`): 1.40-2.00 every 0.02; a best
  index at either end is no minimum and is not used, so the range's ends are the common glasses' (a fixed pattern
  reads n low: an end at 1.30 would let it pull the guess below any glass)."""


def index_grid(lo: float, hi: float, step: float) -> np.ndarray:
    """The indices of :data:`INDEX_GRID` from ``lo`` to ``hi`` (both kept) every ``step`` (a multiple of 0.01)."""
    k = int(round(step / 0.01))
    i0, i1 = (int(round((v - float(INDEX_GRID[0])) / 0.01)) for v in (lo, hi))
    if k < 1 or abs(k * 0.01 - step) > 1e-9 or not 0 <= i0 <= i1 < INDEX_GRID.size:
        raise ValueError(f"no range {lo:g}-{hi:g} every {step:g} in the index grid {INDEX_GRID[0]:g}-{INDEX_GRID[-1]:g} every 0.01")
    return INDEX_GRID[i0:i1 + 1:k].copy()


def fit_glass(scores: dict, prior_n: float, prior_model: str, margin: float) -> dict:
    """Pane model and index from the cone scores (:func:`glass_scores`) of the chosen geometry.

    The model is claimed when its best index beats every other model's best by ``margin``; else
    ``prior_model``.  The index is claimed when the indices within ``margin`` of the model's best form a
    range inside the grid (reaching neither end: the data bound it from both sides); else ``prior_n``
    (moved into that range when outside it).
    """
    models = sorted({k[0] for k in scores})
    best_by_model = {mo: min(v for k, v in scores.items() if k[0] == mo) for mo in models}
    order = sorted(models, key=best_by_model.get)
    model_ok = len(order) > 1 and best_by_model[order[1]] - best_by_model[order[0]] > margin
    model = order[0] if model_ok else prior_model
    if model not in models:
        model = order[0]
    ns = sorted(k[1] for k in scores if k[0] == model)
    vm = min(scores[(model, x)] for x in ns)
    ok_ns = [x for x in ns if scores[(model, x)] <= vm + margin]
    lo_n, hi_n = min(ok_ns), max(ok_ns)
    n_ok = lo_n > ns[0] and hi_n < ns[-1]  # an interval inside the grid: the data reach the cone's edge from both sides
    n = float(min(ok_ns, key=lambda x: scores[(model, x)])) if n_ok else float(prior_n)
    if not n_ok and not (lo_n <= n <= hi_n):
        n = lo_n if n < lo_n else hi_n
    return {
        "model": model, "model_identified": bool(model_ok), "n": n, "n_identified": bool(n_ok), "n_range": [lo_n, hi_n],
        "scores_by_model": best_by_model,
    }
