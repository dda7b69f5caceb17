"""Render speed benchmark: seconds per frame of the Mitsuba tiers per backend and spp.

Measures, in one process and on one scene shrunk or grown to ``width x height``:

* ``full`` tier: one path-traced keyframe (texture sampling, ``mi.load_dict``,
  ``mi.render`` with ``stokes`` + ``path``), per backend and spp.  The first
  keyframe includes JIT compilation ("first_s"); later keyframes reuse the
  kernel cache ("later_s", the mean over ``repeats``).
* ``maps`` tier: the deterministic two-lobe coefficient maps (once per scene),
  per JIT backend, with 2x2 sub-pixel rays.

Speed is also reported as the ratio scalar / LLVM of the later-call times
measured in the same run (how many times faster LLVM is).
"""

from __future__ import annotations

import dataclasses
import logging
import platform
import time
from collections.abc import Callable

import numpy as np

from polinfra.errors import PolspikeError

__all__ = ["run_render_bench"]

log = logging.getLogger(__name__)


def _scene(name: str, width: int, height: int):
    from generator.scene import load_scene

    s = load_scene(name)
    return dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=width, height=height))


def run_render_bench(
    width: int = 400,
    height: int = 250,
    spps: tuple[int, ...] = (4, 16, 64),
    backends: tuple[str, ...] = ("cuda", "llvm", "scalar"),
    scene: str = "brewster",
    repeats: int = 2,
    maps: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Time the Mitsuba tiers; returns a JSON-able dict (see module doc).

    Args:
        width, height: frame size in pixels.
        spps: samples per pixel of the full tier.
        backends: backends to try; unavailable ones are reported, not fatal.
        scene: default scene name (a moving one, so every keyframe is rendered).
        repeats: later keyframes timed per (backend, spp).
        maps: also time the maps tier.
        progress: optional (done, total) callback.
    """
    from generator import tiers_mitsuba as tm
    from generator.mitsuba_backend import resolve_backend
    from generator.render import RenderOptions

    sc = _scene(scene, width, height)
    rows: list[dict] = []
    unavailable: dict[str, str] = {}
    total = len(backends) * (len(spps) + int(maps))
    done = 0
    for be_name in backends:
        try:
            be = resolve_backend(be_name)
        except PolspikeError as exc:
            unavailable[be_name] = str(exc)
            done += len(spps) + int(maps)
            if progress:
                progress(done, total)
            continue
        for spp in spps:
            fr = tm.FullRenderer(sc, RenderOptions(tier="full", spp=spp, variant=be_name, spectral=False, fps=sc.render.fps), {})
            t0 = time.perf_counter()
            S = fr.stokes(0.0)
            first = time.perf_counter() - t0
            later = []
            for j in range(1, repeats + 1):
                t0 = time.perf_counter()
                fr.stokes(j / fr.kf_hz)
                later.append(time.perf_counter() - t0)
            rows.append({
                "tier": "full", "backend": be_name, "variant": be.variant, "spp": spp,
                "first_s": round(first, 4), "later_s": round(float(np.mean(later)), 4),
                "samples_per_s": round(width * height * spp / float(np.mean(later))),
                "mean_S0": round(float(S[0].mean()), 5), "finite": bool(np.all(np.isfinite(S))),
            })
            done += 1
            if progress:
                progress(done, total)
        if maps:
            if be.vectorized:
                ts = []
                for _ in range(2):
                    t0 = time.perf_counter()
                    tm.render_pane_maps(sc, RenderOptions(tier="maps", spp=4, variant=be_name, spectral=False), {})
                    ts.append(time.perf_counter() - t0)
                rows.append({"tier": "maps", "backend": be_name, "variant": be.variant, "spp": 4, "first_s": round(ts[0], 4), "later_s": round(ts[1], 4)})
            done += 1
            if progress:
                progress(done, total)
    ratios = {}
    for spp in spps:
        by = {r["backend"]: r["later_s"] for r in rows if r["tier"] == "full" and r["spp"] == spp}
        if "llvm" in by and "scalar" in by and by["llvm"] > 0:
            ratios[str(spp)] = round(by["scalar"] / by["llvm"], 3)
    return {
        "benchmark": "render",
        "scene": scene,
        "width": width,
        "height": height,
        "rows": rows,
        "scalar_over_llvm_later_s": ratios,
        "unavailable": unavailable,
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "notes": "seconds per frame; first_s includes JIT compilation and scene loading, later_s reuses the kernel cache; "
                 "maps: one evaluation per scene (2x2 sub-pixel rays); scalar runs scalar_spectral_polarized (no scalar mono polarized variant)",
    }
