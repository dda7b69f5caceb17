"""``polspike dataset new --like SCENE.toml``: sample groups around a fitted (or any) pane setup.

The groups are drawn by the ordinary sampler (:mod:`polspike.pipeline.sampler`: content, motion,
light, sensor, camera pointing vary as usual); then each group's camera field of view, image size
and roll and its pane (model, index or glass, tilt, tilt axis, thickness, absorption) are replaced
by the scene's.  The pane's tilt is relative to the camera's own axes (``generator.scene``), so the
geometry the camera sees is the scene's whatever way the sampled camera points.

Jitter (``jitter = "fit"``): when a ``report.json`` of ``polspike calibrate-pane`` sits beside the
scene file, tilt, tilt axis, fov and (where identified) n are drawn from normals with the fit's
1-sigma uncertainties, truncated at 2 sigma; parameters the fit did not identify are kept fixed at
the scene's value.  ``jitter = "none"``: every group has exactly the scene's geometry and glass.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from polinfra.errors import ConfigError

__all__ = ["like_manifest", "like_manifest_text", "fit_sigmas"]

JITTERS = ("fit", "none")


def fit_sigmas(scene_path: Path) -> dict[str, float]:
    """1-sigma jitter per parameter from the calibrate-pane report beside ``scene_path`` ({} when there is none)."""
    rep = Path(scene_path).with_name("report.json")
    if not rep.is_file():
        return {}
    try:
        doc = json.loads(rep.read_text())
        u, ident = doc["uncertainty_1sigma"], doc["identifiability"]
    except (ValueError, KeyError, TypeError):
        raise ConfigError(f"{rep} is not a polspike calibrate-pane report (no uncertainty_1sigma / identifiability)") from None
    out = {"tilt_deg": float(u.get("tilt_deg") or 0.0), "tilt_axis_deg": float(u.get("azimuth_deg") or 0.0), "fov_deg": float(u.get("fov_deg") or 0.0)}
    out["n"] = float(u.get("n") or 0.0) if ident.get("n", {}).get("identified") else 0.0
    return {k: v for k, v in out.items() if math.isfinite(v) and v > 0}


def _tn(rng: np.random.Generator, sigma: float) -> float:
    """Normal(0, sigma) truncated at 2 sigma."""
    while True:
        v = float(rng.normal())
        if abs(v) <= 2.0:
            return v * sigma


def like_manifest(scene_path: str | Path, n_groups: int, seed: int, *, jitter: str = "fit", name: str = "like", duration_s: float = 1.0, tier: str = "analytic", tolerance: float | None = None,
                  test_fraction: float = 0.2, profile: str = "paper") -> dict:
    """Manifest data whose groups share the scene's pane and camera field of view (module docstring)."""
    from generator.scene import load_scene
    from polspike.pipeline.sampler import _pane_need, sample_manifest

    if jitter not in JITTERS:
        raise ConfigError(f"--jitter {jitter!r}: choose one of {', '.join(JITTERS)}")
    sc = load_scene(scene_path)
    if sc.objects is not None:
        raise ConfigError(f"{scene_path}: --like takes a layer scene (a fitted pane.toml); 3-D object scenes have no sampled layers")
    sig = fit_sigmas(Path(scene_path)) if jitter == "fit" else {}
    W, H = sc.camera.width, sc.camera.height
    data = sample_manifest(n_groups, seed, name=name, test_fraction=test_fraction, width=W, height=H, duration_s=duration_s, tier=tier, profile=profile, tolerance=tolerance)
    rng = np.random.default_rng([int(seed), 21])
    p = sc.pane
    if p.normal is not None:
        raise ConfigError(f"{scene_path}: --like needs the pane as tilt_deg / tilt_axis_deg (relative to the camera), not an explicit world normal")
    for g in data["groups"]:
        for _ in range(50):
            d = {k: _tn(rng, s) for k, s in sig.items()}
            cam = dict(g["camera"], width=W, height=H, fov_deg=round(min(150.0, max(1.0, sc.camera.fov_deg + d.get("fov_deg", 0.0))), 4), roll_deg=sc.camera.roll_deg)
            pane = dict(g["pane"], model=p.model, tilt_deg=round(min(89.0, max(0.0, p.tilt_deg + d.get("tilt_deg", 0.0))), 4),
                        tilt_axis_deg=round(p.tilt_axis_deg + d.get("tilt_axis_deg", 0.0), 4), thickness_mm=p.thickness_mm, absorption_per_mm=p.absorption_per_mm, size_m=[1000.0, 1000.0])
            if p.glass:
                pane.pop("n", None)
                pane["glass"] = p.glass
            else:
                pane["n"] = round(float(p.n) + d.get("n", 0.0), 5)
            need = _pane_need({"camera": cam, "pane": pane}, 89.5)
            if need is not None:
                break
        else:
            raise ConfigError(f"{scene_path}: its pane does not cover the view of a sampled camera (edge-on or behind); check the scene with polspike render")
        pane["size_m"] = [math.ceil(need[0] * 1.25 * 10) / 10, math.ceil(need[1] * 1.25 * 10) / 10]
        g["camera"], g["pane"] = cam, pane
        g["description"] = f"{g['description']}; like {sc.name} ({'jittered within the fit' if sig else 'fixed'} pane)"
    data["description"] = (f"{n_groups} groups sampled around {Path(scene_path).name} by `polspike dataset new --like {Path(scene_path).name} --groups {n_groups} --seed {seed}`"
                           f" (pane and fov {'jittered by ' + json.dumps({k: round(v, 4) for k, v in sig.items()}) + ' (1 sigma, truncated at 2)' if sig else 'fixed'}; content, motion, light varied)")
    return data


def like_manifest_text(scene_path: str | Path, n_groups: int, seed: int, **kw) -> str:
    """TOML text of :func:`like_manifest`, validated as a manifest before it is returned."""
    from polspike.pipeline.manifest import checked_manifest_text

    head = f"Sampled by polspike dataset new --like {Path(scene_path).name} --groups {n_groups} --seed {seed}.\nPane and camera fov from the scene; the rest: polspike/pipeline/sampler.py."
    return checked_manifest_text(like_manifest(scene_path, n_groups, seed, **kw), head, "sampled manifest")
