"""Self-calibrated zeta (``--zeta self``): the pane's geometry estimated from the spikes themselves.

For a planar pane seen by a pinhole camera, the plane of incidence at pixel p
contains the viewing ray d(p) and the pane normal N, so the s-direction
phi_perp(p) (in the ray's own Stokes frame, :mod:`polphysics.geometry`) is a
function of N (2 numbers) and the field of view (1 number).  Paper Eq. (1)-(2)
give, for the light behind the polarizer,

    I_k = 1/2 [T + A (R - T)] + 1/4 (R_perp - R_par)(R - T) cos 2(phi_k - phi_perp),

so the angle of linear polarization of the stream is phi_perp where R > T and
phi_perp + 90 deg where R < T (RECONSTRUCTION_NOTES.md, section 2): only the
orientation *modulo 90 deg* is a property of the pane.

Estimator (:func:`self_calibrate`):

1. Harmonic fit (supp. Eq. (1), :func:`reconstruct.physics.harmonic_fit.harmonic_fit`) on
   consecutive chunks of frames, each covering about half a polarizer turn
   (one cycle of 2 phi), over a long span (default 0.1 s).  Each chunk's
   (ac, as) is squared as a complex number, z4 = (ac + i as)^2, whose angle is
   4 AoLP: the sign of R - T, which changes as the layers move, drops out.
   Summing z4 over chunks and over s x s pixel blocks gives a coherent
   orientation psi = arg(sum z4) / 4 (mod 90 deg) and a coherence
   |sum z4| / sum |z4| in [0, 1] (about 1 / sqrt(samples) for pure noise).
2. Blocks whose coherence clears the noise level are "modulating".  The normal
   N (tilt from the optical axis, azimuth) and, when it is not given, the
   horizontal field of view are fitted to minimise
   sum_p c_p sin^2 2(psi_p - phi_perp(p; N, fov)) -- invariant to the
   90 deg flip -- by a grid search over the hemisphere followed by robust
   nonlinear least squares (``scipy.optimize.least_squares``, soft-L1 loss).
   phi_perp(p; N) comes from :func:`polphysics.geometry.incidence_geometry` on
   a block-grid camera (the same pinhole, W/s x H/s pixels: its pixel centres
   are the block centres), so the per-ray frame convention is the project's.
3. theta(p), phi_perp(p) on the full grid, the index (given, default 1.5) and
   the pane model give R_perp, R_par by :func:`reconstruct.physics.zeta.pane_maps_from_geometry`,
   and zeta_k(p) by paper Eq. (2) (:func:`reconstruct.physics.zeta.zeta_from_maps`).

Where the pane whose phi_perp field is turned by 90 deg scores within
``max_twin_ratio`` of the best (modulo 90 deg only the field's curvature
separates the two, which vanishes for a narrow field of view and a glancing
pane; the tilt is loose there too), the polarization cone decides: with the
right phi_perp, m / a0 (modulation along phi_perp over the mean) lies in
[-DoP_T(theta), DoP_R(theta)] for any R, T >= 0 (:func:`cone_bounds`), and the
wrong family breaks it wherever one layer dominates beyond DoP_T
(:func:`valley_candidates`, :func:`cone_violation`).  The same cone scores the
index and the pane model (:func:`fit_glass`; claimed only with a margin, else
``prior_model`` and ``n``, with the reason in ``diagnostics["glass"]``).

Where the transmission dominates everywhere (R < T and no layer ever black), both families hold the cone and
the **layers' content** decides (:func:`layer_gradient_correlation`, ``content_margin``).  Paper Eq. (1) gives
I_k = 1/2 [T + zeta_k (R - T)]; the twin sees the modulation with the opposite sign, so its solve returns
R' - T' ~ -(B / B') (R - T): where T dominates, T' ~ T and R' ~ T + (T - R), i.e. R' carries the transmission's
texture and the gradients of R' and T' are strongly correlated (positively).  With the right pane R^ and T^ are the
two independent layers, whose gradients are uncorrelated (the gradient-exclusion idea of reflection separation;
the paper's Eq. (11) uses it as a loss).  Each cone-consistent candidate of each family is solved in closed form on
consecutive parts of the span of at least half a turn each (R^ of one part against T^ of the next, so the spike
noise, shared by R^ and T^ of one solve, drops out), the layers smoothed by 2 pixels and differenced; the score is
the RMS of the correlation over 3 x 3 tiles (a wrong scale leaks T into R^ by (1 - B / B') T, which changes across
the view, so a wrong (tilt, model) pair may zero the whole view's correlation but not every tile's).  A family scores
its smallest value over its candidates and both pane models (the tilt valley and the model's scale are nuisances),
and wins when the other family's score is larger by ``content_margin`` (0.2) and ``content_ratio`` (3) times, and the
winner holds the cone.  Pixels a hypothesis sees beyond 82 deg are left out (:data:`CONTENT_THETA_MAX_DEG`): there a
twin at near-grazing incidence reflects about as much as it transmits and its solve becomes a layer swap
(T' ~ R, R' ~ T), as uncorrelated as the truth.  Flat or featureless layers, noise too strong for 2-pixel smoothing,
or layers moving fast within half a turn (the closed-form solve assumes them still) leave both scores alike: the
result stays "ambiguous" and says so, with both scores (``diagnostics["cone"]["content"]``).  Where the reflection
dominates instead the cone already decides (the twin's R' goes negative).  The content is scored on every cone
test: where the cone picks one family and the content clearly the other, the result is "ambiguous" too
(``diagnostics["cone"]["conflict"]``): with R nearly black the right family sits on the cone's -DoP_T edge, where
noise can push it out by a little more than the twin.

The same score tells the **pane model** where the cone does not (:func:`content_model`; the cone almost never does,
section "Index and pane model" of docs/selfcal.md): under the wrong model's scale B', R^ = (1 - B / B') T + (B / B') R.
A model is claimed when its score is at most :data:`CONTENT_INDEPENDENT` (0.25: the layers come out nearly
independent) and beats the other model's by :data:`CONTENT_MODEL_MARGIN` (0.05); otherwise ``prior_model``.  For a
twin resolved by the content the pane is then the claimed model's best candidate; with no model claimed the tilt
stays the orientation field's choice (the content's tilt is conditional on the assumed scale) and the model is
scored again at that geometry.  The two thresholds were chosen on the stress set (docs/selfcal.md).

Where nothing modulates (no reflection, R = T, near-normal incidence: the
fitted pane explains the orientation field less than ``z_min`` noise standard
deviations above chance, or makes fewer than ``min_modulating_blocks`` of the 4 x 4
blocks modulate above noise: a scene moving in a stream without a polarizer), or where the cone cannot refute the twin either, the
result carries ``ok = False`` and a reason, a warning is logged, and the
callers fall back (the physics solvers to the learned zeta, the network to zeta = 0 or its learned zeta,
:func:`reconstruct.net.net_zeta.fallback_for`).  ``diagnostics["modulating_px"]`` reports
the share of pixels modulating above noise (:func:`modulating_fraction`).

T depends on zeta's *shape* (phi_perp and DoP_R = (R_perp - R_par) / (R_perp + R_par)),
not its scale (RECONSTRUCTION_NOTES.md, section 1): the index matters little,
the geometry (N and the field of view, hence theta) matters much.

Camera frame: a pinhole at the origin looking along +z with up +y
(``PinholeCamera.look_at([0,0,0], [0,0,1], [0,1,0], ...)``); N is reported in
that frame, with N . forward > 0, and as the vanishing point of N in pixels.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import numpy as np
import torch

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError
from reconstruct.pane.camera import _pane_phi_perp, camera_for, normal_from_angles
from reconstruct.pane.cone import (
    GLASS_SLACK,
    _hypothesis_maps,
    _span_factor_of,
    chunk_harmonics,
    cone_aggregates,
    glass_scores,
    modulating_fraction,
)
from reconstruct.pane.content import content_model
from reconstruct.pane.glass import fit_glass
from reconstruct.pane.normal import _sep, fit_normal, polish_geometry
from reconstruct.pane.orientation import orientation_field
from reconstruct.pane.resolve import _resolve_by_cone
from reconstruct.physics.zeta import PaneMaps, pane_maps_from_geometry, zeta_from_maps

__all__ = ["SelfCalConfig", "SelfCalResult", "StageOutcome", "CASCADE", "self_calibrate", "self_zeta", "group_self_zeta"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class SelfCalConfig:
    """Self-calibration parameters."""

    span_s: float = opt(0.1, "length of the stream used to measure the orientation field, seconds (stationary pane)", lo=0.001, hi=100.0)
    block_px: int = opt(0, "block size of the orientation field in pixels (0 = about 48 blocks across the width)", lo=0, hi=1024)
    fov_deg: float = opt(0.0, "horizontal field of view in degrees (0 = fit it from the orientation field)", lo=0.0, hi=170.0)
    fov_init_deg: float = opt(60.0, "start value when the field of view is fitted", lo=5.0, hi=170.0)
    n: float = opt(1.5, "refractive index of the pane", lo=1.0, hi=4.0)
    model: str = opt("auto", "pane model: auto (the index from the DoP's cone, single or slab from the cone or the layers' content, where the data constrain them, else prior_model and n) or a given model", choices=("auto", "single", "thin_slab", "thick_slab"))
    prior_model: str = opt("thin_slab", "model: auto keeps this pane model where the data do not tell single from slab (the safer guess for ridge / RWPS, docs/selfcal.md)", choices=("single", "thin_slab", "thick_slab"))
    cone_margin: float = opt(9.0, "cone test: a pane family (or glass) is rejected when its DoP-cone violation (chi^2, noise units) exceeds the best by this", lo=0.0, hi=1e9)
    cone_ratio: float = opt(10.0, "cone test: the rejected pane family's DoP-cone violation must also be at least this many times the chosen one's (else neither fits)", lo=1.0, hi=1e9)
    valley_step_deg: float = opt(2.0, "cone test: tilt step of the candidate panes, degrees", lo=0.5, hi=20.0)
    valley_drop_fov_bounds: bool = opt(True, "fov fitted: cone / content candidates whose fitted fov ran into the search bounds (FOV_BOUNDS_DEG) are left out where each family keeps a candidate inside them: degenerate views, not fitted values, whose layers can come out as independent as the right pane's")
    valley_ratio: float = opt(0.97, "cone test: panes scoring at least this fraction of the orientation optimum are candidates", lo=0.0, hi=1.0)
    z_min: float = opt(8.0, "the fitted pane must explain the orientation field this many noise standard deviations above chance, else 'nothing modulates' (ok = False)", lo=0.0, hi=1e6)
    geometry_weighting: str = opt("scatter", "weights of the blocks in the final geometry fit: scatter (each block by 1 / (its orientation's measured variance, from the scatter of its pixels across its direction, plus a misfit floor), robust to blocks the plane does not explain; calibrate-pane's, docs/selfcal.md) or s4 (by |sum z4|, the matched filter of the grid search, which overweights weak blocks whose |sum z4| is mostly their signal's power)", choices=("scatter", "s4"))
    min_modulating_blocks: float = opt(0.002, "the fitted pane must make at least this share of 4 x 4 pixel blocks modulate above 3 noise sigmas (diagnostics modulating_blocks), else 'nothing modulates' (ok = False): a moving scene seen without a polarizer aliases into an orientation field that a narrow pane explains above chance while no block modulates", lo=0.0, hi=1.0)
    coherence_sigmas: float = opt(4.0, "diagnostics: a block counts as modulating when its |sum z4| exceeds this many noise standard deviations", lo=0.0, hi=100.0)
    max_twin_ratio: float = opt(0.98, "the pane turned 90 deg (phi_perp <-> p-direction) scoring above this fraction of the best: the DoP cone decides, else ambiguous (ok = False)", lo=0.0, hi=10.0)
    min_tilt_deg: float = opt(3.0, "a fitted tilt below this is near-normal incidence: no usable modulation (ok = False)", lo=0.0, hi=89.0)
    content_margin: float = opt(0.2, "content test (where the cone leaves the 90 deg twin open): the other family's smallest layer-gradient |correlation| must exceed the chosen one's by this (0 = off: refuse as before)", lo=0.0, hi=2.0)
    content_ratio: float = opt(3.0, "content test: ... and be at least this many times the chosen one's", lo=1.0, hi=1e9)
    twin_check_ratio: float = opt(0.95, "fov fitted: where the 90 deg twin scores between this and max_twin_ratio of the best, the DoP cone and the layers' content are asked too, and the twin is taken where both prefer it, the cone by more than cone_margin (1 = off)", lo=0.0, hi=10.0)
    twin_check_step_deg: float = opt(4.0, "the narrow twin check's tilt step along each family's valley, degrees (the cone test's own is valley_step_deg; the check's scan is most of its time)", lo=0.5, hi=20.0)
    polish_max_move_deg: float = opt(45.0, "the scatter-weighted polish of the geometry is kept only where it turns the normal by less than this (degrees) and stays in the chosen 90 deg family; with the fov free it moves along the fov-tilt valley, where the normal turns a lot for little change in the field", lo=0.0, hi=180.0)


@dataclasses.dataclass
class SelfCalResult:
    """Outcome of :func:`self_calibrate`.

    Attributes:
        ok: True when the pane was calibrated; False means "nothing modulates" (use another zeta source).
        reason: why not (empty when ok).
        normal: (3,) unit pane normal in the camera frame (module docstring), N . forward > 0, or None.
        tilt_deg: angle between N and the optical axis.
        azimuth_deg: direction of N's projection in the image, degrees counter-clockwise from image +x.
        vp_px: vanishing point of N (x, y) in pixels (None when N is perpendicular to the axis).
        fov_deg: field of view used; fov_fitted says whether it was fitted.
        n, model: index and pane model of the maps.
        maps: full-resolution :class:`PaneMaps` (None unless ok); theta: (H, W) incidence angle, radians.
        modulating_fraction: share of blocks that modulate; residual_deg: weighted median orientation residual.
        twin_ratio: matched score of the best pane whose phi_perp field is turned by about 90 deg from the
            optimum's, over the optimum's (near 1: the 90 deg flip cannot be resolved; see ``max_twin_ratio``).
        diagnostics: block-grid fields (psi, coherence, mask, s4), the detection ``z`` and ``alignment``, sizes.
    """

    ok: bool
    reason: str
    normal: np.ndarray | None
    tilt_deg: float | None
    azimuth_deg: float | None
    vp_px: tuple[float, float] | None
    fov_deg: float
    fov_fitted: bool
    n: float
    model: str
    maps: PaneMaps | None
    theta: np.ndarray | None
    modulating_fraction: float
    residual_deg: float | None
    twin_ratio: float | None
    diagnostics: dict

    def summary(self) -> dict:
        """Plain-data summary (for JSON; a value that was not scored, NaN or inf, is None)."""
        return _plain({
            "ok": self.ok,
            "reason": self.reason,
            "normal": None if self.normal is None else [float(v) for v in self.normal],
            "tilt_deg": self.tilt_deg,
            "azimuth_deg": self.azimuth_deg,
            "vp_px": None if self.vp_px is None else [float(v) for v in self.vp_px],
            "fov_deg": self.fov_deg,
            "fov_fitted": self.fov_fitted,
            "n": self.n,
            "model": self.model,
            "modulating_fraction": self.modulating_fraction,
            "residual_deg": self.residual_deg,
            "twin_ratio": self.twin_ratio,
            "z": self.diagnostics.get("z"),
            "alignment": self.diagnostics.get("alignment"),
            "modulating_px": self.diagnostics.get("modulating_px"),
            "modulating_blocks": self.diagnostics.get("modulating_blocks"),
            "cone": self.diagnostics.get("cone"),
            "twin_check": self.diagnostics.get("twin_check"),
            "glass": self.diagnostics.get("glass"),
        })


def _plain(x):
    """JSON-ready copy (numpy scalars to floats, tuple keys to strings, non-finite floats to None: not scored)."""
    if isinstance(x, dict):
        return {(k if isinstance(k, str) else ":".join(map(str, k)) if isinstance(k, tuple) else str(k)): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x




def leave_out_saturated(I: np.ndarray, exposure: float | None) -> tuple[np.ndarray, float]:
    """Frames with every pixel that saturates in any of them set to 0, and the fraction of such pixels.

    A spike-camera pixel fires at most once per step, so a window at the ceiling
    (:data:`reconstruct.physics.span.SPAN_SATURATION` spikes per step) clips the light where the polarizer lets most
    through: the pixel's modulation reads flatter, its degree of polarization lower, which the cone and the
    layers' content would take for a weaker pane (a glancing single interface calibrated as a thin slab, measured
    on the stress set).  A pixel at 0 in every frame adds nothing to the orientation field's or the cone's block
    sums.  ``exposure`` None (unknown): the frames unchanged.
    """
    from reconstruct.physics.span import SPAN_SATURATION

    if exposure is None:
        return I, 0.0
    sat = (np.asarray(I) * float(exposure) >= SPAN_SATURATION).any(0)
    if not sat.any():
        return I, 0.0
    return np.where(sat[None], np.zeros((), np.asarray(I).dtype), I), float(sat.mean())


@dataclasses.dataclass(frozen=True)
class StageOutcome:
    """One stage's verdict in the self-calibration cascade (:data:`CASCADE`).

    Attributes:
        stage: the stage's name.
        verdict: ``"pass"`` (the geometry stands), ``"moved"`` (the stage changed it), ``"skipped"`` (the stage does
            not apply to this stream) or ``"fail"`` (the cascade stops: no self-calibrated zeta).
        reason: why, in words.
        tilt_deg, azimuth_deg, fov_deg: the geometry after the stage (degrees).
    """

    stage: str
    verdict: str
    reason: str
    tilt_deg: float
    azimuth_deg: float
    fov_deg: float


class _Calibration:
    """What one run of the cascade reads and updates: the frames, the orientation field, the current geometry, the
    diagnostics, and the glass once fitted.
    """

    def __init__(self, I, phi, cfg: SelfCalConfig, name: str, f: dict, mask: np.ndarray, diag: dict, fit: dict, fov_given: float | None):
        self.I, self.phi, self.cfg, self.name = I, phi, cfg, name
        self.f, self.mask, self.diag, self.fit, self.fov_given = f, mask, diag, fit, fov_given
        self.H, self.W = I.shape[-2:]
        self.h, self.w = f.psi.shape
        self.frac = float(mask.mean())
        self.auto = cfg.model == "auto"
        self.aggs = None
        self.n_used, self.model_used = cfg.n, cfg.model
        self.modulation()
        self.res_deg = self.residual()

    def modulation(self) -> None:
        pp = _hypothesis_maps(self.W, self.H, self.fit["tilt"], self.fit["azimuth"], self.fit["fov_deg"])[0]
        self.diag["modulating_px"] = modulating_fraction(self.f.s4_px, self.f.q_px, pp, 1)
        self.diag["modulating_blocks"] = modulating_fraction(self.f.s4_px, self.f.q_px, pp, 4)

    def residual(self) -> float | None:
        """Weighted median orientation residual over the coherent blocks, degrees (a report, not a gate)."""
        if not self.mask.any():
            return None
        d = self.f.psi - _pane_phi_perp(self.w, self.h, self.fit["tilt"], self.fit["azimuth"], self.fit["fov_deg"])
        d = np.abs(np.mod(d + math.pi / 4, math.pi / 2) - math.pi / 4)[self.mask]
        wv = np.abs(self.f.s4)[self.mask]
        o = np.argsort(d)
        cw = np.cumsum(wv[o])
        return float(np.degrees(d[o][min(len(o) - 1, int(np.searchsorted(cw, 0.5 * cw[-1])))]))

    def move(self, **geometry) -> None:
        """Take a new geometry (tilt, azimuth radians; fov_deg) and refresh what depends on it."""
        self.fit = {**self.fit, **geometry}
        self.modulation()
        self.res_deg = self.residual()

    def incidence(self):
        """The camera, the pane's normal and plane, and their incidence geometry (theta, phi_perp) at the current fit."""
        key = (self.fit["tilt"], self.fit["azimuth"], self.fit["fov_deg"])
        if getattr(self, "_incidence_key", None) != key:
            from polphysics.geometry import Plane, incidence_geometry

            cam = camera_for(self.W, self.H, self.fit["fov_deg"])
            N = normal_from_angles(self.fit["tilt"], self.fit["azimuth"], cam)
            plane = Plane(cam.position + cam.forward, N)
            self._incidence_key, self._incidence = key, (cam, N, plane, incidence_geometry(cam, plane))
        return self._incidence

    def outcome(self, stage: str, verdict: str, reason: str = "") -> StageOutcome:
        return StageOutcome(stage, verdict, reason, math.degrees(self.fit["tilt"]), math.degrees(self.fit["azimuth"]) % 360.0, float(self.fit["fov_deg"]))

    def failed(self, reason: str) -> SelfCalResult:
        log.warning("self-calibrated zeta for %s: %s; no self-calibrated zeta (the caller's fallback: zeta = 0 for the network, the learned zeta for the physics solvers)", self.name, reason)
        cfg, fit = self.cfg, self.fit
        return SelfCalResult(False, reason, None, None, None, None, float(fit["fov_deg"]), False, cfg.n, cfg.prior_model if self.auto else cfg.model, None, None,
                             self.frac, self.res_deg, fit["twin_ratio"], self.diag)


def _stage_detection(c: _Calibration) -> StageOutcome:
    """Something must modulate: the orientation field's detection z and the share of 4 x 4 blocks above noise."""
    fit, cfg, diag = c.fit, c.cfg, c.diag
    if not fit["z"] >= cfg.z_min:
        return c.outcome("detection", "fail", f"nothing modulates: the best planar pane explains the polarization orientation only {fit['z']:.1f} noise sigmas above chance (need {cfg.z_min:g}; "
                         f"{100 * diag['modulating_px']:.1f} % of pixels modulate above noise); no reflection, R = T, or near-normal incidence")
    if not diag["modulating_blocks"] >= cfg.min_modulating_blocks:
        return c.outcome("detection", "fail", f"nothing modulates: the best planar pane explains the orientation field {fit['z']:.1f} noise sigmas above chance, yet only "
                         f"{100 * diag['modulating_blocks']:.2f} % of 4 x 4 pixel blocks modulate above noise (need {100 * cfg.min_modulating_blocks:g} %): "
                         "motion aliasing into the polarizer's harmonic, no polarizer, or near-normal incidence")
    return c.outcome("detection", "pass", f"z {fit['z']:.1f}, {100 * diag['modulating_blocks']:.1f} % of blocks modulate")


def _stage_twin(c: _Calibration) -> StageOutcome:
    """The 90 deg twin: where the orientation field cannot tell the pane from its twin (``max_twin_ratio``) the DoP cone,
    then the layers' content, decide; where it prefers one only narrowly with the fov free (``twin_check_ratio``), the
    twin is taken only on both votes.
    """
    fit, cfg, diag = c.fit, c.cfg, c.diag
    I, phi = c.I, c.phi
    if c.fov_given is None and cfg.twin_check_ratio <= fit["twin_ratio"] <= cfg.max_twin_ratio:
        # with the fov free the twin family can bend along its own fov-tilt valley and the orientation field's preference
        # is narrow: a twin handed over swaps R and T. Overturn only on two independent votes for the twin
        chk = _resolve_by_cone(I, phi, c.f, fit, c.W, c.H, c.fov_given, dataclasses.replace(cfg, valley_step_deg=cfg.twin_check_step_deg))
        v0, v1 = chk["v_family"]
        cc = (chk.get("content") or {}).get("corr_family") or [None, None]
        content_twin = cc[0] is not None and cc[1] is not None and np.isfinite(cc[1]) and cc[1] < cc[0]
        overturn = bool(v0 - v1 > cfg.cone_margin and content_twin)
        diag["twin_check"] = {"v_family": [v0, v1], "corr_family": cc, "overturned": overturn}
        if not overturn:
            return c.outcome("twin", "pass", "a narrow orientation choice, kept: the cone and the layers' content do not both prefer the twin")
        c.aggs = chk.pop("aggs")
        diag["cone"] = {**chk, "resolved": True, "by": "twin_check", "chosen_family": 1}
        c.move(tilt=chk["tilt"], azimuth=chk["azimuth"], fov_deg=chk["fov_deg"])
        return c.outcome("twin", "moved", "the orientation field's narrow choice overturned: the DoP cone and the layers' content both prefer its 90 deg twin")
    if not fit["twin_ratio"] > cfg.max_twin_ratio:
        return c.outcome("twin", "skipped", f"the orientation field prefers the pane over its 90 deg twin (ratio {fit['twin_ratio']:.3f})")
    # the orientation field cannot separate the pane from its 90 deg twin (nor pin the tilt of a narrow view):
    # the DoP must stay inside the cone [-DoP_T(theta), DoP_R(theta)] (R, T >= 0), which the wrong family breaks
    cone = _resolve_by_cone(I, phi, c.f, fit, c.W, c.H, c.fov_given, cfg)
    c.aggs = cone.pop("aggs")
    diag["cone"] = cone
    if not cone["resolved"]:
        ct = cone.get("content")
        if cone.get("conflict"):
            return c.outcome("twin", "fail", f"ambiguous: a pane with phi_perp turned by 90 deg explains the orientation field {100 * fit['twin_ratio']:.1f} % as well, and the "
                             f"DoP cone (violations {cone['v_family'][0]:.1f} / {cone['v_family'][1]:.1f}) and the layers' content (gradient |correlation| "
                             f"{ct['corr_family'][0]:.2f} / {ct['corr_family'][1]:.2f}) pick different families")
        ctxt = (f"; nor does the layers' content (gradient |correlation| of R^ and T^ {ct['corr_family'][0]:.2f} / {ct['corr_family'][1]:.2f}, "
                f"need the other family {cfg.content_margin:g} above and {cfg.content_ratio:g} times the chosen one, which must hold the cone)") if ct else ""
        return c.outcome("twin", "fail", f"ambiguous: a pane with phi_perp turned by 90 deg explains the orientation field {100 * fit['twin_ratio']:.1f} % as well "
                         f"(narrow field of view or glancing pane), and both keep the DoP inside the Fresnel cone (violations {cone['v_family'][0]:.1f} / "
                         f"{cone['v_family'][1]:.1f}, need the other family {cfg.cone_margin:g} above and {cfg.cone_ratio:g} times the chosen one): "
                         f"no part of the view shows the reflection dominating beyond DoP_T, or neither family fits" + ctxt)
    c.move(tilt=cone["tilt"], azimuth=cone["azimuth"], fov_deg=cone["fov_deg"])
    return c.outcome("twin", "moved", "90 deg twin resolved by the layers' content" if cone.get("by") == "content" else "90 deg twin resolved by the cone")


def _stage_polish(c: _Calibration) -> StageOutcome:
    """The scatter-weighted fit from the chosen geometry, kept only inside the chosen family and within ``polish_max_move_deg``."""
    cfg, fit, diag = c.cfg, c.fit, c.diag
    if cfg.geometry_weighting != "scatter":
        return c.outcome("polish", "skipped", f"geometry_weighting = {cfg.geometry_weighting}")
    # the grid search and the twin / cone decisions weigh blocks by |sum z4|, which holds the signal's power: the final
    # geometry is the scatter-weighted fit from there, kept in the chosen family (a local move, no 90 deg flip)
    pol = polish_geometry(c.f, diag["block_px"], fit["tilt"], fit["azimuth"], fit["fov_deg"], c.fov_given is None and "cone" not in diag)  # the cone chose along the tilt-fov valley: keep its fov
    if pol is None:
        return c.outcome("polish", "skipped", "too few blocks for the scatter-weighted fit")
    pp0 = _pane_phi_perp(c.w, c.h, fit["tilt"], fit["azimuth"], fit["fov_deg"])
    pp1 = _pane_phi_perp(c.w, c.h, pol["tilt"], pol["azimuth"], pol["fov_deg"])
    a4 = np.abs(c.f.s4)
    same = float(np.sum(a4 * np.cos(2.0 * (pp1 - pp0))) / max(float(a4.sum()), 1e-300))
    moved = math.degrees(_sep(fit["tilt"], fit["azimuth"], pol["tilt"], pol["azimuth"]))
    diag["polish"] = {"from": [math.degrees(fit["tilt"]), math.degrees(fit["azimuth"]) % 360.0, float(fit["fov_deg"])],
                      "to": [math.degrees(pol["tilt"]), math.degrees(pol["azimuth"]), pol["fov_deg"]], "same_family": same, "moved_deg": moved}
    if same > 0.5 and moved < cfg.polish_max_move_deg:
        c.move(**pol)
        return c.outcome("polish", "moved", f"the normal moved {moved:.2f} deg within its family")
    diag["polish"]["kept"] = f"the cone's / grid's pane (the polish left the family or moved > {cfg.polish_max_move_deg:g} deg)"
    return c.outcome("polish", "pass", diag["polish"]["kept"])


def _stage_tilt(c: _Calibration) -> StageOutcome:
    """A pane seen near normal incidence modulates too little to calibrate (``min_tilt_deg``)."""
    tilt_deg = math.degrees(c.fit["tilt"])
    if tilt_deg < c.cfg.min_tilt_deg:
        return c.outcome("tilt", "fail", f"near-normal incidence (fitted tilt {tilt_deg:.1f} deg): no usable modulation")
    return c.outcome("tilt", "pass", f"tilt {tilt_deg:.1f} deg")


def _stage_glass(c: _Calibration) -> StageOutcome:
    """Index and pane model (``model = auto``): the DoP cone where it constrains them, else the layers' content for the
    model, else the priors.
    """
    cfg, diag = c.cfg, c.diag
    if not c.auto:
        return c.outcome("glass", "skipped", f"given: {cfg.model}, n {cfg.n:g}")
    _, _, _, geo = c.incidence()
    theta = geo["theta"]
    if c.aggs is None:
        a0, cc = chunk_harmonics(c.I, c.phi)
        c.aggs = cone_aggregates(a0, cc, geo["phi_perp"], theta)
    gl = fit_glass(glass_scores(c.aggs, _span_factor_of(c.phi), slack=GLASS_SLACK), cfg.n, cfg.prior_model, cfg.cone_margin)
    ct = (diag.get("cone") or {}).get("content")
    if not gl["model_identified"] and ct and diag["cone"].get("by") == "content" and ct["model_identified"]:
        # the cone does not tell single from slab, the layers' content did (the pane model's scale leaks T into R^)
        gl["model"], gl["model_by_content"] = ct["model"], True
    elif not gl["model_identified"]:
        cm = content_model(c.I, c.phi, geo["phi_perp"], theta, gl["n"])
        gl["content"] = cm
        if cm["identified"]:
            gl["model"], gl["model_by_content"] = cm["model"], True
    c.n_used, c.model_used = gl["n"], gl["model"]
    gl["scores_by_model"] = {k: float(v) for k, v in gl["scores_by_model"].items()}
    gl["why"] = (("model from the cone" if gl["model_identified"] else "model from the layers' content (the cone does not separate single from slab)" if gl.get("model_by_content")
                  else f"model not identified (no cone edge separates single from slab): assumed {cfg.prior_model}")
                 + "; " + (f"index from the cone (range {gl['n_range'][0]:g}-{gl['n_range'][1]:g})" if gl["n_identified"]
                           else f"index not identified (the data fit {gl['n_range'][0]:g}-{gl['n_range'][1]:g}): {c.n_used:g}"))
    diag["glass"] = gl
    return c.outcome("glass", "pass", f"{c.model_used}, n {c.n_used:g}: {gl['why']}")


CASCADE = (("detection", _stage_detection), ("twin", _stage_twin), ("polish", _stage_polish), ("tilt", _stage_tilt), ("glass", _stage_glass))
"""The self-calibration's stages, in order: each reads the geometry the stages before it left and returns a
:class:`StageOutcome`; the first ``"fail"`` ends the cascade with no self-calibrated zeta."""


def self_calibrate(I: np.ndarray, phi: np.ndarray, cfg: SelfCalConfig = SelfCalConfig(), *, frames_per_s: float | None = None, name: str = "stream",
                   exposure: float | None = None) -> SelfCalResult:
    """Estimate the pane (normal, field of view, and where the data constrain them index and pane model)
    from a stream's frames and build its pane maps.

    Args:
        I: (M, H, W) Eq. (3) frames in radiance units, consecutive (the first ``cfg.span_s`` are used).
        phi: (M,) their polarizer angles (window centres, calibrated), radians.
        cfg: :class:`SelfCalConfig`.
        frames_per_s: frame cadence, to turn ``span_s`` into frames (None: use every frame given).
        name: for the log.
        exposure: the stream's exposure (spikes per step per unit radiance), when known: pixels that saturate in any
            frame are left out (:func:`leave_out_saturated`; their share is ``diagnostics["saturated_px"]``).

    Returns:
        :class:`SelfCalResult`; ``ok = False`` (with a logged warning) where nothing modulates or the
        geometry stays ambiguous.  ``diagnostics`` carries ``modulating_px`` / ``modulating_blocks``
        (share of pixels / 4 x 4 blocks modulating above noise, :func:`modulating_fraction`), ``cone``
        (the 90 deg / tilt-valley resolution, when needed), ``twin_check`` (with the fov fitted, the cone's and the
        content's votes on a narrow orientation choice, and whether they overturned it) and ``glass`` (the index / model fit); ``stages``: each stage of
        :data:`CASCADE` as a plain :class:`StageOutcome` (name, verdict, reason, the geometry after it).
    """
    I = np.asarray(I)
    if I.ndim != 3:
        raise ShapeError(f"self_calibrate needs frames (M, H, W); got {I.shape}", actual_shape=I.shape, expected_shape="(M, H, W)")
    M, H, W = I.shape
    m = M if frames_per_s is None else max(3, min(M, int(round(cfg.span_s * frames_per_s))))
    I, sat_px = leave_out_saturated(I[:m], exposure)
    s = cfg.block_px or max(1, W // 48)
    s = max(1, min(s, max(1, H // 4), max(1, W // 4)))
    I, phi = I[:m], np.asarray(phi)[:m]
    f = orientation_field(I, phi, s)
    thr = cfg.coherence_sigmas
    mask = np.abs(f.s4) > thr * np.sqrt(0.5 * np.maximum(f.q, 1e-300))  # blocks that modulate on their own
    diag = {"psi": f.psi, "coherence": f.coherence, "mask": mask, "block_px": s, "threshold": thr, "frames": m, "chunks": f.chunks, "dop": f.dop, "s4": f.s4, "saturated_px": sat_px}
    fov_given = cfg.fov_deg if cfg.fov_deg > 0 else None
    fit = fit_normal(f.s4, f.q, f.psi.shape[1], f.psi.shape[0], fov_given, cfg.fov_init_deg)
    diag.update({"z": fit["z"], "alignment": fit["alignment"]})
    c = _Calibration(I, phi, cfg, name, f, mask, diag, fit, fov_given)
    diag["stages"] = []
    for _, stage in CASCADE:
        outcome = stage(c)
        diag["stages"].append(dataclasses.asdict(outcome))
        if outcome.verdict == "fail":
            return c.failed(outcome.reason)
    fit = c.fit
    cam, N, plane, geo = c.incidence()
    theta = geo["theta"]
    maps = pane_maps_from_geometry(cam, plane, c.n_used, model=c.model_used)
    vp = None
    if float(N @ cam.forward) > 1e-6:
        x, y = cam.project(cam.position + N)
        vp = (float(x), float(y))
    tilt_deg = math.degrees(fit["tilt"])
    res = SelfCalResult(
        True, "", N, tilt_deg, math.degrees(fit["azimuth"]) % 360.0, vp, float(fit["fov_deg"]), fov_given is None, c.n_used, c.model_used, maps, theta, c.frac,
        c.res_deg, fit["twin_ratio"], diag,
    )
    how = ""
    if "cone" in diag:
        ct = diag["cone"].get("content")
        how = (f" (90 deg twin resolved by the layers' content: R^ / T^ gradient |correlation| {ct['corr_family'][diag['cone']['chosen_family']]:.2f} "
               f"against {ct['corr_family'][1 - diag['cone']['chosen_family']]:.2f} for the twin; the cone held both)") if diag["cone"].get("by") == "content" else (
            " (the orientation field's narrow choice overturned: the DoP cone and the layers' content both prefer its 90 deg twin)" if diag["cone"].get("by") == "twin_check" else " (90 deg twin resolved by the cone)")
    log.info("self-calibrated pane for %s: tilt %.1f deg, azimuth %.1f deg, fov %.1f deg%s, z %.1f, %.0f %% of pixels modulating, %s n %.2f%s",
             name, tilt_deg, res.azimuth_deg, res.fov_deg, " (fitted)" if res.fov_fitted else "", fit["z"], 100 * diag["modulating_px"], c.model_used, c.n_used, how)
    return res


def group_self_zeta(group, n: float | None = None, model: str | None = None, cfg: SelfCalConfig | None = None) -> np.ndarray | None:
    """The ``self`` zeta source for an evaluation group: zeta (M, H, W) at the group's nominal angles, or None.

    ``n`` / ``model`` given: that index and pane model; None: ``cfg``'s (default: fitted from the DoP's cone
    and the layers' content where the data constrain them, else thin slab, n = 1.5).

    The field of view is the group's (``group.fov_deg``, from its scene) when recorded, else fitted.
    A group loaded from a store (``group.source_dir``) is calibrated on every spike of its first
    ``span_s`` (back-to-back Eq. (3) windows, about 4.5 times the data of the 31.5 deg-strided output
    frames); otherwise on its frames.
    None (with a logged warning) where nothing modulates: the caller falls back to the learned zeta.
    """
    base = cfg or SelfCalConfig()
    fov = getattr(group, "fov_deg", None)
    c = dataclasses.replace(base, n=float(n) if n is not None else base.n, model=model or base.model, fov_deg=float(fov) if (fov and not base.fov_deg) else base.fov_deg)
    src_dir = getattr(group, "source_dir", None)
    if src_dir and (Path(src_dir) / "spikes.h5").is_file():
        # a stored group: every spike of the first span_s (back-to-back windows), not only the strided output frames
        from reconstruct.stream.sources import (
            frames_exposure,
            group_source,
            span_frames,
        )

        src = group_source(src_dir)
        exposure = frames_exposure(src)
        I, phi = span_frames(src, c.span_s, exposure=exposure)
    else:
        frames = min(group.I.shape[0], MAX_FRAMES)
        I, phi = group.I[:frames], np.asarray(group.phi_nominal)[:frames]
        exposure = getattr(group, "exposure", None)
    r = self_calibrate(I, phi, c, name=group.name, exposure=exposure)
    group_self_zeta.last = r  # the latest calibration, for reports
    if not r.ok:
        return None
    return self_zeta(r, group.phi_nominal, group.span_rad)


MAX_FRAMES = 400
"""At most this many frames of a group go into the self-calibration (about 1.2 s at 343 frames/s)."""


def self_zeta(result: SelfCalResult, phi: np.ndarray, span_rad: float = 0.0, dtype: torch.dtype = torch.float64) -> np.ndarray:
    """Zeta (M, H, W) at angles phi (M,) from a successful calibration, paper Eq. (2) (window-averaged over span_rad)."""
    if not result.ok or result.maps is None:
        raise ConfigError(f"no self-calibrated pane ({result.reason}); use --zeta learned or physics")
    return zeta_from_maps(result.maps, np.asarray(phi, np.float64), span_rad, dtype=dtype).numpy()
