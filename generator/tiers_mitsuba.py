"""Render tiers backed by Mitsuba 3: ``maps`` and ``full``.

``maps``: the pane's per-pixel polarized response is rendered ONCE per scene by
the deterministic two-lobe tracer (:mod:`generator.mitsuba_integrator`), then
the 2-D layer video is mixed per frame exactly as in the analytic tier
(:func:`generator.analytic.frame_stokes`, Stokes form of paper Eq. (1)-(2)).
Noise-free; agrees with the analytic tier for ``single`` to ~3e-5.

``full``: Mitsuba path-traces the 3-D scene (pane interfaces plus the T and R
layers as textured area emitters) with the ``stokes`` integrator around
``path`` per keyframe; static scenes are rendered once; frames between
keyframes are linear interpolations of the Stokes images.  Its error against
the analytic tier is Monte Carlo noise (falls as spp^-1/2; tested).

Spectral: Mitsuba's ``dielectric`` has one real index per scene, so dispersion
is rendered by band quadrature: ``n_bands`` wavelength bands over 400-700 nm,
each rendered with the glass's Sellmeier index n(lambda) and weighted by the
sensor response (default CIE 1931 Y via colour-science; ``flat``; or a CSV of
``wavelength_nm,response``).  The layers are grey (wavelength-flat), so this
is the exact spectral integral up to the quadrature.  A scene without a named
glass has no dispersion and renders mono whatever the flag says (recorded in
render.json).

Stokes convention: Mitsuba's ``stokes`` integrator frame (x_ref = d x up =
image right, S2 > 0 toward image up) equals the project convention; pinned in
``tests/generator/test_mitsuba_full.py`` with Mitsuba's own ``polarizer``.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
import time
from pathlib import Path

import numpy as np

from generator.mitsuba_scene import render_stokes_image
from polinfra.errors import BackendUnavailableError, ConfigError

__all__ = [
    "render_pane_maps",
    "FullRenderer",
    "render_stokes_image",
    "sensor_response",
    "spectral_bands",
    "DEFAULT_RESPONSE",
    "DEFAULT_BANDS",
]

log = logging.getLogger(__name__)

DEFAULT_RESPONSE = "cie_y"
"""Default sensor spectral response: CIE 1931 2-degree photopic luminosity y-bar."""

DEFAULT_BANDS = 8
"""Wavelength bands of the spectral quadrature (400-700 nm)."""

MAX_SUB = 4
"""Largest sub-pixel grid of the maps tier (spp is clamped to MAX_SUB^2 = 16 rays per pixel):
the pane response is smooth, so more rays only refine pane-edge pixels."""

MAX_DEPTH_FULL = 24
"""Path depth of the full tier (slab interreflections plus the emitter hit)."""


def sensor_response(spec: str, wavelengths_nm: np.ndarray) -> np.ndarray:
    """Sensor spectral response at ``wavelengths_nm`` (relative, >= 0).

    Args:
        spec: ``"cie_y"`` (CIE 1931 2-degree y-bar, colour-science), ``"flat"``,
            or a path to a CSV with columns ``wavelength_nm, response``
            (header optional), linearly interpolated, 0 outside.
        wavelengths_nm: (B,) wavelengths.

    Returns:
        (B,) float64 response.
    """
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if spec == "flat":
        return np.ones_like(wl)
    if spec == "cie_y":
        import colour

        cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
        return np.interp(wl, cmfs.wavelengths, cmfs.values[:, 1], left=0.0, right=0.0)
    p = Path(spec)
    if not p.is_file():
        raise ConfigError(f"sensor response {spec!r} is neither cie_y, flat nor a CSV file")
    rows = []
    with open(p, newline="") as fh:
        for row in csv.reader(fh):
            try:
                rows.append((float(row[0]), float(row[1])))
            except (ValueError, IndexError):
                continue
    if len(rows) < 2:
        raise ConfigError(f"sensor response CSV {p} needs >= 2 rows of 'wavelength_nm,response'")
    a = np.array(sorted(rows))
    if np.any(a[:, 1] < 0) or not np.all(np.isfinite(a)):
        raise ConfigError(f"sensor response CSV {p} has negative or non-finite values")
    return np.interp(wl, a[:, 0], a[:, 1], left=0.0, right=0.0)


def spectral_bands(n_bands: int = DEFAULT_BANDS, response: str = DEFAULT_RESPONSE, lo_nm: float = 400.0, hi_nm: float = 700.0) -> tuple[np.ndarray, np.ndarray]:
    """Band centres (nm) and normalised weights (sum 1) of the spectral quadrature."""
    if n_bands < 1:
        raise ConfigError(f"n_bands must be >= 1, got {n_bands}")
    edges = np.linspace(lo_nm, hi_nm, n_bands + 1)
    centers = 0.5 * (edges[1:] + edges[:-1])
    fine = np.linspace(lo_nm, hi_nm, 20 * n_bands + 1)
    r = sensor_response(response, fine)
    w = np.array([np.trapezoid(r[(fine >= a) & (fine <= b)], fine[(fine >= a) & (fine <= b)]) for a, b in zip(edges[:-1], edges[1:])])
    if w.sum() <= 0:
        raise ConfigError(f"sensor response {response!r} is zero over {lo_nm}-{hi_nm} nm")
    return centers, w / w.sum()


def _bands_for(scene, spectral: bool, n_bands: int, response: str) -> tuple[list[float], list[float], str]:
    """(indices, weights, note) of the render: one band unless dispersion needs more."""
    if spectral and scene.pane.glass is not None:
        wl, w = spectral_bands(n_bands, response)
        return [scene.pane.index(float(x)) for x in wl], list(map(float, w)), f"{n_bands} bands 400-700 nm, {scene.pane.glass} Sellmeier index, response {response}"
    if spectral:
        return [scene.pane.index(550.0)], [1.0], "requested, but the pane has a fixed index (no dispersion): rendered mono"
    return [scene.pane.index(550.0)], [1.0], False


def _resolve(opts, need_jit: bool):
    from generator.mitsuba_backend import load_mitsuba, resolve_backend

    be = resolve_backend(getattr(opts, "variant", "auto") or "auto", spectral=False)
    if need_jit and not be.vectorized:
        raise BackendUnavailableError(
            f"tier 'maps' needs a JIT Mitsuba variant (llvm or cuda); {be.variant} was selected ({'; '.join(be.fallbacks) or 'forced'}); install libllvm19 or use --tier analytic"
        )
    return be, load_mitsuba()


# --------------------------------------------------------------------------- maps tier
def _spectral_opts(opts, response: str | None, n_bands: int | None) -> tuple[str, int]:
    """Sensor response and band count: explicit arguments, else the render options, else the defaults."""
    r = response or getattr(opts, "response", None) or DEFAULT_RESPONSE
    b = int(n_bands or getattr(opts, "n_bands", None) or DEFAULT_BANDS)
    return str(r), b


def render_pane_maps(scene, opts, info: dict, *, response: str | None = None, n_bands: int | None = None, progress=None):
    """Tier ``maps``: rendered per-pixel pane coefficients as a :class:`generator.analytic.PaneMaps`.

    The coefficient maps (R_perp, R_par, T_perp, T_par, G_perp, G_par, theta,
    phi_perp) come from the two-lobe tracer; the layer sampling coordinates
    come from the analytic geometry (the same camera, pane and layer planes).

    Args:
        scene: :class:`generator.scene.SceneConfig`.
        opts: :class:`generator.render.RenderOptions` (uses ``spp`` -> sub-pixel
            grid ``round(sqrt(spp))``^2 capped at :data:`MAX_SUB`^2, or 2x2 when
            ``opts.tier == "full"`` (maps.exr only), ``variant``, ``spectral``).
        info: dict updated in place with ``modelled``, ``variant``, ``spp``.
        response, n_bands: spectral quadrature (see :func:`spectral_bands`); default
            ``opts.response`` / ``opts.n_bands`` (CLI ``--response``), else CIE Y, 8 bands.

    Returns:
        PaneMaps with float64 (H, W) arrays.
    """
    from generator.analytic import analytic_maps
    from generator.mitsuba_integrator import pane_coefficients
    from generator.mitsuba_scene import build_scene_dict, specs_from_scene

    response, n_bands = _spectral_opts(opts, response, n_bands)
    be, mi = _resolve(opts, need_jit=True)
    spp = int(opts.spp or scene.render.spp)
    sub = min(MAX_SUB, max(1, int(round(math.sqrt(spp)))))
    if getattr(opts, "tier", "maps") == "full":
        sub = min(sub, 2)  # the full tier only needs maps.exr and the GT sampling grid
    spectral = bool(scene.render.spectral if opts.spectral is None else opts.spectral)
    idx, wts, note = _bands_for(scene, spectral, n_bands, response)
    t0 = time.perf_counter()
    acc: dict[str, np.ndarray] = {}
    for b, (n_b, w_b) in enumerate(zip(idx, wts)):
        cam, pane = specs_from_scene(scene, n=n_b)
        msc = mi.load_dict(build_scene_dict(mi, cam, pane, []))
        # progress in ray chunks over all bands (the tracer reports chunks of one band)
        sub_prog = None if progress is None else (lambda d, t, b=b: progress(b * t + d, len(idx) * t))
        m = pane_coefficients(mi, msc, pane.axes()[2], cam.up, cam.width, cam.height, model=pane.model, n=n_b, sub=sub, absorption_per_m=pane.absorption_per_m, progress=sub_prog)
        for k in ("S_R", "S_R1", "S_T", "theta", "coverage", "phi_perp_geometric"):
            acc[k] = acc.get(k, 0.0) + w_b * m[k]
    out = _coefficients_from_stokes(acc)
    base = analytic_maps(scene)
    base.theta, base.phi_perp = out["theta"], out["phi_perp"]
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        setattr(base, k, out[k])
    if scene.pane.model == "thick_slab":
        base.G_perp, base.G_par = out["G_perp"], out["G_par"]
    else:
        # thin slab / single: no displaced ghost, everything rides on the primary image
        base.G_perp, base.G_par = np.zeros_like(out["R_perp"]), np.zeros_like(out["R_par"])
    cov = float(acc["coverage"].min())
    info["variant"] = be.variant
    info["spp"] = sub * sub
    info["modelled"] = {
        "fresnel": "Mitsuba dielectric BSDF Mueller matrices, both lobes per hit (deterministic two-lobe trace)",
        "subpixel_rays": f"{sub}x{sub} stratified per pixel (box filter)",
        "slab": "two dielectric interfaces with real thickness, incoherent interreflections to branch weight 1e-7" if scene.pane.model != "single" else False,
        "ghost": "thick_slab: second-surface part G from the trace, displaced as in the analytic tier" if scene.pane.model == "thick_slab" else False,
        "absorption": f"exp(-alpha L) per internal segment, alpha = {scene.pane.absorption_per_m} 1/m" if scene.pane.absorption_per_m > 0 else False,
        "radiance_compression_1_over_n2": False,
        "spectral": note,
        "pane_extent": f"finite rectangle {tuple(scene.pane.size_m)} m; min coverage {cov:.4f}",
        "layer_sampling": "analytic geometry (same camera, pane and planes)",
        "backend": be.to_dict(),
        "maps_render_s": round(time.perf_counter() - t0, 4),
    }
    if cov < 1.0:
        log.warning("maps tier: the pane covers only %.1f%% of some pixels; edges see the T layer unfiltered", 100 * cov)
    return base


def _coefficients_from_stokes(acc: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    from generator.mitsuba_integrator import stokes_to_coefficients

    S_R, S_T, S_R1 = acc["S_R"], acc["S_T"], acc["S_R1"]
    pol = np.hypot(S_R[1], S_R[2])
    phi = np.where(pol > 1e-7, np.mod(0.5 * np.arctan2(S_R[2], S_R[1]), np.pi), acc["phi_perp_geometric"])
    phi = np.where(phi >= np.pi, 0.0, phi)
    R_perp, R_par = stokes_to_coefficients(S_R, phi)
    T_perp, T_par = stokes_to_coefficients(S_T, phi)
    R1_perp, R1_par = stokes_to_coefficients(S_R1, phi)
    return {"theta": acc["theta"], "phi_perp": phi, "R_perp": R_perp, "R_par": R_par, "T_perp": T_perp, "T_par": T_par, "G_perp": R_perp - R1_perp, "G_par": R_par - R1_par}


# --------------------------------------------------------------------------- full tier
def _layer_plane_spec(plane, cam_forward, texture: np.ndarray, name: str, keep_side=None, scale: tuple[float, float] = (1.0, 1.0)):
    from generator.mitsuba_scene import LayerPlane as MiPlane

    return MiPlane(
        center=tuple(map(float, plane.center)),
        u_axis=tuple(map(float, plane.right)),
        v_axis=tuple(map(float, plane.up)),
        half_size=(float(plane.half_w * scale[0]), float(plane.half_h * scale[1])),
        texture=texture,
        name=name,
        normal=tuple(map(float, -np.asarray(cam_forward))),
        keep_side=keep_side,
    )


def layer_sides(scene):
    """Half-spaces the layers must stay in: R on the camera side of the pane's front face, T beyond its back face."""
    plane = scene.pane_plane()
    n = np.asarray(plane.normal, float) / np.linalg.norm(plane.normal)
    t = scene.pane.thickness_m if scene.pane.model != "single" else 0.0
    front = tuple(map(float, plane.point))
    back = tuple(map(float, np.asarray(plane.point) - (t + 1e-6) * n))
    return (back, tuple(map(float, -n))), (front, tuple(map(float, n)))


MAX_TEXTURE = 4096
"""Largest side of a layer texture handed to Mitsuba (enlarged T planes of a single interface)."""


def texture_grid(content, scale: float = 1.0) -> tuple[tuple[int, int], tuple[float, float]]:
    """Texture shape (rows, cols) and per-axis enlargement (x, y) of a layer plane ``scale`` times its content's.

    The content's own texels are kept and padded by a whole number of texels on each side (at least
    ``scale``, capped at :data:`MAX_TEXTURE`), so every texel of the enlarged plane IS a content texel
    (or its mirror): no resampling of the content onto a grid that does not line up with its own.
    """
    th, tw = content.tex_shape
    if scale <= 1.0:
        return (th, tw), (1.0, 1.0)

    def pad(n: int) -> int:
        return max(0, min(int(math.ceil(0.5 * n * (scale - 1.0) - 1e-9)), (MAX_TEXTURE - n) // 2))

    ph, pw = pad(th), pad(tw)
    return (th + 2 * ph, tw + 2 * pw), ((tw + 2 * pw) / tw, (th + 2 * ph) / th)


def _texture(content, t_s: float, scale: float = 1.0) -> np.ndarray:
    """Layer content on its whole plane (texture grid, row 0 = top), at time t.

    ``scale`` > 1 covers a plane about ``scale`` times larger than the content's own (:func:`texture_grid`:
    the content's texels padded by whole texels; the content continues mirrored beyond its edges, as in
    the analytic ground truth).
    """
    (th, tw), (sx, sy) = texture_grid(content, scale)
    X = ((np.arange(tw) + 0.5) / tw - 0.5) * content.extent * sx
    Y = ((np.arange(th) + 0.5) / th - 0.5) * content.extent * sy
    XX, YY = np.meshgrid(X, Y)
    return np.asarray(content.sample(t_s, XX, YY), dtype=np.float64)


def single_interface_t_scale(scene, t_plane, indices, content_extent: float) -> float:
    """How much larger the T plane must be to catch every camera ray refracted INTO the glass of a
    ``single`` interface (they bend toward the pane normal, so they leave a plane sized for
    straight rays: measured 25 % of the bk7_single view black before this).  1.0 for slabs
    (their rays exit parallel, displaced by less than the margin).
    """
    if scene.pane.model != "single":
        return 1.0
    from polphysics.geometry import incidence_geometry, normalize, refract_dir

    cam = scene.camera_model()
    plane = scene.pane_plane()
    need = 0.0
    for sub in ((0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (1.0, 0.0)):  # pixel corners bound the pixel footprints
        geo = incidence_geometry(cam, plane, subpixel=sub)
        for n in (min(indices), max(indices)):
            d_t = refract_dir(geo["d"], normalize(plane.normal), float(n))
            X, Y = t_plane.uv(geo["hit"], d_t)
            ok = np.isfinite(X) & np.isfinite(Y)
            if ok.any():
                need = max(need, 2.0 * float(np.max(np.abs(X[ok]))), 2.0 * float(np.max(np.abs(Y[ok]))))
    return max(1.0, 1.02 * need / content_extent)


def _layer_coverage_warnings(scene, tc, rc, t_scale: float = 1.0) -> list[str]:
    """Pixels whose T or R ray leaves its finite layer plane (black in the full tier; the analytic
    ground truth mirrors the texture there) or whose R point lies behind the pane.  ``t_scale``: the
    T plane's enlargement (a single interface's refracted rays land beyond the straight-ray view).
    """
    from generator.analytic import analytic_maps, layer_planes

    m = analytic_maps(scene)
    out = []
    for name, (X, Y), content, k in (("T", m.t_xy, tc, t_scale), ("R", m.r_xy, rc, 1.0)):
        sx, sy = texture_grid(content, k)[1]
        outside = (np.abs(X) > 0.5 * content.extent * sx) | (np.abs(Y) > 0.5 * content.extent * sy) | ~np.isfinite(X) | ~np.isfinite(Y)
        if outside.any():
            out.append(f"{name} layer plane does not cover {100 * outside.mean():.2f}% of the view; raise layers.{'transmission' if name == 'T' else 'reflection'}.margin")
    # R points on the far side of the pane's front face: clipped (black) in the full tier
    _, r_plane = layer_planes(scene)
    X, Y = m.r_xy
    P = r_plane.center + (2 * r_plane.view_half_w * X)[..., None] * r_plane.right - (2 * r_plane.view_half_h * Y)[..., None] * r_plane.up
    pp = scene.pane_plane()
    nrm = np.asarray(pp.normal, float) / np.linalg.norm(pp.normal)
    behind = ((P - np.asarray(pp.point, float)) @ nrm) <= 0
    if behind.any():
        out.append(
            f"R layer plane crosses the pane in {100 * behind.mean():.2f}% of the view (the full tier sees no reflection "
            "there, or R itself where the plane stands between the camera and the pane; the analytic tier draws the "
            "pane's mixture); raise layers.reflection.distance_m"
        )
    return out


class FullRenderer:
    """Tier ``full``: path-traced Stokes per keyframe, interpolated in between.

    Args:
        scene: :class:`generator.scene.SceneConfig`.
        opts: :class:`generator.render.RenderOptions` (``spp``, ``seed``,
            ``variant``, ``spectral``, ``keyframe_hz``; default keyframe rate =
            the frame rate, i.e. every frame path-traced).
        info: dict updated in place (``modelled``, ``variant``, ``spp``).

    ``stokes(t_s, k)`` returns the (3, H, W) float64 Stokes image at time t.
    """

    def __init__(self, scene, opts, info: dict, *, response: str | None = None, n_bands: int | None = None):
        from generator.analytic import layer_planes
        from generator.layers import LayerContent

        response, n_bands = _spectral_opts(opts, response, n_bands)
        self.scene = scene
        self.be, self.mi = _resolve(opts, need_jit=False)
        self.spp = int(opts.spp or scene.render.spp)
        self.seed = int(scene.render.seed if opts.seed is None else opts.seed)
        spectral = bool(scene.render.spectral if opts.spectral is None else opts.spectral)
        self.idx, self.wts, note = _bands_for(scene, spectral, n_bands, response)
        self.spp_band = max(1, int(math.ceil(self.spp / len(self.idx))))
        fps = float(getattr(opts, "fps", None) or scene.render.fps)
        self.kf_hz = float(getattr(opts, "keyframe_hz", None) or fps)
        H, W = scene.camera.height, scene.camera.width
        self.tc = LayerContent(scene.layers.transmission, (H, W))
        self.rc = LayerContent(scene.layers.reflection, (H, W))
        self.objects = getattr(scene, "objects", None) is not None
        self.static = scene.objects.is_static if self.objects else (self.tc.is_static and self.rc.is_static)
        self._layers: dict[int, dict[str, np.ndarray]] = {}
        self.t_plane, self.r_plane = layer_planes(scene)
        cam = scene.camera_model()
        self.fwd_t = cam.forward
        self.fwd_r = cam.mirrored(scene.pane_plane()).forward
        prev_modelled = dict(info.get("modelled") or {})
        self.side_t, self.side_r = layer_sides(scene)
        self.t_scale = single_interface_t_scale(scene, self.t_plane, self.idx, self.tc.extent)
        self._cache: dict[int, np.ndarray] = {}
        self.n_keyframes_rendered = 0
        self.render_s = 0.0
        info["variant"] = self.be.variant
        info["spp"] = self.spp_band * len(self.idx)
        info["modelled"] = {
            "fresnel": "Mitsuba smooth dielectric, stokes+path integrator (Monte Carlo lobe choice)",
            "slab": "two dielectric interfaces with real thickness (ghost displaced physically)" if scene.pane.model != "single" else False,
            "single_interface": (
                "T rays refract into glass (bent geometry, as the analytic tier's Snell sampling of T); "
                f"T radiance x n^2 undoes the 1/n^2 compression; T plane enlarged x{self.t_scale:.2f} by whole texels of the content (mirrored beyond its edge) to catch the bent rays"
            ) if scene.pane.model == "single" else False,
            "absorption": "not modelled in the full tier (dielectric surfaces only)" if scene.pane.absorption_per_m > 0 else False,
            "radiance_compression_1_over_n2": False,
            "spectral": note,
            "keyframes": "static scene: one render" if self.static else f"path-traced at {self.kf_hz} Hz, Stokes linearly interpolated between",
            "pane_extent": f"finite rectangle {tuple(scene.pane.size_m)} m",
            "layers": "textured area emitters (nearest texel), T plane facing the camera, R plane facing the mirrored camera; each clipped (mask BSDF) to its side of the pane",
            "max_depth": MAX_DEPTH_FULL,
            "backend": self.be.to_dict(),
        }
        if self.objects:
            for k in ("single_interface", "layers"):
                info["modelled"].pop(k, None)
            info["modelled"]["objects"] = (
                f"3-D objects ({len(scene.objects.shapes)} shapes, {len(scene.objects.lights)} area lights, environment {scene.objects.environment:g}); "
                "GT T = S0 of T alone (no pane, front removed), GT R = S0 of R alone (mirrored camera, back removed); "
                + ("static" if scene.objects.is_static else f"moving shapes path-traced at {self.kf_hz} Hz, mixture and GT interpolated between")
            )
            info["modelled"]["max_depth"] = scene.objects.max_depth
        warn = [] if self.objects else _layer_coverage_warnings(scene, self.tc, self.rc, self.t_scale)
        if warn:
            info["modelled"]["warnings"] = warn
            for w in warn:
                log.warning("full tier: %s", w)
        if "subpixel_rays" in prev_modelled or "maps_exr_source" in prev_modelled:  # where maps.exr came from
            info["modelled"]["maps_exr"] = prev_modelled
        self.info = info

    def _keyframe(self, j: int) -> np.ndarray:
        if j in self._cache:
            return self._cache[j]
        from generator.mitsuba_scene import build_scene_dict, specs_from_scene

        if self.objects:
            return self._object_keyframe(j)
        t_s = 0.0 if self.static else j / self.kf_hz
        tex_t = _texture(self.tc, t_s, self.t_scale)
        tex_r = _texture(self.rc, t_s)
        t0 = time.perf_counter()
        S = 0.0
        for b, (n_b, w_b) in enumerate(zip(self.idx, self.wts)):
            cam, pane = specs_from_scene(self.scene, n=n_b)
            scale_t = n_b**2 if pane.model == "single" else 1.0
            layers = [
                _layer_plane_spec(self.t_plane, self.fwd_t, tex_t * scale_t, "T", self.side_t, texture_grid(self.tc, self.t_scale)[1]),
                _layer_plane_spec(self.r_plane, self.fwd_r, tex_r, "R", self.side_r),
            ]
            integ = {"type": "stokes", "inner": {"type": "path", "max_depth": MAX_DEPTH_FULL, "rr_depth": MAX_DEPTH_FULL + 1}}
            d = build_scene_dict(self.mi, cam, pane, layers, integrator=integ, spp=self.spp_band, seed=self.seed)
            S = S + w_b * render_stokes_image(self.mi, d, self.spp_band, self.seed * 1000003 + j * 101 + b)
        self.render_s += time.perf_counter() - t0
        self.n_keyframes_rendered += 1
        self.info["modelled"]["keyframes_rendered"] = self.n_keyframes_rendered
        self.info["modelled"]["path_trace_s"] = round(self.render_s, 4)
        if len(self._cache) > 3:
            self._cache.pop(min(self._cache))
        self._cache[j] = S
        return S

    def _object_keyframe(self, j: int, seed_offset: int = 0) -> np.ndarray:
        """Object scene: mixture, T alone and R alone (band quadrature), cached as ground truth."""
        from generator.objects3d import render_object_layers

        if seed_offset == 0 and j in self._layers:
            return self._layers[j]["S"]
        t0 = time.perf_counter()
        acc: dict[str, np.ndarray] = {}
        scene = self.scene
        if not self.static:  # moving objects: the scene at this keyframe's time
            scene = dataclasses.replace(scene, objects=scene.objects.at(j / self.kf_hz))
        for b, (n_b, w_b) in enumerate(zip(self.idx, self.wts)):
            out = render_object_layers(self.mi, scene, n_b, self.spp_band, self.seed * 1000003 + j * 101 + b + seed_offset)
            for k, v in out.items():
                acc[k] = acc.get(k, 0.0) + w_b * v
        self.render_s += time.perf_counter() - t0
        if seed_offset:
            return acc["S"]
        self.n_keyframes_rendered += 1
        self.info["modelled"]["keyframes_rendered"] = self.n_keyframes_rendered
        self.info["modelled"]["path_trace_s"] = round(self.render_s, 4)
        for cache in (self._layers, self._cache):
            if len(cache) > 3:
                cache.pop(min(cache))
        self._layers[j] = acc
        self._cache[j] = acc["S"]
        return acc["S"]

    def layers(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Object scenes: ground-truth (L_T, L_R), each (H, W): S0 of T alone and of R alone
        (moving objects: interpolated between keyframes like the mixture).
        """
        if self.static:
            self._object_keyframe(0)
            L = self._layers[0]
            return L["S_T"][0], L["S_R"][0]
        x = t_s * self.kf_hz
        j0 = int(math.floor(x + 1e-9))
        w = x - j0
        self._object_keyframe(j0)
        a = self._layers[j0]
        if w < 1e-9:
            return a["S_T"][0], a["S_R"][0]
        self._object_keyframe(j0 + 1)
        b = self._layers[j0 + 1]
        return (1.0 - w) * a["S_T"][0] + w * b["S_T"][0], (1.0 - w) * a["S_R"][0] + w * b["S_R"][0]

    def departure(self, maps) -> tuple[dict[str, np.ndarray], dict]:
        """Object scenes: how far keyframe 0 departs from Eq. (1)-(2) (:func:`generator.objects3d.model_departure`),
        with the noise floor from a second render of the mixture (another seed).
        """
        from generator.objects3d import model_departure

        self._object_keyframe(0)
        S2 = self._object_keyframe(0, seed_offset=7777777)
        chans, summ = model_departure(self._layers[0], maps, self.scene.pane.model, float(self.scene.pane.index(550.0)), S2)
        summ["spp"] = self.spp_band * len(self.idx)
        return chans, summ

    def stokes(self, t_s: float, k: int | None = None) -> np.ndarray:
        """Stokes (3, H, W) at scene time ``t_s`` (keyframe or interpolated)."""
        if self.static:
            return self._keyframe(0)
        x = t_s * self.kf_hz
        j0 = int(math.floor(x + 1e-9))
        w = x - j0
        if w < 1e-9:
            return self._keyframe(j0)
        return (1.0 - w) * self._keyframe(j0) + w * self._keyframe(j0 + 1)
