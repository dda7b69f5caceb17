"""The analytic tier's sampling gap: what the path tracer's pixel sees that a point sample does not.

The analytic (and maps) tier evaluates each layer at ONE point per pixel, the pixel centre's ray,
with the content sampled continuously (bilinear texture, sprites tested at the exact point).  The
path tracer (the full tier) sees the layers as textures rasterized at the texel centres, looked up
nearest-texel, averaged over the pixel's area (box filter), and clipped where a layer plane ends or
the R point lies beyond the pane.  The two agree where a pixel's footprint on the layer falls inside
one texel (a straight view: texels are laid at the pixel pitch) and disagree where it straddles texel
edges of contrasted content: a sub-texel shift of T through a thick slab or a single interface's
refraction, a sprite's hard edge, a layer plane that ends inside the view.

:func:`footprint_stokes` computes the path tracer's expected pixel in closed form, without Monte
Carlo: the pane maps on a ``K x K`` finer grid (sub-pixel rays), each ray's layer value the exact
mean of the same nearest-texel textures the full tier hands to Mitsuba over the ray's cell (a
summed-area table), zero where the full tier sees no layer (a layer plane that ends, an R point
beyond the pane, a T plane crossed before the pane), the R layer seen directly where its
plane stands between the camera and the pane, and the Stokes images averaged over each pixel's
``K x K`` rays.  The
planner's sampling term is the error measure between it and the analytic image.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

__all__ = ["footprint_stokes", "sampling_term", "SUBPIXELS"]

log = logging.getLogger(__name__)

PHIS = np.deg2rad([0.0, 45.0, 90.0, 135.0])
"""Polarizer angles of the error measure (as in the planner and `polspike bench tradeoff`)."""
SUBPIXELS = 2
"""Sub-pixel rays per side (K), each integrating its cell exactly: K = 1, 2, 4 agree to < 1 % on the shipped
scenes and the sampled ones, except where the R plane's edge crosses a pixel (K = 2 resolves it to the
path tracer's noise)."""


def _texel_coords(tex_shape: tuple[int, int], ext, X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Continuous texel coordinates (col, row): texel k spans [k, k + 1], row 0 = top; ``ext``: the plane's
    extent in view coordinates, one number or (x, y).
    """
    th, tw = tex_shape
    ex, ey = (ext, ext) if np.isscalar(ext) else ext
    return (X / ex + 0.5) * tw, (Y / ey + 0.5) * th


def _nearest(tex: np.ndarray, ext: float, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Nearest-texel value of ``tex`` (row 0 = top) spanning view coordinates [-ext/2, ext/2]^2; 0 off the plane."""
    th, tw = tex.shape
    with np.errstate(invalid="ignore"):
        c, r = (np.floor(v) for v in _texel_coords(tex.shape, ext, X, Y))
    ok = np.isfinite(c) & np.isfinite(r) & (c >= 0) & (c < tw) & (r >= 0) & (r < th)
    out = np.zeros(X.shape, np.float64)
    out[ok] = tex[r[ok].astype(np.int64), c[ok].astype(np.int64)]
    return out


def _box_mean(tex: np.ndarray, ext: float, X: np.ndarray, Y: np.ndarray, cell: float = 1.0) -> np.ndarray:
    """Mean of the nearest-texel texture over each sub-pixel ray's footprint, exactly (summed-area table).

    ``X``, ``Y``: (h, w) view coordinates of a grid of rays.  A ray's footprint is the cell between its
    neighbours (half a step each way, from the grid's gradients; ``cell`` times that on each side), taken
    as the axis-aligned rectangle of the same area in texel space; a piecewise-constant texture integrates
    over it exactly with the summed-area table interpolated bilinearly (0 off the plane).
    """
    th, tw = tex.shape
    c, r = _texel_coords(tex.shape, ext, X, Y)
    c = np.nan_to_num(c, nan=-1e9, posinf=-1e9, neginf=-1e9)
    r = np.nan_to_num(r, nan=-1e9, posinf=-1e9, neginf=-1e9)
    (dc_y, dc_x), (dr_y, dr_x) = np.gradient(c), np.gradient(r)
    wc = np.abs(dc_x) + np.abs(dc_y)
    wr = np.abs(dr_x) + np.abs(dr_y)
    area = np.abs(dc_x * dr_y - dc_y * dr_x)
    k = np.sqrt(area / np.maximum(wc * wr, 1e-300))
    wc, wr = np.clip(wc * k * cell, 1e-6, None), np.clip(wr * k * cell, 1e-6, None)
    sat = np.zeros((th + 1, tw + 1))
    sat[1:, 1:] = np.cumsum(np.cumsum(tex, axis=0), axis=1)

    def I(cc, rr):  # integral of the texture over [0, cc] x [0, rr], bilinear in the SAT (exact for texels)
        cc, rr = np.clip(cc, 0.0, tw), np.clip(rr, 0.0, th)
        c0, r0 = np.minimum(np.floor(cc).astype(np.int64), tw - 1), np.minimum(np.floor(rr).astype(np.int64), th - 1)
        fc, fr = cc - c0, rr - r0
        return ((1 - fr) * ((1 - fc) * sat[r0, c0] + fc * sat[r0, c0 + 1]) + fr * ((1 - fc) * sat[r0 + 1, c0] + fc * sat[r0 + 1, c0 + 1]))

    c0, c1, r0, r1 = c - 0.5 * wc, c + 0.5 * wc, r - 0.5 * wr, r + 0.5 * wr
    return (I(c1, r1) - I(c0, r1) - I(c1, r0) + I(c0, r0)) / (wc * wr)


def _r_behind_pane(scene, r_plane, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Rays whose R point lies on the far side of the pane's front face (clipped, black, in the full tier)."""
    P = r_plane.center + (2 * r_plane.view_half_w * X)[..., None] * r_plane.right - (2 * r_plane.view_half_h * Y)[..., None] * r_plane.up
    pp = scene.pane_plane()
    nrm = np.asarray(pp.normal, float) / np.linalg.norm(pp.normal)
    with np.errstate(invalid="ignore"):
        return ~(((P - np.asarray(pp.point, float)) @ nrm) > 0)


def _t_plane_in_front(scene, t_plane, subpixel: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """Camera rays that cross the T layer's plane before the pane (a grazing pane crosses it): that part of
    the plane is clipped, and the transmitted ray, already past the plane, meets no T (black in the full tier).
    ``subpixel``: the rays' position inside each pixel.
    """
    from polphysics.geometry import Plane, incidence_geometry, intersect_plane

    cam = scene.camera_model()
    geo = incidence_geometry(cam, scene.pane_plane(), subpixel)
    t_t, _ = intersect_plane(cam.position + np.zeros_like(geo["d"]), geo["d"], Plane(t_plane.center, t_plane.normal))
    with np.errstate(invalid="ignore"):
        return np.isfinite(t_t) & (t_t > 0) & (t_t < geo["t"])


def _r_plane_in_front_xy(scene, r_plane, ext: float, subpixel: tuple[float, float] = (0.5, 0.5)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera rays (at ``subpixel`` inside each pixel) that meet the R layer's plane before the pane (its part
    on the camera side of a steeply tilted pane stands in the view): mask and the rays' view coordinates on it.
    """
    from polphysics.geometry import Plane, incidence_geometry, intersect_plane

    cam = scene.camera_model()
    geo = incidence_geometry(cam, scene.pane_plane(), subpixel)
    t_r, pts = intersect_plane(cam.position + np.zeros_like(geo["d"]), geo["d"], Plane(r_plane.center, r_plane.normal))
    rel = pts - r_plane.center
    X = rel @ r_plane.right / (2 * r_plane.view_half_w)
    Y = -(rel @ r_plane.up) / (2 * r_plane.view_half_h)
    with np.errstate(invalid="ignore"):
        on = np.isfinite(t_r) & (t_r > 0) & (t_r < geo["t"]) & (np.abs(X) <= 0.5 * ext) & (np.abs(Y) <= 0.5 * ext)
    return on, X, Y


def _r_plane_in_front(scene, r_plane, tex_r: np.ndarray, ext: float) -> tuple[np.ndarray, np.ndarray]:
    """Mask of :func:`_r_plane_in_front_xy` and the R radiance seen directly there (unpolarized), each ray's
    value the mean over its cell.
    """
    on, X, Y = _r_plane_in_front_xy(scene, r_plane, ext)
    return on, _box_mean(tex_r, ext, X, Y)


def footprint_stokes(scene, t_s: float = 0.0, subpixels: int = SUBPIXELS) -> tuple[np.ndarray, np.ndarray]:
    """(analytic Stokes, path tracer's expected Stokes), each (3, H, W), at time ``t_s``, mono at 550 nm.

    The second is the full tier's pixel without its Monte Carlo noise (see the module docstring).  A
    single interface's T plane is enlarged to catch the bent rays by padding the content's own texels with
    whole texels (:func:`generator.tiers_mitsuba.texture_grid`), to cover the indices the full tier renders
    with (a dispersive glass: the spectral bands', as the spectral reference).  Measured on bk7_single at
    80 x 50 (spectral, 2 x 1024 spp), the predicted difference map regresses on the path-traced one with
    slope 0.94-0.96.
    """
    from generator.analytic import analytic_maps, frame_stokes, layer_planes, sample_layers
    from generator.layers import LayerContent
    from generator.tiers_mitsuba import DEFAULT_BANDS, DEFAULT_RESPONSE, _bands_for, _texture, single_interface_t_scale, texture_grid

    H, W = scene.camera.height, scene.camera.width
    K = int(subpixels)
    tc = LayerContent(scene.layers.transmission, (H, W))
    rc = LayerContent(scene.layers.reflection, (H, W))
    m = analytic_maps(scene)
    S_point = frame_stokes(m, *sample_layers(m, tc, rc, t_s))

    fine = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=W * K, height=H * K))
    mf = analytic_maps(fine)  # pixel centres of the K x finer grid = the stratified sub-pixel rays
    t_plane, r_plane = layer_planes(scene)
    indices, _, _ = _bands_for(scene, True, DEFAULT_BANDS, DEFAULT_RESPONSE)
    t_scale = single_interface_t_scale(scene, t_plane, indices, tc.extent)
    tex_t, tex_r = _texture(tc, t_s, t_scale), _texture(rc, t_s)
    sx, sy = texture_grid(tc, t_scale)[1]
    L_T = _box_mean(tex_t, (tc.extent * sx, tc.extent * sy), *mf.t_xy)
    L_R = _box_mean(tex_r, rc.extent, *mf.r_xy)
    L_R[_r_behind_pane(scene, r_plane, *mf.r_xy)] = 0.0
    L_T[_t_plane_in_front(fine, t_plane)] = 0.0
    L_G = _box_mean(tex_r, rc.extent, *mf.g_xy) if mf.g_xy is not None else None
    S_fine = frame_stokes(mf, L_T, L_R, L_G)
    S_fine = np.nan_to_num(S_fine, nan=0.0, posinf=0.0, neginf=0.0)
    occ, L_direct = _r_plane_in_front(fine, r_plane, tex_r, rc.extent)
    if occ.any():
        S_fine[0][occ] = L_direct[occ]
        S_fine[1][occ] = 0.0
        S_fine[2][occ] = 0.0
    S_box = S_fine.reshape(3, H, K, W, K).mean(axis=(2, 4))
    return S_point, S_box


def sampling_term(scene, subpixels: int = SUBPIXELS) -> float:
    """p99 over pixels of the worst case over the polarizer angles of |analytic - path tracer's expected pixel|."""
    from polphysics.stokes import polarizer_intensity

    S_point, S_box = footprint_stokes(scene, 0.0, subpixels)
    worst = np.max([np.abs(polarizer_intensity(*S_point, p) - polarizer_intensity(*S_box, p)) for p in PHIS], axis=0)
    return float(np.percentile(worst, 99))

