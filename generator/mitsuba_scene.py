"""Translate a glass-pane scene into a Mitsuba 3 scene dict (``mi.load_dict``).

The translation works on small neutral geometry records (:class:`CameraSpec`,
:class:`PaneSpec`, :class:`LayerPlane`) so that it does not depend on how a
scene file spells things; :func:`specs_from_scene` builds them from a
:class:`generator.scene.SceneConfig`.

Geometry (world frame, metres):

* Camera: Mitsuba ``perspective`` sensor, ``fov_axis = "x"``, ``to_world =
  look_at(position, look_at, up)``.  Its pixel (x, y) ray is
  ``f + ((x+.5)/W*2-1) tan(fovx/2) r - ((y+.5)/H*2-1) tan(fovx/2) (H/W) u``,
  the pinhole camera of :mod:`polphysics.geometry` (pinned by a test).
  Mitsuba's ``stokes`` integrator expresses Stokes vectors per ray with the
  reference axis ``x_ref = normalize(cross(d, up))`` (image right) and S2 > 0
  toward ``cross(x_ref, d)`` (image up): the project convention.
* Pane: finite rectangle(s) with Mitsuba's smooth ``dielectric`` BSDF.
  ``single`` is one interface (glass on the far side of the camera);
  ``thin_slab`` and ``thick_slab`` are two parallel interfaces
  ``thickness`` apart.  ``thindielectric`` is NOT used: it depolarizes (it
  returns an unpolarized Mueller matrix; measured in
  ``tests/generator/test_mitsuba_scene.py``), see the README note.
* Layers: textured ``area`` emitters on rectangles (``bitmap`` radiance,
  nearest-neighbour lookup, raw linear values).  The texture's row 0 is the
  top edge of the plane as the (mirrored) camera sees it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from polinfra.errors import SceneError

__all__ = [
    "CameraSpec",
    "PaneSpec",
    "LayerPlane",
    "pane_interfaces",
    "build_scene_dict",
    "specs_from_scene",
    "render_stokes_image",
]


def _unit(v, what: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-12:
        raise SceneError(f"{what} must be a non-zero finite 3-vector, got {v.tolist()}")
    return v / n


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera.

    Attributes:
        width, height: image size in pixels (W, H).
        fovx_rad: horizontal field of view, radians.
        position, look_at, up: world-frame 3-vectors (m).
    """

    width: int
    height: int
    fovx_rad: float
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward f, right r, true up u (unit world vectors)."""
        f = _unit(np.subtract(self.look_at, self.position), "camera look_at - position")
        r = _unit(np.cross(f, self.up), "camera right (forward x up)")
        return f, r, np.cross(r, f)

    def pixel_dirs(self, sub: int = 1) -> np.ndarray:
        """Unit ray directions (H*sub, W*sub, 3) through sub-pixel centres."""
        f, r, u = self.frame()
        W, H = self.width * sub, self.height * sub
        t = np.tan(0.5 * self.fovx_rad)
        xs = ((np.arange(W) + 0.5) / W * 2 - 1) * t
        ys = ((np.arange(H) + 0.5) / H * 2 - 1) * t * (self.height / self.width)
        d = f[None, None] + xs[None, :, None] * r[None, None] - ys[:, None, None] * u[None, None]
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class PaneSpec:
    """Glass pane.

    Attributes:
        model: ``"single"``, ``"thin_slab"`` or ``"thick_slab"``.
        n: refractive index (for a mono render, or the index at the band
            being rendered).
        center: pane centre (m); for slabs the mid-plane.
        normal: unit normal pointing toward the camera side.
        size: (width, height) of the rectangle in metres.
        thickness_m: slab thickness (ignored for ``single``).
        absorption_per_m: bulk absorption coefficient of the glass (1/m).
        u_axis: in-plane direction of the rectangle's width (optional).
    """

    model: str
    n: float
    center: tuple[float, float, float]
    normal: tuple[float, float, float]
    size: tuple[float, float]
    thickness_m: float = 0.0
    absorption_per_m: float = 0.0
    u_axis: tuple[float, float, float] | None = None

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pane frame (u, v, n) with cross(u, v) = n."""
        n = _unit(self.normal, "pane normal")
        if self.u_axis is not None:
            u = np.asarray(self.u_axis, dtype=np.float64)
            u = _unit(u - n * float(u @ n), "pane u_axis (projected onto the pane)")
        else:
            ref = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
            u = _unit(np.cross(ref, n), "pane u axis")
        return u, np.cross(n, u), n


@dataclasses.dataclass(frozen=True)
class LayerPlane:
    """A textured emitting rectangle.

    Attributes:
        center: centre (m).
        u_axis: unit vector along the texture's +x (columns) on the plane.
        v_axis: unit vector along the texture's -y (toward row 0, i.e. "up").
        half_size: (half width along u, half height along v) in metres.
        texture: (H_tex, W_tex) float radiance (linear, >= 0), row 0 at +v.
        name: short label used in the scene dict.
        normal: emitting side (default ``cross(u_axis, v_axis)``); give it for
            a mirrored (left-handed) frame such as the R plane's.
        keep_side: optional half-space (point, normal): texels outside it
            (e.g. the part of a tilted R plane that pokes through the pane to
            the far side) neither emit nor block (``mask`` BSDF, opacity 0).
    """

    center: tuple[float, float, float]
    u_axis: tuple[float, float, float]
    v_axis: tuple[float, float, float]
    half_size: tuple[float, float]
    texture: np.ndarray
    name: str = "layer"
    normal: tuple[float, float, float] | None = None
    keep_side: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None

    def side_mask(self) -> np.ndarray | None:
        """(H_tex, W_tex) float 1 where a texel centre lies in ``keep_side``, else 0 (None: no clipping)."""
        if self.keep_side is None:
            return None
        th, tw = np.asarray(self.texture).shape
        X = ((np.arange(tw) + 0.5) / tw * 2 - 1) * self.half_size[0]
        Y = (1 - (np.arange(th) + 0.5) / th * 2) * self.half_size[1]  # row 0 at +v
        u, v = _unit(self.u_axis, "layer u"), _unit(self.v_axis, "layer v")
        P = np.asarray(self.center, float) + X[None, :, None] * u + Y[:, None, None] * v
        pt, nn = np.asarray(self.keep_side[0], float), _unit(self.keep_side[1], "keep_side normal")
        return ((P - pt) @ nn > 0).astype(np.float64)


def _rect_matrix(center, u, v, hu: float, hv: float, normal=None) -> np.ndarray:
    """4x4 to_world of Mitsuba's ``rectangle`` ([-1,1]^2 in local xy, normal +z)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    m = np.eye(4)
    m[:3, 0] = u * hu
    m[:3, 1] = v * hv
    m[:3, 2] = np.cross(u, v) if normal is None else _unit(normal, "layer normal")
    m[:3, 3] = np.asarray(center, float)
    return m


def pane_interfaces(pane: PaneSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    """The dielectric interfaces of a pane model: list of (to_world 4x4, outward normal).

    ``single``: one interface at ``center`` with normal toward the camera (glass
    behind it).  Slabs: the front face at ``center + n t/2`` (normal +n) and the
    back face at ``center - n t/2`` (normal -n), so both normals point out of the glass.
    """
    if pane.model not in ("single", "thin_slab", "thick_slab"):
        raise SceneError(f"unknown pane model {pane.model!r}; use single, thin_slab or thick_slab")
    if not (np.isfinite(pane.n) and 1.0 < pane.n < 5.0):
        raise SceneError(f"non-physical pane refractive index n = {pane.n}; use 1 < n < 5 (glass is about 1.5)")
    u, v, n = pane.axes()
    hu, hv = 0.5 * float(pane.size[0]), 0.5 * float(pane.size[1])
    c = np.asarray(pane.center, float)
    if pane.model == "single":
        return [(_rect_matrix(c, u, v, hu, hv), n)]
    t = float(pane.thickness_m)
    if not (np.isfinite(t) and t > 0):
        raise SceneError(f"pane model {pane.model} needs thickness > 0, got {t} m")
    front = _rect_matrix(c + 0.5 * t * n, u, v, hu, hv)
    back = _rect_matrix(c - 0.5 * t * n, -u, v, hu, hv)  # cross(-u, v) = -n
    return [(front, n), (back, -n)]


def build_scene_dict(
    mi,
    camera: CameraSpec,
    pane: PaneSpec,
    layers: list[LayerPlane] = (),
    *,
    integrator: dict[str, Any] | None = None,
    spp: int = 4,
    seed: int = 0,
    sampler: str = "independent",
    polarizer_deg: float | None = None,
    film_size: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """Mitsuba scene dict for ``mi.load_dict`` (a variant must be set).

    Args:
        mi: the mitsuba module (variant already set).
        camera, pane, layers: geometry records.
        integrator: integrator dict (default: ``stokes`` around ``path``, max_depth 16).
        spp, seed, sampler: sampling settings.
        polarizer_deg: if given, Mitsuba's ``polarizer`` BSDF (its own ``theta``
            = 0) on a rectangle 1 mm in front of the camera whose local x axis
            is turned by this angle from image +x toward image up: it passes
            phi = +angle in the project convention (pinned by a test; turning
            the BSDF's ``theta`` parameter instead passes phi = -theta).
        film_size: override (W, H) of the film.

    Returns:
        dict ready for ``mi.load_dict``.
    """
    T = mi.ScalarTransform4f
    f, r, u = camera.frame()
    W, H = film_size if film_size is not None else (camera.width, camera.height)
    d: dict[str, Any] = {
        "type": "scene",
        "sensor": {
            "type": "perspective",
            "fov": float(np.degrees(camera.fovx_rad)),
            "fov_axis": "x",
            "near_clip": 1e-4,
            "far_clip": 1e5,
            "to_world": T().look_at(origin=list(map(float, camera.position)), target=list(map(float, camera.look_at)), up=list(map(float, camera.up))),
            "film": {"type": "hdrfilm", "width": int(W), "height": int(H), "rfilter": {"type": "box"}, "pixel_format": "luminance"},
            "sampler": {"type": sampler, "sample_count": int(spp), "seed": int(seed)},
        },
        "integrator": integrator if integrator is not None else {"type": "stokes", "inner": {"type": "path", "max_depth": 16, "rr_depth": 1000}},
    }
    for i, (m, _) in enumerate(pane_interfaces(pane)):
        d[f"pane_{i}"] = {
            "type": "rectangle",
            "to_world": T(m.tolist()),
            "bsdf": {"type": "dielectric", "int_ior": float(pane.n), "ext_ior": 1.0},
        }
    for k, layer in enumerate(layers):
        tex = np.asarray(layer.texture, dtype=np.float32)
        if tex.ndim != 2:
            raise SceneError(f"layer {layer.name}: texture must be (H, W), got shape {tex.shape}")
        if not np.all(np.isfinite(tex)) or float(tex.min(initial=0.0)) < 0:
            raise SceneError(f"layer {layer.name}: texture must be finite and >= 0 (min {np.nanmin(tex)})")
        m = _rect_matrix(layer.center, _unit(layer.u_axis, "layer u"), _unit(layer.v_axis, "layer v"), *map(float, layer.half_size), normal=layer.normal)
        # rectangle uv: u = (x+1)/2 along +x, v = (y+1)/2 along +y; the bitmap's row 0
        # is looked up at v = 0, so flip the rows to put row 0 at +v_axis (top).
        mask = layer.side_mask()
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": 0.0}
        if mask is not None and mask.min() < 1.0:
            tex = tex * mask.astype(np.float32)
            opac = np.ascontiguousarray(mask[::-1, :, None].astype(np.float32))
            bsdf = {"type": "mask", "opacity": {"type": "bitmap", "data": mi.TensorXf(opac), "raw": True, "filter_type": "nearest", "wrap_mode": "clamp"}, "bsdf": bsdf}
        data = np.ascontiguousarray(tex[::-1, :, None])
        d[f"layer_{k}_{layer.name}"] = {
            "type": "rectangle",
            "to_world": T(m.tolist()),
            "bsdf": bsdf,
            "emitter": {"type": "area", "radiance": {"type": "bitmap", "data": mi.TensorXf(data), "raw": True, "filter_type": "nearest", "wrap_mode": "clamp"}},
        }
    if polarizer_deg is not None:
        dist = 1e-3
        side = 4.0 * dist * np.tan(0.5 * camera.fovx_rad) + 1e-3
        c = np.asarray(camera.position, float) + dist * f
        ang = np.radians(float(polarizer_deg))
        # rectangle facing the camera (normal -f), its local x rotated by the angle about f
        ax = np.cos(ang) * r + np.sin(ang) * u
        ay = np.cross(-f, ax)
        d["polarizer"] = {
            "type": "rectangle",
            "to_world": T(_rect_matrix(c, ax, ay, side, side).tolist()),
            "bsdf": {"type": "polarizer", "theta": 0.0},
        }
    return d


def specs_from_scene(scene, n: float | None = None) -> tuple[CameraSpec, PaneSpec]:
    """Camera and pane records of a :class:`generator.scene.SceneConfig`.

    The pane's ``pane_plane()`` is its FRONT surface (as in the analytic tier);
    slabs extend ``thickness`` behind it, so the mid-plane is shifted.

    Args:
        scene: the scene.
        n: refractive index to use (default: ``scene.pane.index(550 nm)``).
    """
    cam = scene.camera_model()
    plane = scene.pane_plane()
    nrm = _unit(plane.normal, "pane normal")
    e_w, _ = scene.pane_axes()
    idx = float(scene.pane.index(550.0) if n is None else n)
    t = scene.pane.thickness_m if scene.pane.model != "single" else 0.0
    center = np.asarray(plane.point, float) - 0.5 * t * nrm
    camera = CameraSpec(
        int(cam.width), int(cam.height), float(cam.fov_x_rad),
        tuple(map(float, cam.position)), tuple(map(float, cam.position + cam.forward)), tuple(map(float, cam.up)),
    )
    pane = PaneSpec(scene.pane.model, idx, tuple(map(float, center)), tuple(map(float, nrm)), tuple(map(float, scene.pane.size_m)), t, float(scene.pane.absorption_per_m), tuple(map(float, e_w)))
    return camera, pane


def render_stokes_image(mi, scene_dict: dict, spp: int, seed: int) -> np.ndarray:
    """Render a scene dict with the ``stokes`` integrator; Stokes (3, H, W) float64, camera frame.

    Mono variants give identical R, G, B channels; spectral variants give sRGB
    channels, combined here with the Rec. 709 luminance weights.
    """
    seed = int(seed) % (2**32)  # Mitsuba seeds are 32-bit; derived seeds (group seed x a prime + offsets) may exceed it
    if isinstance(scene_dict.get("sensor"), dict) and isinstance(scene_dict["sensor"].get("sampler"), dict):
        scene_dict = {**scene_dict, "sensor": {**scene_dict["sensor"], "sampler": {**scene_dict["sensor"]["sampler"], "seed": int(scene_dict["sensor"]["sampler"].get("seed", 0)) % (2**32)}}}
    sc = mi.load_dict(scene_dict)
    img = np.array(mi.render(sc, seed=seed, spp=int(spp)), dtype=np.float64)
    # film channels (fixed layout of the stokes integrator): Y, S0.RGB, S1.RGB, S2.RGB, S3.RGB
    lum = np.array([0.2126, 0.7152, 0.0722])
    s = np.stack([img[..., 1 + 3 * i : 4 + 3 * i] @ lum for i in range(3)])
    return np.nan_to_num(s, nan=0.0, posinf=0.0, neginf=0.0)
