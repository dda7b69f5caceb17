"""calibrate-pane's fit of the pane and the camera's field of view to a recording's frames.

Pipeline (physics in ../shared/RECONSTRUCTION_NOTES.md):

1. **Frames**: the first ``span_s`` (default 0.1 s) of the stream as back-to-back Eq. (3) windows
   (:func:`reconstruct.stream.sources.span_frames`).
2. **Start**: the self-calibrated zeta's geometric fit (:func:`reconstruct.pane.selfcal.self_calibrate`:
   pane normal and, unless given, the field of view from the modulation's orientation mod 90 deg).
3. **Geometry** (tilt, azimuth, fov): bounded Gauss-Newton on the block orientation field of
   :func:`reconstruct.pane.orientation.orientation_field` (psi_b = arg(sum z^4)/4), residual
   sqrt(w_b) sin 2(psi_b - phi_perp_b(x)) / 2 with w_b = 1 / (Var psi_b + a misfit floor estimated
   from the best-measured blocks), Var psi_b measured from the scatter of the block's pixels perpendicular to its
   direction (:func:`block_orientation_variance`): invariant to the 90 deg flip where R < T, blocks that do not modulate
   left out.  Where the self-calibration cannot tell the pane from its 90 deg twin, both are fitted and
   the cone of step 4 decides (:func:`find_twin`); where it preferred one only narrowly (``twin_check_ratio``), the
   twin family is profiled along the fov and the cone asked there too (:func:`twin_fov_profile`); where every fov-free
   start slides to a degenerate view, the self-calibration's fov is kept (reported NOT identified); a fitted fov is
   claimed only where theta's 1-sigma is small.  phi_perp_b(x) and its Jacobian come from
   a pane model given by the caller (:class:`reconstruct.pane.levenberg.PaneModelFactory`; ``polspike
   calibrate-pane`` gives the differentiable maps tier, :class:`generator.pane_fit.PaneModelAD`, Dr.Jit forward AD).
4. **Glass** (n, pane model): the modulated component of each chunk's harmonic fit, projected on
   the fitted s-direction, over its mean: rho = m / a0 lies in the cone [-DoP_T(theta), DoP_R(theta)]
   (rho = DoP_R where T is black, -DoP_T where R is black), whatever the layers are.  Per block the
   extreme rho over chunks (minus the expected noise maximum) are compared with the maps tier's
   DoP_R / DoP_T: violations cost their square in noise units, slack a little (the smallest cone
   that holds the data); n is refined by Gauss-Newton on the blocks on the edge.  This constrains
   n and the model ONLY where some part of the view shows one layer black for a moment: otherwise
   the data give a bound, and the report says "not identified" and keeps the prior.
4b. **Content** (where the cone leaves n or the model open; ``content``): under the right zeta the layers solved
   by paper Eq. (1)-(2) are independent, under a wrong one each carries the other's texture
   (:mod:`reconstruct.physics.exclusion`).  For single / slab and n over common glasses (1.40-2.00) the span's time parts
   (one per 3 half turns of the polarizer, at least 2: :func:`content_parts_for`) are solved in closed form and the gradients of R^ (one part) and T^ (another) correlated per tile; the least
   mean squared correlation is the best guess.  A model / n is claimed only when the alternatives score higher by
   ``content_z`` standard errors across the tiles; unclaimed, the best guess still replaces the prior in the maps
   (``content_best``; it is reported NOT identified), unless the best index is at the end of the range or the
   other model scores within ``content_best_z`` (1) standard errors of it.
5. **Maps** at full resolution (2 x 2 rays per pixel, as the maps tier) -> maps.exr; the scene
   file of the fitted setup -> pane.toml; report.json with uncertainties (Gauss-Newton covariance
   scaled by the residual variance) and the identifiability verdicts; figures.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from polinfra.atomic import json_safe as _json_safe  # pane_outputs imports it from here
from reconstruct.pane.calibrate_config import CalibratePaneConfig
from reconstruct.pane.camera import FOV_INNER_DEG
from reconstruct.pane.content_glass import (
    CONTENT_N_GRID,
    _one_sigma_geometries,
    content_glass,
    content_n_sigma_from_geometry,
)
from reconstruct.pane.edges import (
    TWIN_FOVS_DEG,
    _cone_violation,
    _select_glass,
    dop_fov_profile,
    edge_statistics,
    fit_glass_to_edges,
    twin_fov_profile,
)
from reconstruct.pane.geometry_fit import (
    INCIDENCE_QUANTILE,
    _angles_deg,
    _degenerate_view,
    find_twin,
    fit_geometry,
    max_incidence_deg,
)
from reconstruct.pane.levenberg import PaneModelFactory

log = logging.getLogger(__name__)


def calibrate_frames(I: np.ndarray, phi: np.ndarray, cfg: CalibratePaneConfig = CalibratePaneConfig(), *, span_rad: float = 0.0, name: str = "stream", progress=None, pane_model: PaneModelFactory) -> dict:
    """Fit the pane to Eq. (3) frames I (M, H, W) at polarizer angles phi (M,); returns the result dict
    (``ok``, ``params``, ``maps`` (full-resolution dict), ``report`` (JSON-ready), ``figures`` data).
    """
    import dataclasses as dc

    from polphysics.fresnel import glass_index
    from reconstruct.pane.orientation import orientation_field
    from reconstruct.pane.selfcal import SelfCalConfig, self_calibrate

    t_all = time.perf_counter()
    M, H, W = I.shape
    fixed_n = float(glass_index(cfg.glass, 550.0)) if cfg.glass else (cfg.n if cfg.n > 0 else None)
    forced_model = None if cfg.pane_model == "auto" else cfg.pane_model
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    # the start as calibrate-pane's tables were measured: the self-calibration's checks for a fitted fov are off
    # (its narrow-twin check: the twin profile below asks the full forward model's cone, the stronger test; its 45 deg
    # polish and its dropping of valley candidates at the fov bounds: not measured through this fit)
    sc_cfg = SelfCalConfig(span_s=max(cfg.span_s, 0.001), block_px=cfg.block_px, fov_deg=cfg.fov_deg, n=fixed_n or cfg.prior_n, model=forced_model or cfg.prior_model,
                           twin_check_ratio=1.0, polish_max_move_deg=15.0, valley_drop_fov_bounds=False)
    init = self_calibrate(I, phi, sc_cfg, name=name)
    amb_reason = None  # the self-calibration's "ambiguous" reason where the twin is left to the cone below
    if not init.ok and init.reason.startswith("ambiguous") and cfg.twin_delta_chi2 > 0:
        # the orientation field (mod 90 deg) cannot tell the pane from its 90 deg twin; the modulation depth
        # can (R and T swap sides of the cone, and DoP_R > DoP_T): take the best, find its twin, let the cone decide
        init2 = self_calibrate(I, phi, dc.replace(sc_cfg, max_twin_ratio=10.0), name=name)
        if init2.ok:
            amb_reason, init = init.reason, init2
    timings["selfcal_s"] = time.perf_counter() - t0
    report: dict = {"input": name, "frames": int(M), "size": [int(W), int(H)], "config": dc.asdict(cfg), "init": init.summary()}
    if not init.ok:
        report.update({"ok": False, "reason": init.reason})
        return {"ok": False, "report": report}
    block = cfg.block_px or max(int(init.diagnostics["block_px"]), min(4, W // 8, H // 8))  # the self-calibration's blocks, at least 4 px
    if progress:
        progress("geometry")
    t0 = time.perf_counter()
    of = orientation_field(I, phi, block)
    x0 = np.array([math.radians(init.tilt_deg), math.radians(init.azimuth_deg), math.radians(init.fov_deg), fixed_n or cfg.prior_n])
    fit_fov = cfg.fov_deg <= 0
    geo = fit_geometry(of, W, H, block, x0, fit_fov=fit_fov, pane_model=pane_model)
    fov_kept = None
    if fit_fov and _degenerate_view(geo.x, True) and not _degenerate_view(x0, True):
        # every start slid down the fov-tilt valley to an orthographic (or fish-eye) view: the field's curvature is
        # below the noise.  Keep the self-calibration's field of view (its vanishing-point start is not degenerate)
        # and fit the orientation at it; the fov is reported NOT identified.
        fov_kept = {"by": "self_calibration", "ended_at": [math.degrees(v) for v in geo.x[:3]], "fov_deg": math.degrees(x0[2]),
                    "why": f"NOT identified: the orientation fit with the fov free ran into its bounds (tilt {math.degrees(geo.x[0]):.1f} deg, fov "
                           f"{math.degrees(geo.x[2]):.1f} deg: a degenerate view; the field's curvature is below the noise), so the self-calibration's "
                           f"fov {math.degrees(x0[2]):.2f} deg was kept and the orientation fitted at it; theta(p) is as uncertain as that fov: give --fov-deg if the lens is known"}
        geo = fit_geometry(of, W, H, block, x0, fit_fov=False, pane_model=pane_model)
    timings["geometry_s"] = time.perf_counter() - t0
    gblock = cfg.glass_block_px or block
    gain = math.sin(span_rad) / span_rad if span_rad > 1e-9 else 1.0
    if forced_model:
        models = ("single",) if forced_model == "single" else ("thin_slab",)
    else:
        models = ("single", "thin_slab")
    pre = None
    if amb_reason is not None:
        if progress:
            progress("90 deg twin")
        t0 = time.perf_counter()
        tw = find_twin(of, W, H, block, geo.x, fit_fov, pane_model=pane_model)
        v_best, st_b, gl_b = _cone_violation(I, phi, geo.x, W, H, gblock, gain, models, fixed_n, cfg, pane_model=pane_model)
        twin = {"orientation_twin_ratio": init.twin_ratio, "best": {**_angles_deg(geo.x), "cone_violation_chi2": v_best}}
        if tw is not None:
            v_tw, st_t, gl_t = _cone_violation(I, phi, tw.x, W, H, gblock, gain, models, fixed_n, cfg, pane_model=pane_model)
            twin["twin"] = {**_angles_deg(tw.x), "cone_violation_chi2": v_tw}
        else:
            v_tw = float("inf")
        timings["twin_s"] = time.perf_counter() - t0
        report["twin"] = twin
        # a candidate pushed against the bounds is a degenerate view (_degenerate_view): it cannot win
        if _degenerate_view(geo.x, fit_fov):
            v_best = float("inf")
        if tw is not None and _degenerate_view(tw.x, fit_fov):
            v_tw = float("inf")
        twin["best"]["eligible"] = bool(np.isfinite(v_best))
        if "twin" in twin:
            twin["twin"]["eligible"] = bool(np.isfinite(v_tw))
        if not (abs(v_tw - v_best) >= cfg.twin_delta_chi2):  # also both ineligible (inf - inf = nan)
            report.update({"ok": False, "reason": f"{amb_reason}; the modulation depth does not tell them apart either (cone violation chi^2 {v_best:.1f} vs {v_tw:.1f}, "
                                                  f"need a difference of {cfg.twin_delta_chi2:g})"})
            return {"ok": False, "report": report}
        if v_tw < v_best:
            geo, pre = tw, (st_t, gl_t)
            twin["chosen"] = "twin"
        else:
            pre = (st_b, gl_b)
            twin["chosen"] = "best"
        twin["why"] = (f"modulo 90 deg the orientation field could not tell the two panes apart ({100 * init.twin_ratio:.1f} %); the modulation depths violate "
                       f"the {twin['chosen']}'s cone [-DoP_T, DoP_R] by chi^2 {min(v_best, v_tw):.1f}, the other's by {max(v_best, v_tw):.1f}")
    if amb_reason is None and fit_fov and init.twin_ratio is not None and init.twin_ratio >= cfg.twin_check_ratio and not _degenerate_view(geo.x, True):
        # the orientation field chose narrowly: ask the cone along the twin family's fov valley too
        if progress:
            progress("90 deg twin")
        t0 = time.perf_counter()
        v_best, st_b, gl_b = _cone_violation(I, phi, geo.x, W, H, gblock, gain, models, fixed_n, cfg, pane_model=pane_model)
        prof_t = twin_fov_profile(I, phi, of, W, H, block, gblock, gain, geo.x, geo.score, models, fixed_n, cfg, pane_model=pane_model)
        twin = {"orientation_twin_ratio": init.twin_ratio, "best": {**_angles_deg(geo.x), "cone_violation_chi2": v_best}, "profile": prof_t["points"]}
        pre = (st_b, gl_b)
        twin["chosen"] = "best"
        cand = prof_t["best"]
        if cand is not None and cand[0]["cone_violation_chi2"] <= v_best - cfg.twin_delta_chi2 and cand[0]["cone_violation_chi2"] * cfg.twin_close_factor <= v_best:
            row, g_t = cand
            geo = fit_geometry(of, W, H, block, g_t.x, fit_fov=False, pane_model=pane_model)  # the twin at the profile's fov (the orientation alone would slide it away)
            fov_kept = {"by": "twin_profile", "fov_deg": row["fov_deg"],
                        "why": f"NOT identified: the 90 deg twin was taken at fov {row['fov_deg']:g} deg, the point of its fov valley the modulation depths fit best "
                               f"(a grid of {len(TWIN_FOVS_DEG)} fields of view; the orientation alone slides it to a wide view): give --fov-deg if the lens is known"}
            pre = None
            twin["chosen"] = "twin"
            twin["why"] = (f"the orientation field preferred its pane narrowly ({100 * init.twin_ratio:.1f} %) and the modulation depths violate that pane's cone by "
                           f"chi^2 {v_best:.1f}; the 90 deg twin at fov {row['fov_deg']:g} deg (orientation cost {100 * (row['cost_ratio'] - 1):+.1f} %) by {row['cone_violation_chi2']:.1f}: "
                           f"the twin is taken, its fov from the profile (NOT identified by the orientation)")
        else:
            twin["why"] = (f"the orientation field preferred its pane narrowly ({100 * init.twin_ratio:.1f} %); along the twin family's fov valley the least cone violation "
                           f"within {100 * cfg.twin_profile_cost_tol:g} % of its orientation cost is "
                           + (f"chi^2 {cand[0]['cone_violation_chi2']:.1f}" if cand else "none (no twin point that close)")
                           + f" against {v_best:.1f} here: kept (overturned only below both {v_best - cfg.twin_delta_chi2:.1f} and 1/{cfg.twin_close_factor:g} of it)")
        timings["twin_s"] = time.perf_counter() - t0
        report["twin"] = twin
    if fit_fov and fov_kept is None and cfg.max_incidence_deg < 90.0 and not _degenerate_view(geo.x, True):
        # after the twin decisions, which compare the panes where the orientation put them (a narrowed pane's cone
        # would be judged at a fov the data did not choose either); a degenerate end is refused below
        t0 = time.perf_counter()
        mi_fit = max_incidence_deg(geo.x, W, H, block, geo.coherent, INCIDENCE_QUANTILE)
        if mi_fit > cfg.max_incidence_deg:
            # the fov-tilt valley ran to a view in which modulating blocks would see the pane edge-on or not at all:
            # impossible.  Bisect the fov for the widest view whose orientation fit (fov fixed) keeps them in front
            lo, hi, best = math.radians(FOV_INNER_DEG[0]), float(geo.x[2]), None
            for _ in range(8):
                mid = 0.5 * (lo + hi)
                g = fit_geometry(of, W, H, block, np.r_[geo.x[:2], mid, x0[3]], fit_fov=False, pane_model=pane_model)
                if max_incidence_deg(g.x, W, H, block, g.coherent, INCIDENCE_QUANTILE) <= cfg.max_incidence_deg:
                    lo, best = mid, g
                else:
                    hi = mid
            if best is not None:
                fov_kept = {"by": "feasibility", "ended_at": [math.degrees(v) for v in geo.x[:3]], "fov_deg": math.degrees(best.x[2]), "max_incidence_deg_there": mi_fit,
                            "why": f"NOT identified: the orientation fit with the fov free ended at fov {math.degrees(geo.x[2]):.1f} deg, tilt {math.degrees(geo.x[0]):.1f} deg, "
                                   f"where modulating blocks would meet the pane at {mi_fit:.1f} deg (99.5th percentile; edge-on or behind: they could not modulate); the widest view that keeps "
                                   f"the modulating blocks below {cfg.max_incidence_deg:g} deg, fov {math.degrees(best.x[2]):.2f} deg, was taken (the fov-tilt valley is shallow: "
                                   f"the truth may be narrower still): give --fov-deg if the lens is known"}
                geo, pre = best, None  # the cone statistics are recomputed at the narrowed pane
            timings["feasibility_s"] = time.perf_counter() - t0
    x = geo.x
    if _degenerate_view(x, fit_fov):
        report.update({"ok": False, "reason": f"the orientation fit ran into its bounds (tilt {math.degrees(x[0]):.1f} deg, fov {math.degrees(x[2]):.1f} deg): "
                                              "a degenerate view in which theta is not identified (give --fov-deg if it is known)"})
        return {"ok": False, "report": report}
    # glass
    if progress:
        progress("glass")
    t0 = time.perf_counter()
    pm_full = pane_model(W, H, "single", sub=1)
    if pre is not None:
        st, gl = pre
    else:
        st = edge_statistics(I, phi, pm_full.maps(x)["phi_perp"], gblock, gain)
        gl = fit_glass_to_edges(st, W, H, gblock, x, models, fixed_n, cfg, pane_model=pane_model)
    sel = _select_glass(gl, cfg, fixed_n, forced_model)
    prof = None
    if fit_fov and cfg.dop_fov and (fov_kept or {}).get("by") != "feasibility" and gl["models"][sel["model_key"]]["edge_blocks"] >= cfg.min_edge_blocks:
        # the modulation depths reach the cone's edge somewhere: its theta dependence may pin the fov-tilt valley
        t1 = time.perf_counter()
        prof = dop_fov_profile(of, st, W, H, block, gblock, geo, sel["model_key"], fixed_n, cfg, pane_model=pane_model)
        timings["dop_fov_s"] = time.perf_counter() - t1
        if prof["used"]:
            geo = prof.pop("geo")
            x = geo.x
            gl = fit_glass_to_edges(st, W, H, gblock, x, models, fixed_n, cfg, pane_model=pane_model)
            sel = _select_glass(gl, cfg, fixed_n, forced_model)
    if sel["n"]["identified"]:
        # the index rides on theta: propagate the geometry's covariance (n re-fitted at the geometry moved by
        # one standard deviation along each principal direction) and gate on the total
        key = sel["model_key"]
        n_hat = gl["models"][key]["n"]
        shifts = []
        for xp in _one_sigma_geometries(x, geo.cov, geo.wrt):
            g2 = fit_glass_to_edges(st, W, H, gblock, xp, (key,), None, cfg, n_grid=np.round(np.arange(n_hat - 0.1, n_hat + 0.1001, 0.02), 4), pane_model=pane_model)
            shifts.append(g2["models"][key]["n"] - n_hat)
        s_geo = float(np.sqrt(np.sum(np.square(shifts))))
        s_tot = float(math.hypot(sel["n"]["sigma"], s_geo))
        sel["n"].update({"sigma_statistical": sel["n"]["sigma"], "sigma_from_geometry": s_geo, "sigma": s_tot})
        if s_tot > cfg.max_n_sigma:
            sel["n"] = {"identified": False, "value": cfg.prior_n, "sigma": s_tot, "sigma_from_geometry": s_geo, "fitted_if_edges_are_pure_layers": n_hat,
                        "why": f"the cone's edges give n = {n_hat:.4f}, but the geometry's uncertainty moves it by {s_geo:.3f} (total 1-sigma {s_tot:.3f} > {cfg.max_n_sigma:g}): kept {cfg.prior_n}"}
    timings["glass_s"] = time.perf_counter() - t0
    content = None
    if cfg.content and (sel["model"]["identified"] is False or sel["n"]["identified"] is False):
        # the cone leaves n or the model open: ask the layers' content
        if progress:
            progress("content")
        t0 = time.perf_counter()
        mfull = pm_full.maps(x)
        c_models = (forced_model if forced_model != "thick_slab" else "thin_slab",) if forced_model else ("single", "thin_slab")
        content = content_glass(I, phi, mfull["theta"], mfull["phi_perp"], gain, c_models, cfg, fixed_n=fixed_n)
        timings["content_s"] = time.perf_counter() - t0
        # a best index at the end of the range of common glasses is no minimum: nothing is claimed or used then
        interior = bool(content["ok"]) and (fixed_n is not None or float(CONTENT_N_GRID[0]) < content["best_n"] < float(CONTENT_N_GRID[-1]))
        if content["ok"] and interior and sel["model"]["identified"] is False and content.get("model", {}).get("identified"):
            v = content["best_model"]
            value = v if v == "single" else (cfg.prior_model if cfg.prior_model != "single" else "thin_slab")
            sel["model"] = {"identified": True, "value": value, "by": "content", "why": content["model"]["why"] + (f"; thin vs thick slab not identified: kept {value}" if v != "single" else ""),
                            "cone": sel["model"]}
            sel["model_key"] = v
        model_known = sel["model"]["identified"] is not False
        if content["ok"] and sel["n"]["identified"] is False and model_known and content.get("n", {}).get("identified") and content["best_model"] == sel["model_key"]:
            # the content test read n at the fitted geometry; a theta off by its uncertainty moves the index whose
            # reflection DoP it matches (a view 1.3 deg off in theta claimed 1.54 for a true 1.585).
            # Its own 1-sigma: indices max_n_sigma away are rejected by content_z standard errors
            s_geo = content_n_sigma_from_geometry(pm_full, x, geo.cov, geo.wrt, sel["model_key"], content["n"]["value"])
            content["n"]["sigma_from_geometry"] = s_geo
            if s_geo <= cfg.max_n_sigma:
                sel["n"] = {"identified": True, "value": content["n"]["value"], "sigma": math.hypot(cfg.max_n_sigma / max(cfg.content_z, 1.0), s_geo), "sigma_from_geometry": s_geo,
                            "by": "content", "why": content["n"]["why"] + f"; the geometry's uncertainty moves it by {s_geo:.3f}", "cone": sel["n"]}
            else:
                sel["n"]["why"] += (f"; the content test's indices {content['n']['accepted_range'][0]:.2f}-{content['n']['accepted_range'][1]:.2f} "
                                    f"hold at the fitted geometry, but its uncertainty moves the index by {s_geo:.3f} (> {cfg.max_n_sigma:g}): not claimed")
        if content["ok"] and cfg.content_best:
            # not claimed, but the least-mixed layers are a better estimate of zeta than the prior (docs/calibrate_pane.md).
            # The model's guess compares each model's best over the same range of indices, so it stands where the best
            # index sits at the range's end (the fixed pattern reads n low); that index is no minimum, so the
            # prior index stays then
            if sel["model"]["identified"] is False and content.get("model", {}).get("z", 0.0) >= cfg.content_best_z:
                v = content["best_model"]
                sel["model"]["value"] = v if v == "single" else (cfg.prior_model if cfg.prior_model != "single" else "thin_slab")
                sel["model"]["why"] += f"; the maps use the content test's best guess {sel['model']['value']} (not claimed)"
                sel["model_key"] = v
            if interior and sel["n"]["identified"] is False and content["best_model"] == sel["model_key"]:
                sel["n"]["value"] = content["best_n"]
                sel["n"]["why"] += f"; the maps use the content test's best guess {content['best_n']:.2f} (not claimed)"
            elif not interior and sel["n"]["identified"] is False:
                sel["n"]["why"] += (f"; the content test's best index {content['best_n']:.2f} is at the end of the range tried "
                                    f"({CONTENT_N_GRID[0]:.2f}-{CONTENT_N_GRID[-1]:.2f}), no minimum: the prior stays")
    n_final = float(sel["n"]["value"])
    model_final = sel["model"]["value"]
    x = np.r_[x[:3], n_final]  # a new vector: geo.x stays the geometry fit's
    if progress:
        progress("maps")
    t0 = time.perf_counter()
    maps = pane_model(W, H, model_final, sub=cfg.sub).maps(x)
    timings["maps_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_all
    sig = geo.sigma
    tilt, az, fov = (math.degrees(v) for v in x[:3])
    if not fit_fov:
        fov_verdict = {"identified": None, "why": "given (--fov-deg)"}
    else:
        # the field of view is read from phi_perp's weak curvature: fov and tilt slide along a shallow valley of
        # the orientation fit, and theta(p) with them; claim it only where the propagated theta 1-sigma is small
        s_th = float(geo.sigma_theta_deg_median)
        ok_fov = s_th <= cfg.max_theta_sigma_deg and fov_kept is None
        fov_verdict = {"identified": bool(ok_fov), "value": fov, "sigma_deg": math.degrees(sig[2]), "theta_sigma_deg_median": s_th,
                       "why": (fov_kept["why"] if fov_kept else prof["why"] if prof and prof["used"] else
                               f"phi_perp's curvature across the image pins the focal length, hence theta(p), to {s_th:.2f} deg (median 1-sigma)" if ok_fov else
                               f"NOT identified to {cfg.max_theta_sigma_deg:g} deg: fov and tilt trade off along a shallow valley of the orientation fit "
                               f"(the field's curvature is weak: narrow view or glancing pane); theta(p) is uncertain by {s_th:.2f} deg (median 1-sigma), "
                               f"fov {fov:.2f} +- {math.degrees(sig[2]):.2f} deg; the maps are the best estimate: give --fov-deg if the lens is known")}
    params = {"tilt_deg": tilt, "azimuth_deg": az, "fov_deg": fov, "n": n_final, "model": model_final, "glass": cfg.glass,
              "normal_camera": [float(v) for v in _normal(x)]}
    report.update({
        "ok": True,
        "params": params,
        "uncertainty_1sigma": {"tilt_deg": math.degrees(sig[0]), "azimuth_deg": math.degrees(sig[1]), "fov_deg": math.degrees(sig[2]) if cfg.fov_deg <= 0 else 0.0,
                               "n": sel["n"].get("sigma"), "correlation_geometry": geo.corr,
                               "theta_deg_median": geo.sigma_theta_deg_median, "theta_deg_max": geo.sigma_theta_deg_max,
                               "phi_perp_deg_median": geo.sigma_phi_perp_deg_median, "phi_perp_deg_max": geo.sigma_phi_perp_deg_max,
                               "method": "Gauss-Newton covariance (J^T J)^-1 x residual variance (geometry: relative weights 1 / (variance of psi_b measured from its pixels' scatter + misfit floor), x (1 + 2 rho_x)(1 + 2 rho_y) for the lag-1 correlation of neighbouring blocks' residuals; n: edge residuals in noise units, geometry errors not propagated), Jacobians by Dr.Jit forward AD"},
        "geometry": {"blocks": [int(v) for v in of.psi.shape[::-1]], "block_px": block, "fitted_blocks": int(geo.mask.sum()), "coherent_blocks": int(geo.coherent.sum()),
                     "orientation_residual_deg_median": geo.residual_deg_median, "converged": geo.converged, "iterations": len(geo.history) - 1,
                     "init_tilt_deg": init.tilt_deg, "init_azimuth_deg": init.azimuth_deg, "init_fov_deg": init.fov_deg, "starts": geo.starts,
                     "residual_lag1_correlation_xy": geo.residual_lag1_correlation, "covariance_inflation": geo.covariance_inflation,
                     "dop_fov_profile": prof, "fov_kept": fov_kept},
        "glass": {"chunks": st["chunks"], "block_px": gblock, "valid_blocks": int(st["valid"].sum()),
                  "models": {k: {kk: vv for kk, vv in v.items() if kk not in ("dop_R", "dop_T", "grid_n", "grid_loss", "history")} for k, v in gl["models"].items()}},
        "identifiability": {
            "orientation": {"identified": True, "why": "phi_perp(p) (mod 90 deg) from the modulation's orientation pins the normal's tilt and azimuth"},
            "fov": fov_verdict,
            "n": sel["n"],
            "model": sel["model"],
            "thickness": {"identified": False, "why": "the coefficient maps do not depend on the thickness (only the thick slab's ghost displacement does): kept the base scene's value"},
            "reflectance_scale": {"identified": False, "why": "the absolute reflectance scales R, not T (RECONSTRUCTION_NOTES.md section 1): it follows from n and the model, not from the data"},
        },
        "content": _json_safe(content),
        "timings_s": timings,
        "variant": pm_full.variant,
    })
    figs = {"history": geo.history, "psi": of.psi, "mask": geo.mask, "residual_deg": geo.residual_deg_blocks, "st": st, "gl": gl,
            "phi_fit_blocks": pane_model(W, H, "single", block=block).maps(x)["phi_perp"], "theta_g": pane_model(W, H, "single", block=gblock).maps(x)["theta"],
            "model_key": sel["model_key"]}
    return {"ok": True, "report": report, "maps": maps, "params": params, "x": x, "figs": figs}


def _normal(x) -> np.ndarray:
    """Unit pane normal in the reference camera frame (forward +z, up +y, right -x), N . forward > 0."""
    t, a = x[0], x[1]
    st = math.sin(t)
    return np.array([-st * math.cos(a), st * math.sin(a), math.cos(t)])


