"""Sample a dataset manifest: scene parameters drawn from documented ranges.

``polspike dataset new --groups N --seed S --out FILE`` calls :func:`sample_manifest`.
One ``np.random.default_rng(seed)`` draws every group in order, so the same
(N, seed, options) always writes the same manifest.  The last
``round(test_fraction * N)`` groups (at least one when N >= 2) are the test split.

Ranges (U = uniform; all drawn per group):

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

from polspike.pipeline.manifest import MANIFEST_FORMAT, dump_manifest, parse_manifest

__all__ = ["sample_manifest", "sample_manifest_text", "RANGES", "CONTENT_POOLS"]

RANGES: dict[str, tuple[float, float]] = {
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
"""Uniform ranges of the sampled parameters (see the module docstring)."""

PANE_MODELS = (("single", 0.2), ("thin_slab", 0.5), ("thick_slab", 0.3))
MAX_INCIDENCE_DEG = 82.0
SPRITE_PROB = 0.3
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


def _u(rng: np.random.Generator, key: str) -> float:
    lo, hi = RANGES[key]
    return float(rng.uniform(lo, hi))


def _r(x: float, nd: int = 4) -> float:
    return float(round(x, nd))


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


def _motion(rng: np.random.Generator) -> dict:
    return {
        "translate_per_s": [_r(_u(rng, "translate_per_s")), _r(_u(rng, "translate_per_s"))],
        "rotate_deg_per_s": _r(_u(rng, "rotate_deg_per_s"), 3),
        "zoom_per_s": _r(_u(rng, "zoom_per_s")),
    }


def _pane_need(scene_d: dict) -> tuple[float, float] | None:
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
    if float(np.degrees(np.nanmax(geo["theta"]))) >= MAX_INCIDENCE_DEG:
        return None
    e_w, e_h = sc.pane_axes()
    rel = geo["hit"] - sc.pane_plane().point
    return float(np.max(np.abs(rel @ e_w))) * 2, float(np.max(np.abs(rel @ e_h))) * 2


def _group(rng: np.random.Generator, name: str, split: str, width: int, height: int) -> dict:
    while True:  # rejection sampling of the geometry
        fov = _r(_u(rng, "fov_deg"), 3)
        yaw, pitch = math.radians(_u(rng, "yaw_deg")), math.radians(_u(rng, "pitch_deg"))
        look = [_r(math.sin(yaw) * math.cos(pitch), 5), _r(math.sin(pitch), 5), _r(-math.cos(yaw) * math.cos(pitch), 5)]
        roll = _r(_u(rng, "roll_deg"), 3)
        ps = np.array([p for _, p in PANE_MODELS])
        model = PANE_MODELS[int(rng.choice(len(PANE_MODELS), p=ps / ps.sum()))][0]
        pane = {
            "model": model,
            "n": _r(_u(rng, "n")),
            "distance_m": _r(_u(rng, "pane_distance_m"), 3),
            "tilt_deg": _r(_u(rng, "tilt_deg"), 3),
            "tilt_axis_deg": _r(_u(rng, "tilt_axis_deg"), 3),
            "thickness_mm": _r(_u(rng, "thickness_mm"), 3),
            "size_m": [1000.0, 1000.0],
        }
        camera = {"width": width, "height": height, "fov_deg": fov, "position": [0.0, 0.0, 0.0], "look_at": look, "up": [0.0, 1.0, 0.0], "roll_deg": roll}
        need = _pane_need({"camera": camera, "pane": pane})
        if need is not None:
            break
    pane["size_m"] = [math.ceil(need[0] * 1.25 * 10) / 10, math.ceil(need[1] * 1.25 * 10) / 10]
    t_src, t_seed = _content(rng, split)
    r_src, r_seed = _content(rng, split, avoid=t_src)
    if r_src == t_src and r_seed == t_seed:
        r_seed = t_seed + 1 if r_seed + 1 < CONTENT_POOLS[split]["noise_seeds"][1] else t_seed - 1
    trans = {"source": t_src, "seed": t_seed, "distance_m": _r(_u(rng, "t_distance_m"), 3), "brightness": _r(_u(rng, "t_brightness"), 3), "motion": _motion(rng)}
    refl = {"source": r_src, "seed": r_seed, "distance_m": _r(_u(rng, "r_distance_m"), 3), "brightness": _r(_u(rng, "r_brightness"), 3), "motion": _motion(rng)}
    if rng.random() < SPRITE_PROB:
        sp_src, _ = _content(rng, split)
        if sp_src == "procedural:noise":
            sp_src = CONTENT_POOLS[split]["images"][-1]
        refl["sprites"] = [{
            "source": sp_src,
            "size": _r(_u(rng, "sprite_size"), 3),
            "start": [_r(_u(rng, "sprite_start"), 3), _r(_u(rng, "sprite_start"), 3)],
            "velocity_per_s": [_r(_u(rng, "sprite_velocity_per_s"), 3), _r(_u(rng, "sprite_velocity_per_s"), 3)],
        }]
    return {
        "name": name,
        "split": split,
        "seed": int(rng.integers(0, 2**31 - 1)),
        "camera": camera,
        "pane": pane,
        "layers": {"transmission": trans, "reflection": refl},
        "polarizer": {"phase_deg": _r(_u(rng, "phase_deg"), 3)},
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
) -> dict:
    """Plain manifest data with ``n_groups`` groups drawn from :data:`RANGES`.

    Args:
        n_groups: number of groups (>= 1).
        seed: sampler seed (the whole manifest is a function of the arguments).
        name: dataset name.
        test_fraction: share of test groups (the last ones), in [0, 1].
        width, height: image size in pixels.
        duration_s: stream length per group (s).
        tier: generator tier of every group.
        keyframe_fps: radiance keyframes per second.
        rate_hz: polarizer revolutions per second.
        spike_sim_preset: simulator preset name.

    Returns:
        dict ready for :func:`polspike.pipeline.manifest.dump_manifest`; it validates
        with :func:`polspike.pipeline.manifest.parse_manifest`.
    """
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
        groups.append(_group(rng, f"{split}_{idx:03d}", split, width, height))
    return {
        "format": MANIFEST_FORMAT,
        "name": name,
        "description": f"{n_groups} groups sampled by `polspike dataset new --groups {n_groups} --seed {seed}` ({n_train} train / {n_test} test)",
        "defaults": {
            "tier": tier,
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
    text = dump_manifest(data, header=f"Sampled by polspike dataset new --groups {n_groups} --seed {seed}.\nRanges: polspike/pipeline/sampler.py (docs/datasets.md).")
    import tomllib

    parse_manifest(tomllib.loads(text), where="sampled manifest", source_text=text.encode())
    return text
