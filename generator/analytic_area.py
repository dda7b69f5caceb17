"""Area-sampled analytic tier: paper Eq. (1)-(2) integrated over each pixel's area (``--supersample K``).

The analytic tier evaluates each layer at one point per pixel, the pixel centre's ray.  The path tracer's
pixel (the full tier, box pixel filter) is the mean over the pixel's area of what each ray sees, and each
ray reads the layers as the textures the full tier hands to Mitsuba (the content rasterized at the texel
centres, looked up nearest-texel, the single interface's T plane enlarged by whole texels).  Where each
pixel's footprint on a layer falls inside one texel the two agree; where refraction or a steep pane
spreads it over texel edges they do not (the planner's sampling term, :mod:`generator.planner_footprint`).

This tier takes ``K x K`` stratified rays per pixel (the centres of the ``K x K`` cells of the pixel) and
evaluates the analytic pane model on each (Fresnel coefficients, refraction and the layer coordinates at
that ray: :func:`generator.analytic.analytic_maps` at a sub-pixel position).  Each ray's layer value is
the exact mean of the full tier's nearest-texel texture over the ray's cell (its footprint from the
coordinate gradients between neighbouring pixels divided by K, taken as the axis-aligned rectangle of the
same area in texel space, integrated by a summed-area table: :func:`generator.planner_footprint._box_mean`),
with the same clipping as :func:`generator.planner_footprint.footprint_stokes` (a layer plane that ends, an
R point beyond the pane, a T plane crossed before the pane, the R plane seen directly where it stands in
front of the pane).  The Stokes images are averaged with equal weights (the box pixel filter).  Spectral:
the same per wavelength band, response-weighted.  As K grows the cells shrink, the footprint's affine
approximation and the Fresnel variation inside a cell vanish, and the image converges to the path tracer's
expected pixel without Monte Carlo noise.  ``prefilter=False`` reads one texel per ray instead (plain
stratified point sampling): it converges to the same limit, as 1 / K at texel edges, and serves as the
independent oracle of the area integral.

Cost: K^2 evaluations of the pane maps per band (computed once per ray position and reused for every frame
of a batch of :data:`FRAME_BATCH`).  The ground-truth layers (``T``, ``R``) are the same area means of the
layer values (T band-weighted).
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["area_frames", "area_terms", "SUPERSAMPLE_MAX", "FRAME_BATCH"]

log = logging.getLogger(__name__)

SUPERSAMPLE_MAX = 64
"""Largest K accepted (K^2 = 4096 rays per pixel)."""
FRAME_BATCH = 16
"""Frames evaluated together per pass over the ray positions (their accumulators are held in memory)."""


def area_frames(scene, times, supersample: int, bands: list[tuple[float, float]] | None = None, prefilter: bool = True) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Area-sampled frames at ``times``: [(Stokes (3, H, W), L_T, L_R)], the mean over ``supersample`` x
    ``supersample`` stratified rays per pixel.

    ``bands``: [(wavelength nm, weight)] summing to 1; default mono at 550 nm.  ``prefilter``: each ray's
    value the box mean over its cell (the tier); False: one nearest texel per ray (the oracle).
    """
    from generator.analytic import analytic_maps, frame_stokes, layer_planes
    from generator.layers import LayerContent
    from generator.planner_footprint import _box_mean, _nearest, _r_behind_pane, _r_plane_in_front_xy, _t_plane_in_front
    from generator.tiers_mitsuba import DEFAULT_BANDS, DEFAULT_RESPONSE, _bands_for, _texture, single_interface_t_scale, texture_grid
    from polinfra.errors import ConfigError

    K = int(supersample)
    if not (1 <= K <= SUPERSAMPLE_MAX):
        raise ConfigError(f"--supersample {supersample!r} must be an integer from 1 to {SUPERSAMPLE_MAX} (rays per pixel side)")
    bands = bands or [(550.0, 1.0)]
    H, W = scene.camera.height, scene.camera.width
    tc = LayerContent(scene.layers.transmission, (H, W))
    rc = LayerContent(scene.layers.reflection, (H, W))
    t_plane, r_plane = layer_planes(scene)
    indices, _, _ = _bands_for(scene, True, DEFAULT_BANDS, DEFAULT_RESPONSE)  # the full tier's T plane (as the spectral reference)
    t_scale = single_interface_t_scale(scene, t_plane, indices, tc.extent)
    sx, sy = texture_grid(tc, t_scale)[1]
    ext_t, ext_r = (tc.extent * sx, tc.extent * sy), rc.extent
    times = [float(t) for t in times]
    texs = [(_texture(tc, t, t_scale), _texture(rc, t)) for t in times]
    S_acc = [np.zeros((3, H, W)) for _ in times]
    T_acc = [np.zeros((H, W)) for _ in times]
    R_acc = [np.zeros((H, W)) for _ in times]
    wk = 1.0 / (K * K)

    def look(tex, ext, X, Y):
        return _box_mean(tex, ext, X, Y, 1.0 / K) if prefilter else _nearest(tex, ext, X, Y)

    for j in range(K):
        for i in range(K):
            sub = ((i + 0.5) / K, (j + 0.5) / K)
            t_front = _t_plane_in_front(scene, t_plane, sub)
            occ, Xo, Yo = _r_plane_in_front_xy(scene, r_plane, ext_r, sub)
            behind = None
            for wl, wb in bands:
                m = analytic_maps(scene, float(wl), sub)
                if behind is None:  # the R point does not depend on the band
                    behind = _r_behind_pane(scene, r_plane, *m.r_xy)
                w = wb * wk
                for n, (tex_t, tex_r) in enumerate(texs):
                    L_T = look(tex_t, ext_t, *m.t_xy)
                    L_T[t_front] = 0.0
                    L_R = look(tex_r, ext_r, *m.r_xy)
                    L_R[behind] = 0.0
                    L_G = look(tex_r, ext_r, *m.g_xy) if m.g_xy is not None else None
                    S = np.nan_to_num(frame_stokes(m, L_T, L_R, L_G), nan=0.0, posinf=0.0, neginf=0.0)
                    if occ.any():
                        S[0][occ] = look(tex_r, ext_r, Xo, Yo)[occ]
                        S[1][occ] = 0.0
                        S[2][occ] = 0.0
                    S_acc[n] += w * S
                    T_acc[n] += w * L_T
                    R_acc[n] += w * L_R
    return [(S_acc[n], T_acc[n], R_acc[n]) for n in range(len(times))]


def area_terms(scene, subpixels: int = 2) -> tuple[float, float]:
    """(sampling term, area term), p99 of the worst case over the polarizer angles.

    Sampling term: the analytic point sample against the path tracer's expected pixel
    (:func:`generator.planner_footprint.footprint_stokes` on the ``subpixels`` finer grid).  Area term: the
    area-sampled analytic tier with one ray per pixel (:func:`area_frames`, ``supersample`` 1) against
    the same with 2 x 2 rays (the footprint computed on the 2 x 2 finer grid: the same estimate, so it is
    reused when ``subpixels`` is 2), the distance between K and 2K rays per side that the planner turns
    into the area-sampled tier's error at K.
    """
    from generator.planner_footprint import PHIS, footprint_stokes
    from polphysics.stokes import polarizer_intensity

    def p99(A, B):
        return float(np.percentile(np.max([np.abs(polarizer_intensity(*A, p) - polarizer_intensity(*B, p)) for p in PHIS], axis=0), 99))

    S_point, S_box = footprint_stokes(scene, 0.0, subpixels)
    S_2 = S_box if int(subpixels) == 2 else area_frames(scene, [0.0], 2)[0][0]
    S_1 = area_frames(scene, [0.0], 1)[0][0]
    return p99(S_point, S_box), p99(S_1, S_2)
