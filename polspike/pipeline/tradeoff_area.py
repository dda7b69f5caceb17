"""``polspike bench area``: the area-sampled analytic tier's error and cost against K, and the planner's picks.

Truth: the path tracer's expected pixel, the pane model integrated over each pixel's area against the
full tier's textures (:mod:`generator.analytic_area`).  A Monte Carlo reference cannot resolve errors
near 1e-3 (its p99 noise at 1024 spp is about 0.01), so the oracle is deterministic: plain stratified
point sampling (one nearest texel per ray) on ``oracle_k x oracle_k`` rays per pixel, an estimator
independent of the tier's per-ray box means, converging as 1 / K; the sequence of its coarser grids
against it shows the convergence, and its distance to the next coarser grid (``oracle_k / 2``) bounds its
own error (first order: about that distance).

Rows: the point-sampled analytic tier (mono, spectral), the oracle's sequence, and the area-sampled tier at
each K (mono, spectral), each with its p99 error against the oracle, wall and CPU seconds of one frame,
and the planner's prediction.  Then the auto pick at each tolerance.  The oracle images are cached in
the output folder (``oracle_*.npy``), so a rerun resumes.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

__all__ = ["run_area_bench", "area_markdown", "full_check", "full_markdown"]

log = logging.getLogger(__name__)


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def run_area_bench(scene, out: Path, ks=(1, 2, 4), oracle_k: int = 32, tolerances=(5e-3, 2e-3, 1e-3), spectral: bool = True) -> dict:
    """Measure the area-sampled tier on ``scene`` (first keyframe) against the stratified-sampling oracle."""
    from generator.analytic import analytic_maps, frame_stokes, sample_layers, spectral_frame
    from generator.analytic_area import area_frames
    from generator.layers import LayerContent
    from generator.planner import area_error, plan_tier, predict_tiers, scene_features
    from generator.tiers_mitsuba import spectral_bands
    from polinfra.atomic import ensure_dir
    from polinfra.errors import ConfigError
    from polspike.pipeline.tradeoff import _radiance_error

    out = ensure_dir(out)
    disp = scene.pane.glass is not None
    bands = [(float(x), float(w)) for x, w in zip(*spectral_bands())] if (spectral and disp) else None
    tag = "spectral" if bands else "mono"
    H, W = scene.camera.height, scene.camera.width
    hw = (H, W)
    tc, rc = LayerContent(scene.layers.transmission, hw), LayerContent(scene.layers.reflection, hw)

    def oracle(k: int, b) -> np.ndarray:
        path = out / f"oracle_{scene.name}_{W}x{H}_{'spectral' if b else 'mono'}_k{k}.npy"
        if path.is_file():
            return np.load(path)
        S = area_frames(scene, [0.0], k, b, prefilter=False)[0][0]
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, S)
        tmp.replace(path)
        return S

    (feats, t_f, _) = _timed(lambda: scene_features(scene))
    ests = predict_tiers(scene, feats)
    refs = {"mono": oracle(oracle_k, None)}
    if bands:
        refs["spectral"] = oracle(oracle_k, bands)
    rows: list[dict] = []

    def add(candidate: str, ref_tag: str, S, wall, cpu, predicted=None, supersample=0):
        rows.append({"candidate": candidate, "reference": f"oracle {oracle_k}x{oracle_k} {ref_tag}", "supersample": supersample,
                     "p99_vs_oracle": _radiance_error(S, refs[ref_tag]), "wall_s": wall, "cpu_s": cpu, "predicted_p99": predicted})

    def pred(spec: bool, K: int):
        e = next((e for e in ests if e.tier == "analytic" and bool(e.spectral) == spec and e.supersample == K), None)
        if e is None and K:  # a K the planner does not offer: its formula
            e_a = area_error(feats, K)
            return float(np.hypot(e_a, feats.get("dispersion_p99", 0.0))) if (disp and not spec) else e_a
        return None if e is None else e.predicted_p99

    def point():
        m = analytic_maps(scene)
        return frame_stokes(m, *sample_layers(m, tc, rc, 0.0))

    S, wall, cpu = _timed(point)
    add("analytic point sample, mono", "mono", S, wall, cpu, pred(False, 0))
    if bands:
        S, wall, cpu = _timed(lambda: spectral_frame([(w, analytic_maps(scene, x)) for x, w in bands], tc, rc, 0.0)[0])
        add("analytic point sample, spectral", "spectral", S, wall, cpu, pred(True, 0))
        add("analytic point sample, mono (vs spectral oracle)", "spectral", point(), wall, cpu, pred(False, 0))
    k = 1
    while k < oracle_k:  # the oracle's convergence: stratified point sampling on coarser grids (cached too)
        S, wall, cpu = _timed(lambda: oracle(k, None))
        add(f"stratified point sampling {k}x{k}, mono (oracle sequence)", "mono", S, wall, cpu, None, k)
        k *= 2
    for K in ks:
        S, wall, cpu = _timed(lambda: area_frames(scene, [0.0], K, None)[0][0])
        add(f"area {K}x{K}, mono", "mono", S, wall, cpu, area_error(feats, K), K)
        if bands:
            add(f"area {K}x{K}, mono (vs spectral oracle)", "spectral", S, wall, cpu, pred(False, K), K)
            S, wall, cpu = _timed(lambda: area_frames(scene, [0.0], K, bands)[0][0])
            add(f"area {K}x{K}, spectral", "spectral", S, wall, cpu, pred(True, K), K)
    picks = []
    for eps in tolerances:
        try:
            c = plan_tier(scene, eps, feats).choice
            picks.append({"tolerance": eps, "pick": c.label(), "supersample": c.supersample, "predicted_p99": c.predicted_p99,
                          "cost_s_per_frame": c.cost_s_per_frame})
        except ConfigError as exc:
            picks.append({"tolerance": eps, "pick": "unreachable", "message": str(exc)})
    return {"scene": scene.name, "size": [W, H], "oracle_k": oracle_k, "spectral": tag, "features_s": t_f,
            "features": {k: feats.get(k) for k in ("dispersion_p99", "sampling_p99", "area_step_p99", "sampling_source")},
            "rows": rows, "picks": picks}


def area_markdown(res: dict) -> str:
    f = lambda v: "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.3g}"  # noqa: E731
    W, H = res["size"]
    fe = res["features"]
    out = [f"## Area-sampled analytic tier: {res['scene']} at {W} x {H}", "",
           f"Oracle: stratified point sampling on {res['oracle_k']} x {res['oracle_k']} rays per pixel. Planner terms: dispersion {f(fe['dispersion_p99'])}, "
           f"sampling {f(fe['sampling_p99'])}, area step (1 -> 2 rays per side) {f(fe['area_step_p99'])}; features computed in {res['features_s']:.1f} s.", "",
           "| candidate | reference | p99 vs oracle | predicted p99 | wall s | CPU s |", "|---|---|---|---|---|---|"]
    for r in res["rows"]:
        out.append(f"| {r['candidate']} | {r['reference']} | {f(r['p99_vs_oracle'])} | {f(r['predicted_p99'])} | {f(r['wall_s'])} | {f(r['cpu_s'])} |")
    out += ["", "| tolerance | auto pick | predicted p99 | planner cost s/frame |", "|---|---|---|---|"]
    for p in res["picks"]:
        if p["pick"] == "unreachable":
            out.append(f"| {p['tolerance']:g} | unreachable: {p['message'].split(': ', 1)[-1]} | | |")
        else:
            out.append(f"| {p['tolerance']:g} | {p['pick']} | {f(p['predicted_p99'])} | {f(p['cost_s_per_frame'])} |")
    return "\n".join(out) + "\n"


def full_check(scene, spp: int, ks=(1, 2, 4), seeds=(1, 2)) -> dict:
    """The full tier (spectral where the glass disperses) at ``spp``, two seeds, against the point-sampled and
    the area-sampled analytic images: p99 error of the seeds' mean with its noise taken out in quadrature
    (``resolution`` = the mean's own p99 noise, half the two seeds' p99 difference; an error at or below it is
    unresolved).
    """
    from generator.analytic import analytic_maps, spectral_frame
    from generator.analytic_area import area_frames
    from generator.layers import LayerContent
    from generator.render import RenderOptions
    from generator.tiers_mitsuba import FullRenderer, spectral_bands
    from polspike.pipeline.tradeoff import _radiance_error, corrected_error

    disp = scene.pane.glass is not None
    bands = [(float(x), float(w)) for x, w in zip(*spectral_bands())] if disp else None
    hw = (scene.camera.height, scene.camera.width)
    tc, rc = LayerContent(scene.layers.transmission, hw), LayerContent(scene.layers.reflection, hw)
    Ss = [np.asarray(FullRenderer(scene, RenderOptions(tier="full", spp=spp, spectral=disp, variant="llvm", seed=s), {"modelled": {}}).stokes(0.0, 0))
          for s in seeds]
    S_full = 0.5 * (Ss[0] + Ss[1])
    res = _radiance_error(Ss[0], Ss[1]) / 2.0
    rows = []
    if bands:
        S_pt = spectral_frame([(w, analytic_maps(scene, x)) for x, w in bands], tc, rc, 0.0)[0]
    else:
        from generator.analytic import frame_stokes, sample_layers

        m = analytic_maps(scene)
        S_pt = frame_stokes(m, *sample_layers(m, tc, rc, 0.0))
    from polphysics.stokes import polarizer_intensity
    from polspike.pipeline.tradeoff import PHIS

    def I(S):  # (4, H, W): intensity behind the polarizer at the error measure's angles
        return np.stack([polarizer_intensity(*S, p) for p in PHIS])

    I_full, I_pt = I(S_full), I(S_pt)
    noise_var = float(np.mean((I(Ss[0]) - I(Ss[1])) ** 2) / 4.0)  # variance of the seeds' mean, per pixel and angle

    def row(name, S):
        Ix = I(S)
        d = I_full - Ix
        rms = float(np.sqrt(max(float(np.mean(d * d)) - noise_var, 0.0)))
        x = (Ix - I_pt).ravel()  # the candidate's departure from the point sample ...
        y = (I_full - I_pt).ravel()  # ... and the path tracer's: slope 1 = the path tracer sees what the candidate does
        xx = float(np.dot(x, x))
        slope = float(np.dot(x, y) / xx) if xx > 0 else None
        se = float(np.sqrt(np.mean((y - slope * x) ** 2) / xx)) if xx > 0 else None
        return {"candidate": name, **corrected_error(_radiance_error(S, S_full), res), "rms_noise_out": rms, "slope_vs_point": slope, "slope_se": se}

    rows.append(row("analytic point sample" + (", spectral" if bands else ""), S_pt))
    for K in ks:
        rows.append(row(f"area {K}x{K}" + (", spectral" if bands else ""), area_frames(scene, [0.0], K, bands)[0][0]))
    return {"scene": scene.name, "size": [scene.camera.width, scene.camera.height], "spp": spp, "spectral": bool(bands), "resolution": res,
            "noise_rms": float(np.sqrt(noise_var)), "rows": rows}


def full_markdown(res: dict) -> str:
    W, H = res["size"]
    out = [f"## Full tier {res['spp']} spp{' spectral' if res['spectral'] else ''} (two seeds) against the analytic images: {res['scene']} at {W} x {H}", "",
           f"Resolution (the two seeds' mean's own noise): p99 {res['resolution']:.3g}, rms {res['noise_rms']:.3g}. rms: over pixels and the four "
           "polarizer angles, the noise's variance taken out. Slope: the path tracer's departure from the point sample regressed on the "
           "candidate's (1 = it sees what the candidate does; the noise is in the regressand only, so it does not bias the slope).", "",
           "| candidate | p99 vs full | p99, noise out | rms, noise out | slope vs point sample |", "|---|---|---|---|---|"]
    for r in res["rows"]:
        sl = "n/a (is the point sample)" if r["slope_vs_point"] is None else f"{r['slope_vs_point']:.3f} +- {r['slope_se']:.3f}"
        out.append(f"| {r['candidate']} | {r['err_vs_ref_p99']:.3g} | {r['err_corrected']:.3g} | {r['rms_noise_out']:.3g} | {sl} |")
    return "\n".join(out) + "\n"
