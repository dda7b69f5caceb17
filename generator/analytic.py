"""Analytic tier: per-pixel pane coefficients from geometry and Fresnel, layers mixed by paper Eq. (1)-(2).

This is the paper's own pipeline made geometric: theta(p) and phi_perp(p) come
from the camera and pane (:mod:`polphysics.geometry`), the coefficients
from the pane model the scene names (:func:`polphysics.fresnel.pane_coefficients`),
and each frame's Stokes vector from the layer images
(:func:`polphysics.zeta.stokes_from_layers`).

What it models, and what it leaves out (stated in ``render.json``):
- reflection: the R layer seen by the mirrored camera through the pane point of
  each pixel; ``thick_slab`` adds the second-surface ghost, displaced by
  2 d tan(theta_t) along the pane in the plane of incidence, with weight G;
- transmission: the T layer where the transmitted ray lands.  ``single``: the
  ray refracts into the glass at the pane point (Snell, per pixel; the T layer
  lies inside the glass, as in the full tier), so the T image is displaced and
  magnified against the straight-ray view; slabs: the ray leaves the slab
  parallel to the camera ray, displaced laterally by the thickness (the exit
  point after the refracted path through the glass);
- the radiance compression 1/n^2 of a ``single`` interface is NOT applied
  (paper Eq. (1) omits it; :func:`polphysics.fresnel.radiance_scale`);
- the pane is treated as infinite (coverage is checked separately); layer
  occlusion and multiple reflections between layers are ignored.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from generator.layers import LayerContent, LayerPlane
from generator.scene import SceneConfig
from polphysics.fresnel import pane_coefficients
from polphysics.geometry import incidence_geometry, normalize, reflect_dir, refract_dir
from polphysics.zeta import stokes_from_layers

__all__ = ["PaneMaps", "analytic_maps", "layer_planes", "sample_layers", "frame_stokes", "spectral_frame", "MAP_CHANNELS", "ANALYTIC_MODELLED"]

MAP_CHANNELS = ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par")
"""Channels of ``maps.exr`` (angles in radians)."""

ANALYTIC_MODELLED = {
    "fresnel": "per-pixel incidence angle, pane model coefficients (paper Eq. (2))",
    "ghost": "thick_slab second-surface ghost displaced by 2 d tan(theta_t)",
    "transmitted_ray_offset": "single: ray refracted into the glass (Snell per pixel); slabs: lateral displacement of the transmitted ray",
    "radiance_compression_1_over_n2": False,
    "spectral": False,
    "pane_extent": "infinite (coverage checked)",
}


@dataclasses.dataclass
class PaneMaps:
    """Per-pixel pane response and layer sampling coordinates, all (H, W) float64.

    Coefficient maps: theta, phi_perp (radians), R_perp, R_par, T_perp, T_par
    (totals, ghost included), G_perp, G_par (ghost part of R).  Sampling
    coordinates (view fractions, see :mod:`generator.layers`): ``t_xy`` for the T
    layer, ``r_xy`` for the R layer, ``g_xy`` for the ghost (None without ghost).
    """

    theta: np.ndarray
    phi_perp: np.ndarray
    R_perp: np.ndarray
    R_par: np.ndarray
    T_perp: np.ndarray
    T_par: np.ndarray
    G_perp: np.ndarray
    G_par: np.ndarray
    t_xy: tuple[np.ndarray, np.ndarray]
    r_xy: tuple[np.ndarray, np.ndarray]
    g_xy: tuple[np.ndarray, np.ndarray] | None

    def channels(self) -> dict[str, np.ndarray]:
        """The ``maps.exr`` channels."""
        return {k: getattr(self, k) for k in MAP_CHANNELS}


def layer_planes(scene: SceneConfig) -> tuple[LayerPlane, LayerPlane]:
    """The T plane (facing the camera) and the R plane (facing the mirrored camera)."""
    cam = scene.camera_model()
    lt, lr = scene.layers.transmission, scene.layers.reflection
    t_plane = LayerPlane.facing(cam, lt.distance_m, lt.margin)
    vcam = cam.mirrored(scene.pane_plane())
    r_plane = LayerPlane.facing(vcam, scene.pane.distance_m + lr.distance_m, lr.margin)
    return t_plane, r_plane


def analytic_maps(scene: SceneConfig, wavelength_nm: float = 550.0, subpixel: tuple[float, float] = (0.5, 0.5)) -> PaneMaps:
    """Compute the analytic per-pixel pane maps of ``scene`` at one position inside each pixel
    (``subpixel``, fractions of a pixel from its top-left corner; the centre by default).
    """
    cam = scene.camera_model()
    plane = scene.pane_plane()
    geo = incidence_geometry(cam, plane, subpixel)
    n_idx = scene.pane.index(wavelength_nm)
    model = scene.pane.model
    co = pane_coefficients(geo["theta"], n_idx, model, scene.pane.thickness_m, scene.pane.absorption_per_m)
    t_plane, r_plane = layer_planes(scene)
    d, hit = geo["d"], geo["hit"]
    nrm = normalize(plane.normal)
    d_r = reflect_dir(d, nrm)
    t_origin = cam.position + np.zeros_like(d)
    t_dir = d
    g_xy = None
    if model == "single":
        # the transmitted ray bends into the glass at the pane point and stays in it (closed form for a plane)
        t_origin, t_dir = hit, refract_dir(d, nrm, n_idx)
    elif scene.pane.thickness_m > 0:
        d_t = refract_dir(d, nrm, n_idx)
        cos_t = np.clip(-np.sum(d_t * nrm, axis=-1, keepdims=True), 1e-6, 1.0)
        exit_pt = hit + scene.pane.thickness_m / cos_t * d_t
        t_origin = exit_pt
        if model == "thick_slab":
            tan_t = np.sqrt(np.maximum(1.0 - cos_t**2, 0.0)) / cos_t
            tangent = normalize(d - np.sum(d * nrm, axis=-1, keepdims=True) * nrm)
            g_origin = hit + 2.0 * scene.pane.thickness_m * tan_t * tangent
            g_xy = r_plane.uv(g_origin, d_r)
    if model != "thick_slab":
        co["G_perp"] = np.zeros_like(co["R_perp"])
        co["G_par"] = np.zeros_like(co["R_par"])
    return PaneMaps(
        theta=geo["theta"],
        phi_perp=geo["phi_perp"],
        t_xy=t_plane.uv(t_origin, t_dir),
        r_xy=r_plane.uv(hit, d_r),
        g_xy=g_xy,
        **{k: co[k] for k in ("R_perp", "R_par", "T_perp", "T_par", "G_perp", "G_par")},
    )


def sample_layers(maps: PaneMaps, t_content: LayerContent, r_content: LayerContent, t_s: float):
    """Ground-truth layer images at time ``t_s``: (L_T, L_R, L_R_ghost or None), each (H, W)."""
    L_T = t_content.sample(t_s, *maps.t_xy)
    L_R = r_content.sample(t_s, *maps.r_xy)
    L_G = r_content.sample(t_s, *maps.g_xy) if maps.g_xy is not None else None
    return L_T, L_R, L_G


def frame_stokes(maps: PaneMaps, L_T, L_R, L_G=None) -> np.ndarray:
    """Stokes (3, H, W) of the light in front of the polarizer (Stokes form of paper Eq. (1))."""
    return stokes_from_layers(
        L_T, L_R, maps.R_perp, maps.R_par, maps.T_perp, maps.T_par, maps.phi_perp,
        L_R_ghost=L_G, G_perp=maps.G_perp if L_G is not None else None, G_par=maps.G_par if L_G is not None else None,
    )


def spectral_frame(bands: list[tuple[float, PaneMaps]], t_content: LayerContent, r_content: LayerContent, t_s: float):
    """Response-weighted sum over wavelength bands ``[(weight, maps at the band's index)]`` of a dispersive
    pane: Stokes (3, H, W) and the weighted ground-truth layers (L_T, L_R) (T refracts per band).
    """
    S = 0.0
    L_T = 0.0
    L_R = 0.0
    for w, m in bands:
        lt, lr, lg = sample_layers(m, t_content, r_content, t_s)
        S = S + w * frame_stokes(m, lt, lr, lg)
        L_T = L_T + w * lt
        L_R = L_R + w * lr
    return S, L_T, L_R
