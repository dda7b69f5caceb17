"""Sample a dataset manifest: scene parameters drawn from documented ranges.

``polspike dataset new --groups N --seed S [--ranges paper|v1] --out FILE`` calls
:func:`sample_manifest`.  One ``np.random.default_rng(seed)`` draws every group in order, so the
same (N, seed, options) always writes the same manifest.  The last ``round(test_fraction * N)``
groups (at least one when N >= 2) are the test split.  Each group's ``description`` lists its
draws (R/T ratio, centre incidence, pane model, haze, sprites, highlights, pan, light, sensor).

Profile ``paper`` (default; ``paper.toml``): the paper's difficulty, calibrated so
that with the true zeta the solver-only table on its test split (``eval_paper.toml``) lands within
1.5 dB of supp. Table 3 (docs/results/solvers.md).  U = uniform, LU = log-uniform; all drawn per group:

==========================  =====================================================
pane.model                  single, thin_slab, thick_slab: 1/3 each
pane.n                      U[1.45, 1.75]
pane.tilt_deg               incidence at the image centre: 40 % Brewster's angle atan(n)
                            + U[-8, 8] deg, 60 % U[20, 78] deg
camera.fov_deg              U[25, 55] deg, narrowed above 60 deg of incidence so glancing views
                            stay on the pane: upper bound 55 - 2.2 (tilt - 60), at least 12
camera pose                 yaw U[-15, 15], pitch U[-10, 10], roll U[-10, 10] deg
pane.tilt_axis_deg          U[0, 180): every plane-of-incidence orientation
pane.distance_m, thickness  U[0.5, 1.5] m, U[2, 10] mm
max incidence in the view   < 88 deg (the camera is redrawn up to 20 times for a centre
                            incidence, then the incidence is redrawn)
T layer                     distance U[2, 8] m, brightness U[0.5, 1.0]
R / T brightness            ratio of mean radiances LU[0.2, 5] (content mean 0.25 at brightness
                            1): R brightness up to 1, the rest as a uniform offset, R mean <= 0.85
haze (35 %)                 R is bright and low-texture: offset U[0.5, 0.9] of its mean radiance
highlights (30 %)           1-3 uniform discs (procedural:disk) on R, size U[0.03, 0.08] of the
                            view height, velocity U[-0.3, 0.3] view/s per axis
layer motion (T, R apart)   static with probability 0.2, else speed U[0, 1] view width/s in a
                            uniform direction, rotate U[-30, 30] deg/s, zoom U[-0.3, 0.3] 1/s
camera pan (30 %)           a translation U[-0.25, 0.25] view/s per axis added to both layers
                            (a constant pan: the scene format has no oscillating shake)
sprite (30 %)               one textured sprite on T or R (1/2 each), size U[0.1, 0.3], start
                            U[0.2, 0.8]^2, velocity U[-1.5, 1.5] view/s per axis
light                       spike_sim.exposure such that the mean T content fires ``rate`` spikes
                            per pixel per step: 90 % dim, rate LU[0.01, 0.03]; 10 % bright,
                            LU[0.03, 0.3] (peaks of the content, 4x the mean, near saturation)
sensor                      spike_sim preset default or noisy (10x fewer photoelectrons), 1/2 each
polarizer.phase_deg         U[0, 180) deg (rate fixed: ``rate_hz``, 30 rev/s)
==========================  =====================================================

Profile ``paper_motion``: the ``paper`` profile whose 30 % camera pan is replaced by a global camera
motion (static, pan up to 3 view widths/s, hand-held shake, rotation about the optical axis at 30-90
deg/s, zoom) added to both layers on top of their independent motion, and whose sensor is one of the
spike_sim presets ideal / default / noisy / plain_if (1/4 each): :mod:`polspike.pipeline.sampler_motion`.

Profile ``v1`` (``paper_v1.toml``, the first ``paper.toml``; kept byte for byte):

==========================  =====================================================
camera.fov_deg              U[35, 55] deg (horizontal)
camera pose                 yaw U[-15, 15] deg, pitch U[-10, 10] deg of the optical axis
                            (``look_at``), roll_deg U[-10, 10]
pane.model                  single 20 %, thin_slab 50 %, thick_slab 30 %
pane.n                      U[1.45, 1.75]
pane.distance_m             U[0.5, 1.5] m
pane.tilt_deg               U[0, 62] deg (incidence at the image centre; Brewster for
                            n = 1.5 is 56.3 deg)
pane.tilt_axis_deg          U[0, 180) deg: the plane of incidence turns with it
pane.thickness_mm           U[2, 10] mm (slabs)
pane.size_m                 just covers the view (x 1.25, rounded up to 0.1 m)
max incidence in the view   < 82 deg: draws past it are redrawn (rejection)
T layer                     distance U[2, 8] m, brightness U[0.5, 1.0]
R layer                     distance U[1, 4] m, brightness U[0.3, 1.0]
layer motion (each layer)   translate U[-0.3, 0.3] view/s per axis, rotate U[-15, 15] deg/s,
                            zoom U[-0.2, 0.2] 1/s
sprite                      one on the R layer with probability 0.3: size U[0.1, 0.3] of the
                            view height, start U[0.2, 0.8]^2, velocity U[-1, 1] view/s per axis
polarizer.phase_deg         U[0, 180) deg (rate fixed: ``rate_hz``, 30 rev/s)
seed                        integer U[0, 2^31)
==========================  =====================================================

:func:`reduced_manifest` makes the reduced builds (``eval_paper.toml``: the test split at
200 x 125 and 0.1 s; ``fit_paper.toml``: the train split at 200 x 125 and 0.05 s), and
:func:`stress_manifest` the stress grid (``stress.toml``).

Layer content comes from split-specific pools, so no content is shared between
train and test groups (:func:`polspike.pipeline.manifest.check_split`):

* train: ``skimage:`` camera, brick, grass, gravel, coins, moon, page, text,
  hubble_deep_field, immunohistochemistry, retina, colorwheel, chelsea;
  ``procedural:`` checker, stripes, gradient; ``procedural:noise`` with seeds in [1, 50000);
* test: ``skimage:`` astronaut, coffee, rocket, clock, horse; ``procedural:rings``;
  ``procedural:noise`` with seeds in [50000, 100000).

T and R of one group always differ.  Everything works offline.
"""

from __future__ import annotations

import math

import numpy as np

from polinfra.errors import ConfigError, SceneError
from polspike.pipeline.manifest import MANIFEST_FORMAT, checked_manifest_text
from polspike.pipeline.sampler_motion import STRESS_CAMERA, add_camera_motion, camera_motion, camera_tag, sensor_preset

__all__ = ["sample_manifest", "sample_manifest_text", "RANGES", "RANGES_V1", "PROFILES", "CONTENT_POOLS", "exposure_for_rate"]

RANGES_V1: dict[str, tuple[float, float]] = {
    "fov_deg": (35.0, 55.0),
    "yaw_deg": (-15.0, 15.0),
    "pitch_deg": (-10.0, 10.0),
    "roll_deg": (-10.0, 10.0),
    "n": (1.45, 1.75),
    "pane_distance_m": (0.5, 1.5),
    "tilt_deg": (0.0, 62.0),
    "tilt_axis_deg": (0.0, 180.0),
    "thickness_mm": (2.0, 10.0),
    "t_distance_m": (2.0, 8.0),
    "r_distance_m": (1.0, 4.0),
    "t_brightness": (0.5, 1.0),
    "r_brightness": (0.3, 1.0),
    "translate_per_s": (-0.3, 0.3),
    "rotate_deg_per_s": (-15.0, 15.0),
    "zoom_per_s": (-0.2, 0.2),
    "sprite_size": (0.1, 0.3),
    "sprite_start": (0.2, 0.8),
    "sprite_velocity_per_s": (-1.0, 1.0),
    "phase_deg": (0.0, 180.0),
}
"""Uniform ranges of the ``v1`` profile (``paper_v1.toml``; module docstring)."""

RANGES: dict[str, tuple[float, float]] = {
    "fov_deg": (12.0, 55.0),
    "yaw_deg": (-15.0, 15.0),
    "pitch_deg": (-10.0, 10.0),
    "roll_deg": (-10.0, 10.0),
    "n": (1.45, 1.75),
    "pane_distance_m": (0.5, 1.5),
    "tilt_deg": (20.0, 78.0),
    "brewster_window_deg": (-8.0, 8.0),
    "tilt_axis_deg": (0.0, 180.0),
    "thickness_mm": (2.0, 10.0),
    "t_distance_m": (2.0, 8.0),
    "r_distance_m": (1.0, 4.0),
    "log_rt_ratio": (math.log(0.2), math.log(5.0)),
    "t_brightness": (0.5, 1.0),
    "r_brightness": (0.0, 1.0),
    "haze_level": (0.5, 0.9),
    "speed_view_per_s": (0.0, 1.0),
    "pan_per_s": (-0.25, 0.25),
    "translate_per_s": (-1.25, 1.25),
    "rotate_deg_per_s": (-30.0, 30.0),
    "zoom_per_s": (-0.3, 0.3),
    "sprite_size": (0.1, 0.3),
    "sprite_start": (0.2, 0.8),
    "sprite_velocity_per_s": (-1.5, 1.5),
    "highlight_size": (0.03, 0.08),
    "highlight_velocity_per_s": (-0.3, 0.3),
    "log_rate_dim": (math.log(0.01), math.log(0.03)),
    "log_rate_bright": (math.log(0.03), math.log(0.3)),
    "phase_deg": (0.0, 180.0),
}
"""Ranges of the ``paper`` profile (``paper.toml``; module docstring).  ``t_brightness``,
``r_brightness`` and ``translate_per_s`` are the bounds that follow from the other draws."""

PANE_MODELS = (("single", 0.2), ("thin_slab", 0.5), ("thick_slab", 0.3))
MAX_INCIDENCE_DEG = 82.0
SPRITE_PROB = 0.3
PROFILES = ("paper", "v1", "paper_motion")
"""Range profiles: ``paper`` (the paper's difficulty, default), ``v1`` (the first, easier ranges) and
``paper_motion`` (``paper`` with global camera motion and sensor-model randomisation)."""
PAPER_PANE_MODELS = (("single", 1.0 / 3.0), ("thin_slab", 1.0 / 3.0), ("thick_slab", 1.0 / 3.0))
PAPER_MAX_INCIDENCE_DEG = 88.0
PAPER_FOV_DEG = (25.0, 55.0)
GLANCING_FROM_DEG = 60.0
GLANCING_FOV_SLOPE = 2.2
GLANCING_MIN_FOV_DEG = 12.0
BREWSTER_PROB = 0.4
HAZE_PROB = 0.35
DIM_PROB = 0.9
NOISY_PROB = 0.5
HIGHLIGHT_PROB = 0.3
STATIC_PROB = 0.2
PAN_PROB = 0.3
NOMINAL_CONTENT_MEAN = 0.25
R_MEAN_MAX = 0.85
"""Mean linear radiance of a layer's content at brightness 1 (gamma-decoded images and textures), for the light level."""


def exposure_for_rate(rate: float, t_brightness: float) -> float:
    """spike_sim exposure at which the mean T content (brightness ``t_brightness``, behind the polarizer's half) fires
    ``rate`` spikes per pixel per step: the light level of a sampled group and of a training window's redraw.
    """
    return rate / (0.5 * NOMINAL_CONTENT_MEAN * max(t_brightness, 1e-3))

CONTENT_POOLS: dict[str, dict] = {
    "train": {
        "images": [
            "skimage:camera", "skimage:brick", "skimage:grass", "skimage:gravel", "skimage:coins", "skimage:moon",
            "skimage:page", "skimage:text", "skimage:hubble_deep_field", "skimage:immunohistochemistry",
            "skimage:retina", "skimage:colorwheel", "skimage:chelsea",
            "procedural:checker", "procedural:stripes", "procedural:gradient",
        ],
        "noise_seeds": (1, 50000),
    },
    "test": {
        "images": ["skimage:astronaut", "skimage:coffee", "skimage:rocket", "skimage:clock", "skimage:horse", "procedural:rings"],
        "noise_seeds": (50000, 100000),
    },
}
"""Split-specific layer content (no overlap between the splits)."""


def _u1(rng: np.random.Generator, key: str) -> float:
    lo, hi = RANGES_V1[key]
    return float(rng.uniform(lo, hi))


def _u(rng: np.random.Generator, key: str) -> float:
    lo, hi = RANGES[key]
    return float(rng.uniform(lo, hi))


def _r(x: float, nd: int = 4) -> float:
    return float(round(x, nd))


def _pane_size(need: tuple[float, float]) -> list[float]:
    """Pane size (m) that covers the camera's view with a 25 % margin, rounded up to 0.1 m."""
    return [math.ceil(need[0] * 1.25 * 10) / 10, math.ceil(need[1] * 1.25 * 10) / 10]


def _layer_contents(rng: np.random.Generator, split: str) -> tuple[str, int, str, int]:
    """(T source, T seed, R source, R seed) of one group: two contents of the split, never the same one."""
    t_src, t_seed = _content(rng, split)
    r_src, r_seed = _content(rng, split, avoid=t_src)
    if r_src == t_src and r_seed == t_seed:
        r_seed = t_seed + 1 if r_seed + 1 < CONTENT_POOLS[split]["noise_seeds"][1] else t_seed - 1
    return t_src, t_seed, r_src, r_seed


def _content(rng: np.random.Generator, split: str, avoid: str | None = None) -> tuple[str, int]:
    """(source, seed): an image of the split's pool (2/3) or seeded procedural noise (1/3)."""
    pool = CONTENT_POOLS[split]
    while True:
        if rng.random() < 2.0 / 3.0:
            src, seed = pool["images"][int(rng.integers(len(pool["images"])))], 0
        else:
            src, seed = "procedural:noise", int(rng.integers(*pool["noise_seeds"]))
        if src != avoid or src == "procedural:noise":
            return src, seed


def _motion(rng: np.random.Generator) -> dict:  # v1 profile
    return {
        "translate_per_s": [_r(_u1(rng, "translate_per_s")), _r(_u1(rng, "translate_per_s"))],
        "rotate_deg_per_s": _r(_u1(rng, "rotate_deg_per_s"), 3),
        "zoom_per_s": _r(_u1(rng, "zoom_per_s")),
    }


def _pane_need(scene_d: dict, max_incidence_deg: float) -> tuple[float, float] | None:
    """Pane size (m) that just covers the view, or None when the geometry is rejected."""
    from generator.scene import check_scene_geometry, scene_from_dict
    from polphysics.geometry import incidence_geometry
    from polspike.pipeline.manifest import _coarse

    sc = _coarse(scene_from_dict(scene_d, where="sampled scene"))
    try:
        check_scene_geometry(sc)
    except SceneError:
        return None
    geo = incidence_geometry(sc.camera_model(), sc.pane_plane())
    if float(np.degrees(np.nanmax(geo["theta"]))) >= max_incidence_deg:
        return None
    e_w, e_h = sc.pane_axes()
    rel = geo["hit"] - sc.pane_plane().point
    return float(np.max(np.abs(rel @ e_w))) * 2, float(np.max(np.abs(rel @ e_h))) * 2


def _group_v1(rng: np.random.Generator, name: str, split: str, width: int, height: int) -> dict:
    while True:  # rejection sampling of the geometry
        fov = _r(_u1(rng, "fov_deg"), 3)
        yaw, pitch = math.radians(_u1(rng, "yaw_deg")), math.radians(_u1(rng, "pitch_deg"))
        look = [_r(math.sin(yaw) * math.cos(pitch), 5), _r(math.sin(pitch), 5), _r(-math.cos(yaw) * math.cos(pitch), 5)]
        roll = _r(_u1(rng, "roll_deg"), 3)
        ps = np.array([p for _, p in PANE_MODELS])
        model = PANE_MODELS[int(rng.choice(len(PANE_MODELS), p=ps / ps.sum()))][0]
        pane = {
            "model": model,
            "n": _r(_u1(rng, "n")),
            "distance_m": _r(_u1(rng, "pane_distance_m"), 3),
            "tilt_deg": _r(_u1(rng, "tilt_deg"), 3),
            "tilt_axis_deg": _r(_u1(rng, "tilt_axis_deg"), 3),
            "thickness_mm": _r(_u1(rng, "thickness_mm"), 3),
            "size_m": [1000.0, 1000.0],
        }
        camera = {"width": width, "height": height, "fov_deg": fov, "position": [0.0, 0.0, 0.0], "look_at": look, "up": [0.0, 1.0, 0.0], "roll_deg": roll}
        need = _pane_need({"camera": camera, "pane": pane}, MAX_INCIDENCE_DEG)
        if need is not None:
            break
    pane["size_m"] = _pane_size(need)
    t_src, t_seed, r_src, r_seed = _layer_contents(rng, split)
    trans = {"source": t_src, "seed": t_seed, "distance_m": _r(_u1(rng, "t_distance_m"), 3), "brightness": _r(_u1(rng, "t_brightness"), 3), "motion": _motion(rng)}
    refl = {"source": r_src, "seed": r_seed, "distance_m": _r(_u1(rng, "r_distance_m"), 3), "brightness": _r(_u1(rng, "r_brightness"), 3), "motion": _motion(rng)}
    if rng.random() < SPRITE_PROB:
        sp_src, _ = _content(rng, split)
        if sp_src == "procedural:noise":
            sp_src = CONTENT_POOLS[split]["images"][-1]
        refl["sprites"] = [{
            "source": sp_src,
            "size": _r(_u1(rng, "sprite_size"), 3),
            "start": [_r(_u1(rng, "sprite_start"), 3), _r(_u1(rng, "sprite_start"), 3)],
            "velocity_per_s": [_r(_u1(rng, "sprite_velocity_per_s"), 3), _r(_u1(rng, "sprite_velocity_per_s"), 3)],
        }]
    return {
        "name": name,
        "split": split,
        "seed": int(rng.integers(0, 2**31 - 1)),
        "camera": camera,
        "pane": pane,
        "layers": {"transmission": trans, "reflection": refl},
        "polarizer": {"phase_deg": _r(_u1(rng, "phase_deg"), 3)},
    }


def _lu(rng: np.random.Generator, key: str) -> float:
    """exp(U[lo, hi]) for a log range."""
    return float(math.exp(_u(rng, key)))


def _motion_paper(rng: np.random.Generator, pan: tuple[float, float]) -> dict:
    if rng.random() < STATIC_PROB:
        v, rot, zoom = (0.0, 0.0), 0.0, 0.0
    else:
        sp, ang = _u(rng, "speed_view_per_s"), float(rng.uniform(0.0, 2.0 * math.pi))
        v = (sp * math.cos(ang), sp * math.sin(ang))
        rot, zoom = _u(rng, "rotate_deg_per_s"), _u(rng, "zoom_per_s")
    return {"translate_per_s": [_r(v[0] + pan[0]), _r(v[1] + pan[1])], "rotate_deg_per_s": _r(rot, 3), "zoom_per_s": _r(zoom)}


def _group_paper(rng: np.random.Generator, name: str, split: str, width: int, height: int, motion: bool = False) -> dict:
    ps = np.array([p for _, p in PAPER_PANE_MODELS])
    need = None
    while need is None:  # rejection sampling of the geometry: the centre incidence is kept for 20 camera draws
        model = PAPER_PANE_MODELS[int(rng.choice(len(PAPER_PANE_MODELS), p=ps / ps.sum()))][0]
        n = _r(_u(rng, "n"))
        if rng.random() < BREWSTER_PROB:
            tilt = math.degrees(math.atan(n)) + _u(rng, "brewster_window_deg")
        else:
            tilt = _u(rng, "tilt_deg")
        fov_lo, fov_hi = PAPER_FOV_DEG
        fov_hi = max(GLANCING_MIN_FOV_DEG, fov_hi - GLANCING_FOV_SLOPE * max(0.0, tilt - GLANCING_FROM_DEG))
        fov_lo = min(fov_lo, fov_hi - 3.0)
        for _ in range(20):
            fov = _r(float(rng.uniform(fov_lo, fov_hi)), 3)
            yaw, pitch = math.radians(_u(rng, "yaw_deg")), math.radians(_u(rng, "pitch_deg"))
            look = [_r(math.sin(yaw) * math.cos(pitch), 5), _r(math.sin(pitch), 5), _r(-math.cos(yaw) * math.cos(pitch), 5)]
            roll = _r(_u(rng, "roll_deg"), 3)
            pane = {
                "model": model,
                "n": n,
                "distance_m": _r(_u(rng, "pane_distance_m"), 3),
                "tilt_deg": _r(tilt, 3),
                "tilt_axis_deg": _r(_u(rng, "tilt_axis_deg"), 3),
                "thickness_mm": _r(_u(rng, "thickness_mm"), 3),
                "size_m": [1000.0, 1000.0],
            }
            camera = {"width": width, "height": height, "fov_deg": fov, "position": [0.0, 0.0, 0.0], "look_at": look, "up": [0.0, 1.0, 0.0], "roll_deg": roll}
            need = _pane_need({"camera": camera, "pane": pane}, PAPER_MAX_INCIDENCE_DEG)
            if need is not None:
                break
    pane["size_m"] = _pane_size(need)
    t_src, t_seed, r_src, r_seed = _layer_contents(rng, split)
    # brightness: T at t_brightness; R's mean radiance = ratio x T's (ratio log-uniform), from a
    # brighter texture plus, past brightness 1, a uniform offset (capped at R_MEAN_MAX); haze: mostly offset
    ratio = _lu(rng, "log_rt_ratio")
    t_b = _u(rng, "t_brightness")
    r_mean = min(ratio * t_b * NOMINAL_CONTENT_MEAN, R_MEAN_MAX)
    haze = rng.random() < HAZE_PROB
    if haze:  # bright, low-texture R of the same mean radiance: offset + faint content
        level = _u(rng, "haze_level")
        r_b = min(1.0, r_mean * (1.0 - level) / NOMINAL_CONTENT_MEAN)
        r_offset = r_mean - r_b * NOMINAL_CONTENT_MEAN
    else:
        r_b = min(1.0, r_mean / NOMINAL_CONTENT_MEAN)
        r_offset = r_mean - r_b * NOMINAL_CONTENT_MEAN
    cam = camera_motion(rng, width / height) if motion else None
    pan = (0.0, 0.0) if motion else (_u(rng, "pan_per_s"), _u(rng, "pan_per_s")) if rng.random() < PAN_PROB else (0.0, 0.0)
    trans = {"source": t_src, "seed": t_seed, "distance_m": _r(_u(rng, "t_distance_m"), 3), "brightness": _r(t_b, 3), "motion": _motion_paper(rng, pan)}
    refl = {"source": r_src, "seed": r_seed, "distance_m": _r(_u(rng, "r_distance_m"), 3), "brightness": _r(r_b, 3), "motion": _motion_paper(rng, pan)}
    if cam is not None:
        trans["motion"], refl["motion"] = add_camera_motion(trans["motion"], cam), add_camera_motion(refl["motion"], cam)
    if r_offset > 0.0:
        refl["offset"] = _r(r_offset, 4)
    tags = [f"R/T {ratio:.2f}", f"centre incidence {pane['tilt_deg']:.1f} deg", model]
    if haze:
        tags.append("haze")
    if rng.random() < SPRITE_PROB:
        sp_src, _ = _content(rng, split)
        if sp_src == "procedural:noise":
            sp_src = CONTENT_POOLS[split]["images"][-1]
        layer = trans if rng.random() < 0.5 else refl
        layer["sprites"] = [{
            "source": sp_src,
            "size": _r(_u(rng, "sprite_size"), 3),
            "start": [_r(_u(rng, "sprite_start"), 3), _r(_u(rng, "sprite_start"), 3)],
            "velocity_per_s": [_r(_u(rng, "sprite_velocity_per_s"), 3), _r(_u(rng, "sprite_velocity_per_s"), 3)],
        }]
        tags.append("sprite on " + ("T" if layer is trans else "R"))
    if rng.random() < HIGHLIGHT_PROB:  # small bright discs on R (content-free: no split leak)
        k = int(rng.integers(1, 4))
        refl.setdefault("sprites", [])
        for _ in range(k):
            refl["sprites"].append({
                "source": "procedural:disk",
                "size": _r(_u(rng, "highlight_size"), 3),
                "start": [_r(_u(rng, "sprite_start"), 3), _r(_u(rng, "sprite_start"), 3)],
                "velocity_per_s": [_r(_u(rng, "highlight_velocity_per_s"), 3), _r(_u(rng, "highlight_velocity_per_s"), 3)],
            })
        # a disc is content value 1: about 4x the mean R content (NOMINAL_CONTENT_MEAN), saturating at high light
        tags.append(f"{k} highlight(s)")
    if pan != (0.0, 0.0):
        tags.append("camera pan")
    if cam is not None and camera_tag(cam):
        tags.append(camera_tag(cam))
    # light: exposure such that the mean T content fires `rate` spikes per pixel per step
    rate = _lu(rng, "log_rate_dim" if rng.random() < DIM_PROB else "log_rate_bright")
    exposure = exposure_for_rate(rate, t_b)
    tags.append(f"{rate:.3f} spikes/px/step")
    sensor = sensor_preset(rng) if motion else "noisy" if rng.random() < NOISY_PROB else "default"
    tags.append(f"{sensor} sensor")
    return {
        "name": name,
        "split": split,
        "description": "; ".join(tags),
        "seed": int(rng.integers(0, 2**31 - 1)),
        "camera": camera,
        "pane": pane,
        "layers": {"transmission": trans, "reflection": refl},
        "polarizer": {"phase_deg": _r(_u(rng, "phase_deg"), 3)},
        "spike_sim": {"preset": sensor, "exposure": _r(exposure, 4)},
    }


def sample_manifest(
    n_groups: int,
    seed: int,
    name: str = "sampled",
    test_fraction: float = 0.2,
    width: int = 400,
    height: int = 250,
    duration_s: float = 1.0,
    tier: str = "analytic",
    keyframe_fps: float = 100.0,
    rate_hz: float = 30.0,
    spike_sim_preset: str = "default",
    profile: str = "paper",
    tolerance: float | None = None,
) -> dict:
    """Plain manifest data with ``n_groups`` groups drawn from :data:`RANGES`.

    Args:
        n_groups: number of groups (>= 1).
        seed: sampler seed (the whole manifest is a function of the arguments).
        name: dataset name.
        test_fraction: share of test groups (the last ones), in [0, 1].
        width, height: image size in pixels.
        duration_s: stream length per group (s).
        tier: generator tier of every group (``auto``: the planner picks per group, given ``tolerance``).
        tolerance: ``tier = auto``: largest acceptable p99 radiance error (:mod:`generator.planner`).
        keyframe_fps: radiance keyframes per second.
        rate_hz: polarizer revolutions per second.
        spike_sim_preset: simulator preset name.
        profile: range profile, ``paper`` (default), ``v1`` or ``paper_motion`` (:data:`PROFILES`).

    Returns:
        dict ready for :func:`polspike.pipeline.manifest.dump_manifest`; it validates
        with :func:`polspike.pipeline.manifest.parse_manifest`.
    """
    if profile not in PROFILES:
        raise ConfigError(f"--ranges {profile!r} is unknown; choose one of {list(PROFILES)}")
    if (tier == "auto") != (tolerance is not None):
        raise ConfigError("--tier auto and --tolerance EPS go together" + (f" (--tolerance given with --tier {tier})" if tolerance is not None else ""))
    if tolerance is not None and not tolerance > 0:
        raise ConfigError(f"--tolerance {tolerance!r} must be a positive p99 radiance error (e.g. 1e-2)")
    if n_groups < 1:
        raise ConfigError(f"--groups = {n_groups} must be >= 1")
    if not 0.0 <= test_fraction <= 1.0:
        raise ConfigError(f"test_fraction = {test_fraction} must lie in [0, 1]")
    n_test = int(round(test_fraction * n_groups))
    if n_groups >= 2 and test_fraction > 0:
        n_test = min(max(n_test, 1), n_groups - 1)
    n_train = n_groups - n_test
    rng = np.random.default_rng(seed)
    groups = []
    for i in range(n_groups):
        split = "train" if i < n_train else "test"
        idx = i if split == "train" else i - n_train
        if profile == "v1":
            groups.append(_group_v1(rng, f"{split}_{idx:03d}", split, width, height))
        else:
            groups.append(_group_paper(rng, f"{split}_{idx:03d}", split, width, height, motion=profile == "paper_motion"))
    return {
        "format": MANIFEST_FORMAT,
        "name": name,
        "description": f"{n_groups} groups sampled by `polspike dataset new --groups {n_groups} --seed {seed}{'' if profile == 'paper' else ' --ranges ' + profile}` ({n_train} train / {n_test} test)",
        "defaults": {
            "tier": tier,
            **({"tolerance": float(tolerance)} if tolerance is not None else {}),
            "duration_s": float(duration_s),
            "keyframe_fps": float(keyframe_fps),
            "polarizer": {"rate_hz": float(rate_hz)},
            "spike_sim": {"preset": spike_sim_preset},
        },
        "groups": groups,
    }


def sample_manifest_text(n_groups: int, seed: int, **kw) -> str:
    """TOML text of :func:`sample_manifest` (validated before it is returned)."""
    data = sample_manifest(n_groups, seed, **kw)
    prof = kw.get("profile", "paper")
    flag = "" if prof == "paper" else f" --ranges {prof}"
    return checked_manifest_text(data, f"Sampled by polspike dataset new --groups {n_groups} --seed {seed}{flag}.\nRanges: polspike/pipeline/sampler.py (docs/datasets.md), profile {prof}.", "sampled manifest")


def reduced_manifest(data: dict, name: str, width: int, height: int, duration_s: float, split: str = "test", description: str = "") -> dict:
    """The groups of ``split`` of plain manifest data at another image size and duration.

    Everything else (panes, layers, seeds, light) is kept, so a reduced build is the same scenes
    seen by a coarser sensor (same field of view) for a shorter time: e.g. ``eval_paper.toml``
    is ``paper.toml``'s test split at 200 x 125 and 0.1 s.
    """
    import copy

    groups = []
    for g in data["groups"]:
        if g["split"] != split:
            continue
        g = copy.deepcopy(g)
        g["camera"]["width"], g["camera"]["height"] = int(width), int(height)
        groups.append(g)
    if not groups:
        raise ConfigError(f"no group in split {split!r}")
    out = {k: copy.deepcopy(v) for k, v in data.items() if k != "groups"}
    out["name"] = name
    out["description"] = description or f"{data['name']}'s {len(groups)} {split} groups at {width} x {height}, {duration_s} s each"
    out["defaults"]["duration_s"] = float(duration_s)
    out["groups"] = groups
    return out


STRESS_LEVELS: dict[str, dict[str, float | str]] = {
    "refl": {"weak": 0.3, "strong": 1.5, "dominant": 5.0},  # R / T mean-radiance ratio
    "motion": {"static": 0.0, "fast": 0.8},  # view widths per second (T; R moves at 0.6 of it the other way)
    "light": {"dim": 0.025, "bright": 0.3},  # spikes / pixel / step of the mean T content
    "inc": {"normal": 8.0, "brewster": -1.0, "glancing": 74.0},  # centre incidence (deg); -1 = Brewster's angle
    "pane": {"single": "single", "slab": "thin_slab"},
}
"""Levels of the stress grid (:func:`stress_manifest`); factor names as in
:data:`reconstruct.evaluate.harness.REGIME_FACTORS`."""


def stress_design() -> list[dict[str, str]]:
    """The fractional stress design: all 9 (reflection x incidence) pairs twice (motion static, then
    fast), with light and pane alternating so each level of each factor appears 9 times out of 18.
    """
    refl, inc = list(STRESS_LEVELS["refl"]), list(STRESS_LEVELS["inc"])
    out = []
    for r, motion in enumerate(STRESS_LEVELS["motion"]):
        for i, rl in enumerate(refl):
            for j, il in enumerate(inc):
                light = list(STRESS_LEVELS["light"])[(i + j + r) % 2]
                pane = list(STRESS_LEVELS["pane"])[(i + 2 * j + r + 1) % 2]
                out.append({"refl": rl, "motion": motion, "light": light, "inc": il, "pane": pane})
    return out


def _stress_group(rng: np.random.Generator, d: dict[str, str], width: int, height: int, cam: dict | None = None) -> dict:
    """One stress group at design point ``d``; ``cam`` (an entry of :data:`STRESS_CAMERA`): a camera-motion
    regime instead of the grid's layer motion, named ``..._cam-TAG``.
    """
    n = 1.52
    name = "_".join(f"{k}-{v}" for k, v in d.items()) + (f"_cam-{cam['tag']}" if cam else "")
    tilt = math.degrees(math.atan(n)) if d["inc"] == "brewster" else float(STRESS_LEVELS["inc"][d["inc"]])
    fov = 18.0 if d["inc"] == "glancing" else 45.0
    camera = {"width": width, "height": height, "fov_deg": fov, "position": [0.0, 0.0, 0.0], "look_at": [0.0, 0.0, -1.0], "up": [0.0, 1.0, 0.0], "roll_deg": _r(float(rng.uniform(-5, 5)), 3)}
    for _ in range(50):
        pane = {"model": STRESS_LEVELS["pane"][d["pane"]], "n": n, "distance_m": 1.0, "tilt_deg": _r(tilt, 3), "tilt_axis_deg": _r(float(rng.uniform(0, 180)), 3), "thickness_mm": 5.0, "size_m": [1000.0, 1000.0]}
        need = _pane_need({"camera": camera, "pane": pane}, PAPER_MAX_INCIDENCE_DEG)
        if need is not None:
            break
    else:  # pragma: no cover - the levels are chosen to fit
        raise SceneError(f"stress group {name}: no pane geometry fits")
    pane["size_m"] = _pane_size(need)
    if cam and cam.get("natural"):  # photographs only, no procedural content
        imgs = [s for s in CONTENT_POOLS["test"]["images"] if s.startswith("skimage:")]
        i, j = rng.choice(len(imgs), 2, replace=False)
        (t_src, t_seed), (r_src, r_seed) = (imgs[int(i)], 0), (imgs[int(j)], 0)
    else:
        t_src, t_seed = _content(rng, "test")
        r_src, r_seed = _content(rng, "test", avoid=t_src)
        if r_src == t_src and r_seed == t_seed:
            r_seed = t_seed + 1
    t_b = float(cam.get("t_brightness", 0.8)) if cam else 0.8
    ratio = float(cam.get("ratio", STRESS_LEVELS["refl"][d["refl"]])) if cam else float(STRESS_LEVELS["refl"][d["refl"]])
    r_mean = min(ratio * t_b * NOMINAL_CONTENT_MEAN, R_MEAN_MAX)
    r_b = min(1.0, r_mean / NOMINAL_CONTENT_MEAN)
    if cam:  # global camera motion only: the same image motion on both layers
        v = float(cam["speed"])
        cm = camera_motion(rng, width / height, kind=cam["kind"], speed=v)
        mt = mr = add_camera_motion({}, cm)
        motion_desc = {"pan": f"camera pan {v} view/s", "shake": f"camera shake {v} view/s rms", "static": "static camera"}[cam["kind"]]
    else:
        v = float(STRESS_LEVELS["motion"][d["motion"]])
        ang = float(rng.uniform(0, 2 * math.pi))
        mt = {"translate_per_s": [_r(v * math.cos(ang)), _r(v * math.sin(ang))], "rotate_deg_per_s": _r(20.0 * v, 3), "zoom_per_s": 0.0}
        mr = {"translate_per_s": [_r(-0.6 * v * math.cos(ang)), _r(-0.6 * v * math.sin(ang))], "rotate_deg_per_s": _r(-10.0 * v, 3), "zoom_per_s": 0.0}
        motion_desc = f"T {v} view/s"
    refl = {"source": r_src, "seed": r_seed, "distance_m": 2.0, "brightness": _r(r_b, 3), "motion": mr}
    if r_mean - r_b * NOMINAL_CONTENT_MEAN > 0:
        refl["offset"] = _r(r_mean - r_b * NOMINAL_CONTENT_MEAN, 4)
    exposure = exposure_for_rate(float(STRESS_LEVELS["light"][d["light"]]), t_b)
    return {
        "name": name,
        "split": "test",
        "description": f"R/T {_r(ratio, 3) if cam else STRESS_LEVELS['refl'][d['refl']]}; centre incidence {tilt:.1f} deg; {pane['model']}; {STRESS_LEVELS['light'][d['light']]} spikes/px/step; {motion_desc}",
        "seed": int(rng.integers(0, 2**31 - 1)),
        "camera": camera,
        "pane": pane,
        "layers": {"transmission": {"source": t_src, "seed": t_seed, "distance_m": 5.0, "brightness": t_b, "motion": mt}, "reflection": refl},
        "polarizer": {"phase_deg": _r(float(rng.uniform(0, 180)), 3)},
        "spike_sim": {"preset": "default", "exposure": _r(exposure, 4)},
    }


def stress_manifest(seed: int = 4242, width: int = 200, height: int = 125, duration_s: float = 0.05) -> dict:
    """Plain data of ``datasets/manifests/stress.toml``: one test group per design point of
    :func:`stress_design`, named by its regime (``refl-..._motion-..._light-..._inc-..._pane-...``).

    Layer content comes from the test pool only (never seen in training); the remaining
    parameters (tilt axis, camera pose, content, polarizer phase) are drawn from ``seed``.
    """
    rng = np.random.default_rng(seed)
    groups = [_stress_group(rng, d, width, height) for d in stress_design()]
    rng = np.random.default_rng(seed + 1)  # the camera-motion regimes: the grid's draws stay as they were
    for c in STRESS_CAMERA:
        d = {"refl": c["refl"], "motion": "fast" if c["speed"] > 0.5 else "static", "light": c["light"], "inc": c["inc"], "pane": c["pane"]}
        groups.append(_stress_group(rng, d, width, height, c))
    return {
        "format": MANIFEST_FORMAT,
        "name": "stress",
        "description": f"stress grid: {len(groups)} test groups named by regime (sampler.stress_manifest, seed {seed})",
        "defaults": {"tier": "analytic", "duration_s": float(duration_s), "keyframe_fps": 100.0, "polarizer": {"rate_hz": 30.0}, "spike_sim": {"preset": "default"}},
        "groups": groups,
    }


def stress_manifest_text(**kw) -> str:
    """TOML text of :func:`stress_manifest` with its header (validated)."""
    head = (
        "Stress test (test-only; layer content from the test pool, never in training): a fractional grid of\n"
        "regimes, reflection weak / strong / dominant (R/T 0.3 / 1.5 / 5), motion static / fast (T 0.8 view/s,\n"
        "R 0.48 view/s the other way, rotation), light dim / bright (0.025 / 0.3 spikes/pixel/step),\n"
        "centre incidence near normal / Brewster / glancing (8 / 56.7 / 74 deg), single interface / thin slab.\n"
        "All 9 reflection x incidence pairs once static and once fast; light and pane alternate, so every\n"
        "level appears in 9 of the 18 grid groups.  Each group is named by its regime.  Then 5 camera-motion\n"
        "regimes (name suffix cam-TAG; the same image motion on both layers): horizontal pans at 1.1 and 3\n"
        "view widths/s, a hand-held shake of 1 view width/s rms, a weak reflection (R/T 0.2) of natural\n"
        "images under a 1.1 view/s pan, and a near-normal pane whose reflection outshines T eight-fold.\n"
        "Generated by polspike.pipeline.sampler.stress_manifest_text() (tested).\n"
        "Build:    polspike dataset build datasets/manifests/stress.toml --out out/datasets/stress\n"
        "Evaluate: polspike evaluate out/datasets/stress --by-regime --max-frames 3"
    )
    return checked_manifest_text(stress_manifest(**kw), head, "stress manifest")
