"""Cross-validate the analytic zeta (paper Eq. (2)) against a rendered tier's Stokes vectors.

Method (probe renders, no access to a renderer's internals needed):

1. R probe: the scene with a uniform R layer of radiance 1 and a black T layer.
   Its Stokes image is the pane's reflection response: with L = |(S1, S2)|,
   R_perp = S0 + L, R_par = S0 - L, phi_perp = AoLP (paper Eq. (2) in Stokes form).
2. T probe: uniform T layer, black R layer: T_perp = S0 + (S1 cos 2phi_perp +
   S2 sin 2phi_perp), T_par = S0 - (...) with phi_perp from the analytic model.
3. The scene itself, first keyframe: I(phi) from the rendered Stokes against
   paper Eq. (1) with the model's zeta and the ground-truth layers.  A 3-D object
   scene (:mod:`generator.objects3d`) is probed with its objects replaced by flat
   layers, its own frame is rendered in the full tier, and the summary adds
   ``eq12_departure`` (DoP of T alone, the per-pixel error of the unpolarized-T
   assumption, the noise floor).

Errors are per pixel; for zeta it is the worst case over 36 polarizer angles in
[0, pi).  The Monte Carlo noise floor of a stochastic tier is measured, not
assumed: the R probe is rendered twice with different seeds and the floor is
the 99th percentile of |zeta_a - zeta_b| / sqrt(2) (0 for deterministic tiers).
Verdict: pass when p99(zeta error) - noise floor <= tolerance.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from generator.analytic import analytic_maps
from generator.render import RenderOptions, render
from generator.scene import LayerConfig, MotionConfig, SceneConfig
from polinfra.atomic import ensure_dir, write_json
from polinfra.errors import ConfigError
from polinfra.exr import read_exr
from polinfra.plotting import image_grid, save_figure
from polphysics.fresnel import PANE_MODELS, radiance_scale
from polphysics.stokes import polarizer_intensity
from polphysics.zeta import mix_eq1, zeta

__all__ = ["validate_zeta", "probe_scene", "fit_reflection", "fit_transmission", "ZETA_ANGLES"]

log = logging.getLogger(__name__)

ZETA_ANGLES = np.linspace(0.0, np.pi, 36, endpoint=False)
"""Polarizer angles (rad) over which the worst-case zeta error is taken."""


def _flat(cfg: LayerConfig, on: bool) -> LayerConfig:
    return dataclasses.replace(cfg, source="procedural:flat", brightness=1.0 if on else 0.0, offset=0.0, motion=MotionConfig(), sprites=())


def probe_scene(scene: SceneConfig, which: str) -> SceneConfig:
    """The scene with a uniform unit ``which`` ('R' or 'T') layer and the other layer black.

    A 3-D object scene is probed with its objects replaced by the layer planes (zeta
    depends only on the camera and the pane).
    """
    lt, lr = scene.layers.transmission, scene.layers.reflection
    layers = dataclasses.replace(scene.layers, transmission=_flat(lt, which == "T"), reflection=_flat(lr, which == "R"))
    return dataclasses.replace(scene, layers=layers, name=f"{scene.name}-probe{which}", objects=None)


def fit_reflection(S: np.ndarray):
    """(R_perp, R_par, phi_perp) from the Stokes image (3, H, W) of a unit R probe."""
    s0, s1, s2 = (np.asarray(x, np.float64) for x in S)
    lin = np.hypot(s1, s2)
    return s0 + lin, s0 - lin, np.mod(0.5 * np.arctan2(s2, s1), np.pi)


def fit_transmission(S: np.ndarray, phi_perp):
    """(T_perp, T_par) from the Stokes image of a unit T probe, given phi_perp."""
    s0, s1, s2 = (np.asarray(x, np.float64) for x in S)
    proj = s1 * np.cos(2 * phi_perp) + s2 * np.sin(2 * phi_perp)
    return s0 + proj, s0 - proj


def _stats(err: np.ndarray, mask: np.ndarray | None = None) -> dict:
    e = np.abs(err[mask] if mask is not None else err).ravel()
    if e.size == 0:
        return {"max": 0.0, "mean": 0.0, "p99": 0.0, "pixels": 0}
    return {"max": float(e.max()), "mean": float(e.mean()), "p99": float(np.percentile(e, 99)), "pixels": int(e.size)}


def _render_first(scene: SceneConfig, out: Path, opts: RenderOptions) -> np.ndarray:
    o = dataclasses.replace(opts, frames=(0, 1), duration_s=opts.duration_s or scene.render.duration_s)
    render(scene, out, o)
    f = read_exr(out / "frames" / "000000.exr")
    return np.stack([f["S0"], f["S1"], f["S2"]]).astype(np.float64), f["T"].astype(np.float64), f["R"].astype(np.float64)


def validate_zeta(
    scene: SceneConfig,
    out_dir: str | os.PathLike,
    opts: RenderOptions = RenderOptions(tier="analytic"),
    model: str | None = None,
    tolerance: float = 1e-3,
    apply_radiance_scale: bool | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Compare a tier's rendered response of ``scene`` with the analytic model; write maps and summary.json.

    Args:
        scene: the scene.
        out_dir: output folder (probe renders, PNG error maps, histogram, summary.json).
        opts: render options of the tier under test.
        model: analytic pane model to validate against (default: the scene's own);
            validating a slab scene against ``single`` must fail.
        tolerance: allowed p99 worst-case |zeta error| above the noise floor.
        apply_radiance_scale: compare T with the 1/n^2 compression of a single
            interface (default: when the tier reports it modelled it).

    Returns:
        The summary dict (also written to ``out_dir/summary.json``).
    """
    if model is not None and model not in PANE_MODELS:
        raise ConfigError(f"--model {model!r}: choose one of {list(PANE_MODELS)}")
    if not tolerance > 0:
        raise ConfigError(f"--tolerance {tolerance} must be > 0")
    plan = None
    if opts.tier == "auto":  # the planner picks the cheapest tier (and spp) predicted to meet the tolerance
        from generator.planner import apply_plan, plan_tier

        plan = plan_tier(scene, tolerance)
        opts = apply_plan(opts, plan)
    out = ensure_dir(out_dir)
    steps = 4 if opts.tier == "full" else 3
    step = 0

    def tick():
        nonlocal step
        step += 1
        if progress:
            progress(step, steps)

    S_r, _, _ = _render_first(probe_scene(scene, "R"), out / "probe_R", opts)
    tick()
    S_t, _, _ = _render_first(probe_scene(scene, "T"), out / "probe_T", opts)
    tick()
    objects = scene.objects is not None
    # a 3-D object scene renders only in the full tier: its own frame (and Eq. (1)-(2) departure) comes from there
    S_m, L_T, L_R = _render_first(scene, out / "scene", opts if not objects else dataclasses.replace(opts, tier="full"))
    tick()
    rmeta = json.loads((out / "probe_R" / "render.json").read_text())  # one keyframe only: read the metadata directly
    noise = 0.0
    if opts.tier == "full":
        seed2 = (opts.seed if opts.seed is not None else scene.render.seed) + 1
        S_r2, _, _ = _render_first(probe_scene(scene, "R"), out / "probe_R_seed2", dataclasses.replace(opts, seed=seed2))
        tick()
        ra, pa, fa = fit_reflection(S_r)
        rb, pb, fb = fit_reflection(S_r2)
        d = np.max([np.abs(zeta(p, ra, pa, fa) - zeta(p, rb, pb, fb)) for p in ZETA_ANGLES], axis=0) / math.sqrt(2.0)
        noise = float(np.percentile(d, 99))

    model_scene = scene if model is None else dataclasses.replace(scene, pane=dataclasses.replace(scene.pane, model=model))
    ref = analytic_maps(model_scene)
    Rp_fit, Rl_fit, phi_fit = fit_reflection(S_r)
    Tp_fit, Tl_fit = fit_transmission(S_t, ref.phi_perp)
    if apply_radiance_scale is None:
        apply_radiance_scale = bool(rmeta.get("modelled", {}).get("radiance_compression_1_over_n2", False))
    k = radiance_scale(model_scene.pane.index(), model_scene.pane.model) if apply_radiance_scale else 1.0

    z_err = np.max([np.abs(zeta(p, Rp_fit, Rl_fit, phi_fit) - zeta(p, ref.R_perp, ref.R_par, ref.phi_perp)) for p in ZETA_ANGLES], axis=0)
    dphi = np.mod(phi_fit - ref.phi_perp + np.pi / 2, np.pi) - np.pi / 2
    polarized = (ref.R_perp - ref.R_par) > 1e-3
    errs = {
        "zeta_worst_over_phi": z_err,
        "R_perp": Rp_fit - ref.R_perp,
        "R_par": Rl_fit - ref.R_par,
        "phi_perp_rad": np.where(polarized, dphi, 0.0),
        "T_perp": Tp_fit - k * ref.T_perp,
        "T_par": Tl_fit - k * ref.T_par,
    }
    i_phis = np.deg2rad([0.0, 45.0, 90.0, 135.0])
    for p in i_phis:
        z = zeta(p, ref.R_perp, ref.R_par, ref.phi_perp)
        tau = k * zeta(p, ref.T_perp, ref.T_par, ref.phi_perp)
        i_model = 0.5 * (z * L_R + tau * L_T) if k != 1.0 else mix_eq1(L_R, L_T, z)
        errs[f"I_phi{int(round(np.rad2deg(p)))}"] = polarizer_intensity(*S_m, p) - i_model
    stats = {name: _stats(e, polarized if name == "phi_perp_rad" else None) for name, e in errs.items()}
    stats["phi_perp_rad"]["masked_unpolarized_fraction"] = float(1.0 - polarized.mean())
    excess = max(0.0, stats["zeta_worst_over_phi"]["p99"] - noise)
    verdict = "pass" if excess <= tolerance else "fail"

    figs = ensure_dir(out / "figures")
    panels = []
    for name, e in errs.items():
        a = np.abs(e)
        panels.append((f"|error| {name}", a, {"cmap": "inferno", "vmin": 0, "vmax": max(float(np.percentile(a, 99.5)), 1e-12), "label": "rad" if "rad" in name else "absolute"}))
    save_figure(image_grid(panels, ncols=4, title=f"{scene.name}: tier {opts.tier} vs analytic model '{model_scene.pane.model}' ({verdict})"), figs / "error_maps.png")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ze = np.maximum(z_err.ravel(), 1e-12)
    ax.hist(np.log10(ze), bins=60, color="#4477aa")
    ax.axvline(np.log10(tolerance), color="r", ls="--", label=f"tolerance {tolerance:g}")
    if noise > 0:
        ax.axvline(np.log10(noise), color="k", ls=":", label=f"MC noise floor {noise:.2g}")
    ax.set_xlabel("log10 worst-case |zeta error| over phi")
    ax.set_ylabel("pixels")
    ax.set_title(f"{scene.name}: {opts.tier} vs analytic ({model_scene.pane.model})")
    ax.legend(fontsize=8)
    save_figure(fig, figs / "zeta_error_hist.png")

    summary = {
        "scene": scene.name,
        "tier": opts.tier,
        "spp": rmeta.get("spp"),
        "variant": rmeta.get("variant"),
        "analytic_model": model_scene.pane.model,
        "radiance_scale_applied": k,
        "errors": stats,
        "noise_floor_p99": noise,
        "model_error_p99_above_noise": excess,
        "tolerance": tolerance,
        "verdict": verdict,
    }
    if objects:
        # how far the rendered 3-D mixture departs from Eq. (1)-(2) (DoP of T alone, unpolarized-T error per pixel);
        # the I_phi* rows above are the same departure at four angles (GT layers = S0 of T alone / R alone)
        smeta = json.loads((out / "scene" / "render.json").read_text())
        summary["scene_tier"] = "full"
        summary["eq12_departure"] = smeta.get("eq12_departure")
    if plan is not None:
        summary["tier_plan"] = plan.to_dict()
    write_json(out / "summary.json", summary)
    return summary
