"""Reproduce the tables of docs/calibrate_pane.md.

    PYTHONPATH=. python docs/calibrate_pane_report.py out/datasets/eval_paper [--fov-given] [--solvers [--compare-prior]] [--no-content] [--frames 40] [--span-s 0.1]

For every group of the dataset: calibrate-pane on its spikes (default options; --fov-given passes the
scene's fov), errors of theta / phi_perp against the group's stored maps, the fitted vs true tilt, fov,
n and model; with --solvers, T PSNR of LS / ridge / IRLS / RWPS with zeta from the true maps and from the
fitted maps (same frames, same solver configuration, same run); --compare-prior adds the same solvers with the
fitted geometry and the prior n / model (thin slab, 1.5: the maps without the content test); --no-content
calibrates without the content test.  Prints one JSON line per group, a markdown table and the goal counts
(claims and the content test's best guesses against the truth).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--fov-given", action="store_true")
    ap.add_argument("--solvers", action="store_true")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--compare-prior", action="store_true", help="with --solvers: also the fitted geometry with the prior n / model (the maps before the content test)")
    ap.add_argument("--no-content", action="store_true", help="calibrate without the content test")
    ap.add_argument("--content-sigma", type=float, default=None, help="CalibratePaneConfig.content_sigma_px (default: the config's)")
    ap.add_argument("--content-parts", type=int, default=None, help="CalibratePaneConfig.content_parts")
    ap.add_argument("--content-pixels", default=None, choices=("auto", "same", "split"), help="CalibratePaneConfig.content_pixels")
    ap.add_argument("--span-s", type=float, default=0.1, help="CalibratePaneConfig.span_s: seconds of each group calibrated (at most the group's length)")
    ap.add_argument("--content-true-geometry", action="store_true", help="only the content test, on the stored (true) theta / phi_perp of each group")
    ap.add_argument("--identifiability", action="store_true", help="only the content test on the true geometry, from the spikes and from noiseless harmonics of the ground-truth layers (what the layers' content allows without spike noise)")
    ap.add_argument("--content-power", default="same", choices=("same", "cross"), help="CalibratePaneConfig.content_power")
    ap.add_argument("--valley", action="store_true", help="only the geometry: fit_geometry with the fov fitted and given, per weighting (--weightings), the cost at the fit and at the truth, and a profile along the fov")
    ap.add_argument("--weightings", default="floor,scatter", help="with --valley: comma-separated fit_geometry weightings")
    a = ap.parse_args()
    if a.valley:
        return valley(Path(a.dataset), a.weightings.split(","))
    if a.identifiability:
        return identifiability(Path(a.dataset), a.content_power, a.span_s, a.content_sigma)
    if a.content_true_geometry:
        return content_on_true_geometry(Path(a.dataset))
    from polspike.pipeline.calibrate_pane import calibrate_input
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups
    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.physics.zeta import PaneMaps
    from reconstruct.stream.groups import load_store_group
    from spike_sim.store import open_group

    rows = []
    for gd in sorted((Path(a.dataset) / "groups").iterdir()):
        spec = json.loads((gd / "group_spec.json").read_text())["scene"]
        t0 = time.time()
        res, _, _, _ = calibrate_input(gd, CalibratePaneConfig(fov_deg=spec["camera"]["fov_deg"] if a.fov_given else 0.0, content=not a.no_content, content_power=a.content_power, span_s=a.span_s,
                                                           **{k: v for k, v in (("content_sigma_px", a.content_sigma), ("content_pixels", a.content_pixels), ("content_parts", a.content_parts)) if v is not None}))
        r = res["report"]
        if not res["ok"]:
            rows.append({"group": gd.name, "refused": r["reason"]})
            print(json.dumps(rows[-1]), flush=True)
            continue
        with open_group(gd) as g:
            mp = g.maps()
        th = np.degrees(np.abs(res["maps"]["theta"] - mp["theta"]))
        dp = np.degrees(np.abs(np.mod(res["maps"]["phi_perp"] - mp["phi_perp"] + np.pi / 2, np.pi) - np.pi / 2))
        p, idn = r["params"], r["identifiability"]
        row = {"group": gd.name, "s": round(time.time() - t0, 1), "tilt": [spec["pane"]["tilt_deg"], p["tilt_deg"]], "sigma_tilt": r["uncertainty_1sigma"]["tilt_deg"],
               "fov": [spec["camera"]["fov_deg"], p["fov_deg"]], "theta_err_median": float(np.median(th)), "phi_perp_err_median": float(np.median(dp)),
               "n": [spec["pane"]["n"], p["n"], idn["n"]["identified"]], "model": [spec["pane"]["model"], p["model"], idn["model"]["identified"]],
               "twin": r.get("twin", {}).get("chosen"), "sigma_theta_median": r["uncertainty_1sigma"]["theta_deg_median"],
               "theta_claimed": idn["fov"]["identified"] is not False, "glass_models": r["glass"]["models"], "why_model": idn["model"]["why"], "why_n": idn["n"]["why"],
               "model_by": idn["model"].get("by", "cone" if idn["model"]["identified"] else None), "n_by": idn["n"].get("by", "cone" if idn["n"]["identified"] else None)}
        ct = r.get("content") or {}
        if ct.get("ok"):
            row["content"] = {"best": [ct["best_model"], ct["best_n"]], "model_z": ct.get("model", {}).get("z"), "other": [ct.get("model", {}).get("other"), ct.get("model", {}).get("other_n")],
                              "n_range": ct.get("n", {}).get("accepted_range"), "score": ct["best_score"]}
        if a.solvers:
            cfg = EvalConfig(zeta="gt", methods="ls,ridge,irls,rwps", max_frames=a.frames, figure_frames=0)
            grp = load_store_group(gd, max_frames=a.frames)
            m = res["maps"]
            fitted = PaneMaps(R_perp=m["R_perp"], R_par=m["R_par"], phi_perp=m["phi_perp"])
            cands = [("true", grp.maps), ("fitted", fitted)]
            if a.compare_prior:
                from generator.pane_fit import PaneModelAD

                cfg0 = CalibratePaneConfig()
                x = np.array([np.radians(p["tilt_deg"]), np.radians(p["azimuth_deg"]), np.radians(p["fov_deg"]), cfg0.prior_n])
                m0 = PaneModelAD(m["theta"].shape[1], m["theta"].shape[0], cfg0.prior_model, sub=cfg0.sub).maps(x)
                cands.append(("prior", PaneMaps(R_perp=m0["R_perp"], R_par=m0["R_par"], phi_perp=m0["phi_perp"])))
            for label, maps in cands:
                rep = evaluate_groups([dataclasses.replace(grp, maps=maps)], cfg)
                row[f"psnr_T_{label}"] = {x["method"]: x["psnr_T"] for x in rep.rows if x.get("group") == "overall"}
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| group | tilt true / fitted | 1-sigma | fov true / fitted | theta err | phi_perp err | n true / used (identified) | model true / used (identified) |" + (" delta T PSNR ls / ridge / irls / rwps |" if a.solvers else ""))
    print("|---|---|---|---|---|---|---|---|" + ("---|" if a.solvers else ""))
    for r in rows:
        if "refused" in r:
            print(f"| {r['group']} | refused: {r['refused'][:60]} |")
            continue
        line = (f"| {r['group']} | {r['tilt'][0]:.2f} / {r['tilt'][1]:.2f} | {r['sigma_tilt']:.2f} | {r['fov'][0]:.2f} / {r['fov'][1]:.2f} | {r['theta_err_median']:.3f} | "
                f"{r['phi_perp_err_median']:.3f} | {r['n'][0]:.3f} / {r['n'][1]:.3f} ({r['n'][2]}) | {r['model'][0]} / {r['model'][1]} ({r['model'][2]}) |")
        if a.solvers:
            line += " " + " / ".join(f"{r['psnr_T_fitted'][k] - r['psnr_T_true'][k]:+.2f}" for k in ("ls", "ridge", "irls", "rwps")) + " |"
            if a.compare_prior:
                line += " prior: " + " / ".join(f"{r['psnr_T_prior'][k] - r['psnr_T_true'][k]:+.2f}" for k in ("ls", "ridge", "irls", "rwps")) + " |"
        print(line)
    # the goals of the pane calibration, counted over every group of the dataset (a refused group meets none)
    ok = [r for r in rows if "refused" not in r]
    geo = [r for r in ok if r["theta_err_median"] <= 0.5 and r["phi_perp_err_median"] <= 0.5]
    claimed = [r for r in ok if r["theta_claimed"]]
    print(f"theta claimed (fov given, or fitted with theta 1-sigma <= 0.5 deg) on {len(claimed)} groups; median errors <= 0.5 deg on "
          f"{sum(1 for r in claimed if r['theta_err_median'] <= 0.5 and r['phi_perp_err_median'] <= 0.5)} of them")
    n_claims = [r for r in ok if r["n"][2]]
    n_good = [r for r in n_claims if abs(r["n"][0] - r["n"][1]) <= 0.03]
    slab = lambda m: "single" if m == "single" else "slab"  # noqa: E731  thin vs thick: same maps, not identifiable
    m_claims = [r for r in ok if r["model"][2] and r["tilt"][0] >= 30]
    m_good = [r for r in m_claims if slab(r["model"][0]) == slab(r["model"][1])]
    print(f"\ngroups {len(rows)}, calibrated {len(ok)}, twin resolved by the modulation depth {sum(1 for r in ok if r['twin'])}")
    print(f"median |theta err| and |phi_perp err| <= 0.5 deg: {len(geo)} of {len(rows)} ({len(geo)} of {len(ok)} calibrated); theta only: "
          f"{sum(1 for r in ok if r['theta_err_median'] <= 0.5)}, phi_perp only: {sum(1 for r in ok if r['phi_perp_err_median'] <= 0.5)}")
    print(f"n claimed on {len(n_claims)} groups, within 0.03 on {len(n_good)}; model claimed on {len(m_claims)} groups with tilt >= 30, right on {len(m_good)}")
    tilted = [r for r in ok if r["tilt"][0] >= 30]
    print(f"model in the maps (claimed or not) right on {sum(1 for r in tilted if slab(r['model'][0]) == slab(r['model'][1]))} of {len(tilted)} calibrated groups with tilt >= 30")
    by = lambda rs, k, v: sum(1 for r in rs if r.get(k) == v)  # noqa: E731
    print(f"  of these by the content test: n {by(n_claims, 'n_by', 'content')} (within 0.03: {by(n_good, 'n_by', 'content')}), "
          f"model {by(m_claims, 'model_by', 'content')} (right: {by(m_good, 'model_by', 'content')})")
    cs = [r for r in ok if "content" in r]
    if cs:
        right = sum(1 for r in cs if r["tilt"][0] >= 30 and slab(r["content"]["best"][0]) == slab(r["model"][0]))
        print(f"content test's best model (claimed or not), tilt >= 30: right on {right} of {sum(1 for r in cs if r['tilt'][0] >= 30)}; "
              f"its best n within 0.03 on {sum(1 for r in cs if abs(r['content']['best'][1] - r['n'][0]) <= 0.03)} of {len(cs)}")
    if a.solvers:
        within = [r for r in ok if all(r["psnr_T_fitted"][k] - r["psnr_T_true"][k] >= -0.3 for k in ("ls", "ridge", "irls", "rwps"))]
        print(f"every solver within 0.3 dB of the true maps: {len(within)} of {len(rows)} ({len(within)} of {len(ok)} calibrated)")
        dl = {k: np.array([r["psnr_T_fitted"][k] - r["psnr_T_true"][k] for r in ok]) for k in ("ls", "ridge", "irls", "rwps")}
        if ok:
            print("fitted - true maps over the calibrated groups, mean / median dB: " + ", ".join(f"{k} {v.mean():+.2f} / {np.median(v):+.2f}" for k, v in dl.items()))
        if a.compare_prior:
            w0 = [r for r in ok if all(r["psnr_T_prior"][k] - r["psnr_T_true"][k] >= -0.3 for k in ("ls", "ridge", "irls", "rwps"))]
            d = {k: float(np.mean([r["psnr_T_fitted"][k] - r["psnr_T_prior"][k] for r in ok])) for k in ("ls", "ridge", "irls", "rwps")}
            print(f"  with the prior n / model instead (same geometry): {len(w0)} of {len(rows)}; mean gain of the fitted over the prior maps "
                  + " / ".join(f"{d[k]:+.2f}" for k in ("ls", "ridge", "irls", "rwps")) + " dB (LS / ridge / IRLS / RWPS)")


def _group_spans(dataset: Path, cfg):
    """(group dir, its scene spec, the calibration span's frames I and angles phi, the window's sweep in radians) per
    stored group of ``dataset`` (the spikes calibrate-pane reads with ``cfg``).
    """
    import math

    from reconstruct.stream.sources import group_source, span_frames

    for gd in sorted((dataset / "groups").iterdir()):
        spec = json.loads((gd / "group_spec.json").read_text())["scene"]
        src = group_source(gd)
        I, phi = span_frames(src, cfg.span_s, cfg.window_steps)
        yield gd, spec, I, phi, 2 * math.pi * src.polarizer_rev_s * cfg.window_steps / src.rate_hz


def content_on_true_geometry(dataset: Path) -> None:
    """The content test alone (default options) with each group's stored theta / phi_perp: how well the layers' content
    tells the model and n when the geometry is right.
    """
    import math

    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.content_glass import content_glass
    from spike_sim.store import open_group

    cfg = CalibratePaneConfig()
    slab = lambda m: "single" if m == "single" else "slab"  # noqa: E731
    rows = []
    for gd, spec, I, phi, span in _group_spans(dataset, cfg):
        with open_group(gd) as g:
            mp = g.maps()
        r = content_glass(I, phi, mp["theta"], mp["phi_perp"], math.sin(span) / span, ("single", "thin_slab"), cfg)
        row = {"group": gd.name, "model": spec["pane"]["model"], "n": spec["pane"]["n"], "tilt": spec["pane"]["tilt_deg"]}
        if r["ok"]:
            row.update({"best": [r["best_model"], r["best_n"]], "z": r["model"]["z"], "claimed": r["model"]["identified"], "n_claimed": r["n"]["identified"], "n_range": r["n"]["accepted_range"]})
        rows.append(row)
        print(json.dumps(row), flush=True)
    t30 = [r for r in rows if "best" in r and r["tilt"] >= 30]
    right = [r for r in t30 if slab(r["best"][0]) == slab(r["model"])]
    cl = [r for r in t30 if r["claimed"]]
    print(f"tilt >= 30: {len(t30)} groups; best model right on {len(right)}; claimed on {len(cl)}, right on {sum(1 for r in cl if slab(r['best'][0]) == slab(r['model']))}; "
          f"best n within 0.03 on {sum(1 for r in right if abs(r['best'][1] - r['n']) <= 0.03)} of the {len(right)} with the right model; "
          f"n claimed on {sum(1 for r in rows if r.get('n_claimed'))}")


def valley(dataset: Path, weightings: list[str]) -> None:
    """The fov-tilt valley of the orientation fit (docs/calibrate_pane.md).

    Per group: the pipeline's self-calibrated start and orientation field; the truth (tilt, azimuth, fov fitted to the
    group's stored theta / phi_perp maps by Gauss-Newton); for each weighting, fit_geometry with the fov fitted and with
    the scene's fov, the median |theta error| over pixels and theta's median 1-sigma; the cost sum w (1 - cos 4 d) at
    the fit and at the truth with the fit's final weights held fixed, and the profile of that cost along the fov
    (tilt and azimuth refitted at 0.75 / 0.9 / 1 / 1.1 / 1.25 x the true fov).
    """
    import dataclasses as dc
    import math

    from generator.pane_fit import PaneModelAD
    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.geometry_fit import _wrap90, fit_geometry
    from reconstruct.pane.levenberg import gauss_newton
    from reconstruct.pane.orientation import block_orientation_variance, orientation_field
    from reconstruct.pane.selfcal import SelfCalConfig, self_calibrate
    from reconstruct.stream.sources import group_source, span_frames
    from spike_sim.store import open_group

    cfg = CalibratePaneConfig()
    for gd in sorted((dataset / "groups").iterdir()):
        spec = json.loads((gd / "group_spec.json").read_text())["scene"]
        src = group_source(gd)
        I, phi = span_frames(src, cfg.span_s, cfg.window_steps)
        M, H, W = I.shape
        with open_group(gd) as g:
            mp = g.maps()
        fov_t = math.radians(spec["camera"]["fov_deg"])
        sc = SelfCalConfig(span_s=cfg.span_s, block_px=0, fov_deg=0.0, n=cfg.prior_n, model=cfg.prior_model)
        init = self_calibrate(I, phi, sc, name=gd.name)
        if not init.ok and init.reason.startswith("ambiguous"):
            init = self_calibrate(I, phi, dc.replace(sc, max_twin_ratio=10.0), name=gd.name)
        if not init.ok:
            print(json.dumps({"group": gd.name, "refused": init.reason[:80]}), flush=True)
            continue
        block = max(int(init.diagnostics["block_px"]), min(4, W // 8, H // 8))
        of = orientation_field(I, phi, block)
        x0 = np.array([math.radians(init.tilt_deg), math.radians(init.azimuth_deg), math.radians(init.fov_deg), cfg.prior_n])
        pmf = PaneModelAD(W, H, "single", sub=1)
        pmb = PaneModelAD(W, H, "single", block=block)
        sl = (slice(2, None, 6), slice(2, None, 6))

        def f_true(z):
            m, J = pmf.maps_and_jacobian(np.r_[z, cfg.prior_n], (0, 1, 2))
            d = np.mod(m["phi_perp"][sl] - mp["phi_perp"][sl] + np.pi / 2, np.pi) - np.pi / 2
            return (np.concatenate([(m["theta"][sl] - mp["theta"][sl]).ravel(), d.ravel()]),
                    np.concatenate([J["theta"][:, sl[0], sl[1]].reshape(3, -1).T, J["phi_perp"][:, sl[0], sl[1]].reshape(3, -1).T]))

        best = None
        for off in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi):
            r = gauss_newton(f_true, np.array([x0[0], x0[1] + off, fov_t]), [0.0, -10.0, 0.05], [1.56, 10.0, 2.6], max_iter=50)
            best = r if best is None or r.chi2 < best.chi2 else best
        xt = np.r_[best.x, cfg.prior_n]
        th_err = lambda x: float(np.degrees(np.median(np.abs(pmf.maps(x)["theta"] - mp["theta"]))))  # noqa: E731
        row = {"group": gd.name, "tilt_fov_true": [spec["pane"]["tilt_deg"], spec["camera"]["fov_deg"]], "truth_fit_theta_err": th_err(xt)}
        for wname in weightings:
            geo = fit_geometry(of, W, H, block, x0, fit_fov=True, weighting=wname, pane_model=PaneModelAD)
            giv = fit_geometry(of, W, H, block, np.r_[x0[:2], fov_t, cfg.prior_n], fit_fov=False, weighting=wname, pane_model=PaneModelAD)
            mask = geo.mask
            if wname == "scatter":
                v = block_orientation_variance(of.s4, of.s4_px, block)[0][mask]
            else:
                v = (np.maximum(of.q, 1e-300) / (32.0 * np.maximum(np.abs(of.s4), 1e-300) ** 2))[mask]
            resid = lambda x: _wrap90(of.psi[mask] - pmb.maps(x)["phi_perp"][mask])  # noqa: E731
            d = resid(geo.x)
            top = v <= np.quantile(v, 0.25)
            sys2 = max(math.radians(0.1) ** 2, float(np.median(d[top] ** 2)) / 0.455 - float(np.median(v[top])))
            w = 1.0 / (v + sys2)
            w = w / w.sum() * w.size
            cost = lambda x: float(np.sum(w * (1.0 - np.cos(4.0 * resid(x)))))  # noqa: E731
            prof = []
            for rel in (0.75, 0.9, 1.0, 1.1, 1.25):
                gp = fit_geometry(of, W, H, block, np.r_[geo.x[:2], fov_t * rel, cfg.prior_n], fit_fov=False, rounds=1, weighting=wname, pane_model=PaneModelAD)
                prof.append([round(math.degrees(fov_t * rel), 2), round(cost(gp.x), 3), round(th_err(gp.x), 2)])
            row[wname] = {"fitted": {"theta_err": round(th_err(geo.x), 3), "theta_sigma": round(geo.sigma_theta_deg_median, 3), "fov": round(math.degrees(geo.x[2]), 2),
                                     "starts_end_fov": [round(t["end"][2], 2) for t in geo.starts]},
                          "given": {"theta_err": round(th_err(giv.x), 3), "theta_sigma": round(giv.sigma_theta_deg_median, 3)},
                          "cost_fit_truth": [round(cost(geo.x), 3), round(cost(xt), 3)], "chi2_per_block_at_truth": round(float(np.mean(resid(xt) ** 2 / (v + sys2))), 3),
                          "profile_fov_cost_theta_err": prof}
        print(json.dumps(row), flush=True)


def identifiability(dataset: Path, content_power: str = "same", span_s: float = 0.1, content_sigma: float | None = None) -> None:
    """How far the layers' content, not the spike noise, limits the pane model and the index.

    Per group, the content test (default options) on the true theta / phi_perp twice: (a) from the spikes, as
    calibrate-pane runs it; (b) from noiseless parts: the time-mean ground-truth layers of each half of the group,
    put through paper Eq. (1)-(2) with the true maps' A, B (a0 = [T + A (R - T)] / 2, c = B (R - T) / 2 e^{2 i phi_perp}).
    Per pixel (a0, c) -> (R', T') is invertible under ANY hypothesis (A', B'), so the likelihood of the spikes alone is
    flat in n and the model; only the layers' content (and positivity: the cone) tells.  (b) is that information with
    the spike noise removed: where (b) does not claim, no amount of spikes lets this test claim.
    """
    import math

    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.content_glass import content_glass, content_parts_for
    from spike_sim.store import open_group

    cfg = CalibratePaneConfig(content_power=content_power, span_s=span_s)
    if content_sigma is not None:
        cfg = dataclasses.replace(cfg, content_sigma_px=content_sigma)
    slab = lambda m: "single" if m == "single" else "slab"  # noqa: E731
    rows = []
    for gd, spec, I, phi, span in _group_spans(dataset, cfg):
        with open_group(gd) as g:
            mp = g.maps()
            nf = g.f["gt/R"].shape[0]
            Rg = np.stack([g.gt_frame("R", i) for i in range(nf)]).astype(np.float64)
            Tg = np.stack([g.gt_frame("T", i) for i in range(nf)]).astype(np.float64)
        A = 0.5 * (mp["R_perp"] + mp["R_par"])
        B = 0.5 * (mp["R_perp"] - mp["R_par"])
        rot = np.exp(2j * mp["phi_perp"])
        n_parts = content_parts_for(phi, I.shape[0], cfg.content_parts)
        bounds = np.linspace(0, nf, n_parts + 1).round().astype(int)
        parts = []
        for p in range(n_parts):
            R, T = Rg[bounds[p]:bounds[p + 1]].mean(0), Tg[bounds[p]:bounds[p + 1]].mean(0)
            parts.append((0.5 * (T + A * (R - T)), 0.5 * B * (R - T) * rot))
        row = {"group": gd.name, "model": spec["pane"]["model"], "n": spec["pane"]["n"], "tilt": spec["pane"]["tilt_deg"]}
        for key, kw in (("spikes", {}), ("noiseless", {"parts": parts})):
            r = content_glass(I, phi, mp["theta"], mp["phi_perp"], math.sin(span) / span if key == "spikes" else 1.0, ("single", "thin_slab"), cfg, **kw)
            if r["ok"]:
                row[key] = {"best": [r["best_model"], r["best_n"]], "z": round(r["model"]["z"], 2), "model_claimed": r["model"]["identified"],
                            "n_claimed": r["n"]["identified"], "n_range": r["n"]["accepted_range"]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| group | model / n | tilt | spikes: best (z) / n accepted | noiseless layers: best (z) / n accepted |\n|---|---|---|---|---|")
    for r in rows:
        cells = []
        for key in ("spikes", "noiseless"):
            c = r.get(key)
            cells.append(f"{c['best'][0]} {c['best'][1]:.2f} ({c['z']:.1f}) / {c['n_range'][0]:.2f}-{c['n_range'][1]:.2f}" if c else "not scored")
        print(f"| {r['group']} | {r['model']} / {r['n']:.3f} | {r['tilt']:.0f} | {cells[0]} | {cells[1]} |")
    for key in ("spikes", "noiseless"):
        t30 = [r for r in rows if key in r and r["tilt"] >= 30]
        cl = [r for r in t30 if r[key]["model_claimed"]]
        right = [r for r in t30 if slab(r[key]["best"][0]) == slab(r["model"])]
        ncl = [r for r in rows if key in r and r[key]["n_claimed"]]
        w = [r[key]["n_range"][1] - r[key]["n_range"][0] for r in rows if key in r]
        print(f"{key}: tilt >= 30: {len(t30)} groups, best model right on {len(right)}, claimed (z >= {cfg.content_z:g}) on {len(cl)} "
              f"(right on {sum(1 for r in cl if slab(r[key]['best'][0]) == slab(r['model']))}); n claimed on {len(ncl)} "
              f"(within 0.03 on {sum(1 for r in ncl if abs(r[key]['best'][1] - r['n']) <= 0.03)}); best n within 0.03 on "
              f"{sum(1 for r in rows if key in r and abs(r[key]['best'][1] - r['n']) <= 0.03)} of {sum(1 for r in rows if key in r)}; "
              f"accepted n range median width {np.median(w) if w else float('nan'):.2f}")


if __name__ == "__main__":
    main()
