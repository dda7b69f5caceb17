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

1. Harmonic fit (supp. Eq. (1), :func:`reconstruct.harmonic_fit.harmonic_fit`) on
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
   the pane model give R_perp, R_par by :func:`reconstruct.zeta_source.pane_maps_from_geometry`,
   and zeta_k(p) by paper Eq. (2) (:func:`reconstruct.zeta_source.zeta_from_maps`).

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
:func:`reconstruct.net_zeta.fallback_for`).  ``diagnostics["modulating_px"]`` reports
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
import json
import logging
import math
from pathlib import Path

import numpy as np
import torch

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError

from reconstruct.exclusion import cross_gradient_sums
from reconstruct.harmonic_fit import half_turn_frames, harmonic_fit
from reconstruct.zeta_source import PaneMaps, pane_maps_from_geometry, zeta_from_maps

__all__ = [
    "StreamTooShortError",
    "SelfCalConfig",
    "SelfCalResult",
    "orientation_field",
    "fit_normal",
    "layer_gradient_correlation",
    "content_model",
    "self_calibrate",
    "self_zeta",
    "group_self_zeta",
    "camera_for",
    "normal_from_angles",
    "fov_from_group_dir",
]

log = logging.getLogger(__name__)



class StreamTooShortError(ConfigError):
    """The stream is shorter than the self-calibration needs (half a polarizer turn of frames): a caller with
    another zeta source (the network's learned zeta) falls back to it; one without says so (exit 2)."""

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
    valley_drop_fov_bounds: bool = opt(True, "fov fitted: cone / content candidates whose fitted fov ran into the search bounds (5 or 150 deg) are left out where each family keeps a candidate inside them: degenerate views, not fitted values, whose layers can come out as independent as the right pane's (the stress set's weak glancing 18 deg view with the fov withheld: the twin family's 5 deg candidates scored 0.23 against the pane's 0.10 and the group was refused; without them 0.40, resolved)")
    valley_ratio: float = opt(0.97, "cone test: panes scoring at least this fraction of the orientation optimum are candidates", lo=0.0, hi=1.0)
    z_min: float = opt(8.0, "the fitted pane must explain the orientation field this many noise standard deviations above chance, else 'nothing modulates' (ok = False)", lo=0.0, hi=1e6)
    geometry_weighting: str = opt("scatter", "weights of the blocks in the final geometry fit: scatter (each block by 1 / (its orientation's measured variance, from the scatter of its pixels across its direction, plus a misfit floor), robust to blocks the plane does not explain; calibrate-pane's, docs/selfcal.md) or s4 (by |sum z4|, the matched filter of the grid search, which overweights weak blocks whose |sum z4| is mostly their signal's power)", choices=("scatter", "s4"))
    min_modulating_blocks: float = opt(0.002, "the fitted pane must make at least this share of 4 x 4 pixel blocks modulate above 3 noise sigmas (diagnostics modulating_blocks), else 'nothing modulates' (ok = False): a moving scene seen without a polarizer aliases into an orientation field that a narrow pane explains above chance while no block modulates (the REDS stream: z 11.5, 0 % of blocks); the weakest real pane measured (paper_val train_004, R close to T) has 0.45 %, the stress and test groups 5 % and more", lo=0.0, hi=1.0)
    coherence_sigmas: float = opt(4.0, "diagnostics: a block counts as modulating when its |sum z4| exceeds this many noise standard deviations", lo=0.0, hi=100.0)
    max_twin_ratio: float = opt(0.98, "the pane turned 90 deg (phi_perp <-> p-direction) scoring above this fraction of the best: the DoP cone decides, else ambiguous (ok = False)", lo=0.0, hi=10.0)
    min_tilt_deg: float = opt(3.0, "a fitted tilt below this is near-normal incidence: no usable modulation (ok = False)", lo=0.0, hi=89.0)
    content_margin: float = opt(0.2, "content test (where the cone leaves the 90 deg twin open): the other family's smallest layer-gradient |correlation| must exceed the chosen one's by this (0 = off: refuse as before)", lo=0.0, hi=2.0)
    content_ratio: float = opt(3.0, "content test: ... and be at least this many times the chosen one's", lo=1.0, hi=1e9)
    twin_check_ratio: float = opt(0.95, "fov fitted: where the 90 deg twin scores between this and max_twin_ratio of the best, the DoP cone and the layers' content are asked too, and the twin is taken where both prefer it, the cone by more than cone_margin (1 = off)", lo=0.0, hi=10.0)
    twin_check_step_deg: float = opt(4.0, "the narrow twin check's tilt step along each family's valley, degrees (the cone test's own is valley_step_deg; the check's scan is most of its time)", lo=0.5, hi=20.0)
    polish_max_move_deg: float = opt(45.0, "the scatter-weighted polish of the geometry is kept only where it turns the normal by less than this (degrees) and stays in the chosen 90 deg family; with the fov free it moves along the fov-tilt valley, where the normal turns a lot for little change in the field (eval_paper test_005, fov withheld: 16 deg from a grid fov of 70 to 43.8, truth 43.1; 15 deg until session 13)", lo=0.0, hi=180.0)


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


def camera_for(width: int, height: int, fov_deg: float):
    """The reference pinhole (origin, looking along +z, up +y) of ``width`` x ``height`` pixels."""
    from polphysics.geometry import PinholeCamera

    return PinholeCamera.look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], fov_x_deg=float(fov_deg), width=int(width), height=int(height))


def normal_from_angles(tilt_rad: float, azimuth_rad: float, camera) -> np.ndarray:
    """Unit normal at ``tilt`` from the camera's forward axis, its image projection at ``azimuth``
    counter-clockwise from image +x (camera.right) towards image up (camera.up)."""
    st = math.sin(tilt_rad)
    return st * math.cos(azimuth_rad) * camera.right + st * math.sin(azimuth_rad) * camera.up + math.cos(tilt_rad) * camera.forward


def _angles_of(normal: np.ndarray, camera) -> tuple[float, float]:
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    if float(n @ camera.forward) < 0:
        n = -n
    tilt = math.acos(min(1.0, float(n @ camera.forward)))
    az = math.atan2(float(n @ camera.up), float(n @ camera.right)) % (2 * math.pi)
    return tilt, az


def fov_from_group_dir(path) -> float | None:
    """Horizontal field of view (degrees) recorded in a dataset group's ``group_spec.json`` (scene.camera.fov_deg), else None."""
    p = Path(path) / "group_spec.json"
    try:
        doc = json.loads(p.read_text())
        return float(doc["scene"]["camera"]["fov_deg"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _block(x: np.ndarray, s: int) -> np.ndarray:
    H, W = x.shape[-2:]
    h, w = H // s, W // s
    return x[..., : h * s, : w * s].reshape(*x.shape[:-2], h, s, w, s).sum(axis=(-3, -1))


def orientation_field(I: np.ndarray, phi: np.ndarray, block: int) -> dict:
    """Modulation orientation (mod 90 deg) and coherence on a block grid (module docstring, step 1).

    Each chunk's harmonic coefficients are normalised by the chunk mean (a0, with a small floor):
    z = (ac + i as) / a0, and z4 = z^2 carries angle 4 AoLP.  Spike noise on z grows as 1/sqrt(a0),
    so this roughly whitens bright and dark pixels alike.  Pure noise gives z4 of random phase:
    sum z4 grows as sqrt(samples) there and as samples where the pane modulates.

    Args:
        I: (M, H, W) Eq. (3) frames, radiance units, consecutive in time.
        phi: (M,) polarizer angles (window centres, unwrapped), radians.
        block: block size s in pixels.

    Returns:
        dict with block-grid (h, w) fields ``s4`` (complex sum of z4), ``q`` (sum |z4|^2, the
        noise scale: Var Re(s4 e^{-i t}) = q / 2 under pure noise), ``energy`` (sum |z4|),
        ``psi`` = arg(s4) / 4 in [0, pi/2), ``coherence`` = |s4| / energy in [0, 1]; and
        ``samples`` (chunks x s^2), ``chunks``, ``chunk_frames``, full-grid ``dop`` (mean per-chunk DoP),
        ``a0`` (mean intensity), ``s4_px`` and ``q_px`` (the per-pixel sums before blocking).
    """
    I = np.asarray(I, np.float64)
    phi = np.asarray(phi, np.float64)
    if I.ndim != 3 or phi.shape != I.shape[:1]:
        raise ShapeError(f"orientation_field needs I (M, H, W) and phi (M,); got {I.shape} and {phi.shape}", actual_shape=I.shape, expected_shape="(M, H, W)")
    # chunks of about half a polarizer turn (one cycle of 2 phi), at least 3 frames
    L = half_turn_frames(phi)
    n_chunks = I.shape[0] // L
    if n_chunks < 1:
        raise StreamTooShortError(f"self-calibration needs at least {L} frames (half a polarizer turn); got {I.shape[0]}: use a longer span")
    H, W = I.shape[1:]
    s4 = np.zeros((H, W), np.complex128)
    q = np.zeros((H, W))
    en = np.zeros((H, W))
    dop = np.zeros((H, W))
    a0s = np.zeros((H, W))
    floor = 0.05 * max(float(I.mean()), 1e-12)
    # sliding windows (every start frame): the design's anisotropy (angles not uniform over a cycle)
    # biases z4 of noise and of content drift along 4 x the window's start angle; over all starts
    # (the start advances by one stride) that angle turns round and the bias averages out
    starts = range(0, I.shape[0] - L + 1)
    for j in starts:
        sl = slice(j, j + L)
        a0, ac, as_ = (t.numpy() for t in harmonic_fit(torch.from_numpy(I[sl]), torch.from_numpy(phi[sl])))  # supp. Eq. (1)
        z = (ac + 1j * as_) / (np.abs(a0) + floor)
        z4 = z * z  # angle 4 AoLP: the sign of R - T (the 90 deg flip) drops out
        s4 += z4
        a = np.abs(z4)
        en += a
        q += a * a
        dop += np.abs(ac + 1j * as_) / np.maximum(np.abs(a0), 1e-12)
        a0s += a0
    n_win = len(starts)
    q *= L  # overlapping windows: each sample is correlated with about L neighbours (conservative noise scale)
    bs4 = _block(s4.real, block) + 1j * _block(s4.imag, block)
    ben, bq = _block(en, block), _block(q, block)
    coh = np.where(ben > 0, np.abs(bs4) / np.maximum(ben, 1e-300), 0.0)
    psi = np.mod(0.25 * np.angle(bs4), 0.5 * math.pi)
    return {"s4": bs4, "q": bq, "energy": ben, "psi": psi, "coherence": coh, "samples": n_chunks * block * block, "chunks": n_chunks, "windows": n_win, "chunk_frames": L, "dop": dop / n_win, "a0": a0s / n_win,
            "s4_px": s4, "q_px": q}


def _phi_perp_many(camera, normals: np.ndarray, batch: int = 128):
    """phi_perp grids for many normals (K, 3): incidence_geometry broadcast over a (k, 1, 1, 3) normal, in batches."""
    from polphysics.geometry import Plane, incidence_geometry

    for i in range(0, normals.shape[0], batch):
        yield incidence_geometry(camera, Plane(camera.position + camera.forward, normals[i : i + batch, None, None, :]))["phi_perp"]


def _phi_perp_grid(camera, normal: np.ndarray) -> np.ndarray:
    from polphysics.geometry import Plane, incidence_geometry

    return incidence_geometry(camera, Plane(camera.position + camera.forward, normal))["phi_perp"]


def _pane_phi_perp(width: int, height: int, tilt: float, az: float, fov_deg: float) -> np.ndarray:
    """phi_perp (height, width) of the pane with normal (tilt, az) on a width x height grid seen with horizontal fov fov_deg."""
    cam = camera_for(width, height, fov_deg)
    return _phi_perp_grid(cam, normal_from_angles(tilt, az, cam))


FOV_BOUNDS_DEG = (5.0, 150.0)
"""Search bounds (degrees) of a fitted field of view: :func:`fit_normal`, :func:`polish_geometry` and
:func:`valley_candidates`, which leaves out candidates that ran into them."""


def fit_normal(s4: np.ndarray, q: np.ndarray, width_blocks: int, height_blocks: int, fov_deg: float | None, fov_init_deg: float = 60.0) -> dict:
    """Fit the pane normal (and optionally the field of view) to a block-grid orientation field.

    Maximises the matched statistic C(N) = sum_b Re(s4_b exp(-4 i phi_perp_b(N))) (module docstring,
    step 2), i.e. minimises sum_b |s4_b| (1 - cos 4 delta_b) = 2 sum_b |s4_b| sin^2 2 delta_b with
    delta_b = psi_b - phi_perp_b: invariant to the 90 deg flip, blocks weighted by their coherent
    modulation (noise blocks add little and have random phase).

    Args:
        s4: (h, w) complex block sums of z4 (:func:`orientation_field`).
        q: (h, w) block sums of |z4|^2 (noise scale).
        width_blocks, height_blocks: w, h.
        fov_deg: known horizontal field of view, or None to fit it.
        fov_init_deg: start value for a fitted field of view.

    Returns:
        dict with ``tilt``, ``azimuth`` (radians), ``fov_deg``, ``score`` = C(N*), ``z`` = C(N*) / sqrt(q_total / 2)
        (its size in noise standard deviations), ``alignment`` = C(N*) / sum |s4| in [-1, 1],
        ``twin_ratio`` = C of the best pane whose phi_perp field is rotated by about 90 deg from the optimum's
        (weighted mean cos 2 (phi_perp - phi_perp*) < 0), over C(N*): near 1 = the 90 deg flip cannot be resolved.
    """
    from scipy.optimize import least_squares

    mag = np.abs(s4).ravel()
    ang4 = np.angle(s4).ravel()
    tot = float(mag.sum())
    if tot <= 0:
        return {"tilt": 0.0, "azimuth": 0.0, "fov_deg": float(fov_deg or fov_init_deg), "score": 0.0, "z": 0.0, "alignment": 0.0, "twin_ratio": float("nan")}
    fov0 = float(fov_deg) if fov_deg else float(fov_init_deg)

    def phis(tilt, az, fov):
        return _pane_phi_perp(width_blocks, height_blocks, tilt, az, fov).ravel()

    def score(tilt, az, fov):
        return float(np.sum(mag * np.cos(ang4 - 4.0 * phis(tilt, az, fov))))

    # grid search over the hemisphere (tilt up to 88 deg, every azimuth): Hough-like, no local-minimum trap
    tilts = np.deg2rad(np.arange(2.0, 89.0, 4.0))
    azs = np.deg2rad(np.arange(0.0, 360.0, 8.0))
    cam0 = camera_for(width_blocks, height_blocks, fov0)
    normals = np.array([normal_from_angles(t, a, cam0) for t in tilts for a in azs])
    pp_all = np.concatenate([pp.reshape(pp.shape[0], -1) for pp in _phi_perp_many(cam0, normals)])  # (candidates, blocks)
    grid = np.sum(mag * np.cos(ang4 - 4.0 * pp_all), axis=1).reshape(len(tilts), len(azs))
    order = np.argsort(-grid, axis=None)
    starts: list[tuple[float, float]] = []
    for idx in order:
        ti, ai = np.unravel_index(idx, grid.shape)
        t, a = float(tilts[ti]), float(azs[ai])
        if all(_sep(t, a, t2, a2) > math.radians(15) for t2, a2 in starts):
            starts.append((t, a))
        if len(starts) >= 3:
            break
    sw = np.sqrt(2.0 * mag / tot)

    def refine(t0, a0):
        if fov_deg:
            fun = lambda x: sw * np.sin(0.5 * (ang4 - 4.0 * phis(x[0], x[1], fov0)))  # noqa: E731  (= sin 2 delta)
            x0, lb, ub = [t0, a0], [0.0, a0 - math.pi], [math.radians(89.9), a0 + math.pi]
        else:
            fun = lambda x: sw * np.sin(0.5 * (ang4 - 4.0 * phis(x[0], x[1], x[2])))  # noqa: E731
            x0, lb, ub = [t0, a0, fov0], [0.0, a0 - math.pi, FOV_BOUNDS_DEG[0]], [math.radians(89.9), a0 + math.pi, FOV_BOUNDS_DEG[1]]
        r = least_squares(fun, x0, bounds=(lb, ub), x_scale=[0.1, 0.1] + ([10.0] if not fov_deg else []))
        f = float(r.x[2]) if not fov_deg else fov0
        return (score(r.x[0], r.x[1], f), float(r.x[0]), float(r.x[1]) % (2 * math.pi), f)

    fits = sorted((refine(t0, a0) for t0, a0 in starts), reverse=True)
    best = fits[0]
    # the 90 deg twin: the best pane whose s-directions run (mostly) along the best fit's p-directions.
    # Modulo 90 deg the two fields agree where the view is narrow and the pane glancing; only the
    # field's curvature tells them apart, and twin_ratio near 1 says it cannot.
    pp_best = phis(best[1], best[2], best[3])
    wcos = np.sum(mag * np.cos(2.0 * (pp_all - pp_best)), axis=1) / tot
    twin_ratio = float("nan")
    cand = np.flatnonzero(wcos < 0.0)
    if cand.size and best[0] > 0:
        k = int(cand[np.argmax(grid.ravel()[cand])])
        tw = refine(float(tilts[k // len(azs)]), float(azs[k % len(azs)]))
        pp_tw = phis(tw[1], tw[2], tw[3])
        is_twin = float(np.sum(mag * np.cos(2.0 * (pp_tw - pp_best)))) < 0
        tw_score = tw[0] if is_twin else float(grid.ravel()[k])
        twin_ratio = max(tw_score, float(grid.ravel()[k])) / best[0]
        twin = tw if (is_twin and tw[0] >= float(grid.ravel()[k])) else (float(grid.ravel()[k]), float(tilts[k // len(azs)]), float(azs[k % len(azs)]), fov0)
    else:
        twin = None
    z = best[0] / math.sqrt(0.5 * max(float(q.sum()), 1e-300))
    out = {"tilt": best[1], "azimuth": best[2], "fov_deg": best[3], "score": best[0], "z": z, "alignment": best[0] / tot, "twin_ratio": twin_ratio}
    if twin is not None:
        out.update({"twin_tilt": twin[1], "twin_azimuth": twin[2], "twin_fov_deg": twin[3], "twin_score": twin[0]})
    return out


def _sep(t1, a1, t2, a2) -> float:
    """Angle between two normals given as (tilt, azimuth)."""
    v1 = np.array([math.sin(t1) * math.cos(a1), math.sin(t1) * math.sin(a1), math.cos(t1)])
    v2 = np.array([math.sin(t2) * math.cos(a2), math.sin(t2) * math.sin(a2), math.cos(t2)])
    return math.acos(max(-1.0, min(1.0, float(v1 @ v2))))


def block_orientation_variance(of: dict, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Noise variance (rad^2) of each block's orientation psi_b = arg(s4_b) / 4, measured from the scatter of its
    pixels' sums s4_px perpendicular to the block's direction: Var Im(s4_b e^{-i 4 psi_b}) = (pixels) x their
    variance, and 4 |s4_b| dpsi = Im(...).  Unlike q / (32 |s4|^2) (the pure-noise scale, which holds the signal's
    power too), this is the orientation's actual spread, spike noise and content alike.  Also returns the block's
    effective number of contributing pixels (sum |s4_px|)^2 / sum |s4_px|^2."""
    s4, sp = of["s4"], of["s4_px"]
    h, w = s4.shape
    b = int(block)
    sp = sp[: h * b, : w * b].reshape(h, b, w, b)
    u = np.exp(-1j * np.angle(s4))[:, None, :, None]
    perp = np.imag(sp * u)
    npx = b * b
    v = (perp ** 2).sum(axis=(1, 3)) * npx / max(npx - 1, 1) / (16.0 * np.maximum(np.abs(s4), 1e-300) ** 2)
    a = np.abs(sp)
    n_eff = a.sum(axis=(1, 3)) ** 2 / np.maximum((a * a).sum(axis=(1, 3)), 1e-300)
    return v, n_eff


POLISH_MIN_BLOCK = 4
"""Smallest block (pixels per side) whose orientation variance the polish measures from its pixels' scatter."""

POLISH_ROBUST_C = 4.0
"""Cauchy scale of the scatter-weighted geometry polish, in standard deviations of a block's orientation."""


def polish_geometry(of: dict, block: int, tilt: float, az: float, fov_deg: float, fit_fov: bool) -> dict | None:
    """Scatter-weighted, robust least squares of the pane geometry on the block orientation field, from (tilt, az, fov).

    Each block weighs 1 / (v_b + floor): v_b its orientation's measured variance (:func:`block_orientation_variance`),
    the floor the misfit the best-measured quarter of the blocks shows beyond their noise (content moving through the
    harmonic fit), re-estimated once; Cauchy loss at :data:`POLISH_ROBUST_C` standard deviations.  Blocks without a
    measurable modulation (|s4| under its noise, or modulation in <= a quarter of their pixels) are left out.  The
    residual is sin(2 delta) / 2 (delta = psi - phi_perp): invariant to the 90 deg flip where R < T.
    Returns {"tilt", "azimuth", "fov_deg"} (radians, radians, degrees), or None with fewer than 8 usable blocks.
    """
    from scipy.optimize import least_squares

    if block < POLISH_MIN_BLOCK and "q_px" in of:  # a variance from a handful of pixels is too noisy to weigh by: re-block
        block = POLISH_MIN_BLOCK
        H, W = of["s4_px"].shape
        hb, wb = H // block, W // block
        if hb < 2 or wb < 2:
            return None
        s4b = _block(of["s4_px"], block)
        of = {"s4": s4b, "q": _block(of["q_px"], block), "psi": np.angle(s4b) / 4.0, "s4_px": of["s4_px"]}
    s4, q = of["s4"], of["q"]
    h, w = s4.shape
    v, n_eff = block_orientation_variance(of, block)
    mask = (np.abs(s4) > np.sqrt(0.5 * np.maximum(q, 1e-300))) & (n_eff >= 0.25 * block * block) & (v > 0)
    if mask.sum() < 8:
        return None
    v = v[mask]
    psi = of["psi"][mask]
    top = v <= np.quantile(v, 0.25)

    def pp(x):
        return _pane_phi_perp(w, h, x[0], x[1], x[2] if fit_fov else fov_deg)[mask]

    x = np.array([tilt, az] + ([fov_deg] if fit_fov else []), np.float64)
    lb = [0.0, az - math.pi] + ([FOV_BOUNDS_DEG[0]] if fit_fov else [])
    ub = [math.radians(89.9), az + math.pi] + ([FOV_BOUNDS_DEG[1]] if fit_fov else [])
    x = np.clip(x, lb, ub)
    sys2 = math.radians(1.0) ** 2
    for _ in range(2):
        sd = np.sqrt(v + sys2)
        r = least_squares(lambda z: 0.5 * np.sin(2.0 * (psi - pp(z))) / sd, x, bounds=(lb, ub), loss="cauchy", f_scale=POLISH_ROBUST_C,
                          x_scale=[0.1, 0.1] + ([10.0] if fit_fov else []))
        x = r.x
        d = 0.5 * np.abs(np.sin(2.0 * (psi - pp(x))))
        sys2 = max(math.radians(0.1) ** 2, float(np.median(d[top] ** 2)) / 0.455 - float(np.median(v[top])))
    return {"tilt": float(x[0]), "azimuth": float(x[1]) % (2 * math.pi), "fov_deg": float(x[2]) if fit_fov else float(fov_deg)}


# --------------------------------------------------------------------------- the polarization cone
CONE_N_GRID = (1.4, 1.45, 1.5, 1.55, 1.6, 1.65, 1.7)
"""Indices tried by the cone test (common glasses); the index that explains the data best is reported."""

CONE_MODELS = ("single", "thin_slab")
"""Pane models told apart by the cone (``thick_slab`` has the same reflectances as ``thin_slab`` without absorption)."""

GLASS_SLACK = 3.0
"""Noise standard deviations of slack per aggregate in the glass (index / model) fit (:func:`cone_violation`)."""

CONE_SCALES = (2, 4, 8)
"""Block sizes (pixels) of the cone statistics; each also summed over the whole span."""


def chunk_harmonics(I: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Harmonic fit (supp. Eq. (1)) on back-to-back chunks of about half a polarizer turn.

    Returns (a0, c), each (C, H, W): the chunk's mean and its complex modulation c = ac + i as.  The
    modulation along an orientation psi is m = Re(c exp(-2 i psi)); with the pane's phi_perp and
    paper Eq. (1)-(2), m = B sinc (R - T) / 2 and a0 = ((1 - A) T + A R) / 2 (A, B the mean and half
    difference of R_perp, R_par), so m / a0 lies in the cone [-DoP_T, DoP_R] x sinc whatever R, T >= 0
    (:func:`cone_bounds`).  Chunks do not overlap: their noise is independent.
    """
    I = np.asarray(I, np.float64)
    phi = np.asarray(phi, np.float64)
    L = half_turn_frames(phi)
    C = I.shape[0] // L
    if C < 1:
        raise ConfigError(f"the cone test needs at least {L} frames (half a polarizer turn); got {I.shape[0]}")
    Ic = torch.from_numpy(I[: C * L].reshape(C, L, *I.shape[1:]))
    Pc = torch.from_numpy(phi[: C * L].reshape(C, L))
    a0, ac, as_ = (t.numpy() for t in harmonic_fit(Ic, Pc))  # supp. Eq. (1)
    return a0, ac + 1j * as_


def cone_bounds(theta: np.ndarray, n: float, model: str, span_factor: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) = (-DoP_T, DoP_R) x span_factor at incidence theta: the range of m / a0 for any R, T >= 0.

    DoP_R = (R_perp - R_par) / (R_perp + R_par) (T black), DoP_T = (R_perp - R_par) / (2 - R_perp - R_par)
    (R black; paper Eq. (1) transmits 1 - zeta).
    """
    from polphysics.fresnel import pane_coefficients

    co = pane_coefficients(theta, n, model=model)
    A = 0.5 * (co["R_perp"] + co["R_par"])
    B = 0.5 * (co["R_perp"] - co["R_par"])
    return -span_factor * B / np.maximum(1.0 - A, 1e-9), span_factor * B / np.maximum(A, 1e-12)


CONE_SYSTEMATIC = 0.03
"""Model error of the cone statistics, as a fraction of the aggregate's mean (layers moving within a chunk,
saturation, the Eq. (1) simplification): added in quadrature to the spike noise."""


def cone_aggregates(a0: np.ndarray, c: np.ndarray, phi_perp: np.ndarray, theta: np.ndarray, scales=CONE_SCALES, systematic: float = CONE_SYSTEMATIC) -> list[dict]:
    """Cone statistics of one pane hypothesis (its phi_perp, theta on the full grid).

    For each block size s: per chunk and over all chunks, the block sums a (of a0), m (modulation along
    phi_perp) and o (along phi_perp + 45 deg: no signal for the right orientation, the noise probe), and
    the block-mean theta.  Sums of points of a convex cone stay in the cone, so every aggregate obeys it.
    The noise variance of m is modelled as kappa * a (spike counts are Poisson), kappa fitted to o per set,
    plus (systematic * a)^2.
    """
    rot = np.exp(-2j * phi_perp)[None]
    p = c * rot
    m_px, o_px = p.real, p.imag
    out = []
    for s in scales:
        h, w = a0.shape[-2] // s, a0.shape[-1] // s
        if h < 1 or w < 1:
            continue
        th = _block(theta, s) / (s * s)
        A, Mm, O = _block(a0, s), _block(m_px, s), _block(o_px, s)
        for a, m, o, t in ((A, Mm, O, np.broadcast_to(th, A.shape)), (A.sum(0), Mm.sum(0), O.sum(0), th)):
            a, m, o, t = (np.asarray(x, np.float64).ravel() for x in (a, m, o, t))
            keep = a > 0
            a, m, o, t = a[keep], m[keep], o[keep], t[keep]
            if a.size < 4:
                continue
            kappa = float(np.median(o * o / a)) / 0.4549  # median of chi^2_1
            out.append({"scale": s, "a": a, "m": m, "theta": t, "sigma": np.sqrt(max(kappa, 1e-30) * a + (systematic * a) ** 2)})
    return out


_THETA_TABLE = np.linspace(0.0, 0.5 * math.pi, 1801)


def _bounds_table(n: float, model: str, span_factor: float) -> tuple[np.ndarray, np.ndarray]:
    key = (float(n), model, float(span_factor))
    tab = _bounds_table.cache.get(key)
    if tab is None:
        tab = _bounds_table.cache[key] = cone_bounds(_THETA_TABLE, n, model, span_factor)
    return tab


_bounds_table.cache = {}


def cone_violation(aggs: list[dict], n: float, model: str, span_factor: float = 1.0, cap: float = 8.0, slack: float = 0.0) -> float:
    """Sum over aggregates of the squared cone violation beyond ``slack`` noise standard deviations (each capped at
    ``cap``), mean over sets.  A slack keeps data sitting on the edge (a layer black there) from adding half-normal
    noise terms that grow with their number (the glass fit uses 3: the true glass then scores about 0 however much
    of the view is on the edge; the family test uses 0, measured on the stress groups, docs/selfcal.md)."""
    tlo, thi = _bounds_table(n, model, span_factor)
    tot = []
    for g in aggs:
        lo, hi = np.interp(g["theta"], _THETA_TABLE, tlo), np.interp(g["theta"], _THETA_TABLE, thi)
        v = np.maximum(np.maximum(g["m"] - hi * g["a"], lo * g["a"] - g["m"]) / g["sigma"] - slack, 0.0)
        tot.append(float(np.sum(np.minimum(v, cap) ** 2)))
    return float(np.mean(tot)) if tot else 0.0


def glass_scores(aggs: list[dict], span_factor: float = 1.0, models=CONE_MODELS, n_grid=CONE_N_GRID, slack: float = 0.0) -> dict:
    """{(model, n): cone violation} over the glass grid."""
    return {(mo, float(n)): cone_violation(aggs, n, mo, span_factor, slack=slack) for mo in models for n in n_grid}


def _hypothesis_maps(W: int, H: int, tilt: float, az: float, fov: float) -> tuple[np.ndarray, np.ndarray]:
    from polphysics.geometry import Plane, incidence_geometry

    cam = camera_for(W, H, fov)
    g = incidence_geometry(cam, Plane(cam.position + cam.forward, normal_from_angles(tilt, az, cam)))
    return g["phi_perp"], g["theta"]


def fit_glass(scores: dict, prior_n: float, prior_model: str, margin: float) -> dict:
    """Pane model and index from the cone scores (:func:`glass_scores`) of the chosen geometry.

    The model is claimed when its best index beats every other model's best by ``margin``; else
    ``prior_model``.  The index is claimed when the indices within ``margin`` of the model's best form a
    range inside the grid (reaching neither end: the data bound it from both sides); else ``prior_n``
    (moved into that range when outside it).
    """
    models = sorted({k[0] for k in scores})
    best_by_model = {mo: min(v for k, v in scores.items() if k[0] == mo) for mo in models}
    order = sorted(models, key=best_by_model.get)
    model_ok = len(order) > 1 and best_by_model[order[1]] - best_by_model[order[0]] > margin
    model = order[0] if model_ok else prior_model
    if model not in models:
        model = order[0]
    ns = sorted(k[1] for k in scores if k[0] == model)
    vm = min(scores[(model, x)] for x in ns)
    ok_ns = [x for x in ns if scores[(model, x)] <= vm + margin]
    lo_n, hi_n = min(ok_ns), max(ok_ns)
    n_ok = lo_n > ns[0] and hi_n < ns[-1]  # an interval inside the grid: the data reach the cone's edge from both sides
    n = float(min(ok_ns, key=lambda x: scores[(model, x)])) if n_ok else float(prior_n)
    if not n_ok and not (lo_n <= n <= hi_n):
        n = lo_n if n < lo_n else hi_n
    return {
        "model": model, "model_identified": bool(model_ok), "n": n, "n_identified": bool(n_ok), "n_range": [lo_n, hi_n],
        "scores_by_model": best_by_model,
    }


def valley_candidates(s4: np.ndarray, width_blocks: int, height_blocks: int, seeds: list[tuple[float, float, float]], fov_deg: float | None,
                      tilt_step_deg: float = 2.0, keep_ratio: float = 0.97, drop_fov_bounds: bool = False) -> list[dict]:
    """Panes the orientation field cannot tell apart: for each seed (tilt, azimuth, fov) and every tilt on a
    ``tilt_step_deg`` grid, the azimuth (and the field of view when not given) that best explain the field
    (matched statistic of :func:`fit_normal`), kept when they score at least ``keep_ratio`` of the best.

    Narrow views of glancing panes leave a valley of near-equal scores along the tilt and a 90 deg twin
    family; the cone test (:func:`cone_violation`) chooses among them.
    """
    from scipy.optimize import least_squares

    mag = np.abs(s4).ravel()
    ang4 = np.angle(s4).ravel()
    tot = float(mag.sum())
    if tot <= 0:
        return []
    sw = np.sqrt(2.0 * mag / tot)

    def phis(tilt, az, fov):
        return _pane_phi_perp(width_blocks, height_blocks, tilt, az, fov).ravel()

    def at_tilt(t, a_seed, f_seed):
        if fov_deg:
            fun = lambda x: sw * np.sin(0.5 * (ang4 - 4.0 * phis(t, x[0], fov_deg)))  # noqa: E731
            r = least_squares(fun, [a_seed], bounds=([a_seed - math.pi / 2], [a_seed + math.pi / 2]), x_scale=[0.1])
            az, fv = float(r.x[0]), float(fov_deg)
        else:
            fun = lambda x: sw * np.sin(0.5 * (ang4 - 4.0 * phis(t, x[0], x[1])))  # noqa: E731
            r = least_squares(fun, [a_seed, f_seed], bounds=([a_seed - math.pi / 2, FOV_BOUNDS_DEG[0]], [a_seed + math.pi / 2, FOV_BOUNDS_DEG[1]]), x_scale=[0.1, 10.0])
            az, fv = float(r.x[0]), float(r.x[1])
        return float(np.sum(mag * np.cos(ang4 - 4.0 * phis(t, az, fv)))), az, fv

    out = []
    for fam, (t_seed, a_seed, f_seed) in enumerate(seeds):
        for t in np.deg2rad(np.arange(tilt_step_deg, 89.9, tilt_step_deg)):
            # the seed's azimuth and the opposite one: near 90 deg of tilt the two describe nearly the same plane,
            # so an optimum found at the edge of the hemisphere may continue on the other side at lower tilts
            sc, az, fv = max(at_tilt(t, a, f_seed) for a in (a_seed, a_seed + math.pi))
            out.append({"tilt": float(t), "azimuth": az % (2 * math.pi), "fov_deg": fv, "score": sc, "family": fam})
    best = max([c["score"] for c in out], default=0.0)
    keep = [c for c in out if c["score"] >= keep_ratio * best]
    if drop_fov_bounds and not fov_deg:
        inside = [c for c in keep if FOV_BOUNDS_DEG[0] + 0.05 < c["fov_deg"] < FOV_BOUNDS_DEG[1] - 0.05]
        if {c["family"] for c in inside} == {c["family"] for c in keep}:
            # only where every family keeps a fitted view: a family whose whole valley sits on a bound (a field as
            # uniform as an orthographic view's) would otherwise lose by default, and the ambiguity stands
            keep = inside
    return keep



def modulating_fraction(s4_px: np.ndarray, q_px: np.ndarray, phi_perp: np.ndarray, block: int = 1, sigmas: float = 3.0) -> float:
    """Share of pixels (or ``block`` x ``block`` blocks) whose modulation is above the spike noise.

    The coherent sum of z^4 (:func:`orientation_field`) projected on the pane's 4 phi_perp, in noise standard
    deviations (variance kappa q, kappa calibrated on the projection at 4 phi_perp + 90 deg, which carries no
    pane signal), is compared with +-``sigmas``: pure noise is symmetric, so the share above +sigmas minus the
    share below -sigmas estimates the modulating share.
    """
    r = s4_px * np.exp(-4j * phi_perp)
    p, o, q = r.real, r.imag, q_px
    if block > 1:
        p, o, q = _block(p, block), _block(o, block), _block(q, block)
    q = np.maximum(q, 1e-300)
    kappa = float(np.median(o * o / q)) / 0.4549  # the orthogonal part carries no pane signal: it calibrates the noise scale
    z = p / np.sqrt(max(kappa, 1e-300) * q)
    return float(max(0.0, np.mean(z > sigmas) - np.mean(z < -sigmas)))


def _resolve_by_cone(I, phi, f, fit, W, H, fov_given, cfg) -> dict:
    """Choose among the panes the orientation field cannot tell apart (the tilt valley and the 90 deg twin
    family of a narrow view) by the polarization cone: the one whose DoP bounds hold the data.

    Returns a dict with ``resolved`` (bool), the chosen ``tilt``, ``azimuth``, ``fov_deg``, the best cone
    violation of each family (``v_family``), ``chosen_family`` (0 = the orientation optimum's) and the
    aggregates of the chosen pane (``aggs``) for the glass fit.
    """
    h, w = f["psi"].shape
    seeds = [(fit["tilt"], fit["azimuth"], fit["fov_deg"])]
    if "twin_tilt" in fit:
        seeds.append((fit["twin_tilt"], fit["twin_azimuth"], fit["twin_fov_deg"]))
    cands = valley_candidates(f["s4"], w, h, seeds, fov_given, tilt_step_deg=cfg.valley_step_deg, keep_ratio=cfg.valley_ratio, drop_fov_bounds=cfg.valley_drop_fov_bounds)
    cands += [{"tilt": t, "azimuth": a, "fov_deg": fv, "score": sc, "family": k}
              for k, (t, a, fv, sc) in enumerate([(fit["tilt"], fit["azimuth"], fit["fov_deg"], fit["score"])]
                                                 + ([(fit["twin_tilt"], fit["twin_azimuth"], fit["twin_fov_deg"], fit["twin_score"])] if "twin_tilt" in fit else []))]
    a0, c = chunk_harmonics(I, phi)
    sf = _span_factor_of(phi)
    pp_best = _hypothesis_maps(W, H, fit["tilt"], fit["azimuth"], fit["fov_deg"])[0]
    for cd in cands:
        pp, th = _hypothesis_maps(W, H, cd["tilt"], cd["azimuth"], cd["fov_deg"])
        cd["family"] = 0 if float(np.mean(np.cos(2.0 * (pp - pp_best)))) > 0 else 1  # by the field, not by the seed
        cd["aggs"] = cone_aggregates(a0, c, pp, th)
        cd["V"] = min(glass_scores(cd["aggs"], sf).values())
    v_fam = {k: min((cd["V"] for cd in cands if cd["family"] == k), default=float("inf")) for k in (0, 1)}
    fam = 0 if v_fam[0] <= v_fam[1] else 1
    other = v_fam[1 - fam]
    resolved = other - v_fam[fam] > cfg.cone_margin and other >= cfg.cone_ratio * v_fam[fam]
    content = None
    conflict = False
    if cfg.content_margin > 0:
        content = _resolve_by_content(I, phi, cands, v_fam, W, H, sf, cfg)
        if not resolved and content["resolved"]:
            fam, resolved = content["chosen_family"], True
            content["used"] = True
        elif resolved and content["clear"] and content["chosen_family"] != fam:
            # the cone and the content disagree: the cone's edge is noise-sensitive where one layer is nearly black
            # (the right family sits on -DoP_T there with no slack), the content is blind to motion within half a turn;
            # neither is trusted over the other
            resolved, conflict = False, True
    ok = [cd for cd in cands if cd["family"] == fam and cd["V"] <= v_fam[fam] + cfg.cone_margin]
    if content is not None and content.get("used") and (content["model_identified"] or cfg.model != "auto"):
        pick = content["pick"]  # within the family: the pane whose layers come out least correlated under the model they identify
    else:
        pick = max(ok, key=lambda cd: cd["score"])  # within the family: the cone-consistent pane the orientation field prefers
    out = {"resolved": bool(resolved), "by": ("content" if content is not None and content.get("used") else "cone") if resolved else None, "conflict": conflict,
           "tilt": pick["tilt"], "azimuth": pick["azimuth"], "fov_deg": pick["fov_deg"], "score": pick["score"],
           "v_family": [v_fam[0], v_fam[1]], "chosen_family": fam, "candidates": len(cands), "aggs": pick["aggs"],
           "tilt_range_deg": [math.degrees(min(cd["tilt"] for cd in ok)), math.degrees(max(cd["tilt"] for cd in ok))]}
    if content is not None:
        out["content"] = {k: v for k, v in content.items() if k != "pick"}
    return out


CONTENT_SIGMA_PX = 2.0
"""Gaussian smoothing (pixels) of the solved layers before their gradients are correlated (:func:`layer_gradient_correlation`):
keeps the texture, damps the per-pixel spike noise (measured on the stress set: 1.5-2 px separate the families alike)."""

CONTENT_TILES = 3
"""The content score is the RMS of the layer-gradient correlation over CONTENT_TILES x CONTENT_TILES tiles of the view."""

CONTENT_THETA_MAX_DEG = 82.0
"""Pixels a hypothesis sees beyond this incidence are left out of the content test: there the pane reflects about as much as
it transmits (A >= 0.5 for n = 1.5), and a 90 deg twin's solve turns into a layer swap (T' ~ R, R' ~ T) that is as
uncorrelated as the truth (module docstring).  Hypotheses with under a quarter of their pixels below it are not scored."""


def _content_parts(I: np.ndarray, phi: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The span cut into consecutive parts of at least half a polarizer turn (as many as fit, every frame used), each
    as its harmonic mean a0 and modulation c = ac + i as (supp. Eq. (1) fitted over the part); [] when fewer than two
    fit.  Their spike noise is independent (disjoint spikes), so correlating one part's R^ with the next one's T^
    carries no noise term (consecutive frames are not independent: integrate-and-fire makes a pixel's consecutive
    counts anticorrelated), and adjacent parts keep the layers' motion between the two small."""
    I = np.asarray(I, np.float64)
    phi = np.asarray(phi, np.float64)
    L = half_turn_frames(phi)
    C = I.shape[0] // L
    if C < 2:
        return []
    b = np.linspace(0, I.shape[0], C + 1).astype(int)
    out = []
    for j in range(C):
        a0, ac, as_ = (t.numpy() for t in harmonic_fit(torch.from_numpy(I[b[j]:b[j + 1]]), torch.from_numpy(phi[b[j]:b[j + 1]])))  # supp. Eq. (1)
        out.append((a0, ac + 1j * as_))
    return out


def layer_gradient_correlation(parts, phi_perp: np.ndarray, theta: np.ndarray, n: float, model: str, span_factor: float = 1.0,
                               sigma: float = CONTENT_SIGMA_PX, theta_max_deg: float = CONTENT_THETA_MAX_DEG, tiles: int = CONTENT_TILES) -> dict:
    """Normalised correlation of the gradients of R^ and T^ solved under one pane hypothesis (module docstring, "content").

    Per chunk (``parts``, :func:`_content_parts`), paper Eq. (1)-(2) invert in closed form: the modulation along phi_perp is
    m = B sinc (R - T) / 2 and the mean a0 = (T + A (R - T)) / 2, so D = 2 m / (B sinc), T^ = 2 a0 - A D, R^ = T^ + D
    (A, B the mean and half difference of R_perp, R_par for ``n`` and ``model``).  Each layer is smoothed by ``sigma``
    pixels and differenced along x and y; the correlation is the mean over adjacent chunks of (gR_j gT_j+1 + gR_j+1 gT_j) / 2
    over sqrt(mean power of gR x mean power of gT), over pixel pairs the hypothesis sees below ``theta_max_deg``.  Independent layers give about 0;
    a pane read as its 90 deg twin where T dominates gives R^ ~ T + (T - R) and T^ ~ T: strongly positive.

    Returns ``corr`` (the whole view) and ``rms``: the root mean square of the correlation over ``tiles`` x ``tiles``
    tiles.  A wrong scale or DoP shape leaks T into R^ by (1 - B / B') T, which changes with theta across the view, so
    a wrong (tilt, model) pair can zero the whole view's correlation but not every tile's; ``rms`` is the score.
    Both NaN when fewer than a quarter of the pixels qualify (a tile with fewer than 16 pairs is skipped).
    """
    from polphysics.fresnel import pane_coefficients

    nan = {"corr": float("nan"), "rms": float("nan")}
    if len(parts) < 2:
        return nan
    co = pane_coefficients(theta, n, model=model)
    A = 0.5 * (co["R_perp"] + co["R_par"])
    B = 0.5 * (co["R_perp"] - co["R_par"]) * span_factor
    ok = np.degrees(theta) <= theta_max_deg
    okx, oky = ok[:-1, :-1] & ok[:-1, 1:], ok[:-1, :-1] & ok[1:, :-1]
    if 0.5 * (okx.mean() + oky.mean()) < 0.25:
        return nan
    sums = cross_gradient_sums(parts, phi_perp, A, B, sigma=sigma, mask=ok, pairs="adjacent", pixels=CONTENT_PIXELS)  # reconstruct.exclusion
    cross, pr, pt = sums["cross"], sums["pr"], sums["pt"]
    cnt = okx.astype(int) + oky.astype(int)

    def corr(sl):
        den = math.sqrt(max(float(pr[sl].sum()) * float(pt[sl].sum()), 1e-300))
        return float(cross[sl].sum()) / den

    h, w = cross.shape
    per_tile = [corr((slice(i * h // tiles, (i + 1) * h // tiles), slice(j * w // tiles, (j + 1) * w // tiles)))
                for i in range(tiles) for j in range(tiles)
                if cnt[i * h // tiles:(i + 1) * h // tiles, j * w // tiles:(j + 1) * w // tiles].sum() >= 16]
    return {"corr": corr(slice(None)), "rms": float(np.sqrt(np.mean(np.square(per_tile)))) if per_tile else float("nan")}


def _resolve_by_content(I, phi, cands, v_fam, W, H, sf, cfg) -> dict:
    """The content test between the two families where the cone leaves them both open (module docstring, "content").

    Every cone-consistent candidate of each family is scored by :func:`layer_gradient_correlation` (``rms``) under each
    pane model that may be used (``cfg.model``, or for auto both of :data:`CONE_MODELS`, at ``cfg.n``); a family's score
    is its smallest (the tilt valley and the model's scale are nuisances: some tilt of the right family makes the layers
    independent).  The family with the smaller score wins when the other's exceeds it by ``content_margin`` and by
    ``content_ratio`` times, and the winner itself holds the cone (violation within ``cone_margin``: a family that
    breaks the cone is not rescued by its content).  Within the winner, the pane model is claimed when its best score
    is low and beats the other model's best (:func:`_content_claims_model`; else ``cfg.prior_model``), and the pane is
    that model's best-scoring candidate (unclaimed: the caller keeps the orientation field's choice, the content's
    tilt being conditional on an assumed scale).  Returns ``resolved``, ``chosen_family``, ``corr_family`` (the two scores),
    ``corr_by_model`` (the winner's best per model), ``model``, ``model_identified``, ``n`` and ``pick``.
    """
    models = CONE_MODELS if cfg.model == "auto" else (cfg.model,)
    halves = _content_parts(I, phi)
    best: dict = {}
    for cd in cands:
        k = cd["family"]
        if cd["V"] > v_fam[k] + cfg.cone_margin:
            continue
        pp, th = _hypothesis_maps(W, H, cd["tilt"], cd["azimuth"], cd["fov_deg"])
        cd["content"] = {}
        for mo in models:
            r = layer_gradient_correlation(halves, pp, th, cfg.n, mo, sf)["rms"]
            cd["content"][mo] = r
            if np.isfinite(r) and ((k, mo) not in best or r < best[(k, mo)][0]):
                best[(k, mo)] = (r, cd)
    score = {k: min((best[(k, mo)][0] for mo in models if (k, mo) in best), default=float("inf")) for k in (0, 1)}
    fam = 0 if score[0] <= score[1] else 1
    o, c = score[1 - fam], score[fam]
    clear = bool(np.isfinite(c) and np.isfinite(o) and o - c > cfg.content_margin and o >= cfg.content_ratio * c)  # both families scored
    resolved = clear and v_fam[fam] <= cfg.cone_margin
    by_model = {mo: best[(fam, mo)][0] for mo in models if (fam, mo) in best}
    order = sorted(by_model, key=by_model.get)
    model_ok = len(order) > 1 and _content_claims_model(by_model[order[0]], by_model[order[1]])
    model = order[0] if order and (model_ok or len(models) == 1) else cfg.prior_model  # nothing scored (no candidate within the cone): the prior
    pick = best.get((fam, model), best.get((fam, order[0]) if order else None, (None, None)))[1] if order else None
    return {"resolved": resolved, "clear": clear, "chosen_family": fam, "corr_family": [score[0], score[1]], "corr_by_model": by_model,
            "model": model, "model_identified": bool(model_ok), "n": cfg.n,
            "scored": sum(1 for cd in cands if "content" in cd), "pick": pick}


CONTENT_PIXELS = "same"
"""Pixels of the content test (reconstruct.exclusion.cross_gradient_sums).  ``split`` would take R^ and T^ from the two
sets of a checkerboard, so that the sensor's static fixed pattern, common to both layers at a pixel, drops out; the
thresholds below were set with the pattern in, and with ``split`` the network's self-zeta validation moved little
(v7, 3 frames: eval_fresh_val T 33.60 -> 33.60, R 24.15 -> 23.94; eval_paper_val T 35.07 -> 35.03, R 22.63 -> 23.43),
so ``same`` stays."""

CONTENT_MODEL_MARGIN = 0.05
"""Content test: a pane model is claimed when its tile-RMS correlation beats the other model's by this much ..."""

CONTENT_INDEPENDENT = 0.25
"""... and is at most this (the layers come out nearly independent under it: the chance correlation of independent
textures is 0.1-0.25 on 100-200 px views).  Both chosen on the stress set (docs/selfcal.md, "Pane model from the
content"): every claim made there is right; a fast, dim, strong-reflection slab scores 0.34 / 0.45 (single / slab)
and would be read as a single pane by the margin alone."""


def _content_claims_model(best: float, second: float) -> bool:
    return bool(best <= CONTENT_INDEPENDENT and second - best > CONTENT_MODEL_MARGIN)


def content_model(I: np.ndarray, phi: np.ndarray, phi_perp: np.ndarray, theta: np.ndarray, n: float, models=CONE_MODELS) -> dict:
    """The pane model by the layers' content at a fixed geometry (module docstring, "content"): the tile-RMS layer-gradient
    correlation (:func:`layer_gradient_correlation`) under each model; the best is claimed by :func:`_content_claims_model`.
    A wrong model's scale leaks T into R^ by (1 - B / B') T.  Returns ``scores``, ``model`` (or None) and ``identified``."""
    halves = _content_parts(I, phi)
    sf = _span_factor_of(phi)
    sc = {mo: layer_gradient_correlation(halves, phi_perp, theta, n, mo, sf)["rms"] for mo in models}
    fin = sorted((v, k) for k, v in sc.items() if np.isfinite(v))
    ok = len(fin) > 1 and _content_claims_model(fin[0][0], fin[1][0])
    return {"scores": sc, "model": fin[0][1] if ok else None, "identified": ok}


def _span_factor_of(phi: np.ndarray) -> float:
    """Modulation kept by a window's own sweep: sinc of the polarizer step between frames when they are back-to-back
    windows (step under 0.25 rad, about 14 deg); 1 otherwise (strided frames: the sweep is unknown, 1 is the wider cone)."""
    step = float(np.median(np.abs(np.diff(np.asarray(phi, np.float64))))) if np.size(phi) > 1 else 0.0
    return 1.0 if step <= 0 or step > 0.25 else math.sin(step) / step


def leave_out_saturated(I: np.ndarray, exposure: float | None) -> tuple[np.ndarray, float]:
    """Frames with every pixel that saturates in any of them set to 0, and the fraction of such pixels.

    A spike-camera pixel fires at most once per step, so a window at the ceiling
    (:data:`reconstruct.solvers.SPAN_SATURATION` spikes per step) clips the light where the polarizer lets most
    through: the pixel's modulation reads flatter, its degree of polarization lower, which the cone and the
    layers' content would take for a weaker pane (a glancing single interface calibrated as a thin slab, measured
    on the stress set).  A pixel at 0 in every frame adds nothing to the orientation field's or the cone's block
    sums.  ``exposure`` None (unknown): the frames unchanged."""
    from reconstruct.solvers import SPAN_SATURATION

    if exposure is None:
        return I, 0.0
    sat = (np.asarray(I) * float(exposure) >= SPAN_SATURATION).any(0)
    if not sat.any():
        return I, 0.0
    return np.where(sat[None], np.zeros((), np.asarray(I).dtype), I), float(sat.mean())


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
        content's votes on a narrow orientation choice, and whether they overturned it) and ``glass`` (the index / model fit).
    """
    I = np.asarray(I)
    if I.ndim != 3:
        raise ShapeError(f"self_calibrate needs frames (M, H, W); got {I.shape}", actual_shape=I.shape, expected_shape="(M, H, W)")
    M, H, W = I.shape
    m = M if frames_per_s is None else max(3, min(M, int(round(cfg.span_s * frames_per_s))))
    I, sat_px = leave_out_saturated(I[:m], exposure)
    s = cfg.block_px or max(1, W // 48)
    s = max(1, min(s, max(1, H // 4), max(1, W // 4)))
    f = orientation_field(I[:m], np.asarray(phi)[:m], s)
    h, w = f["psi"].shape
    thr = cfg.coherence_sigmas
    mask = np.abs(f["s4"]) > thr * np.sqrt(0.5 * np.maximum(f["q"], 1e-300))  # blocks that modulate on their own
    frac = float(mask.mean())
    diag = {"psi": f["psi"], "coherence": f["coherence"], "mask": mask, "block_px": s, "threshold": thr, "frames": m, "chunks": f["chunks"], "dop": f["dop"], "s4": f["s4"], "saturated_px": sat_px}
    fov_given = cfg.fov_deg if cfg.fov_deg > 0 else None
    fit = fit_normal(f["s4"], f["q"], w, h, fov_given, cfg.fov_init_deg)
    diag.update({"z": fit["z"], "alignment": fit["alignment"]})

    def modulation(tilt, az, fov):
        pp = _hypothesis_maps(W, H, tilt, az, fov)[0]
        diag["modulating_px"] = modulating_fraction(f["s4_px"], f["q_px"], pp, 1)
        diag["modulating_blocks"] = modulating_fraction(f["s4_px"], f["q_px"], pp, 4)

    modulation(fit["tilt"], fit["azimuth"], fit["fov_deg"])

    def residual():
        # weighted median orientation residual over the coherent blocks (a report, not a gate)
        if not mask.any():
            return None
        d = f["psi"] - _pane_phi_perp(w, h, fit["tilt"], fit["azimuth"], fit["fov_deg"])
        d = np.abs(np.mod(d + math.pi / 4, math.pi / 2) - math.pi / 4)[mask]
        wv = np.abs(f["s4"])[mask]
        o = np.argsort(d)
        cw = np.cumsum(wv[o])
        return float(np.degrees(d[o][min(len(o) - 1, int(np.searchsorted(cw, 0.5 * cw[-1])))]))

    res_deg = residual()
    auto = cfg.model == "auto"

    def fail(reason):
        log.warning("self-calibrated zeta for %s: %s; no self-calibrated zeta (the caller's fallback: zeta = 0 for the network, the learned zeta for the physics solvers)", name, reason)
        return SelfCalResult(False, reason, None, None, None, None, float(fit["fov_deg"]), False, cfg.n, cfg.prior_model if auto else cfg.model, None, None, frac, res_deg, fit["twin_ratio"], diag)

    if not fit["z"] >= cfg.z_min:
        return fail(f"nothing modulates: the best planar pane explains the polarization orientation only {fit['z']:.1f} noise sigmas above chance (need {cfg.z_min:g}; "
                    f"{100 * diag['modulating_px']:.1f} % of pixels modulate above noise); no reflection, R = T, or near-normal incidence")
    if not diag["modulating_blocks"] >= cfg.min_modulating_blocks:
        return fail(f"nothing modulates: the best planar pane explains the orientation field {fit['z']:.1f} noise sigmas above chance, yet only "
                    f"{100 * diag['modulating_blocks']:.2f} % of 4 x 4 pixel blocks modulate above noise (need {100 * cfg.min_modulating_blocks:g} %): "
                    "motion aliasing into the polarizer's harmonic, no polarizer, or near-normal incidence")
    aggs = None
    if fov_given is None and cfg.twin_check_ratio <= fit["twin_ratio"] <= cfg.max_twin_ratio:
        # the fov is free, so the twin family can bend along its own fov-tilt valley and the orientation field's
        # preference is narrow: a twin handed over swaps R and T (eval_paper_val train_004 with the fov withheld: the
        # network's T 17.6 dB against 36.3 on the right pane).  Overturn only on two independent votes for the twin
        chk = _resolve_by_cone(I[:m], np.asarray(phi)[:m], f, fit, W, H, fov_given, dataclasses.replace(cfg, valley_step_deg=cfg.twin_check_step_deg))
        v0, v1 = chk["v_family"]
        cc = (chk.get("content") or {}).get("corr_family") or [None, None]
        content_twin = cc[0] is not None and cc[1] is not None and np.isfinite(cc[1]) and cc[1] < cc[0]
        overturn = bool(v0 - v1 > cfg.cone_margin and content_twin)
        diag["twin_check"] = {"v_family": [v0, v1], "corr_family": cc, "overturned": overturn}
        if overturn:
            aggs = chk.pop("aggs")
            diag["cone"] = {**chk, "resolved": True, "by": "twin_check", "chosen_family": 1}
            fit = {**fit, "tilt": chk["tilt"], "azimuth": chk["azimuth"], "fov_deg": chk["fov_deg"]}
            modulation(fit["tilt"], fit["azimuth"], fit["fov_deg"])
            res_deg = residual()
    elif fit["twin_ratio"] > cfg.max_twin_ratio:
        # the orientation field cannot separate the pane from its 90 deg twin (nor pin the tilt of a narrow view):
        # the DoP must stay inside the cone [-DoP_T(theta), DoP_R(theta)] (R, T >= 0), which the wrong family breaks
        cone = _resolve_by_cone(I[:m], np.asarray(phi)[:m], f, fit, W, H, fov_given, cfg)
        aggs = cone.pop("aggs")
        diag["cone"] = cone
        if not cone["resolved"]:
            ct = cone.get("content")
            if cone.get("conflict"):
                return fail(f"ambiguous: a pane with phi_perp turned by 90 deg explains the orientation field {100 * fit['twin_ratio']:.1f} % as well, and the "
                            f"DoP cone (violations {cone['v_family'][0]:.1f} / {cone['v_family'][1]:.1f}) and the layers' content (gradient |correlation| "
                            f"{ct['corr_family'][0]:.2f} / {ct['corr_family'][1]:.2f}) pick different families")
            ctxt = (f"; nor does the layers' content (gradient |correlation| of R^ and T^ {ct['corr_family'][0]:.2f} / {ct['corr_family'][1]:.2f}, "
                    f"need the other family {cfg.content_margin:g} above and {cfg.content_ratio:g} times the chosen one, which must hold the cone)") if ct else ""
            return fail(f"ambiguous: a pane with phi_perp turned by 90 deg explains the orientation field {100 * fit['twin_ratio']:.1f} % as well "
                        f"(narrow field of view or glancing pane), and both keep the DoP inside the Fresnel cone (violations {cone['v_family'][0]:.1f} / "
                        f"{cone['v_family'][1]:.1f}, need the other family {cfg.cone_margin:g} above and {cfg.cone_ratio:g} times the chosen one): "
                        f"no part of the view shows the reflection dominating beyond DoP_T, or neither family fits" + ctxt)
        fit = {**fit, "tilt": cone["tilt"], "azimuth": cone["azimuth"], "fov_deg": cone["fov_deg"]}
        modulation(fit["tilt"], fit["azimuth"], fit["fov_deg"])
        res_deg = residual()
    if cfg.geometry_weighting == "scatter":
        # the grid search and the twin / cone decisions weigh blocks by |sum z4|, which holds the signal's power: the final
        # geometry is the scatter-weighted fit from there, kept in the chosen family (a local move, no 90 deg flip)
        pol = polish_geometry(f, s, fit["tilt"], fit["azimuth"], fit["fov_deg"], fov_given is None and "cone" not in diag)  # the cone chose along the tilt-fov valley: keep its fov
        if pol is not None:
            pp0 = _pane_phi_perp(w, h, fit["tilt"], fit["azimuth"], fit["fov_deg"])
            pp1 = _pane_phi_perp(w, h, pol["tilt"], pol["azimuth"], pol["fov_deg"])
            a4 = np.abs(f["s4"])
            same = float(np.sum(a4 * np.cos(2.0 * (pp1 - pp0))) / max(float(a4.sum()), 1e-300))
            moved = math.degrees(_sep(fit["tilt"], fit["azimuth"], pol["tilt"], pol["azimuth"]))
            diag["polish"] = {"from": [math.degrees(fit["tilt"]), math.degrees(fit["azimuth"]) % 360.0, float(fit["fov_deg"])],
                              "to": [math.degrees(pol["tilt"]), math.degrees(pol["azimuth"]), pol["fov_deg"]], "same_family": same, "moved_deg": moved}
            if same > 0.5 and moved < cfg.polish_max_move_deg:
                fit = {**fit, **pol}
                modulation(fit["tilt"], fit["azimuth"], fit["fov_deg"])
                res_deg = residual()
            else:
                diag["polish"]["kept"] = f"the cone's / grid's pane (the polish left the family or moved > {cfg.polish_max_move_deg:g} deg)"
    tilt_deg = math.degrees(fit["tilt"])
    if tilt_deg < cfg.min_tilt_deg:
        return fail(f"near-normal incidence (fitted tilt {tilt_deg:.1f} deg): no usable modulation")
    from polphysics.geometry import Plane, incidence_geometry

    cam = camera_for(W, H, fit["fov_deg"])
    N = normal_from_angles(fit["tilt"], fit["azimuth"], cam)
    plane = Plane(cam.position + cam.forward, N)
    geo = incidence_geometry(cam, plane)
    theta = geo["theta"]
    n_used, model_used = cfg.n, cfg.model
    if auto:
        if aggs is None:
            a0, c = chunk_harmonics(I[:m], np.asarray(phi)[:m])
            aggs = cone_aggregates(a0, c, geo["phi_perp"], theta)
        gl = fit_glass(glass_scores(aggs, _span_factor_of(np.asarray(phi)[:m]), slack=GLASS_SLACK), cfg.n, cfg.prior_model, cfg.cone_margin)
        ct = (diag.get("cone") or {}).get("content")
        if not gl["model_identified"] and ct and diag["cone"].get("by") == "content" and ct["model_identified"]:
            # the cone does not tell single from slab, the layers' content did (the pane model's scale leaks T into R^)
            gl["model"], gl["model_by_content"] = ct["model"], True
        elif not gl["model_identified"]:
            cm = content_model(I[:m], np.asarray(phi)[:m], geo["phi_perp"], theta, gl["n"])
            gl["content"] = cm
            if cm["identified"]:
                gl["model"], gl["model_by_content"] = cm["model"], True
        n_used, model_used = gl["n"], gl["model"]
        gl["scores_by_model"] = {k: float(v) for k, v in gl["scores_by_model"].items()}
        gl["why"] = (("model from the cone" if gl["model_identified"] else "model from the layers' content (the cone does not separate single from slab)" if gl.get("model_by_content")
                      else f"model not identified (no cone edge separates single from slab): assumed {cfg.prior_model}")
                     + "; " + (f"index from the cone (range {gl['n_range'][0]:g}-{gl['n_range'][1]:g})" if gl["n_identified"]
                               else f"index not identified (the data fit {gl['n_range'][0]:g}-{gl['n_range'][1]:g}): {n_used:g}"))
        diag["glass"] = gl
    maps = pane_maps_from_geometry(cam, plane, n_used, model=model_used)
    vp = None
    if float(N @ cam.forward) > 1e-6:
        x, y = cam.project(cam.position + N)
        vp = (float(x), float(y))
    res = SelfCalResult(
        True, "", N, tilt_deg, math.degrees(fit["azimuth"]) % 360.0, vp, float(fit["fov_deg"]), fov_given is None, n_used, model_used, maps, theta, frac,
        res_deg, fit["twin_ratio"], diag,
    )
    how = ""
    if "cone" in diag:
        ct = diag["cone"].get("content")
        how = (f" (90 deg twin resolved by the layers' content: R^ / T^ gradient |correlation| {ct['corr_family'][diag['cone']['chosen_family']]:.2f} "
               f"against {ct['corr_family'][1 - diag['cone']['chosen_family']]:.2f} for the twin; the cone held both)") if diag["cone"].get("by") == "content" else (
            " (the orientation field's narrow choice overturned: the DoP cone and the layers' content both prefer its 90 deg twin)" if diag["cone"].get("by") == "twin_check" else " (90 deg twin resolved by the cone)")
    log.info("self-calibrated pane for %s: tilt %.1f deg, azimuth %.1f deg, fov %.1f deg%s, z %.1f, %.0f %% of pixels modulating, %s n %.2f%s",
             name, tilt_deg, res.azimuth_deg, res.fov_deg, " (fitted)" if res.fov_fitted else "", fit["z"], 100 * diag["modulating_px"], model_used, n_used, how)
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
        from reconstruct.physics_video import frames_exposure, span_frames
        from reconstruct.video import group_source

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
    """zeta (M, H, W) at angles phi (M,) from a successful calibration, paper Eq. (2) (window-averaged over span_rad)."""
    if not result.ok or result.maps is None:
        raise ConfigError(f"no self-calibrated pane ({result.reason}); use --zeta learned or physics")
    return zeta_from_maps(result.maps, np.asarray(phi, np.float64), span_rad, dtype=dtype).numpy()
