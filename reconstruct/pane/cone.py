"""The DoP cone: the modulation a pane of index n can make at each incidence angle, and how many blocks a hypothesis violates."""

from __future__ import annotations

import functools
import logging
import math

import numpy as np
import torch

from polinfra.errors import ConfigError
from reconstruct.pane.camera import CHI2_1_MEDIAN, camera_for, normal_from_angles
from reconstruct.pane.glass import index_grid
from reconstruct.pane.orientation import block_sum
from reconstruct.physics.harmonic_fit import half_turn_frames, harmonic_fit

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the polarization cone
CONE_N_GRID = tuple(float(n) for n in index_grid(1.40, 1.70, 0.05))
"""Indices tried by the cone test (common glasses; why this range: :data:`reconstruct.pane.glass.INDEX_GRID`); the
index that explains the data best is reported."""


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
        th = block_sum(theta, s) / (s * s)
        A, Mm, O = block_sum(a0, s), block_sum(m_px, s), block_sum(o_px, s)
        for a, m, o, t in ((A, Mm, O, np.broadcast_to(th, A.shape)), (A.sum(0), Mm.sum(0), O.sum(0), th)):
            a, m, o, t = (np.asarray(x, np.float64).ravel() for x in (a, m, o, t))
            keep = a > 0
            a, m, o, t = a[keep], m[keep], o[keep], t[keep]
            if a.size < 4:
                continue
            kappa = float(np.median(o * o / a)) / CHI2_1_MEDIAN
            out.append({"scale": s, "a": a, "m": m, "theta": t, "sigma": np.sqrt(max(kappa, 1e-30) * a + (systematic * a) ** 2)})
    return out


_THETA_TABLE = np.linspace(0.0, 0.5 * math.pi, 1801)


def _bounds_table(n: float, model: str, span_factor: float) -> tuple[np.ndarray, np.ndarray]:
    return _bounds_table_cached(float(n), model, float(span_factor))


@functools.lru_cache(maxsize=256)
def _bounds_table_cached(n: float, model: str, span_factor: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cone_bounds` on the fine theta table, once per (n, model, span factor); read-only arrays."""
    lo, hi = cone_bounds(_THETA_TABLE, n, model, span_factor)
    lo.setflags(write=False)
    hi.setflags(write=False)
    return lo, hi


def cone_violation(aggs: list[dict], n: float, model: str, span_factor: float = 1.0, cap: float = 8.0, slack: float = 0.0) -> float:
    """Sum over aggregates of the squared cone violation beyond ``slack`` noise standard deviations (each capped at
    ``cap``), mean over sets.  A slack keeps data sitting on the edge (a layer black there) from adding half-normal
    noise terms that grow with their number (the glass fit uses 3: the true glass then scores about 0 however much
    of the view is on the edge; the family test uses 0, measured on the stress groups, docs/selfcal.md).
    """
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
        p, o, q = block_sum(p, block), block_sum(o, block), block_sum(q, block)
    q = np.maximum(q, 1e-300)
    kappa = float(np.median(o * o / q)) / CHI2_1_MEDIAN  # the orthogonal part carries no pane signal: it calibrates the noise scale
    z = p / np.sqrt(max(kappa, 1e-300) * q)
    return float(max(0.0, np.mean(z > sigmas) - np.mean(z < -sigmas)))


def _span_factor_of(phi: np.ndarray) -> float:
    """Modulation kept by a window's own sweep: sinc of the polarizer step between frames when they are back-to-back
    windows (step under 0.25 rad, about 14 deg); 1 otherwise (strided frames: the sweep is unknown, 1 is the wider cone).
    """
    step = float(np.median(np.abs(np.diff(np.asarray(phi, np.float64))))) if np.size(phi) > 1 else 0.0
    return 1.0 if step <= 0 or step > 0.25 else math.sin(step) / step
