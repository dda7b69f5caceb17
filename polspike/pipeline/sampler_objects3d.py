"""Sampler profile ``objects3d``: 3-D arrangements of the object primitives around the pane, with motion.

``polspike dataset new --ranges objects3d`` (and ``bench tradeoff --sampled N --sampled-profile
objects3d``) draws, per group, with one ``np.random.default_rng(seed)`` in order:

==========================  =====================================================
pane                        thin_slab 70 % / single 30 %, n U[1.45, 1.6], tilt U[28, 60] deg
                            (the reflected view then points away from the camera's own view)
                            about an axis U[0, 180) deg, 1 m away, 8 x 8 m
camera                      fov U[35, 45] deg, looking down -z
behind the pane (T)         a diffuse back wall 6-8 m away (reflectance U[0.3, 0.8]) and 2-3
                            primitives (sphere 50 %, cube 50 %) 2.5-5 m away inside the view,
                            materials drawn from plastic, roughplastic, conductor,
                            roughconductor, dielectric, diffuse (the first four polarize T)
in front (R)                a diffuse wall 3.5-4.5 m along the reflected optical axis and 1-2
                            diffuse or plastic primitives 1.5-3 m along it
lights                      constant environment U[0.2, 0.6], one area light per side
                            (radiance U[1, 3]) above the objects, facing them
motion                      every primitive moves with a velocity of |v| U[0, 0.6] m/s in a
                            uniform direction across the view (z speed a third of it); cubes
                            spin about y at U[-90, 90] deg/s; draws that cross the pane during
                            the clip are redrawn
==========================  =====================================================

Rendered by the full tier only (the analytic and maps tiers cannot render 3-D objects).
"""

from __future__ import annotations

import math

import numpy as np

from polinfra.errors import PolspikeError

__all__ = ["sampled_scenes", "objects3d_group", "objects3d_manifest", "objects3d_manifest_text", "OBJECT_MATERIALS_T"]

OBJECT_MATERIALS_T = ("plastic", "roughplastic", "conductor", "roughconductor", "dielectric", "diffuse")
METALS_DRAWN = ("Al", "Au", "Cu", "Cr", "Ag")


def _r(x: float, nd: int = 4) -> float:
    return round(float(x), nd)


def _vec(v) -> list[float]:
    return [_r(x) for x in v]


def _material(rng: np.random.Generator, mat: str) -> dict:
    d: dict = {"material": mat}
    if mat in ("plastic", "roughplastic", "diffuse"):
        d["reflectance"] = _r(rng.uniform(0.05, 0.8), 3)
    if mat in ("plastic", "roughplastic", "dielectric"):
        d["ior"] = _r(rng.uniform(1.4, 1.7), 3)
    if mat in ("conductor", "roughconductor"):
        d["metal"] = str(rng.choice(METALS_DRAWN))
    if mat.startswith("rough"):
        d["alpha"] = _r(rng.uniform(0.03, 0.3), 3)
    return d


def _primitive(rng: np.random.Generator, centre: np.ndarray, size: float, mat: str, speed_max: float, lateral: np.ndarray, depth_dir: np.ndarray) -> dict:
    kind = "sphere" if rng.uniform() < 0.5 else "cube"
    sp: dict = {"type": kind, "center": _vec(centre)}
    if kind == "sphere":
        sp["radius"] = _r(size / 2, 3)
    else:
        sp["size"] = _vec(rng.uniform(0.6, 1.0, 3) * size)
        sp["rotate_deg"] = _vec([rng.uniform(-20, 20), rng.uniform(0, 90), rng.uniform(-10, 10)])
        sp["spin_deg_per_s"] = [0.0, _r(rng.uniform(-90, 90), 2), 0.0]
    speed = rng.uniform(0.0, speed_max)
    ang = rng.uniform(0.0, 2 * math.pi)
    v = speed * (math.cos(ang) * lateral[0] + math.sin(ang) * lateral[1]) + (speed / 3.0) * rng.uniform(-1, 1) * depth_dir
    sp["velocity_m_per_s"] = _vec(v)
    sp.update(_material(rng, mat))
    return sp


def _facing_rect(centre: np.ndarray, facing: np.ndarray, size: float, refl: float) -> dict:
    """A diffuse square at ``centre`` whose front (+z local) faces along ``facing`` (rotation x then y)."""
    f = facing / np.linalg.norm(facing)
    ry = math.degrees(math.atan2(f[0], f[2]))
    rx = -math.degrees(math.asin(max(-1.0, min(1.0, f[1]))))
    return {"type": "rectangle", "center": _vec(centre), "size": [_r(size, 3), _r(size, 3), 1.0], "rotate_deg": [_r(rx, 3), _r(ry, 3), 0.0],
            "material": "diffuse", "reflectance": _r(refl, 3)}


def _light(centre: np.ndarray, target: np.ndarray, radiance: float) -> dict:
    return {"center": _vec(centre), "size": [2.0, 2.0], "target": _vec(target), "radiance": _r(radiance, 3)}


def objects3d_group(rng: np.random.Generator, name: str, split: str, width: int, height: int, duration_s: float, spp: int, max_depth: int = 12) -> dict:
    """One manifest group of the ``objects3d`` profile (module docstring); redrawn until it is valid."""
    from generator.objects3d import object_sides
    from generator.scene import check_scene_geometry, scene_from_dict

    for _ in range(50):
        fov = float(rng.uniform(35, 45))
        model = "thin_slab" if rng.uniform() < 0.7 else "single"
        pane = {"model": model, "n": _r(rng.uniform(1.45, 1.6), 3), "distance_m": 1.0, "tilt_deg": _r(rng.uniform(28, 60), 3),
                "tilt_axis_deg": _r(rng.uniform(0, 180), 3), "size_m": [8.0, 8.0], "thickness_mm": 5.0}
        camera = {"width": width, "height": height, "fov_deg": _r(fov, 3)}
        base = {"name": name, "camera": camera, "pane": pane, "render": {"duration_s": duration_s, "spp": spp}}
        sc0 = scene_from_dict(base)
        plane = sc0.pane_plane()
        nrm = np.asarray(plane.normal, float)
        p0 = np.asarray(plane.point, float)
        fwd = np.array([0.0, 0.0, -1.0])
        d_r = fwd - 2.0 * (fwd @ nrm) * nrm  # the reflected optical axis
        tan_h = math.tan(math.radians(fov) / 2)
        aspect = height / width
        shapes: list[dict] = []
        # behind: a back wall and 2-3 primitives inside the view
        z_wall = -rng.uniform(6.0, 8.0)
        shapes.append(_facing_rect(np.array([0.0, 0.0, z_wall]), np.array([0.0, 0.0, 1.0]), 3.0 * abs(z_wall) * tan_h, rng.uniform(0.3, 0.8)))
        for _k in range(int(rng.integers(2, 4))):
            z = -rng.uniform(2.5, 5.0)
            x = rng.uniform(-0.6, 0.6) * abs(z) * tan_h
            y = rng.uniform(-0.6, 0.6) * abs(z) * tan_h * aspect
            size = rng.uniform(0.25, 0.45) * abs(z) * tan_h
            shapes.append(_primitive(rng, np.array([x, y, z]), size, str(rng.choice(OBJECT_MATERIALS_T)), 0.6,
                                     (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])), np.array([0.0, 0.0, 1.0])))
        # in front: a wall across the reflected axis and 1-2 primitives along it
        u = np.cross(d_r, [0.0, 1.0, 0.0])
        u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-6 else np.array([1.0, 0.0, 0.0])
        v = np.cross(u, d_r)
        dist_wall = rng.uniform(3.5, 4.5)
        shapes.append(_facing_rect(p0 + dist_wall * d_r, -d_r, 3.0 * dist_wall * tan_h, rng.uniform(0.3, 0.8)))
        for _k in range(int(rng.integers(1, 3))):
            dist = rng.uniform(1.5, 3.0)
            c = p0 + dist * d_r + rng.uniform(-0.5, 0.5) * dist * tan_h * u + rng.uniform(-0.5, 0.5) * dist * tan_h * aspect * v
            size = rng.uniform(0.25, 0.45) * dist * tan_h
            shapes.append(_primitive(rng, c, size, "diffuse" if rng.uniform() < 0.6 else "plastic", 0.6, (u, v), d_r))
        lights = [
            _light(np.array([0.0, 2.5, -3.5]), np.array([0.0, 0.0, -3.5]), rng.uniform(1.0, 3.0)),
            _light(p0 + 2.0 * d_r + 2.5 * v, p0 + 2.0 * d_r, rng.uniform(1.0, 3.0)),
        ]
        objects = {"environment": _r(rng.uniform(0.2, 0.6), 3), "max_depth": max_depth, "shapes": shapes, "lights": lights}
        try:
            sc = scene_from_dict({**base, "objects": objects})
            check_scene_geometry(sc)
            object_sides(sc)
        except PolspikeError:
            continue
        if object_sides(sc)[1] != ["behind", "front"]:
            continue
        mats = sorted({s["material"] for s in shapes[1:] if s["type"] != "rectangle"})
        return {"name": name, "split": split, "description": f"{model}, tilt {pane['tilt_deg']:.1f} deg; {len(shapes)} shapes ({', '.join(mats)}); moving",
                "seed": int(rng.integers(0, 2**31 - 1)), "camera": camera, "pane": pane, "render": {"spp": spp}, "objects": objects}
    raise PolspikeError(f"objects3d group {name}: no valid arrangement in 50 draws")  # pragma: no cover


SHIPPED_OBJECT_SCENES = ("glossy_street", "shop_window")
"""The shipped 3-D scenes (static, strongly polarized T) appended to an objects3d manifest."""


def objects3d_manifest(n_groups: int, seed: int, name: str = "objects3d", width: int = 200, height: int = 125, duration_s: float = 0.1,
                       spp: int = 64, keyframe_fps: float = 50.0, split: str = "test", shipped: tuple[str, ...] = SHIPPED_OBJECT_SCENES) -> dict:
    """Plain manifest data: ``n_groups`` drawn object groups, then one group per ``shipped`` scene (all in ``split``), full tier."""
    from polspike.pipeline.manifest import MANIFEST_FORMAT

    rng = np.random.default_rng(seed)
    groups = [objects3d_group(rng, f"{split}_{i:03d}", split, width, height, duration_s, spp) for i in range(n_groups)]
    for sc in shipped:  # drawn after the sampled groups: adding them leaves the sampled ones unchanged
        groups.append({"name": sc, "split": split, "description": f"scenes/{sc}.toml (static)", "seed": int(rng.integers(0, 2**31 - 1)),
                       "scene": sc, "camera": {"width": width, "height": height}, "render": {"spp": spp}})
    return {
        "format": MANIFEST_FORMAT,
        "name": name,
        "description": f"{n_groups} 3-D object groups (sampler profile objects3d, seed {seed}) and {len(shipped)} shipped object scenes, full tier, {spp} spp, {width} x {height}, {duration_s} s",
        "defaults": {"tier": "full", "duration_s": float(duration_s), "keyframe_fps": float(keyframe_fps), "polarizer": {"rate_hz": 30.0}, "spike_sim": {"preset": "default"}},
        "groups": groups,
    }


def objects3d_manifest_text(n_groups: int, seed: int, **kw) -> str:
    """TOML text of :func:`objects3d_manifest` with its header (validated before it is returned)."""
    from polspike.pipeline.manifest import checked_manifest_text

    data = objects3d_manifest(n_groups, seed, **kw)
    head = (
        f"3-D object arrangements (sampler profile objects3d, polspike/pipeline/sampler_objects3d.py): {n_groups} test groups,\n"
        "then the shipped object scenes glossy_street and shop_window (static) at the same size and spp.\n"
        "Primitives (spheres, cubes) of polarizing and diffuse materials behind the pane and diffuse / plastic ones in front,\n"
        "moving, lit by an environment and one area light per side; rendered by the full tier (path tracing).\n"
        "Paper Eq. (1) assumes unpolarized T: these scenes measure where that model breaks.\n"
        f"Generated by polspike dataset new --ranges objects3d --groups {n_groups} --seed {seed}"
        + "".join(f" --{k.replace('_', '-')} {v}" for k, v in kw.items() if k in ("width", "height", "duration_s")) + "\n"
        "Build:    polspike dataset build datasets/manifests/objects3d.toml --out out/datasets/objects3d\n"
        "Evaluate: polspike evaluate out/datasets/objects3d --method ls,ridge,irls,rwps,full"
    )
    return checked_manifest_text(data, head, "objects3d manifest")


def sampled_scenes(n: int, seed: int, width: int, height: int, profile: str = "paper") -> list:
    """``n`` :class:`generator.scene.SceneConfig` drawn by the sampler ``profile`` at ``width`` x ``height``."""
    from generator.scene import scene_from_dict
    from polspike.pipeline.manifest import parse_manifest
    from polspike.pipeline.sampler import sample_manifest

    if profile == "objects3d":
        data = objects3d_manifest(n, seed, width=width, height=height, duration_s=0.05, shipped=())
    else:
        data = sample_manifest(n, seed, name="sampled", test_fraction=0.0, width=width, height=height, duration_s=0.05, profile=profile)
    m = parse_manifest(data, where="sampled scenes")
    return [scene_from_dict({**g.scene, "name": f"sampled_{profile}_{seed}_{i:02d}"}) for i, g in enumerate(m.groups)]
