"""Fidelity planner: ``--tier auto --tolerance EPS`` picks the cheapest tier (and spp) whose predicted error is <= EPS.

Error measure (the one ``polspike bench tradeoff`` measures): the p99 over pixels of the
worst case over the polarizer angles {0, 45, 90, 135} deg of |I(phi) - I_true(phi)|, radiance
units (1.0 = brightest layer value).  The planner predicts it per tier from what the scene holds:

* **analytic / maps** (paper Eq. (1)-(2) with the pane's Fresnel maps).  The pane models match the
  path tracer's physics (measured: the analytic image agrees with the full tier's to its Monte Carlo
  noise on every layer scene), so what remains is what the model leaves out, each term computed in
  closed form on the scene's own layers:

  - dispersion: a named glass is evaluated at 550 nm; the term is the p99 difference between that
    image and the response-weighted sum over the spectral bands (T refracts differently per band);
  - sampling: the analytic tier point-samples each layer at the pixel centre's ray, the path tracer
    averages nearest-texel lookups over the pixel's area and sees no layer where a plane is clipped
    (and the R plane itself where it stands in front of a steeply tilted pane); the term is the error
    measure between the analytic image and the path tracer's expected pixel computed without noise
    (:mod:`generator.planner_footprint`; zero where each pixel's footprint falls inside one texel,
    as in a straight view of layer content);
  - absorption: the full tier does not model it, so it is a term of the full tier, not of these;
  - 3-D objects: these tiers cannot render them (and paper Eq. (1) departs from the rendered
    mixture where the transmitted light is polarized); never chosen.

  The maps tier computes the same maps with Mitsuba and costs more: predicted like analytic, never
  cheaper, so it is chosen only when asked for by name.
* **analytic on the pixel's area** (``--supersample K``, :mod:`generator.analytic_area`): the sampling term
  is gone (the tier integrates the pixel's area as the path tracer does); what is left is the stratified
  estimate's error, ``AREA_GAIN * d / K`` with ``d`` the measured p99 step between 1 and 2 rays per side
  (first-order convergence: the step from K to 2K is half the error at K), and, mono, the dispersion term.
* **full** (Mitsuba path tracing at ``spp``).  Monte Carlo noise: p99 = ``k / sqrt(spp)``.  For a layer
  scene ``k`` is predicted from the lobe choice at the pane: a camera path reflects with probability
  about R and transmits otherwise, so one sample's intensity is ``L_R`` or ``T L_T / (1 - R)`` and its
  variance per pixel is ``R L_R^2 + T^2 L_T^2 / (1 - R) - (R L_R + T L_T)^2``; with the polarizer's
  worst-angle factor ``(1 + DoP) / 2`` and a normal tail the p99 over pixels follows, times
  :data:`NOISE_GAIN` fitted on the measured trade table.  The proxy is a guide, not a bound (on
  sampled scenes the measured ``k`` is 0.49-2.0 times it), so whenever the full tier could be the
  pick (no cheaper tier meets the tolerance, :func:`pilot_needed`) ``k`` is measured by a pilot
  render instead and the proxy stands only where Mitsuba is missing.  A 3-D object scene's ``k`` is
  always the pilot's: its noise depends on lights and BSDFs no closed form covers.  The pilot
  (:func:`with_noise_pilot`) renders the full tier twice (two seeds, :data:`PILOT_SPP` spp, at most
  :data:`PILOT_WIDTH` px wide) and takes the upper 95 % confidence bound of the p99 of their
  difference (:func:`pilot_noise_k`).  A spectral render of a dispersive glass spreads spp over
  the bands: ``k`` grows by ``sqrt(n_bands * sum w_b^2)``; a mono render of it adds the dispersion
  term.

Cost (seconds per keyframe, for the choice only): per pixel, from the trade table's order of
magnitude; the order analytic < analytic on the pixel's area (K^2 passes per band) < maps, and full by
spp, is what matters.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from polinfra.errors import ConfigError

__all__ = ["TierEstimate", "TierPlan", "plan_tier", "scene_features", "predict_tiers", "apply_plan", "with_noise_pilot", "pilot_noise_k", "pilot_needed", "NOISE_GAIN", "SPP_MAX", "PHIS"]

log = logging.getLogger(__name__)

PHIS = np.deg2rad([0.0, 45.0, 90.0, 135.0])
"""Polarizer angles of the error measure (as in `polspike bench tradeoff`)."""
NOISE_GAIN = 1.33
"""Measured full-tier noise coefficient / lobe-choice proxy, geometric mean over the layer scenes
(near_normal 1.10, brewster 1.27, oblique_diagonal 1.33, bk7_single 1.65; docs/tradeoff.md)."""
SPP_MAX = 16384
"""Largest spp the planner proposes (a render beyond it is not a practical data generator)."""
MAX_FEATURE_WIDTH = 200
"""The noise proxy is computed at most this wide (same aspect): its per-pixel statistics barely change."""
MAX_DISPERSION_WIDTH = 800
"""The dispersion term grows with resolution (T's per-band shift in pixels): computed at the scene's own size up to this width."""
Z99 = 2.5758
"""Two-sided normal 99 % point."""
COST_ANALYTIC_PX = 4e-7
COST_MAPS_ONEOFF_PX = 4e-5
COST_FULL_PX_SPP = 6e-7
"""Seconds per pixel (per spp for the full tier) on this 2-core machine (orders of magnitude from the trade table)."""
COST_AREA_PX_ONEOFF = 5e-6
COST_AREA_PX_PASS = 2.7e-6
"""Seconds of CPU per pixel of the area-sampled analytic tier: once per frame (textures, the T plane's size),
and per ray position of a mono pass (`polspike bench area` on bk7_single at 400 x 250: 0.89 / 1.6 / 4.95 s
at K = 1 / 2 / 4)."""
AREA_BAND_COST = 0.78
"""Cost of each band of a spectral pass relative to a mono pass (the ray's masks are shared; measured 2.05 /
7.1 / 27.3 s at K = 1 / 2 / 4 with 8 bands)."""
AREA_BANDS = 8
AREA_SUPERSAMPLES = (1, 2, 4)
"""Rays per pixel side the planner offers for the area-sampled analytic tier."""
AREA_GAIN = 2.0
"""Error at K rays per side over the step from K to 2K (first-order convergence, 1 / K)."""
MAX_SAMPLING_WIDTH = 400
"""The sampling term is computed at the scene's size up to this width (it shrinks with resolution as
the content's edges get more texels; a wider scene gets the narrower, larger estimate), with
:data:`SAMPLING_RAYS` sub-pixel rays at most."""
SAMPLING_RAYS = 400_000
PILOT_SPP = 16
PILOT_WIDTH = 100
"""The full tier's noise pilot: two seeds at this spp, at most this wide (same aspect); about 4 s on this machine."""
PILOT_CONFIDENCE_Z = 1.645
"""One-sided 95 % normal point of the pilot's upper confidence bound on k (:func:`pilot_noise_k`)."""


@dataclasses.dataclass(frozen=True)
class TierEstimate:
    """One tier's predicted error and cost for a scene."""

    tier: str
    spp: int | None
    spectral: bool
    predicted_p99: float
    cost_s_per_frame: float
    feasible: bool
    reasons: tuple[str, ...]
    supersample: int = 0
    """Analytic tier: 0 = the pixel centre's point sample, K = the pixel's area on K x K rays (:mod:`generator.analytic_area`)."""

    def label(self) -> str:
        """Short name: ``analytic``, ``analytic spectral area 2x2``, ``full 256spp spectral``."""
        if self.tier == "full":
            return f"full {self.spp}spp" + (" spectral" if self.spectral else "")
        return self.tier + (" spectral" if self.spectral else "") + (f" area {self.supersample}x{self.supersample}" if self.supersample else "")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["reasons"] = list(self.reasons)
        d["predicted_p99"] = None if math.isinf(self.predicted_p99) else float(self.predicted_p99)
        return d


@dataclasses.dataclass(frozen=True)
class TierPlan:
    """The planner's choice for a tolerance, with every tier's prediction."""

    tolerance: float
    choice: TierEstimate
    estimates: tuple[TierEstimate, ...]
    features: dict

    def to_dict(self) -> dict:
        return {
            "tolerance": self.tolerance,
            "choice": {"tier": self.choice.tier, "spp": self.choice.spp, "spectral": self.choice.spectral, "supersample": self.choice.supersample,
                       "predicted_p99": self.choice.predicted_p99},
            "reasons": list(self.choice.reasons),
            "estimates": [e.to_dict() for e in self.estimates],
            "features": self.features,
            "error_measure": "p99 over pixels of the worst case over phi in {0,45,90,135} deg of |I(phi) - I_true(phi)| (radiance)",
        }


def _worst(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    from polphysics.stokes import polarizer_intensity

    return np.max([np.abs(polarizer_intensity(*A, p) - polarizer_intensity(*B, p)) for p in PHIS], axis=0)


def _small(scene, max_width: int = MAX_FEATURE_WIDTH):
    W, H = scene.camera.width, scene.camera.height
    if W <= max_width:
        return scene
    w = max_width
    h = max(2, int(round(H * w / W)))
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=w, height=h))


def _p99_abs_normal(sigma: np.ndarray) -> float:
    """p99 over pixels of |N(0, sigma_px^2)| (a mixture of normals: quantile by bisection)."""
    from scipy.special import erf

    s = np.asarray(sigma, np.float64).ravel()
    n_zero = int(np.sum(s <= 0))
    s = s[s > 0]
    if s.size == 0:
        return 0.0
    total = s.size + n_zero
    lo, hi = 0.0, float(s.max()) * 6.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        frac = (n_zero + float(np.sum(erf(mid / (s * math.sqrt(2.0)))))) / total  # P(|x| <= mid) over pixels
        lo, hi = (mid, hi) if frac < 0.99 else (lo, mid)
    return 0.5 * (lo + hi)


def scene_features(scene, pilot: bool = True) -> dict:
    """What the planner needs to know of a scene (computed on the first keyframe).

    Layer scenes: the lobe-choice noise proxy, the dispersion and absorption terms (closed forms,
    numpy only); ``pilot`` allows :func:`plan_tier` to replace the proxy by a pilot render where the
    full tier could be picked.  Object scenes: the pilot-measured noise coefficient (Mitsuba, ``pilot``).
    """
    f: dict = {"pane_model": scene.pane.model, "dispersive": scene.pane.glass is not None, "objects": scene.objects is not None,
               "absorption_per_mm": float(scene.pane.absorption_per_mm)}
    if scene.objects is not None:
        ob = scene.objects
        f["materials"] = sorted({s.material for s in ob.shapes})
        f["lights"] = len(ob.lights)
        f["environment"] = float(ob.environment)
        f["noise_k"], f["noise_source"] = None, "not measured"
        return with_noise_pilot(scene, f) if pilot else f
    from generator.analytic import analytic_maps, frame_stokes, sample_layers
    from generator.layers import LayerContent

    s = _small(scene)
    H, W = s.camera.height, s.camera.width
    tc = LayerContent(s.layers.transmission, (H, W))
    rc = LayerContent(s.layers.reflection, (H, W))
    m = analytic_maps(s)
    L_T, L_R, L_G = sample_layers(m, tc, rc, 0.0)
    S = frame_stokes(m, L_T, L_R, L_G)
    R = 0.5 * (m.R_perp + m.R_par)
    T = 0.5 * (m.T_perp + m.T_par)
    p = np.clip(R, 1e-3, 1.0 - 1e-3)
    mean = R * L_R + T * L_T
    var = np.maximum(R * L_R**2 + T**2 / (1.0 - p) * L_T**2 - mean**2, 0.0)
    dop = np.hypot(S[1], S[2]) / np.maximum(S[0], 1e-9)
    proxy = _p99_abs_normal(np.sqrt(var) * 0.5 * (1.0 + np.clip(dop, 0.0, 1.0)))
    f["noise_proxy"] = proxy
    f["noise_k"] = NOISE_GAIN * proxy
    f["noise_source"] = f"lobe-choice proxy {proxy:.3g} x NOISE_GAIN {NOISE_GAIN}"
    f["pilot_allowed"] = bool(pilot)
    f["feature_size"] = [W, H]
    f["dispersion_p99"] = 0.0
    f["spectral_noise_factor"] = 1.0
    if scene.pane.glass is not None:
        from generator.analytic import spectral_frame
        from generator.tiers_mitsuba import spectral_bands

        wl, w = spectral_bands()
        sd = _small(scene, MAX_DISPERSION_WIDTH)
        hd = (sd.camera.height, sd.camera.width)
        tcd, rcd = (tc, rc) if sd is s else (LayerContent(sd.layers.transmission, hd), LayerContent(sd.layers.reflection, hd))
        md = m if sd is s else analytic_maps(sd)
        Sd = frame_stokes(md, *sample_layers(md, tcd, rcd, 0.0))
        Ss, _, _ = spectral_frame([(float(wi), analytic_maps(sd, float(x))) for x, wi in zip(wl, w)], tcd, rcd, 0.0)
        f["dispersion_p99"] = float(np.percentile(_worst(Sd, Ss), 99))
        f["dispersion_size"] = [sd.camera.width, sd.camera.height]
        f["spectral_noise_factor"] = float(math.sqrt(len(w) * float(np.sum(np.asarray(w) ** 2))))
    from generator.analytic_area import area_terms
    from generator.planner_footprint import SUBPIXELS

    ss = _small(scene, MAX_SAMPLING_WIDTH)
    k_sub = max(1, min(SUBPIXELS, int(math.sqrt(SAMPLING_RAYS / (ss.camera.width * ss.camera.height)))))
    f["sampling_p99"], f["area_step_p99"] = area_terms(ss, k_sub)
    f["sampling_source"] = f"point sample vs box filter over nearest texels, {ss.camera.width} x {ss.camera.height}, {k_sub} x {k_sub} sub-pixel rays"
    f["absorption_p99"] = 0.0
    if scene.pane.absorption_per_mm > 0:
        m0 = analytic_maps(dataclasses.replace(s, pane=dataclasses.replace(s.pane, absorption_per_mm=0.0)))
        f["absorption_p99"] = float(np.percentile(_worst(S, frame_stokes(m0, *sample_layers(m0, tc, rc, 0.0))), 99))
    return f


def _pilot_pair(scene) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Two full-tier renders of ``scene`` (mono, :data:`PILOT_SPP` spp, seeds 11 and 12, at most
    :data:`PILOT_WIDTH` px wide): Stokes (3, h, w) each, and (w, h).  A 3-D object scene renders its mixture
    only; a layer scene its first keyframe, as :class:`generator.tiers_mitsuba.FullRenderer` renders it.
    """
    from types import SimpleNamespace

    W, H = scene.camera.width, scene.camera.height
    w = min(W, PILOT_WIDTH)
    s = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=w, height=max(2, int(round(H * w / W)))))
    size = (s.camera.width, s.camera.height)
    if scene.objects is not None:
        from generator.mitsuba_scene import render_stokes_image, specs_from_scene
        from generator.objects3d import objects_scene_dict
        from generator.tiers_mitsuba import _resolve

        _, mi = _resolve(SimpleNamespace(variant="auto"), need_jit=False)  # the render options' backend choice
        cam, pane = specs_from_scene(s, n=float(s.pane.index(550.0)))
        S1, S2 = (render_stokes_image(mi, objects_scene_dict(mi, s, cam, pane, spp=PILOT_SPP, seed=sd), PILOT_SPP, sd) for sd in (11, 12))
        return np.asarray(S1, np.float64), np.asarray(S2, np.float64), size
    from generator.tiers_mitsuba import FullRenderer

    def opts(seed: int):  # the render options FullRenderer reads (generator.render imports this module)
        return SimpleNamespace(tier="full", spp=PILOT_SPP, spectral=False, variant="auto", seed=seed, fps=None, keyframe_hz=None, response=None, n_bands=None)

    S1, S2 = (np.asarray(FullRenderer(s, opts(sd), {}).stokes(0.0, 0), np.float64) for sd in (11, 12))
    return S1, S2, size


def pilot_noise_k(S1: np.ndarray, S2: np.ndarray, spp: int = PILOT_SPP) -> tuple[float, float]:
    """Noise coefficient k (p99 = k / sqrt(spp)) from two independent renders at ``spp``: (estimate, upper bound).

    Each pixel's worst-angle difference of the two, over sqrt 2, is one draw of a render's error there; the
    estimate is their p99 over pixels, the upper bound the distribution-free one-sided 95 % confidence bound
    of that p99 (the order statistic of rank ``0.99 n + 1.645 sqrt(0.0099 n)`` of ``n`` pixels), both times
    ``sqrt(spp)``.
    """
    d = np.sort(_worst(S1, S2).ravel())
    n = d.size
    scale = math.sqrt(spp / 2.0)
    k = float(np.percentile(d, 99)) * scale
    r = min(n - 1, int(math.ceil(0.99 * n + PILOT_CONFIDENCE_Z * math.sqrt(n * 0.99 * 0.01))))
    return k, max(k, float(d[r]) * scale)


def with_noise_pilot(scene, f: dict) -> dict:
    """``f`` with the full tier's noise coefficient measured by a pilot render (:func:`_pilot_pair`).

    ``noise_k`` becomes the pilot's upper confidence bound (:func:`pilot_noise_k`), so a pick errs on the
    safe side; the estimate, the bound, the pilot's size and seconds are kept (``noise_pilot``).  Without
    Mitsuba a layer scene keeps its lobe-choice proxy (the reason says why); an object scene has no other
    estimate and the error propagates.  Already measured: ``f`` unchanged.
    """
    from polinfra.errors import BackendUnavailableError

    if "noise_pilot" in f:
        return f
    t0 = time.perf_counter()
    try:
        S1, S2, (w, h) = _pilot_pair(scene)
    except BackendUnavailableError as exc:
        if f.get("objects"):
            raise
        log.warning("noise pilot not possible for %s (%s): the lobe-choice proxy stands", scene.name, exc)
        return {**f, "noise_pilot": {"error": str(exc).splitlines()[0]}, "noise_source": f"{f['noise_source']} (pilot not possible: {str(exc).splitlines()[0]})"}
    k, k_hi = pilot_noise_k(S1, S2)
    secs = time.perf_counter() - t0
    src = (f"pilot: full tier {PILOT_SPP} spp, two seeds, {w} x {h} px, {secs:.1f} s: k {k_hi:.3g} = 95 % upper bound "
           f"(estimate {k:.3g})")
    if "noise_proxy" in f:
        src += f"; the lobe-choice proxy gives {NOISE_GAIN * f['noise_proxy']:.3g}"
    log.info("noise pilot for %s: k %.3g (upper bound %.3g), %.1f s", scene.name, k, k_hi, secs)
    return {**f, "noise_k": k_hi, "noise_source": src,
            "noise_pilot": {"k": k, "k_upper": k_hi, "spp": PILOT_SPP, "size": [w, h], "seconds": secs,
                            "proxy_k": NOISE_GAIN * f["noise_proxy"] if "noise_proxy" in f else None}}


def pilot_needed(scene, f: dict, tolerance: float, analytic_spectral: bool = True) -> bool:
    """Whether the full tier's noise must be measured for ``tolerance``: a layer scene whose proxy stands
    (and the pilot is allowed) and no other tier meets the tolerance at a cost below the full tier at 1 spp
    (otherwise no full-tier row can be the cheapest, whatever its noise).
    """
    if f.get("objects") or "noise_pilot" in f or not f.get("pilot_allowed", False):
        return False
    ests = predict_tiers(scene, f, spp_grid=(1,), analytic_spectral=analytic_spectral)
    full1 = min(e.cost_s_per_frame for e in ests if e.tier == "full")
    return not any(e.tier != "full" and e.feasible and e.predicted_p99 <= tolerance and e.cost_s_per_frame < full1 for e in ests)


def _full_error(f: dict, spp: int, spectral: bool) -> tuple[float, list[str]]:
    k = f["noise_k"]
    reasons = []
    if spectral and f["dispersive"]:
        k = k * f.get("spectral_noise_factor", 1.0)
        reasons.append(f"spectral: spp spread over the bands, noise x{f.get('spectral_noise_factor', 1.0):.2f}")
    noise = k / math.sqrt(spp)
    reasons.insert(0, f"Monte Carlo noise {k:.3g}/sqrt({spp}) = {noise:.3g} ({f['noise_source']})")
    terms = [noise]
    if f["dispersive"] and not spectral:
        terms.append(f.get("dispersion_p99", 0.0))
        reasons.append(f"mono render of a dispersive glass: dispersion term {f.get('dispersion_p99', 0.0):.3g}")
    if f.get("absorption_p99", 0.0) > 0:
        terms.append(f["absorption_p99"])
        reasons.append(f"absorption not modelled by the full tier: {f['absorption_p99']:.3g}")
    return float(math.sqrt(sum(t * t for t in terms))), reasons


def area_error(f: dict, supersample: int) -> float:
    """Predicted p99 error of the area-sampled analytic tier at ``supersample`` rays per side (mono at 550 nm
    without the dispersion term): ``AREA_GAIN * d / K``, with ``d`` the measured distance between 1 and 2 rays
    per side (``features['area_step_p99']``): the stratified estimate's error falls as 1 / K, so the step from
    K to 2K is half the error at K.
    """
    return AREA_GAIN * float(f.get("area_step_p99", 0.0)) / max(1, int(supersample))


def _area_estimates(f: dict, px: int, analytic_spectral: bool) -> list[TierEstimate]:
    """The area-sampled analytic tier at :data:`AREA_SUPERSAMPLES` rays per side, mono and (dispersive glass) spectral."""
    out = []
    disp = f.get("dispersion_p99", 0.0)
    n_b = AREA_BANDS if f["dispersive"] else 1
    for K in AREA_SUPERSAMPLES:
        e = area_error(f, K)
        why = (f"pixel area on {K} x {K} rays, each the box mean of the full tier's texels over its cell: area term "
               f"{AREA_GAIN:g} x {f.get('area_step_p99', 0.0):.3g} / {K} = {e:.3g} (the step from 1 to 2 rays per side, falling as 1 / K)")
        cost = COST_AREA_PX_ONEOFF * px + COST_AREA_PX_PASS * px * K * K
        if f["dispersive"]:
            out.append(TierEstimate("analytic", None, False, math.hypot(disp, e), cost, True, (
                why, f"dispersive glass evaluated at 550 nm: dispersion term {disp:.3g}"), K))
            if analytic_spectral:
                cost_s = COST_AREA_PX_ONEOFF * px + COST_AREA_PX_PASS * px * K * K * n_b * AREA_BAND_COST
                out.append(TierEstimate("analytic", None, True, e, cost_s, True, (
                    why, f"spectral: {n_b} bands, response-weighted: dispersion modelled"), K))
        else:
            out.append(TierEstimate("analytic", None, False, e, cost, True, (why,), K))
    return out


def predict_tiers(scene, features: dict | None = None, spp_grid: tuple[int, ...] | None = None, analytic_spectral: bool = True) -> list[TierEstimate]:
    """Every tier's prediction for ``scene`` (full tier: one row per spp in ``spp_grid``, mono and, for a
    dispersive glass, spectral).
    """
    f = features if features is not None else scene_features(scene)
    px = scene.camera.width * scene.camera.height
    out: list[TierEstimate] = []
    if f["objects"]:
        why = "3-D objects: only the full tier renders them (paper Eq. (1) departs from the mixture where T is polarized)"
        out.append(TierEstimate("analytic", None, False, math.inf, COST_ANALYTIC_PX * px, False, (why,)))
        out.append(TierEstimate("maps", 1, False, math.inf, COST_MAPS_ONEOFF_PX * px, False, (why,)))
    else:
        disp = f.get("dispersion_p99", 0.0)
        samp = f.get("sampling_p99", 0.0)
        model_err = math.hypot(disp, samp)
        reasons = ["pane model, single-interface refraction and ghost modelled as the path tracer does",
                   f"sampling term {samp:.3g} ({f.get('sampling_source', 'not computed')})"]
        if f["dispersive"]:
            reasons.append(f"dispersive glass evaluated at 550 nm: dispersion term {disp:.3g} (closed form over the spectral bands)")
        out.append(TierEstimate("analytic", None, False, model_err, COST_ANALYTIC_PX * px, True, tuple(reasons)))
        if f["dispersive"] and analytic_spectral:
            out.append(TierEstimate("analytic", None, True, samp, COST_ANALYTIC_PX * px * 8.5, True, (
                "analytic, spectral: Eq. (1)-(2) per wavelength band (8 bands), weighted by the sensor response: dispersion modelled",
                f"sampling term {samp:.3g}")))
        out.append(TierEstimate("maps", 1, False, model_err, COST_MAPS_ONEOFF_PX * px + COST_ANALYTIC_PX * px, True,
                                tuple(reasons) + ("maps rendered by Mitsuba: same model as analytic, costs more",)))
        out += _area_estimates(f, px, analytic_spectral)
    grid = spp_grid or tuple(2**i for i in range(0, int(math.log2(SPP_MAX)) + 1))
    mult = 3.0 if f["objects"] else 1.0  # object keyframes: the mixture plus T alone and R alone
    for spectral in ((False, True) if f["dispersive"] else (False,)):
        for spp in grid:
            err, reasons = _full_error(f, spp, spectral)
            out.append(TierEstimate("full", int(spp), spectral, err, mult * COST_FULL_PX_SPP * px * spp * (1.15 if spectral else 1.0), True, tuple(reasons)))
    return out


def plan_tier(scene, tolerance: float, features: dict | None = None, analytic_spectral: bool = True) -> TierPlan:
    """The cheapest tier (and spp) whose predicted p99 error is <= ``tolerance``.

    Raises:
        ConfigError: ``tolerance`` <= 0 (or not finite), or no tier can reach it (the message names the
            best reachable error).
    """
    if not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance) and tolerance > 0):
        raise ConfigError(f"--tolerance {tolerance!r} must be a positive p99 radiance error (e.g. 1e-2)")
    f = features if features is not None else scene_features(scene)
    if pilot_needed(scene, f, tolerance, analytic_spectral):
        f = with_noise_pilot(scene, f)
    ests = predict_tiers(scene, f, analytic_spectral=analytic_spectral)
    ok = [e for e in ests if e.feasible and e.predicted_p99 <= tolerance]
    if not ok:
        best = min((e for e in ests if e.feasible), key=lambda e: e.predicted_p99)
        raise ConfigError(
            f"--tolerance {tolerance:g} cannot be reached for scene {scene.name!r}: the best reachable p99 error is "
            f"{best.predicted_p99:.3g} (tier {best.tier}{f' at {best.spp} spp' if best.tier == 'full' else ''}"
            f"{', --spectral' if best.tier == 'analytic' and best.spectral else ''}{f', --supersample {best.supersample}' if best.supersample else ''})"
        )
    choice = min(ok, key=lambda e: (e.cost_s_per_frame, e.predicted_p99))
    reasons = (f"cheapest tier with predicted p99 {choice.predicted_p99:.3g} <= tolerance {tolerance:g}",) + choice.reasons
    if choice.tier != "full" and "noise_pilot" in f:
        reasons += (f"full tier's noise coefficient: {f['noise_source']}",)
    choice = dataclasses.replace(choice, reasons=reasons)
    log.info("tier auto for %s at tolerance %g: %s (predicted p99 %.3g)", scene.name, tolerance, choice.label(), choice.predicted_p99)
    return TierPlan(float(tolerance), choice, tuple(ests), {k: v for k, v in f.items()})


def apply_plan(opts, plan: TierPlan):
    """``opts`` (a :class:`generator.render.RenderOptions` with ``tier='auto'``) with the plan's tier, spp and spectral."""
    c = plan.choice
    kw: dict = {"tier": c.tier, "spectral": c.spectral, "supersample": c.supersample if c.tier == "analytic" else None}
    if c.tier == "full":
        kw["spp"] = c.spp
    return dataclasses.replace(opts, **kw)
