"""calibrate-pane's glass: edge statistics of the DoP cone, the index / pane-model fit on them, and the fov profiles judged by the cone."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from polinfra.errors import ConfigError
from reconstruct.pane.calibrate_config import CalibratePaneConfig
from reconstruct.pane.camera import FOV_INNER_DEG
from reconstruct.pane.geometry_fit import (
    GeometryFit,
    _degenerate_view,
    _expected_max,
    _sigma_maps,
    _turned_against,
    fit_geometry,
)
from reconstruct.pane.glass import index_grid
from reconstruct.pane.levenberg import PaneModelFactory
from reconstruct.pane.orientation import OrientationField, block_sum

log = logging.getLogger(__name__)


N_GRID = index_grid(1.30, 2.20, 0.02)
"""Index grid of the glass search (before the Gauss-Newton refinement, bounded by its ends; why this range:
:data:`reconstruct.pane.glass.INDEX_GRID`)."""


# --------------------------------------------------------------------------- glass
def edge_statistics(I: np.ndarray, phi: np.ndarray, phi_perp: np.ndarray, block: int, gain: float) -> dict:
    """Per block, the extreme modulation ratios over chunks (module docstring, step 4).

    Returns block-grid arrays ``upper``, ``lower`` (rho extremes minus / plus the expected noise
    maximum), ``s_upper``, ``s_lower`` (their noise), ``valid`` and the chunk count.
    """
    import torch

    from reconstruct.physics.harmonic_fit import half_turn_frames, harmonic_fit

    L = half_turn_frames(phi)
    C = I.shape[0] // L
    if C < 2:
        raise ConfigError(f"the glass fit needs at least {2 * L} frames (two half turns of the polarizer); got {I.shape[0]}: use a longer --span-s")
    rot = np.exp(-2j * phi_perp)
    A, P, O = [], [], []
    for c in range(C):
        sl = slice(c * L, (c + 1) * L)
        a0, ac, as_ = (t.numpy() for t in harmonic_fit(torch.from_numpy(np.asarray(I[sl], np.float64)), torch.from_numpy(np.asarray(phi[sl], np.float64))))
        z = (ac + 1j * as_) * rot
        A.append(block_sum(a0, block))
        P.append(block_sum(z.real, block) / gain)
        O.append(block_sum(z.imag, block) / gain)
    A, P, O = np.array(A), np.array(P), np.array(O)
    # the orthogonal component is pure noise under the model; a robust scale (median over chunks) ignores the
    # chunks where moving content leaks into the harmonic fit
    sig = 1.4826 * np.median(np.abs(O), axis=0)
    Am = np.maximum(A, 1e-12)
    rho = P / Am
    srho = sig[None] / Am
    iu = np.argmax(rho, axis=0)
    il = np.argmin(rho, axis=0)
    take = lambda a, i: np.take_along_axis(a, i[None], 0)[0]  # noqa: E731
    b = _expected_max(C)
    up, lo = take(rho, iu), take(rho, il)
    su, sl_ = take(srho, iu), take(srho, il)
    valid = (A.min(0) > 0) & np.isfinite(sig) & (sig > 0)
    return {"upper": up - b * su, "lower": lo + b * sl_, "s_upper": su, "s_lower": sl_, "valid": valid, "chunks": C, "chunk_frames": L, "noise_max_bias": b}


def _cone(pm, x) -> tuple[np.ndarray, np.ndarray]:
    m = pm.maps(x)
    dR = (m["R_perp"] - m["R_par"]) / np.maximum(m["R_perp"] + m["R_par"], 1e-12)
    dT = (m["T_perp"] - m["T_par"]) / np.maximum(m["T_perp"] + m["T_par"], 1e-12)
    return dR, dT


def _edge_loss(st: dict, dR: np.ndarray, dT: np.ndarray, slack: float = 0.05) -> tuple[float, np.ndarray, np.ndarray]:
    v = st["valid"]
    eu = ((st["upper"] - dR) / np.maximum(st["s_upper"], 1e-6))[v]
    el = ((dT - st["lower"]) / np.maximum(st["s_lower"], 1e-6))[v]
    e = np.concatenate([eu, el])
    loss = float(np.sum(np.where(e > 0, e * e, -slack * e)))
    return loss, eu, el


def fit_glass_to_edges(st: dict, width: int, height: int, block: int, x_geo: np.ndarray, models: tuple[str, ...], fixed_n: float | None, cfg: CalibratePaneConfig, n_grid: np.ndarray | None = None, *, pane_model: PaneModelFactory) -> dict:
    """Index and pane model from the cone's edges (module docstring, step 4)."""
    from reconstruct.pane.levenberg import gauss_newton

    out: dict = {"models": {}}
    for model in models:
        pm = pane_model(width, height, model, block=block)
        grid = np.array([fixed_n]) if fixed_n else (N_GRID if n_grid is None else n_grid)
        losses = []
        for n in grid:
            x = x_geo.copy()
            x[3] = n
            losses.append(_edge_loss(st, *_cone(pm, x))[0])
        losses = np.array(losses)
        n0 = float(grid[int(np.argmin(losses))])
        x = x_geo.copy()
        x[3] = n0
        dR, dT = _cone(pm, x)
        _, eu, el = _edge_loss(st, dR, dT)
        v = st["valid"]
        on_u = np.zeros_like(v)
        on_l = np.zeros_like(v)
        # on the edge: within one noise sigma of the fitted cone, and measured precisely enough to matter
        on_u[v] = (eu > -1.0) & (st["s_upper"][v] <= cfg.max_edge_noise)
        on_l[v] = (el > -1.0) & (st["s_lower"][v] <= cfg.max_edge_noise)
        n_edge = int(on_u.sum() + on_l.sum())
        precise = int((v & (st["s_upper"] <= cfg.max_edge_noise)).sum() + (v & (st["s_lower"] <= cfg.max_edge_noise)).sum())
        sig_n = float("inf")
        chi2 = float(np.sum(np.maximum(eu, 0) ** 2) + np.sum(np.maximum(el, 0) ** 2))
        hist = []
        if not fixed_n and n_edge >= 2:
            su, sl = np.maximum(st["s_upper"][on_u], 1e-6), np.maximum(st["s_lower"][on_l], 1e-6)

            def fun(xs):
                xx = x_geo.copy()
                xx[3] = xs[0]
                m, J = pm.maps_and_jacobian(xx, (3,))
                SR, DR = m["R_perp"] + m["R_par"], m["R_perp"] - m["R_par"]
                ST, DT = m["T_perp"] + m["T_par"], m["T_perp"] - m["T_par"]
                dRn = (J["R_perp"][0] - J["R_par"][0]) / SR - DR * (J["R_perp"][0] + J["R_par"][0]) / SR**2
                dTn = (J["T_perp"][0] - J["T_par"][0]) / ST - DT * (J["T_perp"][0] + J["T_par"][0]) / ST**2
                r = np.concatenate([(st["upper"][on_u] - (DR / SR)[on_u]) / su, ((DT / ST)[on_l] - st["lower"][on_l]) / sl])
                Jr = np.concatenate([-dRn[on_u] / su, dTn[on_l] / sl])[:, None]
                return r, Jr

            res = gauss_newton(fun, [n0], [float(N_GRID[0])], [float(N_GRID[-1])], max_iter=20)
            n_fit = float(res.x[0])
            sig_n = float(res.sigma[0])
            hist = res.history
            x = x_geo.copy()
            x[3] = n_fit
            dR, dT = _cone(pm, x)
            loss, eu, el = _edge_loss(st, dR, dT)
            chi2 = float(np.sum(np.maximum(eu, 0) ** 2) + np.sum(np.maximum(el, 0) ** 2))
        else:
            n_fit = n0
            loss = float(losses.min())
        out["models"][model] = {"n": n_fit, "sigma_n": sig_n, "loss": loss, "violation_chi2": chi2, "edge_blocks": n_edge, "precise_blocks": precise, "edge_fraction": n_edge / max(precise, 1), "edge_upper": int(on_u.sum()), "edge_lower": int(on_l.sum()),
                                "grid_n": grid.tolist(), "grid_loss": losses.tolist(), "history": hist, "dop_R": dR, "dop_T": dT}
    return out


def dop_fov_profile(of: OrientationField, st: dict, width: int, height: int, block: int, gblock: int, geo: GeometryFit, model: str, fixed_n: float | None,
                    cfg: CalibratePaneConfig, rel: tuple[float, float] = (0.85, 1.15), points: int = 9, *, pane_model: PaneModelFactory) -> dict:
    """Profile the fov-tilt valley of the orientation fit with the modulation depth's theta dependence.

    The orientation field pins the vanishing point of the normal, f tan(tilt), well and the focal length f
    only through the field's weak curvature, so (fov, tilt) slide along a shallow valley.  theta(p) moves
    along it, and with it the cone [-DoP_T(theta), DoP_R(theta)] that the modulation depths must stay in.
    At each fov of a grid the orientation is refitted (tilt, azimuth) and the cone's violation chi^2 taken
    at its best index; the sum of the orientation's chi^2 (scaled to a reduced chi^2 of 1 and deflated for
    the blocks' correlation) and the violation chi^2 is minimised.  Used only where it is informative: the
    minimum inside the grid and the violations at both ends at least ``dop_fov_delta_chi2`` above it.
    Returns the profile and, when used, the geometry at the minimum with a 3 x 3 covariance (the fov's
    variance from the profile's curvature, carried along the valley).
    """
    f0 = float(geo.x[2])
    fovs = f0 * np.linspace(rel[0], rel[1], points)
    fovs = fovs[(fovs > math.radians(FOV_INNER_DEG[0])) & (fovs < math.radians(FOV_INNER_DEG[1]))]
    rows = []
    for f in fovs:
        xs = geo.x.copy()
        xs[2] = f
        g = fit_geometry(of, width, height, block, xs, fit_fov=False, fov_starts=(), rounds=1, pane_model=pane_model)
        gg = fit_glass_to_edges(st, width, height, gblock, g.x, (model,), fixed_n, cfg, pane_model=pane_model)
        rows.append((float(f), float(g.chi2), float(gg["models"][model]["violation_chi2"]), float(gg["models"][model]["n"]), g))
    o = np.array([r[1] for r in rows])
    dof = max(1, int(geo.mask.sum()) - 2)
    o_chi2 = (o - o.min()) / max(o.min() / dof, 1e-300) / max(float(geo.covariance_inflation), 1.0)
    v = np.array([r[2] for r in rows])
    tot = o_chi2 + v
    i = int(np.argmin(tot))
    prof = {"fov_deg": [math.degrees(r[0]) for r in rows], "tilt_deg": [math.degrees(r[4].x[0]) for r in rows], "orientation_chi2": o_chi2.tolist(),
            "violation_chi2": v.tolist(), "n": [r[3] for r in rows], "used": False}
    if not (0 < i < len(rows) - 1 and min(v[0], v[-1]) - v[i] >= cfg.dop_fov_delta_chi2):
        prof["why"] = "the modulation depths do not pin the fov along the orientation's valley (no interior minimum of the cone's violations)"
        return prof
    # the violations are a one-sided (hinge) loss, not a parabola: refine the minimum between the neighbours
    # by a bounded scalar search; its 1-sigma: the delta-chi^2 = 1 half-width of the profile's local
    # curvature, never below half a grid step (the cone edge is read from block extremes, not a likelihood)
    from scipy.optimize import minimize_scalar

    F = np.array([rows[j][0] for j in (i - 1, i, i + 1)])

    def total(f):
        xs_ = rows[i][4].x.copy()
        xs_[2] = f
        g_ = fit_geometry(of, width, height, block, xs_, fit_fov=False, fov_starts=(), rounds=1, pane_model=pane_model)
        v_ = fit_glass_to_edges(st, width, height, gblock, g_.x, (model,), fixed_n, cfg, pane_model=pane_model)["models"][model]["violation_chi2"]
        return (g_.chi2 - o.min()) / max(o.min() / dof, 1e-300) / max(float(geo.covariance_inflation), 1.0) + v_

    opt_ = minimize_scalar(total, bounds=(float(F[0]), float(F[2])), method="bounded", options={"xatol": math.radians(0.05), "maxiter": 12})
    f_hat = float(opt_.x)
    a = np.polyfit(F, tot[i - 1:i + 2], 2)[0]
    s_f = max(float(math.sqrt(1.0 / a)) if a > 0 else float(F[2] - F[0]), 0.5 * float(F[1] - F[0]))
    xs = rows[i][4].x.copy()
    xs[2] = f_hat
    g = fit_geometry(of, width, height, block, xs, fit_fov=False, fov_starts=(), rounds=0, pane_model=pane_model)
    # slope of (tilt, azimuth) along the valley: the fov's uncertainty carried into them
    T = np.array([r[4].x[0] for r in rows[i - 1:i + 2]])
    A = np.array([r[4].x[1] for r in rows[i - 1:i + 2]])
    dv = np.array([np.polyfit(F, T, 1)[0], np.polyfit(F, A, 1)[0], 1.0])
    cov3 = np.zeros((3, 3))
    cov3[:2, :2] = g.cov
    cov3 += s_f**2 * np.outer(dv, dv)
    sig = np.sqrt(np.maximum(np.diag(cov3), 0.0))
    g = dataclasses.replace(g, cov=cov3, wrt=(0, 1, 2), sigma=np.concatenate([sig, [0.0]]), corr=(cov3 / np.outer(sig, sig)).tolist() if np.all(sig > 0) else None)
    g = dataclasses.replace(g, **_sigma_maps(g, pane_model(width, height, "single", block=block), cov3, (0, 1, 2)))
    prof.update({"used": True, "fov_fitted_deg": math.degrees(f_hat), "fov_sigma_deg": math.degrees(s_f),
                 "why": f"the cone's violations and the orientation together are least at fov {math.degrees(f_hat):.2f} +- {math.degrees(s_f):.2f} deg "
                        f"(violation chi^2 {v[i]:.1f} there, {v[0]:.1f} / {v[-1]:.1f} at the ends of the profile)"})
    return {**prof, "geo": g}


def twin_fov_profile(I, phi, of: OrientationField, width: int, height: int, block: int, gblock: int, gain: float, x_best: np.ndarray, best_score: float,
                     models: tuple[str, ...], fixed_n: float | None, cfg: CalibratePaneConfig, *, pane_model: PaneModelFactory) -> dict:
    """The 90 deg twin family profiled along the field of view, each point judged by the cone.

    With the fov free, a family's orientation optimum slides along its fov-tilt valley, and the twin family's optimum
    can be a wide view far from the right pane (eval_paper_val train_004: the right pane is a point of that valley,
    2 % worse in orientation cost, not a local optimum).  So at each fov of ``TWIN_FOVS_DEG`` the twin family's tilt
    and azimuth are fitted (starts at several tilts, azimuth turned by +-90 deg; kept only where the phi_perp field is
    turned against ``x_best``'s), and the points whose orientation cost is within ``twin_profile_cost_tol`` of the
    chosen pane's get the cone's violation.  Returns ``points`` and ``best``: among the judged points whose violation is within
    ``twin_delta_chi2`` of the least, the best explanation of the orientation field (None when none is judged).
    """
    turned = _turned_against(of, width, height, block, x_best, pane_model=pane_model)
    points, judged, best, prev = [], [], None, None
    for f in TWIN_FOVS_DEG:
        top = None
        # the first fov from several tilts and both azimuth turns; then along the valley from the previous point
        starts = [(math.radians(tl), x_best[1] + da) for tl in (30.0, 55.0, 75.0) for da in (0.5 * math.pi, -0.5 * math.pi)] if prev is None else [(prev[0], prev[1])]
        for tl, az in starts:
            xs = np.asarray(x_best, np.float64).copy()
            xs[0], xs[1], xs[2] = tl, az, math.radians(f)
            g = fit_geometry(of, width, height, block, xs, False, fov_starts=(), rounds=1, pane_model=pane_model)
            if turned(g.x) and not _degenerate_view(g.x, False) and (top is None or g.score < top.score):
                top = g
        prev = None if top is None else top.x
        if top is None:
            continue
        row = {"fov_deg": f, "tilt_deg": math.degrees(top.x[0]), "azimuth_deg": math.degrees(top.x[1]) % 360.0, "orientation_cost": top.score,
               "cost_ratio": top.score / max(best_score, 1e-300)}
        if top.score <= (1.0 + cfg.twin_profile_cost_tol) * best_score:
            row["cone_violation_chi2"] = _cone_violation(I, phi, top.x, width, height, gblock, gain, models, fixed_n, cfg, pane_model=pane_model)[0]
            judged.append((row, top))
        points.append(row)
    if judged:
        # the cone bounds the fov (a hinge: flat wherever the depths stay inside); within what it allows, the orientation decides
        v_min = min(r["cone_violation_chi2"] for r, _ in judged)
        best = min(((r, g) for r, g in judged if r["cone_violation_chi2"] <= v_min + cfg.twin_delta_chi2), key=lambda rg: rg[0]["orientation_cost"])
    return {"points": points, "best": best}


TWIN_FOVS_DEG = (15.0, 20.0, 25.0, 30.0, 40.0, 50.0, 65.0, 90.0)
"""Fields of view (degrees) at which :func:`twin_fov_profile` fits the twin family."""


def _cone_violation(I, phi, x, width, height, gblock, gain, models, fixed_n, cfg, *, pane_model: PaneModelFactory) -> tuple[float, dict, dict]:
    """Least chi^2 of the modulation depths' excursions beyond the cone of pane ``x`` (over the models and n)."""
    st = edge_statistics(I, phi, pane_model(width, height, "single", sub=1).maps(x)["phi_perp"], gblock, gain)
    gl = fit_glass_to_edges(st, width, height, gblock, x, models, fixed_n, cfg, pane_model=pane_model)
    return min(v["violation_chi2"] for v in gl["models"].values()), st, gl


# --------------------------------------------------------------------------- top level
def _edge_ok(m: dict, cfg: CalibratePaneConfig) -> bool:
    """A real edge: enough precisely measured block extremes pile up on the fitted cone, on both of its
    sides (a black T somewhere and a black R somewhere), and the index lands inside the search range
    (an index at the bound means the extremes were not pure layers).
    """
    inside = float(N_GRID[0]) + 0.011 < m["n"] < float(N_GRID[-1]) - 0.011
    both = m["edge_upper"] >= 3 and m["edge_lower"] >= 3
    return m["edge_blocks"] >= cfg.min_edge_blocks and m["edge_fraction"] >= cfg.min_edge_fraction and both and inside


def _select_glass(gl: dict, cfg: CalibratePaneConfig, fixed_n: float | None, forced_model: str | None) -> dict:
    """Decide what the data claim about n and the model (identifiability verdicts)."""
    ms = gl["models"]
    if forced_model:
        best = forced_model if forced_model in ms else ("thin_slab" if forced_model == "thick_slab" else forced_model)
        model_verdict = {"identified": None, "value": forced_model, "why": "given (--pane-model)"}
    else:
        # each model at its own best index: the one whose cone the data violate less (chi^2 of the
        # excursions beyond the edges, noise units) explains them; the slack term only located the edges
        ranked = sorted(ms, key=lambda k: ms[k]["violation_chi2"])
        best = ranked[0]
        delta = ms[ranked[1]]["violation_chi2"] - ms[best]["violation_chi2"] if len(ranked) > 1 else 0.0
        enough = _edge_ok(ms[best], cfg) and ms[best]["edge_lower"] >= 1
        if enough and delta >= cfg.model_delta_chi2:
            value = best if best == "single" else (cfg.prior_model if cfg.prior_model != "single" else "thin_slab")
            model_verdict = {"identified": True, "value": value, "delta_loss": delta,
                             "why": f"{best} is violated less by the modulation depths (chi^2 {delta:.1f} lower); thin vs thick slab differ only by the ghost's displacement, not identified: kept {value}"}
        else:
            value = cfg.prior_model
            best = value if value in ms else "thin_slab"
            model_verdict = {"identified": False, "value": value, "delta_loss": delta,
                             "why": ("too few blocks on the cone's edge (no part of the view shows one layer black): " if not enough else f"single and slab explain the data equally well (delta {delta:.1f} < {cfg.model_delta_chi2:g}): ")
                             + f"kept {value}"}
    m = ms[best]
    if fixed_n:
        n_verdict = {"identified": None, "value": fixed_n, "sigma": 0.0, "why": "given (--n / --glass)"}
    elif _edge_ok(m, cfg) and m["sigma_n"] <= cfg.max_n_sigma:
        n_verdict = {"identified": True, "value": m["n"], "sigma": m["sigma_n"], "why": f"{m['edge_blocks']} blocks on the cone's edge pin DoP_R / DoP_T(theta)"}
    else:
        n_verdict = {"identified": False, "value": cfg.prior_n, "sigma": m["sigma_n"], "fitted_if_edges_are_pure_layers": m["n"],
                     "why": f"{m['edge_blocks']} of {m['precise_blocks']} precise block extremes on the fitted cone's edge (need {cfg.min_edge_blocks} and {100 * cfg.min_edge_fraction:g} %), "
                            f"sigma_n {m['sigma_n']:.3g}: without a part of the view where one layer is black the extreme polarization ratios only bound n; kept {cfg.prior_n}"}
    return {"model_key": best, "model": model_verdict, "n": n_verdict}
