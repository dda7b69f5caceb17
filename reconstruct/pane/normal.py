"""The pane normal (and fov) from the orientation field: the robust fit, the scatter-weighted polish, the valley candidates along the fov-tilt valley."""

from __future__ import annotations

import logging
import math

import numpy as np

from reconstruct.pane.camera import (
    CHI2_1_MEDIAN,
    FOV_BOUNDS_DEG,
    _pane_phi_perp,
    _phi_perp_many,
    camera_for,
    normal_from_angles,
)
from reconstruct.pane.orientation import OrientationField, block_orientation_variance, block_sum

log = logging.getLogger(__name__)


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


POLISH_MIN_BLOCK = 4
"""Smallest block (pixels per side) whose orientation variance the polish measures from its pixels' scatter."""


POLISH_ROBUST_C = 4.0
"""Cauchy scale of the scatter-weighted geometry polish, in standard deviations of a block's orientation."""


def polish_geometry(of: OrientationField, block: int, tilt: float, az: float, fov_deg: float, fit_fov: bool) -> dict | None:
    """Scatter-weighted, robust least squares of the pane geometry on the block orientation field, from (tilt, az, fov).

    Each block weighs 1 / (v_b + floor): v_b its orientation's measured variance (:func:`block_orientation_variance`),
    the floor the misfit the best-measured quarter of the blocks shows beyond their noise (content moving through the
    harmonic fit), re-estimated once; Cauchy loss at :data:`POLISH_ROBUST_C` standard deviations.  Blocks without a
    measurable modulation (|s4| under its noise, or modulation in <= a quarter of their pixels) are left out.  The
    residual is sin(2 delta) / 2 (delta = psi - phi_perp): invariant to the 90 deg flip where R < T.
    Returns {"tilt", "azimuth", "fov_deg"} (radians, radians, degrees), or None with fewer than 8 usable blocks.
    """
    from scipy.optimize import least_squares

    s4, q, psi = of.s4, of.q, of.psi
    if block < POLISH_MIN_BLOCK:  # a variance from a handful of pixels is too noisy to weigh by: re-block
        block = POLISH_MIN_BLOCK
        H, W = of.s4_px.shape
        hb, wb = H // block, W // block
        if hb < 2 or wb < 2:
            return None
        s4, q = block_sum(of.s4_px, block), block_sum(of.q_px, block)
        psi = np.angle(s4) / 4.0
    h, w = s4.shape
    v, n_eff = block_orientation_variance(s4, of.s4_px, block)
    mask = (np.abs(s4) > np.sqrt(0.5 * np.maximum(q, 1e-300))) & (n_eff >= 0.25 * block * block) & (v > 0)
    if mask.sum() < 8:
        return None
    v = v[mask]
    psi = psi[mask]
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
        sys2 = max(math.radians(0.1) ** 2, float(np.median(d[top] ** 2)) / CHI2_1_MEDIAN - float(np.median(v[top])))
    return {"tilt": float(x[0]), "azimuth": float(x[1]) % (2 * math.pi), "fov_deg": float(x[2]) if fit_fov else float(fov_deg)}


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
