"""The planner (``--tier auto``) checked against measurement: part of ``polspike bench tradeoff``.

For every measured candidate row (analytic, maps, full at some spp) the planner's prediction
(:func:`generator.planner.predict_tiers`) is set beside the measured error with the reference's
noise taken out (``err_corrected``, :func:`polspike.pipeline.tradeoff.corrected_error`).  A row
agrees when prediction and measurement are within a factor of 2, both floored at the measurement's
resolution (the reference noise left in ``err_vs_ref_p99``: an error below it is unresolved, and a
prediction below it cannot be told from it).

For every tolerance the planner's pick is rendered (unless a measured row already is that
candidate) and measured: ``met`` when its corrected error is <= EPS; ``resolved`` when the
measurement's resolution is <= EPS too (otherwise ``met`` only says the error is not visibly
larger).  ``cheapest`` when no measured candidate of a lower cost rank (analytic < area-sampled analytic < maps < full by
spp) met EPS.
"""

from __future__ import annotations

import logging
import math

from polinfra.errors import ConfigError

__all__ = ["check_planner", "planner_markdown", "DEFAULT_TOLERANCES"]

log = logging.getLogger(__name__)

DEFAULT_TOLERANCES = (5e-2, 2e-2, 1e-2, 1e-3)


def _rank(tier: str, spp: int | None, spectral: bool = False, supersample: int = 0) -> float:
    if tier == "analytic":
        return 0.5 if supersample else 0.0  # the area-sampled analytic tier: between the point sample and maps
    if tier == "maps":
        return 1.0
    return 2.0 + math.log2(max(1, int(spp or 1))) + (0.5 if spectral else 0.0)


def _agree(pred: float, meas: float, resolution: float) -> bool:
    a, b = max(pred, resolution), max(meas, resolution)
    return 0.5 <= a / b <= 2.0


def _spectral(row: dict, dispersive: bool) -> bool:
    """A spectral render of a fixed-index pane is rendered mono (one band)."""
    return bool(row.get("spectral")) and dispersive


def _match(e, row: dict, dispersive: bool) -> bool:
    if row.get("tier") != e.tier:
        return False
    if e.tier == "analytic":
        return bool(e.spectral) == bool(row.get("spectral") and dispersive) and int(row.get("supersample") or 0) == int(e.supersample)
    if e.tier == "maps":
        return True
    return int(row.get("spp") or 0) == int(e.spp) and _spectral(row, dispersive) == bool(e.spectral)


def check_planner(scenes: list, rows: list[dict], refs: dict, tolerances=DEFAULT_TOLERANCES, max_pick_spp: int = 256) -> dict:
    """Predictions vs measurements and the auto picks, per scene (see the module docstring)."""
    from generator.planner import plan_tier, predict_tiers, scene_features, with_noise_pilot
    from polspike.pipeline.tradeoff import Candidate, _radiance_error, _render_first, corrected_error

    pred_rows, picks, noise = [], [], []
    for scene in scenes:
        if scene.name not in refs:
            continue
        S_ref, res = refs[scene.name]
        feats = with_noise_pilot(scene, scene_features(scene))  # every scene's k measured, to set beside the rows
        ests = predict_tiers(scene, feats)
        disp = scene.pane.glass is not None
        measured = [r for r in rows if r["scene"] == scene.name and "err_corrected" in r and r.get("tier") in ("analytic", "maps", "full")]
        noise.append(_noise_row(scene.name, feats, measured, disp))
        for r in measured:
            e = next((e for e in ests if _match(e, r, disp)), None)
            if e is None:
                spp = int(r.get("spp") or 1)
                e = next(x for x in predict_tiers(scene, feats, spp_grid=(spp,)) if x.tier == "full" and x.spectral == _spectral(r, disp))
            pred_rows.append({"scene": scene.name, "candidate": r["candidate"], "tier": r["tier"], "spp": r.get("spp"), "spectral": _spectral(r, disp),
                              "predicted_p99": e.predicted_p99, "measured_p99": r["err_corrected"], "resolution": r["resolution"],
                              "ratio": (max(e.predicted_p99, r["resolution"]) / max(r["err_corrected"], r["resolution"])) if max(r["err_corrected"], r["resolution"]) > 0 else None,
                              "agree_x2": _agree(e.predicted_p99, r["err_corrected"], r["resolution"])})
        for eps in tolerances:
            try:
                plan = plan_tier(scene, eps, feats)
            except ConfigError as exc:
                picks.append({"scene": scene.name, "tolerance": eps, "pick": "unreachable", "message": str(exc)})
                continue
            c = plan.choice
            row = next((r for r in measured if _match(c, r, disp)), None)
            if row is None and c.tier == "full" and c.spp <= max_pick_spp:
                cand = Candidate(f"auto pick full {c.spp}spp", "full", int(c.spp), spectral=bool(c.spectral), variant="llvm")
                S, _, per = _render_first(scene, cand, seed=5)
                row = {"candidate": cand.label, "per_frame_s": per, **corrected_error(_radiance_error(S, S_ref), res)}
                measured.append({**row, "scene": scene.name, "tier": "full", "spp": c.spp, "spectral": c.spectral})
                pred_rows.append({"scene": scene.name, "candidate": cand.label, "tier": "full", "spp": c.spp, "spectral": bool(c.spectral),
                                  "predicted_p99": c.predicted_p99, "measured_p99": row["err_corrected"], "resolution": res,
                                  "ratio": max(c.predicted_p99, res) / max(row["err_corrected"], res), "agree_x2": _agree(c.predicted_p99, row["err_corrected"], res)})
            if row is None and c.tier == "analytic" and c.spectral and not c.supersample:  # Eq. (1)-(2) per band, weighted
                from generator.analytic import analytic_maps, spectral_frame
                from generator.layers import LayerContent
                from generator.tiers_mitsuba import spectral_bands

                hw = (scene.camera.height, scene.camera.width)
                wl, w = spectral_bands()
                S, _, _ = spectral_frame([(float(wi), analytic_maps(scene, float(x))) for x, wi in zip(wl, w)],
                                         LayerContent(scene.layers.transmission, hw), LayerContent(scene.layers.reflection, hw), 0.0)
                row = {"candidate": "auto pick analytic spectral", **corrected_error(_radiance_error(S, S_ref), res)}
                measured.append({**row, "scene": scene.name, "tier": "analytic", "spp": None, "spectral": True})
                pred_rows.append({"scene": scene.name, "candidate": row["candidate"], "tier": "analytic", "spp": None, "spectral": True,
                                  "predicted_p99": c.predicted_p99, "measured_p99": row["err_corrected"], "resolution": res,
                                  "ratio": max(c.predicted_p99, res) / max(row["err_corrected"], res), "agree_x2": _agree(c.predicted_p99, row["err_corrected"], res)})
            if row is None and c.tier == "analytic" and c.supersample:  # the pixel's area on K x K rays
                from generator.analytic_area import area_frames
                from generator.tiers_mitsuba import spectral_bands

                bands = list(zip(*spectral_bands())) if c.spectral and disp else None
                S = area_frames(scene, [0.0], c.supersample, bands)[0][0]
                row = {"candidate": f"auto pick {c.label()}", **corrected_error(_radiance_error(S, S_ref), res)}
                measured.append({**row, "scene": scene.name, "tier": "analytic", "spp": None, "spectral": bool(c.spectral and disp), "supersample": c.supersample})
                pred_rows.append({"scene": scene.name, "candidate": row["candidate"], "tier": "analytic", "spp": None, "spectral": bool(c.spectral and disp),
                                  "predicted_p99": c.predicted_p99, "measured_p99": row["err_corrected"], "resolution": res,
                                  "ratio": max(c.predicted_p99, res) / max(row["err_corrected"], res), "agree_x2": _agree(c.predicted_p99, row["err_corrected"], res)})
            label = c.label()
            if row is None:
                picks.append({"scene": scene.name, "tolerance": eps, "pick": label, "predicted_p99": c.predicted_p99, "measured_p99": None,
                              "met": None, "resolved": None, "cheapest": None, "note": f"not rendered (spp > {max_pick_spp})"})
                continue
            met = row["err_corrected"] <= eps
            better = [r for r in measured if r["err_corrected"] <= eps
                      and _rank(r["tier"], r.get("spp"), _spectral(r, disp), int(r.get("supersample") or 0)) < _rank(c.tier, c.spp, c.spectral, c.supersample)]
            picks.append({"scene": scene.name, "tolerance": eps, "pick": label, "predicted_p99": c.predicted_p99, "measured_p99": row["err_corrected"],
                          "resolution": row["resolution"], "met": met, "resolved": row["resolution"] <= eps, "cheapest": not better,
                          "cheaper_that_met": [r["candidate"] for r in better]})
    n = len(pred_rows)
    n_ok = sum(r["agree_x2"] for r in pred_rows)
    judged = [p for p in picks if p.get("met") is not None]
    summary = {
        "prediction_rows": n, "agree_x2": n_ok,
        "picks": len(picks), "picks_measured": len(judged),
        "picks_met": sum(bool(p["met"]) for p in judged), "picks_cheapest": sum(bool(p["cheapest"]) for p in judged),
        "picks_unresolved": sum(not p["resolved"] for p in judged),
    }
    return {"predictions": pred_rows, "picks": picks, "summary": summary, "noise_k": noise, "features": {}}


def _noise_row(name: str, feats: dict, measured: list[dict], dispersive: bool) -> dict:
    """The full tier's noise coefficient: the lobe-choice proxy's, the pilot's (estimate and the upper bound the
    planner uses) and the measured one (geometric mean over the mono full-tier rows of ``err_corrected * sqrt(spp)``).
    """
    from generator.planner import NOISE_GAIN

    p = feats.get("noise_pilot") or {}
    ks = [r["err_corrected"] * math.sqrt(int(r["spp"])) for r in measured
          if r.get("tier") == "full" and not _spectral(r, dispersive) and r.get("spp") and r["err_corrected"] > 0]
    k_meas = math.exp(sum(math.log(k) for k in ks) / len(ks)) if ks else None
    k_used = feats.get("noise_k")
    return {"scene": name, "proxy_k": p.get("proxy_k", (feats["noise_proxy"] * NOISE_GAIN) if "noise_proxy" in feats else None),
            "pilot_k": p.get("k"), "pilot_k_upper": p.get("k_upper"), "pilot_s": p.get("seconds"), "k_used": k_used,
            "measured_k": k_meas, "used_over_measured": (k_used / k_meas) if (k_used and k_meas) else None}


def planner_markdown(res: dict) -> str:
    f = lambda v: "n/a" if v is None else f"{v:.3g}"  # noqa: E731
    out = ["## Planner (`--tier auto`): predicted vs measured p99 radiance error", "",
           "| scene | candidate | predicted p99 | measured p99 (ref noise out) | resolution | ratio | within x2 |", "|---|---|---|---|---|---|---|"]
    for r in res["predictions"]:
        out.append(f"| {r['scene']} | {r['candidate']} | {f(r['predicted_p99'])} | {f(r['measured_p99'])} | {f(r['resolution'])} | {f(r['ratio'])} | {'yes' if r['agree_x2'] else '**no**'} |")
    out += ["", "| scene | tolerance | auto pick | predicted | measured | met | resolved | cheapest |", "|---|---|---|---|---|---|---|---|"]
    yn = lambda v: "n/a" if v is None else ("yes" if v else "**no**")  # noqa: E731
    for p in res["picks"]:
        if p["pick"] == "unreachable":
            out.append(f"| {p['scene']} | {p['tolerance']:g} | unreachable: {p['message'].split(': ', 1)[-1]} | | | | | |")
            continue
        out.append(f"| {p['scene']} | {p['tolerance']:g} | {p['pick']} | {f(p['predicted_p99'])} | {f(p['measured_p99'])} | {yn(p['met'])} | {yn(p['resolved'])} | {yn(p['cheapest'])} |")
    if res.get("noise_k"):
        out += ["", "| scene | proxy k | pilot k | pilot k, 95 % upper (used) | pilot s | measured k | used / measured |", "|---|---|---|---|---|---|---|"]
        for r in res["noise_k"]:
            out.append(f"| {r['scene']} | {f(r['proxy_k'])} | {f(r['pilot_k'])} | {f(r['pilot_k_upper'])} | {f(r['pilot_s'])} | {f(r['measured_k'])} | {f(r['used_over_measured'])} |")
    s = res["summary"]
    out += ["", f"Within a factor of 2: {s['agree_x2']} / {s['prediction_rows']} rows. Picks measured: {s['picks_measured']} / {s['picks']}; "
            f"met EPS {s['picks_met']}, cheapest {s['picks_cheapest']}, measurement resolution above EPS on {s['picks_unresolved']}.", ""]
    return "\n".join(out)

