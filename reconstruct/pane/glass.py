"""The glass: index and pane model (single interface or thin slab) from the cone scores, with a prior where the data do not decide."""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)


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
