"""The speed/accuracy trade, measured: ``polspike bench tradeoff``.

For each scene, every candidate (tier, spp, mono/spectral, backend, keyframe
rate, simulator step) renders the scene's first keyframe in this process, and
is compared with a high-fidelity reference rendered in the same run (full tier,
spectral where the glass disperses, high spp).  Errors are measured where they
matter:

* radiance: p99 over pixels of the worst case over 4 polarizer angles of
  |I_candidate(phi) - I_reference(phi)| (I from the Stokes images), and the
  mean |S0 error|; the reference's own Monte Carlo noise (two seeds) is
  reported as the first row of each scene: errors near it are unresolved;
* spike frames: both radiances drive the spike simulator with the same seed
  and noise realisation for a short burst; the RMS difference of the paper
  Eq. (3) frames I(i) is compared with the RMS difference between two seeds of
  the reference (the spike noise).  A candidate whose spike-frame error is far
  below the spike noise is accurate enough for training data; more accuracy is
  wasted there.

Cost: seconds per frame (measured) and per 1 s group
= one-off cost + frames per second needed x per-frame cost + simulator cost.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from polinfra.atomic import ensure_dir, write_json, write_text
from polphysics.stokes import polarizer_intensity

log = logging.getLogger(__name__)

__all__ = ["Candidate", "run_tradeoff", "default_candidates", "corrected_error", "planner_candidates"]

PHIS = np.deg2rad([0.0, 45.0, 90.0, 135.0])


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One point of the trade: a tier and its knobs."""

    label: str
    tier: str
    spp: int = 1
    spectral: bool = False
    variant: str = "auto"
    keyframe_hz: float | None = None


def default_candidates(quick: bool = False) -> list[Candidate]:
    """The grid measured by the bench (``quick``: a reduced grid for tests)."""
    if quick:
        return [Candidate("analytic", "analytic"), Candidate("maps 1spp", "maps", 1), Candidate("full 4spp llvm", "full", 4, variant="llvm")]
    return [
        Candidate("analytic", "analytic"),
        Candidate("maps 1spp mono", "maps", 1),
        Candidate("maps 4spp mono", "maps", 4),
        Candidate("maps 16spp mono", "maps", 16),
        Candidate("maps 4spp spectral", "maps", 4, spectral=True),
        Candidate("full 4spp mono llvm", "full", 4, variant="llvm"),
        Candidate("full 16spp mono llvm", "full", 16, variant="llvm"),
        Candidate("full 64spp mono llvm", "full", 64, variant="llvm"),
        Candidate("full 16spp spectral llvm", "full", 16, spectral=True, variant="llvm"),
        Candidate("full 4spp scalar", "full", 4, variant="scalar"),
        Candidate("full 16spp scalar", "full", 16, variant="scalar"),
    ]


def planner_candidates(spectral: bool = False) -> list[Candidate]:
    """The grid that checks the planner's predictions: analytic, maps and full at 4 / 16 / 64 spp (+ spectral 16)."""
    c = [Candidate("analytic", "analytic"), Candidate("maps 1spp", "maps", 1)]
    c += [Candidate(f"full {n}spp mono llvm", "full", n, variant="llvm") for n in (4, 16, 64)]
    if spectral:
        c.append(Candidate("full 16spp spectral llvm", "full", 16, spectral=True, variant="llvm"))
    return c


def _render_first(scene, cand: Candidate, seed: int = 0) -> tuple[np.ndarray, float, float]:
    """Stokes (3, H, W) of the first keyframe, one-off seconds, per-frame seconds."""
    from generator.analytic import analytic_maps, frame_stokes, sample_layers
    from generator.layers import LayerContent
    from generator.render import RenderOptions

    opts = RenderOptions(tier=cand.tier, spp=cand.spp, spectral=cand.spectral, variant=cand.variant, seed=seed, keyframe_hz=cand.keyframe_hz)
    info: dict = {"modelled": {}}
    H, W = scene.camera.height, scene.camera.width
    t0 = time.perf_counter()
    if cand.tier == "full":
        from generator.tiers_mitsuba import FullRenderer

        fr = FullRenderer(scene, opts, info)
        t1 = time.perf_counter()
        S = fr.stokes(0.0, 0)
        return np.asarray(S, np.float64), t1 - t0, time.perf_counter() - t1
    if cand.tier == "maps":
        from generator.tiers_mitsuba import render_pane_maps

        maps = render_pane_maps(scene, opts, info)
    else:
        maps = analytic_maps(scene)
    t1 = time.perf_counter()
    tc = LayerContent(scene.layers.transmission, (H, W))
    rc = LayerContent(scene.layers.reflection, (H, W))
    t2 = time.perf_counter()
    L_T, L_R, L_G = sample_layers(maps, tc, rc, 0.0)
    S = frame_stokes(maps, L_T, L_R, L_G)
    return S, (t1 - t0) + (t2 - t1), time.perf_counter() - t2


def corrected_error(err_p99: float, resolution: float) -> dict:
    """The error with the reference's own noise taken out (p99s combined in quadrature, an approximation):
    ``err_corrected = sqrt(max(err^2 - resolution^2, 0))``; errors near ``resolution`` are unresolved.
    """
    return {"err_vs_ref_p99": float(err_p99), "resolution": float(resolution),
            "err_corrected": float(math.sqrt(max(err_p99 * err_p99 - resolution * resolution, 0.0)))}


def _radiance_error(S: np.ndarray, ref: np.ndarray) -> float:
    err = np.max([np.abs(polarizer_intensity(*S, p) - polarizer_intensity(*ref, p)) for p in PHIS], axis=0)
    return float(np.percentile(err, 99))


def _spike_frames(S: np.ndarray, seed: int, steps: int, polarizer, sim_config=None) -> np.ndarray:
    """Eq. (3) frames I(i) from a static Stokes image through the spike simulator (default noise model)."""
    from spike_sim.aggregate import aggregate_stream, frame_centres
    from spike_sim.config import DEFAULT
    from spike_sim.simulate import keyframes_from_arrays, simulate

    cfg = sim_config or DEFAULT
    dur = steps / cfg.rate_hz
    S32 = np.asarray(S, np.float32)
    src = keyframes_from_arrays([0.0, dur], np.stack([S32, S32]), polarizer=polarizer)
    H, W = S.shape[1:]
    chunks: dict[int, np.ndarray] = {}
    simulate(src, dur, seed, cfg, out=None, spikes_sink=lambda n0, packed: chunks.__setitem__(n0, packed.copy()))
    packed = np.concatenate([chunks[k] for k in sorted(chunks)])
    spikes = np.unpackbits(packed, axis=1, bitorder="little", count=H * W).reshape(-1, H, W)
    from polphysics.polarizer import phi_nominal

    t_mid = (np.arange(spikes.shape[0]) + 0.5) / cfg.rate_hz
    centres, _ = frame_centres(np.asarray(phi_nominal(t_mid, polarizer), np.float64))
    return aggregate_stream(spikes, centres)


def run_tradeoff(
    scenes: list,
    out_dir: str | Path,
    candidates: list[Candidate] | None = None,
    ref: Candidate = Candidate("reference full 256spp spectral llvm", "full", 256, spectral=True, variant="llvm"),
    keyframe_rates_hz: tuple[float, ...] = (25.0, 50.0, 100.0, 200.0),
    spike_steps: int = 260,
    progress: Callable[[int, int], None] | None = None,
    refs: dict | None = None,
) -> dict:
    """Measure the trade for each scene; write ``tradeoff.json``, ``tradeoff.md`` and ``pareto.png``.

    ``refs`` (optional dict): filled with ``scene name -> (reference Stokes, resolution)``, what a
    further candidate is compared with (:mod:`polspike.pipeline.tradeoff_planner`).
    """
    out = ensure_dir(out_dir)
    cands = candidates or default_candidates()
    rows: list[dict] = []
    total = len(scenes) * (len(cands) + 1 + len(keyframe_rates_hz))  # + the (cheap) simulator-step rows
    done = 0
    for scene in scenes:
        if getattr(scene, "objects", None) is not None:  # 3-D objects: full tier only, plus the Eq. (1)-(2) rows
            rows.extend(_objects_rows(scene, ref, cands, spike_steps, refs))
            done += len(cands) + 1 + len(keyframe_rates_hz)
            if progress:
                progress(done, total)
            continue
        S_ref, one_ref, frame_ref = _render_first(scene, ref, seed=1)
        S_ref2, _, _ = _render_first(scene, ref, seed=2)
        ref_noise = _radiance_error(S_ref, S_ref2) / math.sqrt(2.0)  # the reference's own Monte Carlo noise
        S_mean, resolution = 0.5 * (S_ref + S_ref2), ref_noise / math.sqrt(2.0)  # noise-corrected errors: against the seeds' mean
        if refs is not None:
            refs[scene.name] = (S_mean, resolution)
        rows.append({"scene": scene.name, "candidate": ref.label + " (its own noise: seed 1 vs 2, / sqrt 2)", "tier": "full", "spp": ref.spp,
                     "spectral": ref.spectral, "variant": ref.variant, "one_off_s": one_ref, "per_frame_s": frame_ref,
                     "per_1s_group_s": one_ref + scene.render.fps * frame_ref, "radiance_err_p99": ref_noise,
                     "radiance_err_mean": float(np.mean(np.abs(S_ref[0] - S_ref2[0]))) / math.sqrt(2.0),
                     "spike_frame_rmse": None, "spike_noise_rmse": None})
        done += 1
        if progress:
            progress(done, total)
        pol = scene.polarizer
        spk_ref = _spike_frames(S_ref, 7, spike_steps, pol)
        spk_ref2 = _spike_frames(S_ref, 8, spike_steps, pol)
        spike_noise = float(np.sqrt(np.mean((spk_ref - spk_ref2) ** 2)))
        fps = scene.render.fps
        for c in cands:
            try:
                S, one, per = _render_first(scene, c)
            except Exception as exc:  # a backend missing on this machine: reported, not fatal
                log.warning("%s: %s skipped (%s)", scene.name, c.label, exc)
                rows.append({"scene": scene.name, "candidate": c.label, "skipped": str(exc).splitlines()[0]})
                done += 1
                continue
            spk = _spike_frames(S, 7, spike_steps, pol)
            group_s = one + fps * per  # fps keyframes per second of video
            rows.append({
                "scene": scene.name, "candidate": c.label, "tier": c.tier, "spp": c.spp, "spectral": c.spectral, "variant": c.variant,
                "one_off_s": one, "per_frame_s": per, "per_1s_group_s": group_s,
                "radiance_err_p99": _radiance_error(S, S_ref),
                "radiance_err_mean": float(np.mean(np.abs(S[0] - S_ref[0]))),
                "spike_frame_rmse": float(np.sqrt(np.mean((spk - spk_ref) ** 2))),
                "spike_noise_rmse": spike_noise,
                **corrected_error(_radiance_error(S, S_mean), resolution),
            })
            done += 1
            if progress:
                progress(done, total)
        rows.extend(_keyframe_rows(scene, keyframe_rates_hz, frame_ref))
        rows.extend(_sim_step_rows(scene, S_ref, spike_noise))
        done += len(keyframe_rates_hz)
        if progress:
            progress(done, total)
    result = {"reference": dataclasses.asdict(ref), "rows": rows}
    write_json(out / "tradeoff.json", result)
    write_text(out / "tradeoff.md", _markdown(rows))
    _pareto_plot(rows, out / "pareto.png")
    return result


def _objects_rows(scene, ref: Candidate, cands: list[Candidate], spike_steps: int, refs: dict | None = None) -> list[dict]:
    """A 3-D object scene (:mod:`generator.objects3d`): the reference's noise, paper Eq. (1)-(2) mixing the
    rendered layers (unpolarized T: the paper's assumption) and with T's polarization carried through the
    pane, and the full-tier candidates.  The models take their layers from the seed-1 reference and are
    compared with the seed-2 mixture (independent noise); the analytic and maps tiers cannot render it.
    """
    from generator.analytic import analytic_maps
    from generator.objects3d import _transmit_polarized
    from generator.render import RenderOptions
    from generator.tiers_mitsuba import FullRenderer
    from polphysics.zeta import stokes_from_layers

    def full(c: Candidate, seed: int):
        t0 = time.perf_counter()
        fr = FullRenderer(scene, RenderOptions(tier="full", spp=c.spp, spectral=False, variant=c.variant, seed=seed), {})
        t1 = time.perf_counter()
        S = fr.stokes(0.0)
        return fr, S, t1 - t0, time.perf_counter() - t1

    fr1, S1, one, per = full(ref, 1)
    _, S2, _, _ = full(ref, 2)
    maps = analytic_maps(scene)
    L = fr1._layers[0]
    L_T, L_R = L["S_T"][0], L["S_R"][0]
    pol = scene.polarizer
    spk_ref = _spike_frames(S2, 7, spike_steps, pol)
    spike_noise = float(np.sqrt(np.mean((spk_ref - _spike_frames(S2, 8, spike_steps, pol)) ** 2)))
    base = {"scene": scene.name, "spectral": False}
    rows = [{**base, "candidate": f"reference full {ref.spp}spp mono (3-D objects; its own noise: seed 1 vs 2, / sqrt 2)", "tier": "full", "spp": ref.spp,
             "variant": ref.variant, "one_off_s": one, "per_frame_s": per, "per_1s_group_s": one + per,  # static: one keyframe
             "radiance_err_p99": _radiance_error(S1, S2) / math.sqrt(2.0), "radiance_err_mean": float(np.mean(np.abs(S1[0] - S2[0]))) / math.sqrt(2.0),
             "spike_frame_rmse": None, "spike_noise_rmse": None}]
    if refs is not None:
        refs[scene.name] = (S2, rows[0]["radiance_err_p99"])
    R_part = stokes_from_layers(np.zeros_like(L_T), L_R, maps.R_perp, maps.R_par, maps.T_perp, maps.T_par, maps.phi_perp)
    models = [("Eq. (1)-(2) on the rendered layers (unpolarized T: the paper's assumption)", stokes_from_layers(L_T, L_R, maps.R_perp, maps.R_par, maps.T_perp, maps.T_par, maps.phi_perp))]
    polT = _transmit_polarized(L["S_T"], maps, scene.pane.model, float(scene.pane.index(550.0)))
    if polT is not None:
        models.append(("Eq. (1)-(2) with T's polarization through the pane (thin-slab Mueller)", polT + R_part))
    for label, S in models:
        rows.append({**base, "candidate": label, "tier": "eq12-model", "spp": ref.spp, "variant": "numpy", "one_off_s": None, "per_frame_s": None,
                     "per_1s_group_s": None, "radiance_err_p99": _radiance_error(S, S2), "radiance_err_mean": float(np.mean(np.abs(S[0] - S2[0]))),
                     "spike_frame_rmse": float(np.sqrt(np.mean((_spike_frames(S, 7, spike_steps, pol) - spk_ref) ** 2))), "spike_noise_rmse": spike_noise})
    for c in cands:
        if c.tier != "full":
            rows.append({**base, "candidate": c.label, "skipped": "3-D objects: only the full tier renders them"})
            continue
        try:
            _, S, one_c, per_c = full(c, 3)
        except Exception as exc:  # a backend missing on this machine: reported, not fatal
            rows.append({**base, "candidate": c.label, "skipped": str(exc).splitlines()[0]})
            continue
        e = _radiance_error(S, S2)
        rows.append({**base, "candidate": c.label, "tier": "full", "spp": c.spp, "variant": c.variant, "one_off_s": one_c, "per_frame_s": per_c,
                     "per_1s_group_s": one_c + per_c, "radiance_err_p99": e, "radiance_err_mean": float(np.mean(np.abs(S[0] - S2[0]))),
                     "spike_frame_rmse": float(np.sqrt(np.mean((_spike_frames(S, 7, spike_steps, pol) - spk_ref) ** 2))), "spike_noise_rmse": spike_noise,
                     **corrected_error(e, rows[0]["radiance_err_p99"])})
    return rows


def _keyframe_rows(scene, rates, full_frame_s: float) -> list[dict]:
    """Keyframe-rate knob: Stokes interpolated between keyframes vs rendered at every 1 ms (analytic motion)."""
    from generator.analytic import analytic_maps, frame_stokes, sample_layers
    from generator.layers import LayerContent

    H, W = scene.camera.height, scene.camera.width
    maps = analytic_maps(scene)
    tc = LayerContent(scene.layers.transmission, (H, W))
    rc = LayerContent(scene.layers.reflection, (H, W))
    if tc.is_static and rc.is_static:
        return [{"scene": scene.name, "candidate": f"keyframes {r:g} Hz", "skipped": "static scene: one keyframe is exact"} for r in rates]

    def S(t):
        return frame_stokes(maps, *sample_layers(maps, tc, rc, t))

    rows = []
    for r in rates:
        dt = 1.0 / r
        ts = np.linspace(0.0, dt, 6)[1:-1]  # inside the first interval
        a, b = S(0.0), S(dt)
        errs = [_radiance_error((1 - t / dt) * a + (t / dt) * b, S(t)) for t in ts]
        rows.append({
            "scene": scene.name, "candidate": f"keyframes {r:g} Hz (full tier cost model)", "tier": "full-keyframes", "keyframe_hz": r,
            "per_frame_s": full_frame_s, "per_1s_group_s": r * full_frame_s, "radiance_err_p99": float(max(errs)),
            "spike_frame_rmse": None, "spike_noise_rmse": None,
        })
    return rows


def _sim_step_rows(scene, S: np.ndarray, spike_noise: float, n_steps: int = 520, samples=(1, 4)) -> list[dict]:
    """Simulator time-step knob: the polarizer's light over each 50 us step from
    point samples (1 = mid-step, 4 = four sub-steps) vs the closed-form step integral
    the simulator uses.  Error measured on noise-free Eq. (3) frames I(i), in the
    same units as the spike noise, and cost per 1 s of stream (20 000 steps).
    """
    from polphysics.polarizer import step_mean_intensity, step_phi_edges
    from polphysics.stokes import polarizer_intensity
    from spike_sim.aggregate import AggregateConfig

    pol = scene.polarizer
    dt = 1.0 / 20000.0
    a, b = step_phi_edges(0, n_steps, dt, pol)
    s0, s1, s2 = (np.asarray(c, np.float64) for c in S)
    win = AggregateConfig().window_steps

    def frames(per_step) -> np.ndarray:  # noise-free Eq. (3) frames: window means of step intensities
        m = (n_steps // win) * win
        return per_step[:m].reshape(-1, win, *per_step.shape[1:]).mean(1)

    t0 = time.perf_counter()
    exact = np.stack([step_mean_intensity(s0, s1, s2, a[n], b[n]) for n in range(0, n_steps)])
    t_exact = time.perf_counter() - t0
    f_exact = frames(exact)
    rows = []
    for k in samples:
        t0 = time.perf_counter()
        u = (np.arange(k) + 0.5) / k
        approx = np.stack([np.mean([polarizer_intensity(s0, s1, s2, a[n] + (b[n] - a[n]) * x) for x in u], axis=0) for n in range(n_steps)])
        t_k = time.perf_counter() - t0
        rows.append({
            "scene": scene.name, "candidate": f"simulator: {k} point sample(s) per step vs closed form", "tier": "sim-step", "sub_samples": k,
            "per_frame_s": None, "per_1s_group_s": t_k * 20000.0 / n_steps, "cost_ratio_vs_closed_form": t_k / t_exact,
            "radiance_err_p99": float(np.percentile(np.abs(approx - exact), 99)),
            "spike_frame_rmse": float(np.sqrt(np.mean((frames(approx) - f_exact) ** 2))), "spike_noise_rmse": spike_noise,
        })
    return rows


def _markdown(rows: list[dict]) -> str:
    head = "| scene | candidate | s/frame | s per 1 s group | radiance err p99 | S0 err mean | spike-frame RMSE | spike noise RMSE |\n|---|---|---|---|---|---|---|---|\n"
    lines = []
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['scene']} | {r['candidate']} | skipped: {r['skipped']} | | | | | |")
            continue
        f = lambda v, p=3: "n/a" if v is None else f"{v:.{p}g}"  # noqa: E731
        lines.append(f"| {r['scene']} | {r['candidate']} | {f(r['per_frame_s'])} | {f(r['per_1s_group_s'])} | {f(r['radiance_err_p99'])} | {f(r.get('radiance_err_mean'))} | {f(r['spike_frame_rmse'])} | {f(r['spike_noise_rmse'])} |")
    return head + "\n".join(lines) + "\n"


def _pareto_plot(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    from polinfra.plotting import save_figure

    fig, ax = plt.subplots(figsize=(8, 5))
    scenes = sorted({r["scene"] for r in rows})
    markers = {s: "osD^v<>ph*XP"[i % 12] for i, s in enumerate(scenes)}
    for r in rows:
        if "skipped" in r or r["radiance_err_p99"] is None or r.get("per_1s_group_s") is None:
            continue
        x, y = r["per_1s_group_s"], max(r["radiance_err_p99"], 1e-9)
        colour = {"analytic": "C0", "maps": "C1", "full": "C2", "full-keyframes": "C3", "sim-step": "C4"}.get(r["tier"], "k")
        ax.scatter(x, y, marker=markers[r["scene"]], c=colour, s=36)
        ax.annotate(r["candidate"].split(" (")[0], (x, y), fontsize=6, alpha=0.7)
    for t, c in (("analytic", "C0"), ("maps", "C1"), ("full", "C2"), ("keyframe rate", "C3"), ("simulator step sampling", "C4")):
        ax.scatter([], [], c=c, label=t)
    for s, m in markers.items():
        ax.scatter([], [], marker=m, c="grey", label=s)
    noise = [r["spike_noise_rmse"] for r in rows if r.get("spike_noise_rmse")]
    if noise:
        ax.axhline(float(np.median(noise)), ls=":", c="k", label="spike noise (RMSE of I(i), median)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("cost: seconds per 1 s group (400x250, this machine)")
    ax.set_ylabel("error vs reference: p99 worst-case |I(phi)| (radiance)")
    ax.set_title("speed / accuracy trade (Pareto)")
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path)
