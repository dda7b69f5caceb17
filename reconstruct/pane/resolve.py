"""The twin decision: which of the candidate geometries along the fov-tilt valley, and which 90 deg family, the DoP cone and then the layers' content prefer."""

from __future__ import annotations

import logging
import math

import numpy as np

from reconstruct.pane.cone import (
    CONE_MODELS,
    _hypothesis_maps,
    _span_factor_of,
    chunk_harmonics,
    cone_aggregates,
    glass_scores,
)
from reconstruct.pane.content import (
    _content_claims_model,
    _content_parts,
    layer_gradient_correlation,
)
from reconstruct.pane.normal import valley_candidates

log = logging.getLogger(__name__)


def _resolve_by_cone(I, phi, f, fit, W, H, fov_given, cfg) -> dict:
    """Choose among the panes the orientation field cannot tell apart (the tilt valley and the 90 deg twin
    family of a narrow view) by the polarization cone: the one whose DoP bounds hold the data.

    Returns a dict with ``resolved`` (bool), the chosen ``tilt``, ``azimuth``, ``fov_deg``, the best cone
    violation of each family (``v_family``), ``chosen_family`` (0 = the orientation optimum's) and the
    aggregates of the chosen pane (``aggs``) for the glass fit.
    """
    h, w = f.psi.shape
    seeds = [(fit["tilt"], fit["azimuth"], fit["fov_deg"])]
    if "twin_tilt" in fit:
        seeds.append((fit["twin_tilt"], fit["twin_azimuth"], fit["twin_fov_deg"]))
    cands = valley_candidates(f.s4, w, h, seeds, fov_given, tilt_step_deg=cfg.valley_step_deg, keep_ratio=cfg.valley_ratio, drop_fov_bounds=cfg.valley_drop_fov_bounds)
    cands += [{"tilt": t, "azimuth": a, "fov_deg": fv, "score": sc, "family": k}
              for k, (t, a, fv, sc) in enumerate([(fit["tilt"], fit["azimuth"], fit["fov_deg"], fit["score"])]
                                                 + ([(fit["twin_tilt"], fit["twin_azimuth"], fit["twin_fov_deg"], fit["twin_score"])] if "twin_tilt" in fit else []))]
    a0, c = chunk_harmonics(I, phi)
    sf = _span_factor_of(phi)
    pp_best = _hypothesis_maps(W, H, fit["tilt"], fit["azimuth"], fit["fov_deg"])[0]
    for cd in cands:
        pp, th = _hypothesis_maps(W, H, cd["tilt"], cd["azimuth"], cd["fov_deg"])
        cd["family"] = 0 if float(np.mean(np.cos(2.0 * (pp - pp_best)))) > 0 else 1  # by the field, not by the seed
        cd["aggs"] = cone_aggregates(a0, c, pp, th)
        cd["V"] = min(glass_scores(cd["aggs"], sf).values())
    v_fam = {k: min((cd["V"] for cd in cands if cd["family"] == k), default=float("inf")) for k in (0, 1)}
    fam = 0 if v_fam[0] <= v_fam[1] else 1
    other = v_fam[1 - fam]
    resolved = other - v_fam[fam] > cfg.cone_margin and other >= cfg.cone_ratio * v_fam[fam]
    content = None
    conflict = False
    if cfg.content_margin > 0:
        content = _resolve_by_content(I, phi, cands, v_fam, W, H, sf, cfg)
        if not resolved and content["resolved"]:
            fam, resolved = content["chosen_family"], True
            content["used"] = True
        elif resolved and content["clear"] and content["chosen_family"] != fam:
            # the cone and the content disagree: the cone's edge is noise-sensitive where one layer is nearly black
            # (the right family sits on -DoP_T there with no slack), the content is blind to motion within half a turn;
            # neither is trusted over the other
            resolved, conflict = False, True
    ok = [cd for cd in cands if cd["family"] == fam and cd["V"] <= v_fam[fam] + cfg.cone_margin]
    if content is not None and content.get("used") and (content["model_identified"] or cfg.model != "auto"):
        pick = content["pick"]  # within the family: the pane whose layers come out least correlated under the model they identify
    else:
        pick = max(ok, key=lambda cd: cd["score"])  # within the family: the cone-consistent pane the orientation field prefers
    out = {"resolved": bool(resolved), "by": ("content" if content is not None and content.get("used") else "cone") if resolved else None, "conflict": conflict,
           "tilt": pick["tilt"], "azimuth": pick["azimuth"], "fov_deg": pick["fov_deg"], "score": pick["score"],
           "v_family": [v_fam[0], v_fam[1]], "chosen_family": fam, "candidates": len(cands), "aggs": pick["aggs"],
           "tilt_range_deg": [math.degrees(min(cd["tilt"] for cd in ok)), math.degrees(max(cd["tilt"] for cd in ok))]}
    if content is not None:
        out["content"] = {k: v for k, v in content.items() if k != "pick"}
    return out


def _resolve_by_content(I, phi, cands, v_fam, W, H, sf, cfg) -> dict:
    """The content test between the two families where the cone leaves them both open (module docstring, "content").

    Every cone-consistent candidate of each family is scored by :func:`layer_gradient_correlation` (``rms``) under each
    pane model that may be used (``cfg.model``, or for auto both of :data:`CONE_MODELS`, at ``cfg.n``); a family's score
    is its smallest (the tilt valley and the model's scale are nuisances: some tilt of the right family makes the layers
    independent).  The family with the smaller score wins when the other's exceeds it by ``content_margin`` and by
    ``content_ratio`` times, and the winner itself holds the cone (violation within ``cone_margin``: a family that
    breaks the cone is not rescued by its content).  Within the winner, the pane model is claimed when its best score
    is low and beats the other model's best (:func:`_content_claims_model`; else ``cfg.prior_model``), and the pane is
    that model's best-scoring candidate (unclaimed: the caller keeps the orientation field's choice, the content's
    tilt being conditional on an assumed scale).  Returns ``resolved``, ``chosen_family``, ``corr_family`` (the two scores),
    ``corr_by_model`` (the winner's best per model), ``model``, ``model_identified``, ``n`` and ``pick``.
    """
    models = CONE_MODELS if cfg.model == "auto" else (cfg.model,)
    halves = _content_parts(I, phi)
    best: dict = {}
    for cd in cands:
        k = cd["family"]
        if cd["V"] > v_fam[k] + cfg.cone_margin:
            continue
        pp, th = _hypothesis_maps(W, H, cd["tilt"], cd["azimuth"], cd["fov_deg"])
        cd["content"] = {}
        for mo in models:
            r = layer_gradient_correlation(halves, pp, th, cfg.n, mo, sf)["rms"]
            cd["content"][mo] = r
            if np.isfinite(r) and ((k, mo) not in best or r < best[(k, mo)][0]):
                best[(k, mo)] = (r, cd)
    score = {k: min((best[(k, mo)][0] for mo in models if (k, mo) in best), default=float("inf")) for k in (0, 1)}
    fam = 0 if score[0] <= score[1] else 1
    o, c = score[1 - fam], score[fam]
    clear = bool(np.isfinite(c) and np.isfinite(o) and o - c > cfg.content_margin and o >= cfg.content_ratio * c)  # both families scored
    resolved = clear and v_fam[fam] <= cfg.cone_margin
    by_model = {mo: best[(fam, mo)][0] for mo in models if (fam, mo) in best}
    order = sorted(by_model, key=by_model.get)
    model_ok = len(order) > 1 and _content_claims_model(by_model[order[0]], by_model[order[1]])
    model = order[0] if order and (model_ok or len(models) == 1) else cfg.prior_model  # nothing scored (no candidate within the cone): the prior
    pick = best.get((fam, model), best.get((fam, order[0]) if order else None, (None, None)))[1] if order else None
    return {"resolved": resolved, "clear": clear, "chosen_family": fam, "corr_family": [score[0], score[1]], "corr_by_model": by_model,
            "model": model, "model_identified": bool(model_ok), "n": cfg.n,
            "scored": sum(1 for cd in cands if "content" in cd), "pick": pick}
