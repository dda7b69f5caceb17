"""3-D object scenes: glossy objects behind the pane, a 3-D room in front (full tier only).

Paper Eq. (1)-(2) assumes both layers are flat pictures and the transmitted light is
unpolarized.  Real scenes behind glass hold glossy objects whose specular
reflections are polarized and depth with parallax.  A scene with an ``[objects]``
section is built from Mitsuba's own polarization-aware BSDFs and shapes instead of
the two textured layer planes:

* shapes: ``sphere`` (centre, radius), ``cube`` (centre, size, rotation),
  ``rectangle`` (a floor or wall: centre, size, rotation; its front is local +z);
* materials: ``diffuse`` (depolarizing), ``plastic`` / ``roughplastic``
  (polarized Fresnel coat over a diffuse base: Mitsuba's ``pplastic``; its
  ``plastic`` and ``roughplastic`` depolarize), ``conductor`` /
  ``roughconductor`` (complex index of a named metal, e.g. Al, Au, Cu, Ag),
  ``dielectric`` (smooth glass-like solid);
* lights: one-sided rectangular ``area`` emitters, and optionally a ``constant``
  environment.

Every shape and light lies wholly on one side of the pane (checked); its side
decides whether it belongs to the transmitted scene (behind) or the reflected
scene (in front).  Layers of such a scene are 3-D, so only the ``full`` tier
renders it; the ``[layers]`` section is not used.

Ground truth of each keyframe (three renders, :func:`render_object_layers`):

* the mixture: the whole scene, pane included (what the camera sees);
* T alone: the camera's view with the pane and the front half removed; its S0 is
  the ground-truth T, its DoP how polarized the transmitted light is;
* R alone: the camera mirrored in the pane's front plane, pane and back half
  removed; its image (columns flipped: the mirrored camera's frame is
  right-handed again) is the scene the pane reflects, S0 = ground-truth R.

Lighting is per side: lights on one side reach the other side only through the
pane (a few per cent; lost in the T-/R-alone renders) and a constant
environment lights both.

How far the rendered mixture departs from Eq. (1)-(2) (:func:`model_departure`):
the DoP of T alone and of R alone, and per pixel the worst case over polarizer
angles of |I_rendered(phi) - I_Eq(1)-(2)(phi)|, where the model mixes the
unpolarized layers L_T, L_R with the analytic zeta maps; beside it the same error
of a model that carries T's measured polarization through the pane's
transmission Mueller matrix (thin slab), which isolates the unpolarized-T
assumption, and the Monte Carlo noise floor.
"""

from __future__ import annotations

import math

import numpy as np

from generator.objects_config import MATERIALS, METALS, SHAPES, LightConfig, ObjectsConfig, ShapeConfig, Vec3, require_full_tier
from polinfra.errors import ConfigError, SceneError

__all__ = [
    "ShapeConfig",
    "LightConfig",
    "ObjectsConfig",
    "MATERIALS",
    "SHAPES",
    "METALS",
    "object_sides",
    "objects_scene_dict",
    "render_object_layers",
    "model_departure",
    "require_full_tier",
    "DEPARTURE_CHANNELS",
]

DEPARTURE_CHANNELS = ("dop_T", "dop_R", "eq12_err", "polT_model_err")
"""Extra ``maps.exr`` channels of an object scene (per pixel, keyframe 0): DoP of T alone and of R
alone, worst case over phi of |I_rendered - I_Eq(1)-(2)|, and the same error of the polarized-T model."""

PLASTIC_SMOOTH_ALPHA = 0.02
"""Roughness of the "plastic" coat (Mitsuba's polarized ``pplastic`` is a microfacet BSDF)."""

DEPARTURE_ANGLES = np.linspace(0.0, np.pi, 12, endpoint=False)


def _rot(deg: Vec3) -> np.ndarray:
    ax, ay, az = np.deg2rad(deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _shape_points(s: ShapeConfig) -> tuple[np.ndarray, float]:
    """Corner points (k, 3) and an extra radius that bound the shape."""
    c = np.asarray(s.center, float)
    if s.type == "sphere":
        return c[None], float(s.radius)
    half = 0.5 * np.asarray(s.size, float)
    if s.type == "rectangle":
        half = np.array([half[0], half[1], 0.0])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    return c + corners @ _rot(s.rotate_deg).T, 0.0


def _light_frame(li: LightConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = np.asarray(li.center, float)
    n = np.asarray(li.target, float) - c
    if np.linalg.norm(n) < 1e-9:
        raise SceneError(f"light at {list(li.center)}: target equals the centre; give a point the light faces")
    n /= np.linalg.norm(n)
    ref = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(ref, n)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u), n


def _light_points(li: LightConfig) -> np.ndarray:
    u, v, _ = _light_frame(li)
    c = np.asarray(li.center, float)
    return np.array([c + a * 0.5 * li.size[0] * u + b * 0.5 * li.size[1] * v for a in (-1, 1) for b in (-1, 1)])


def object_sides(scene) -> tuple[list[str], list[str]]:
    """Side ("front" = camera side, reflected; "behind" = transmitted) of every shape and light.

    Raises:
        SceneError: an object or light crosses the pane's plane (its slab, for slabs).
    """
    plane = scene.pane_plane()
    nrm = np.asarray(plane.normal, float) / np.linalg.norm(plane.normal)
    p0 = np.asarray(plane.point, float)
    t = scene.pane.thickness_m if scene.pane.model != "single" else 0.0

    def side(pts: np.ndarray, r: float, what: str) -> str:
        if not np.all(np.isfinite(pts)):
            raise SceneError(f"{what} has a non-finite position; give finite coordinates in metres")
        d = (pts - p0) @ nrm
        if np.all(d - r > 0):
            return "front"
        if np.all(d + r < -t):
            return "behind"
        raise SceneError(f"{what} crosses the pane's plane; move it wholly in front of or behind the pane")

    ob = scene.objects
    times = [0.0] if ob.is_static else list(np.linspace(0.0, float(scene.render.duration_s), 9))  # moving objects: along the clip
    shapes: list[str] = []
    for t_s in times:
        got = [side(*_shape_points(s.at(t_s)), f"objects.shapes[{i}] ({s.type} at {[round(x, 4) for x in s.at(t_s).center]}{f', t = {t_s:.3g} s' if t_s else ''})")
               for i, s in enumerate(ob.shapes)]
        if shapes and got != shapes:
            bad = next(i for i, (a, b) in enumerate(zip(shapes, got)) if a != b)
            raise SceneError(f"objects.shapes[{bad}] moves from one side of the pane to the other during the clip; keep it on one side")
        shapes = got
    lights = [side(_light_points(li), 0.0, f"objects.lights[{i}] (at {list(li.center)})") for i, li in enumerate(ob.lights)]
    return shapes, lights


# ---------------------------------------------------------------------------- Mitsuba dict
def _bsdf(s: ShapeConfig) -> dict:
    m = s.material
    if m == "diffuse":
        return {"type": "diffuse", "reflectance": float(s.reflectance)}
    if m in ("plastic", "roughplastic"):
        # Mitsuba's polarization-aware plastic is ``pplastic`` (microfacet Fresnel coat over a depolarizing base);
        # its ``plastic`` / ``roughplastic`` depolarize in polarized variants.  "plastic" = a near-smooth coat.
        alpha = PLASTIC_SMOOTH_ALPHA if m == "plastic" else float(s.alpha)
        return {"type": "pplastic", "int_ior": float(s.ior), "ext_ior": 1.0, "diffuse_reflectance": float(s.reflectance), "alpha": alpha}
    if m == "conductor":
        return {"type": "conductor", "material": s.metal}
    if m == "roughconductor":
        return {"type": "roughconductor", "material": s.metal, "alpha": float(s.alpha)}
    return {"type": "dielectric", "int_ior": float(s.ior), "ext_ior": 1.0}


def _shape_dict(mi, s: ShapeConfig) -> dict:
    T = mi.ScalarTransform4f
    if s.type == "sphere":
        return {"type": "sphere", "center": list(map(float, s.center)), "radius": float(s.radius), "bsdf": _bsdf(s)}
    m = np.eye(4)
    half = 0.5 * np.asarray(s.size, float)
    m[:3, :3] = _rot(s.rotate_deg) @ np.diag(half if s.type == "cube" else [half[0], half[1], 1.0])
    m[:3, 3] = np.asarray(s.center, float)
    return {"type": s.type, "to_world": T(m.tolist()), "bsdf": _bsdf(s)}


def _light_dict(mi, li: LightConfig) -> dict:
    u, v, n = _light_frame(li)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = u * 0.5 * li.size[0], v * 0.5 * li.size[1], n
    m[:3, 3] = np.asarray(li.center, float)
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "bsdf": {"type": "diffuse", "reflectance": 0.0},
        "emitter": {"type": "area", "radiance": float(li.radiance)},
    }


def objects_scene_dict(mi, scene, camera, pane, *, parts: str = "all", spp: int = 16, seed: int = 0, max_depth: int | None = None) -> dict:
    """Mitsuba scene dict of an object scene.

    Args:
        mi: mitsuba (variant set).
        scene: the SceneConfig (with ``objects``).
        camera: :class:`generator.mitsuba_scene.CameraSpec` to render with.
        pane: :class:`generator.mitsuba_scene.PaneSpec`, or None for no pane.
        parts: "all" (both sides), "behind" or "front" (that side's shapes and lights only).
        spp, seed: sampler settings.
        max_depth: path depth (default ``objects.max_depth``).
    """
    from generator.mitsuba_scene import build_scene_dict

    if parts not in ("all", "behind", "front"):
        raise ConfigError(f"parts = {parts!r}: choose all, behind or front")
    ob = scene.objects
    depth = int(max_depth or ob.max_depth)
    integ = {"type": "stokes", "inner": {"type": "path", "max_depth": depth, "rr_depth": depth + 1}}
    if pane is None:  # a placeholder pane to build the camera part, then dropped
        from generator.mitsuba_scene import PaneSpec

        pane_d = PaneSpec("single", 1.5, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0))
        d = {k: v for k, v in build_scene_dict(mi, camera, pane_d, [], integrator=integ, spp=spp, seed=seed).items() if not k.startswith("pane_")}
    else:
        d = build_scene_dict(mi, camera, pane, [], integrator=integ, spp=spp, seed=seed)
    s_side, l_side = object_sides(scene)
    for i, (s, side) in enumerate(zip(ob.shapes, s_side)):
        if parts in ("all", side):
            d[f"obj_{i}_{s.type}"] = _shape_dict(mi, s)
    for i, (li, side) in enumerate(zip(ob.lights, l_side)):
        if parts in ("all", side):
            d[f"light_{i}"] = _light_dict(mi, li)
    if ob.environment > 0:
        d["environment"] = {"type": "constant", "radiance": float(ob.environment)}
    return d


def _mirrored_camera(camera, scene):
    """The camera mirrored in the pane's front plane (a right-handed look_at frame: image columns flipped)."""
    from generator.mitsuba_scene import CameraSpec

    plane = scene.pane_plane()
    n = np.asarray(plane.normal, float) / np.linalg.norm(plane.normal)
    p0 = np.asarray(plane.point, float)

    def mp(p):
        p = np.asarray(p, float)
        return p - 2.0 * ((p - p0) @ n) * n

    def md(v):
        v = np.asarray(v, float)
        return v - 2.0 * (v @ n) * n

    return CameraSpec(camera.width, camera.height, camera.fovx_rad, tuple(map(float, mp(camera.position))), tuple(map(float, mp(camera.look_at))), tuple(map(float, md(camera.up))))


def render_object_layers(mi, scene, n_index: float, spp: int, seed: int) -> dict[str, np.ndarray]:
    """The three renders of one keyframe: ``S`` (mixture), ``S_T`` (T alone), ``S_R`` (R alone), each (3, H, W).

    ``S_R`` is in the real camera's image frame (columns flipped back, S2 negated: the
    mirror reverses angles), so its S0 is the ground-truth R at each pixel.
    """
    from generator.mitsuba_scene import render_stokes_image, specs_from_scene

    cam, pane = specs_from_scene(scene, n=n_index)
    S = render_stokes_image(mi, objects_scene_dict(mi, scene, cam, pane, spp=spp, seed=seed), spp, seed)
    S_T = render_stokes_image(mi, objects_scene_dict(mi, scene, cam, None, parts="behind", spp=spp, seed=seed), spp, seed + 7919)
    S_Rm = render_stokes_image(mi, objects_scene_dict(mi, scene, _mirrored_camera(cam, scene), None, parts="front", spp=spp, seed=seed), spp, seed + 104729)
    S_R = S_Rm[:, :, ::-1].copy()
    S_R[2] *= -1.0
    return {"S": S, "S_T": S_T, "S_R": S_R}


# ---------------------------------------------------------------------------- Eq. (1)-(2) departure
def _transmit_polarized(S_T: np.ndarray, maps, model: str, n: float) -> np.ndarray | None:
    """Stokes of T's light after the pane, carrying T's own polarization (thin slab, incoherent):
    in the s/p frame M = [[a, b, 0], [b, a, 0], [0, 0, c]], a = (T_perp + T_par)/2, b = (T_perp - T_par)/2,
    c = (1 - R_s)(1 - R_p) / (1 - R_s R_p) (each internal path keeps its s/p phase relation; R_s, R_p of
    one interface).  None for other pane models.
    """
    if model != "thin_slab":
        return None
    from polphysics.fresnel import pane_coefficients

    one = pane_coefficients(maps.theta, n, "single")
    Rs, Rp = one["R_perp"], one["R_par"]
    c = (1 - Rs) * (1 - Rp) / np.maximum(1 - Rs * Rp, 1e-12)
    a, b = 0.5 * (maps.T_perp + maps.T_par), 0.5 * (maps.T_perp - maps.T_par)
    c2, s2 = np.cos(2 * maps.phi_perp), np.sin(2 * maps.phi_perp)
    s0, s1, s2v = S_T
    p1 = s1 * c2 + s2v * s2  # into the s/p frame
    p2 = -s1 * s2 + s2v * c2
    q0, q1, q2 = a * s0 + b * p1, b * s0 + a * p1, c * p2
    return np.stack([q0, q1 * c2 - q2 * s2, q1 * s2 + q2 * c2])  # back to the camera frame


def model_departure(layers: dict[str, np.ndarray], maps, model: str, n: float, S_second_seed: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Per-pixel maps and a summary of how far the rendered mixture departs from Eq. (1)-(2).

    Args:
        layers: :func:`render_object_layers` output.
        maps: analytic :class:`generator.analytic.PaneMaps` of the scene (zeta model).
        model: pane model; n: its index (the polarized-T model needs thin_slab).
        S_second_seed: the mixture rendered with another seed (noise floor), optional.

    Returns:
        ({channel: (H, W)} for :data:`DEPARTURE_CHANNELS`, summary dict).
    """
    from polphysics.stokes import dop, polarizer_intensity
    from polphysics.zeta import stokes_from_layers

    S, S_T, S_R = layers["S"], layers["S_T"], layers["S_R"]
    L_T, L_R = S_T[0], S_R[0]
    S_eq = stokes_from_layers(L_T, L_R, maps.R_perp, maps.R_par, maps.T_perp, maps.T_par, maps.phi_perp)

    def worst(A, B):
        return np.max([np.abs(polarizer_intensity(*A, p) - polarizer_intensity(*B, p)) for p in DEPARTURE_ANGLES], axis=0)

    err = worst(S, S_eq)
    S_Tpol = _transmit_polarized(S_T, maps, model, n)
    if S_Tpol is not None:
        S_pol = S_Tpol + stokes_from_layers(np.zeros_like(L_T), L_R, maps.R_perp, maps.R_par, maps.T_perp, maps.T_par, maps.phi_perp)
        err_pol = worst(S, S_pol)
    else:
        err_pol = np.full_like(err, np.nan)
    dT = np.nan_to_num(dop(*S_T), nan=0.0)
    dR = np.nan_to_num(dop(*S_R), nan=0.0)
    lit_T = L_T > 0.05 * max(float(np.percentile(L_T, 99)), 1e-9)
    lit_R = L_R > 0.05 * max(float(np.percentile(L_R, 99)), 1e-9)

    def st(a, mask=None):
        v = a[mask] if mask is not None else a.ravel()
        v = v[np.isfinite(v)]
        if v.size == 0:
            return None
        return {"mean": float(v.mean()), "p99": float(np.percentile(v, 99)), "max": float(v.max())}

    noise = None
    if S_second_seed is not None:
        noise = float(np.percentile(worst(S, S_second_seed), 99) / math.sqrt(2.0))
    summary = {
        "definition": (
            "dop_T / dop_R: degree of linear polarization of T alone / R alone (pixels lit above 5 % of the p99 radiance); "
            "eq12_err: per pixel, worst case over 12 polarizer angles of |I_rendered(phi) - I_Eq(1)-(2)(phi)| with unpolarized "
            "L_T = S0(T alone), L_R = S0(R alone) and the analytic zeta maps; polT_model_err: the same error when T's own "
            "polarization is carried through the pane's Mueller matrix (thin slab only; what remains is Monte Carlo noise and "
            "light crossing between the sides); noise_floor_p99: p99 of the worst-case |I| between two seeds / sqrt 2"
        ),
        "dop_T": st(dT, lit_T),
        "dop_R": st(dR, lit_R),
        "dop_T_fraction_above_0.1": float(np.mean(dT[lit_T] > 0.1)) if lit_T.any() else 0.0,
        "eq12_err": st(err),
        "polT_model_err": st(err_pol) if S_Tpol is not None else None,
        "noise_floor_p99": noise,
        "radiance_p99": float(np.percentile(S[0], 99)),
    }
    chans = {"dop_T": dT, "dop_R": dR, "eq12_err": err, "polT_model_err": err_pol}
    return chans, summary
