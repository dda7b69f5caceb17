"""Tier dispatcher and writer of a render directory (the generator's output format).

Tiers (cheapest first; colour-science style mapping with one dispatcher):
    ``analytic``  coefficient maps from geometry + Fresnel, layers mixed by Eq. (1)-(2);
    ``maps``      coefficient maps rendered once by Mitsuba (deterministic two-lobe
                  evaluation), layers mixed per frame exactly as ``analytic``;
    ``full``      Mitsuba path-traces the 3-D scene's Stokes per keyframe.

Output (written atomically, resumable over frames)::

    DIR/render.json            scene hash, tier, frame times, timings, what was modelled
    DIR/maps.exr               theta, phi_perp, R_perp, R_par, T_perp, T_par
    DIR/frames/NNNNNN.exr      S0, S1, S2 (in front of the polarizer), T, R (ground truth)
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from generator.analytic import ANALYTIC_MODELLED, PaneMaps, analytic_maps, frame_stokes, sample_layers, spectral_frame
from generator.layers import LayerContent
from generator.scene import SceneConfig, check_scene_geometry, scene_hash
from polinfra.atomic import ensure_dir, write_json
from polinfra.config import to_dict
from polinfra.errors import ConfigError, OutputError
from polinfra.exr import write_exr

__all__ = ["RenderOptions", "render", "TIERS", "frame_times", "CONVENTIONS", "RENDER_FORMAT"]

log = logging.getLogger(__name__)

TIERS = ("analytic", "maps", "full")
RENDER_FORMAT = "polspike-render/1"
CONVENTIONS = (
    "image x right, y down; angles in radians from image +x toward image up (counter-clockwise); "
    "Stokes (S0,S1,S2) in the camera frame, S1>0 along image x, S2>0 along +45 deg; "
    "ideal polarizer at phi passes 1/2 (S0 + S1 cos 2phi + S2 sin 2phi); radiance linear, 1.0 = brightest layer value"
)


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """Options of one render (CLI flags; scene ``[render]`` gives the defaults)."""

    tier: str = "analytic"
    fps: float | None = None
    duration_s: float | None = None
    frames: tuple[int, int] | None = None
    spp: int | None = None
    variant: str = "auto"
    spectral: bool | None = None
    seed: int | None = None
    keyframe_hz: float | None = None
    response: str = "cie_y"
    """Sensor spectral response of spectral renders: ``cie_y``, ``flat`` or a CSV path (``wavelength_nm,response``)."""
    n_bands: int = 8
    """Wavelength bands of the spectral quadrature (400-700 nm)."""
    supersample: int | None = None
    """Analytic tier: 0 = the pixel centre's point sample; K >= 1 = the pixel's area, K x K stratified rays each the box
    mean of the full tier's texels over its cell (:mod:`generator.analytic_area`) [default: scene ``render.supersample``]."""


def _supersample(scene: SceneConfig, opts: RenderOptions) -> int:
    """The analytic tier's rays per pixel side (0: point sample; 0 for the other tiers)."""
    if opts.tier != "analytic":
        return 0
    return int(opts.supersample if opts.supersample is not None else scene.render.supersample)


def _resume_key(scene: SceneConfig, opts: RenderOptions) -> dict:
    """Resolved options that change the pixels of a frame: a resumed render must use the same ones."""
    key: dict = {
        "fps": float(opts.fps or scene.render.fps),
        "seed": int(opts.seed if opts.seed is not None else scene.render.seed),
    }
    if opts.tier == "analytic" and opts.spectral and scene.pane.glass is not None:
        key["spectral"] = True  # the analytic tier integrates bands only when asked explicitly
        key["response"] = str(opts.response)
        key["n_bands"] = int(opts.n_bands)
    if _supersample(scene, opts) > 0:
        key["supersample"] = _supersample(scene, opts)
    if opts.tier != "analytic":
        key["spp"] = int(opts.spp or scene.render.spp)
        spectral = bool(scene.render.spectral if opts.spectral is None else opts.spectral)
        key["spectral"] = spectral
        if spectral and scene.pane.glass is not None:
            key["response"] = str(opts.response)
            key["n_bands"] = int(opts.n_bands)
    if opts.tier == "full":
        key["keyframe_hz"] = float(opts.keyframe_hz or key["fps"])
    return key


def frame_times(scene: SceneConfig, opts: RenderOptions) -> np.ndarray:
    """Keyframe times (s): k / fps for k = 0..ceil(duration * fps) (endpoint included)."""
    fps = opts.fps or scene.render.fps
    dur = opts.duration_s or scene.render.duration_s
    if fps <= 0 or dur <= 0:
        raise ConfigError(f"fps and duration must be > 0 (got fps={fps}, duration={dur})")
    n = int(math.ceil(dur * fps - 1e-9)) + 1
    return np.arange(n) / fps


def _tier_maps(scene: SceneConfig, opts: RenderOptions, info: dict, progress: Callable[[int, int], None] | None = None) -> PaneMaps:
    """Coefficient maps for the analytic or maps tier (``progress``: ray chunks of the Mitsuba tracer)."""
    if opts.tier == "analytic":
        return analytic_maps(scene)
    from generator import tiers_mitsuba  # lazy: imports Mitsuba
    from generator.mitsuba_backend import resolve_backend

    be = resolve_backend(opts.variant or "auto", spectral=False)  # unknown / unavailable forced variant: error
    if not be.vectorized:
        if opts.tier == "full":
            # the full tier path-traces on any backend; only its maps.exr needs the JIT two-lobe tracer
            log.warning("full tier on %s: maps.exr falls back to the analytic maps (the two-lobe tracer needs llvm or cuda)", be.variant)
            info["modelled"] = dict(ANALYTIC_MODELLED, maps_exr_source=f"analytic: the two-lobe tracer needs a JIT variant, {be.variant} selected")
            return analytic_maps(scene)
        if (opts.variant or "auto") == "auto":
            # no JIT backend works here: never crash, fall back to the analytic maps (same Fresnel model; agrees
            # with the two-lobe maps to 1e-4 except dispersion) and say so loudly
            why = "; ".join(be.fallbacks) or be.variant
            log.warning("maps tier: no JIT Mitsuba variant works (%s); falling back to the ANALYTIC coefficient maps", why)
            info["modelled"] = dict(ANALYTIC_MODELLED, maps_source=f"analytic fallback: the two-lobe tracer needs llvm or cuda ({why})", backend=be.to_dict())
            info["variant"] = be.variant
            return analytic_maps(scene)
    return tiers_mitsuba.render_pane_maps(scene, opts, info, progress=progress)


def render(
    scene: SceneConfig,
    out_dir: str | os.PathLike,
    opts: RenderOptions = RenderOptions(),
    progress: Callable[[int, int], None] | None = None,
    tolerance: float | None = None,
) -> dict:
    """Render ``scene`` with the chosen tier into ``out_dir`` and return the render.json dict.

    ``opts.tier == 'auto'``: :func:`generator.planner.plan_tier` picks the cheapest tier (and spp)
    whose predicted p99 error is <= ``tolerance``; render.json's ``tier_plan`` holds the choice, every
    tier's prediction and the reasons.

    Resumable: frames already present for the same scene hash and tier are kept.
    """
    plan = None
    if opts.tier == "auto":
        from generator.planner import apply_plan, plan_tier

        if tolerance is None:
            raise ConfigError("--tier auto needs --tolerance EPS (the largest acceptable p99 radiance error)")
        if opts.supersample is not None:
            raise ConfigError("--supersample is chosen by --tier auto (with the tier); drop it or name the tier")
        plan = plan_tier(scene, tolerance)
        opts = apply_plan(opts, plan)
    if opts.tier not in TIERS:
        raise ConfigError(f"unknown tier {opts.tier!r}; choose one of {list(TIERS) + ['auto']}")
    if opts.supersample is not None and opts.tier != "analytic" and plan is None:
        raise ConfigError(f"--supersample is for the analytic tier (tier is {opts.tier!r}); the full tier samples the pixel with --spp")
    K = _supersample(scene, opts)
    if not 0 <= K <= 64:
        raise ConfigError(f"--supersample {K} must be from 0 (point sample) to 64 (rays per pixel side)")
    from generator.objects3d import object_sides, require_full_tier

    require_full_tier(scene, opts.tier)
    check_scene_geometry(scene)
    if scene.objects is not None:
        object_sides(scene)  # every object and light on one side of the pane
    if opts.response not in ("cie_y", "flat") and not Path(opts.response).is_file():
        raise ConfigError(f"--response {opts.response!r} is neither cie_y, flat nor an existing CSV file (wavelength_nm,response)")
    h = scene_hash(scene)
    times = frame_times(scene, opts)
    a, b = opts.frames or (0, len(times))
    if not (0 <= a < b <= len(times)):
        raise ConfigError(f"--frames {a}:{b} is outside 0:{len(times)} for this duration and fps")
    if opts.tier != "analytic" and (opts.variant or "auto") != "auto":
        from generator.mitsuba_backend import resolve_backend

        resolve_backend(opts.variant, spectral=False)  # a forced variant that cannot run fails before --out is touched
    out = ensure_dir(out_dir)
    ensure_dir(out / "frames")
    meta_path = out / "render.json"
    prev = None
    if meta_path.is_file():
        try:
            prev = json.loads(meta_path.read_text())
        except json.JSONDecodeError:
            prev = None
    if prev and (prev.get("scene_hash") != h or prev.get("tier") != opts.tier):
        raise OutputError(f"{out} holds a render of another scene or tier ({prev.get('tier')}, {prev.get('scene_hash')}); choose an empty --out")
    rkey = _resume_key(scene, opts)
    if prev and isinstance(prev.get("resume_key"), dict):
        diff = sorted(k for k in set(rkey) | set(prev["resume_key"]) if rkey.get(k) != prev["resume_key"].get(k))
        if diff:
            k = diff[0]
            raise OutputError(
                f"{out} was rendered with {k} = {prev['resume_key'].get(k)!r}, this run has {k} = {rkey.get(k)!r}; "
                "resume with the same options or choose an empty --out"
            )
        names_prev = prev.get("frames") or []
        if (
            prev.get("complete")
            and len(names_prev) == len(times)
            and (out / "maps.exr").is_file()
            and all((out / nm).is_file() for nm in names_prev)
        ):
            log.info("%s: render already complete (same scene, tier and options); nothing to do", out)
            if progress:
                progress(b - a, b - a)
            return prev
    timings: dict[str, float] = dict(prev.get("timings", {})) if prev else {}
    info: dict = {"modelled": dict(ANALYTIC_MODELLED), "tier": opts.tier}
    t0 = time.perf_counter()
    maps = _tier_maps(scene, opts, info, progress)  # the bar first counts the maps' ray chunks, then frames
    timings["maps_s"] = time.perf_counter() - t0
    write_exr(out / "maps.exr", {k: v.astype(np.float32) for k, v in maps.channels().items()}, attrs={"scene_hash": h, "tier": opts.tier})
    names = [f"frames/{k:06d}.exr" for k in range(len(times))]
    meta = {
        "format": RENDER_FORMAT,
        "scene_hash": h,
        "tier": opts.tier,
        "width": scene.camera.width,
        "height": scene.camera.height,
        "fps": float(opts.fps or scene.render.fps),
        "frame_times_s": times.tolist(),
        "frames": names,
        "scene": to_dict(scene),
        "modelled": info["modelled"],
        "spp": info.get("spp"),
        "variant": info.get("variant"),
        "seed": opts.seed if opts.seed is not None else scene.render.seed,
        "resume_key": rkey,
        "conventions": CONVENTIONS,
        "complete": False,
        "timings": timings,
    }
    if plan is not None:
        meta["tier_plan"] = plan.to_dict()
    elif prev and prev.get("tier_plan"):
        meta["tier_plan"] = prev["tier_plan"]
    write_json(meta_path, meta)
    tc = LayerContent(scene.layers.transmission, (scene.camera.height, scene.camera.width))
    rc = LayerContent(scene.layers.reflection, (scene.camera.height, scene.camera.width))
    bands = area_bands = None
    if opts.tier == "analytic" and opts.spectral and scene.pane.glass is not None:  # dispersion: Eq. (1)-(2) per band, weighted
        from generator.tiers_mitsuba import spectral_bands

        wl, w = spectral_bands(opts.n_bands, opts.response)
        if K > 0:
            area_bands = [(float(x), float(wi)) for x, wi in zip(wl, w)]
        else:
            bands = [(float(wi), analytic_maps(scene, float(x))) for x, wi in zip(wl, w)]
        info["modelled"]["spectral"] = f"{opts.n_bands} bands 400-700 nm, {scene.pane.glass} Sellmeier index, response {opts.response} (maps.exr at 550 nm)"
        meta["modelled"] = info["modelled"]
    if K > 0:
        info["modelled"]["supersample"] = f"pixel area: {K}x{K} stratified rays per pixel, box filter, each the mean of the full tier's nearest-texel textures over its cell"
        meta["modelled"] = info["modelled"]
    full = None
    if opts.tier == "full":
        from generator import tiers_mitsuba

        full = tiers_mitsuba.FullRenderer(scene, opts, info)
        if full.objects:
            # 3-D objects: keyframe 0's departure from Eq. (1)-(2) joins maps.exr (dop_T, dop_R, eq12_err, polT_model_err)
            chans, dep = full.departure(maps)
            write_exr(out / "maps.exr", {**{k: v.astype(np.float32) for k, v in maps.channels().items()}, **{k: v.astype(np.float32) for k, v in chans.items()}}, attrs={"scene_hash": h, "tier": opts.tier})
            info["modelled"]["eq12_departure"] = dep
            meta["eq12_departure"] = dep
    t1 = time.perf_counter()
    todo = [k for k in range(a, b) if not (out / names[k]).is_file()]
    done = (b - a) - len(todo)
    area: dict[int, tuple] = {}
    for n, k in enumerate(todo):
        t = float(times[k])
        if K > 0:
            if k not in area:  # a batch of frames per pass over the ray positions
                from generator.analytic_area import FRAME_BATCH, area_frames

                batch = todo[n:n + FRAME_BATCH]
                area = dict(zip(batch, area_frames(scene, [float(times[j]) for j in batch], K, area_bands)))
            S, L_T, L_R = area.pop(k)
        elif full is not None and full.objects:
            S = full.stokes(t, k)
            L_T, L_R = full.layers(t)
        elif bands is not None:
            S, L_T, L_R = spectral_frame(bands, tc, rc, t)
        else:
            L_T, L_R, L_G = sample_layers(maps, tc, rc, t)
            S = full.stokes(t, k) if full is not None else frame_stokes(maps, L_T, L_R, L_G)
        write_exr(
            out / names[k],
            {"S0": S[0], "S1": S[1], "S2": S[2], "T": L_T, "R": L_R},
            attrs={"time_s": f"{t:.9f}", "scene_hash": h},
        )
        done += 1
        if progress:
            progress(done, b - a)
    n_new = len(todo)
    timings["frames_s"] = timings.get("frames_s", 0.0) + (time.perf_counter() - t1)
    if n_new:
        timings["per_frame_s"] = (time.perf_counter() - t1) / n_new
    meta["modelled"] = info["modelled"]
    meta["variant"], meta["spp"] = info.get("variant"), info.get("spp")  # the full tier's path tracer, not its maps.exr
    meta["complete"] = all((out / nm).is_file() for nm in names)
    meta["timings"] = timings
    write_json(meta_path, meta)
    return meta
