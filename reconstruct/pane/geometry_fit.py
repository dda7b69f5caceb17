"""calibrate-pane's geometry: the bounded Gauss-Newton fit of (tilt, azimuth, fov) to the block orientation field, its uncertainty maps, and the 90 deg twin."""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from polinfra.errors import ConfigError
from reconstruct.pane.camera import CHI2_1_MEDIAN, FOV_BOUNDS_DEG, FOV_INNER_DEG, camera_for, normal_from_angles
from reconstruct.pane.levenberg import PaneModelFactory
from reconstruct.pane.orientation import OrientationField

log = logging.getLogger(__name__)


_ROUNDS = 3


_ROBUST_C = 4.0
"""Rounds of robust re-weighting of the geometry fit."""


# --------------------------------------------------------------------------- helpers
def _wrap90(d: np.ndarray) -> np.ndarray:
    """Angle difference folded to [-45, 45) deg (radians in, radians out)."""
    return np.mod(d + math.pi / 4, math.pi / 2) - math.pi / 4


def _expected_max(c: int) -> float:
    """Expected maximum of c standard normal samples (Blom's approximation)."""
    from scipy.stats import norm

    return float(norm.ppf((c - 0.375) / (c + 0.25))) if c > 1 else 0.0


def _wmedian(v: np.ndarray, w: np.ndarray) -> float:
    if v.size == 0:
        return float("nan")
    o = np.argsort(v)
    cw = np.cumsum(w[o])
    return float(v[o][min(len(o) - 1, int(np.searchsorted(cw, 0.5 * cw[-1])))])


# --------------------------------------------------------------------------- geometry
def _degenerate_view(x: np.ndarray, fit_fov: bool) -> bool:
    """A geometry pushed against the fit's bounds (tilt >= 89 deg; a fitted fov outside FOV_INNER_DEG): a degenerate
    view in which theta hardly varies across the image, so any index fits any modulation depth.
    """
    return bool(x[0] >= math.radians(89.0) or (fit_fov and not math.radians(FOV_INNER_DEG[0]) < x[2] < math.radians(FOV_INNER_DEG[1])))


def max_incidence_deg(x: np.ndarray, width: int, height: int, block: int, mask: np.ndarray, quantile: float = 1.0) -> float:
    """The largest angle (degrees) between a masked block's viewing ray and the pane normal on the far side, in the
    camera frame of :class:`generator.pane_fit.PaneModelAD` (block centres); ``quantile`` < 1: that quantile over
    the masked blocks instead (a few blocks flagged by noise do not decide).  Above 90 the ray runs away from the
    pane: it never meets the pane in front of the camera, so such a block cannot see a reflection, let alone
    modulate; near 90 it grazes it.  (The maps' theta folds this angle into [0, 90].)
    """
    tilt, az, fov = (float(v) for v in x[:3])
    gh, gw = mask.shape
    yp, xp = (np.mgrid[0:gh, 0:gw] + 0.5) * block
    cam = camera_for(width, height, math.degrees(fov))
    d = cam.directions_at(xp / width * 2.0 - 1.0, yp / height * 2.0 - 1.0)
    N = normal_from_angles(tilt, az, cam)
    c = (d @ N) / np.linalg.norm(d, axis=-1)
    if not mask.any():
        return 0.0
    a = np.degrees(np.arccos(np.clip(c[mask], -1.0, 1.0)))
    return float(a.max() if quantile >= 1.0 else np.quantile(a, quantile))


@dataclasses.dataclass(frozen=True)
class GeometryFit:
    """A fit of the pane's geometry to the orientation field (:func:`fit_geometry`).

    Attributes:
        x: (4,) tilt, azimuth, fov (radians) and the index it was started with (not fitted here).
        sigma: (4,) 1-sigma of x (0 where not fitted); cov: covariance of the fitted parameters ``wrt``; corr: its
            correlation matrix (None where a sigma is 0).
        wrt: indices of x that were fitted ((0, 1) or (0, 1, 2)).
        mask: (h, w) blocks in the fit; coherent: blocks modulating above ``coherence_sigmas``.
        score: the bounded orientation cost sum_b w_b (1 - cos 4 delta_b) (comparable across starts and fits).
        chi2, dof, converged, history: the Gauss-Newton's; starts: each start's end and cost.
        residual_deg_blocks: (h, w) |psi_b - phi_perp_b| folded to 45 deg; residual_deg_median: its |s4|-weighted median
            over the mask.
        residual_lag1_correlation: (x, y) lag-1 correlation of neighbouring blocks' residuals; covariance_inflation:
            the factor (1 + 2 rho_x)(1 + 2 rho_y) applied to the covariance.
        sigma_theta_deg_max / _median, sigma_phi_perp_deg_max / _median: the covariance propagated to the maps over the mask.
        seconds: wall time of the fit.
    """

    x: np.ndarray
    sigma: np.ndarray
    cov: np.ndarray
    wrt: tuple[int, ...]
    mask: np.ndarray
    coherent: np.ndarray
    score: float
    chi2: float
    dof: int
    converged: bool
    history: list
    starts: list
    residual_deg_blocks: np.ndarray
    residual_deg_median: float
    residual_lag1_correlation: list
    covariance_inflation: float
    sigma_theta_deg_max: float
    sigma_theta_deg_median: float
    sigma_phi_perp_deg_max: float
    sigma_phi_perp_deg_median: float
    corr: list | None
    seconds: float


INCIDENCE_QUANTILE = 0.995
"""The feasibility check of the fitted fov reads this quantile of the modulating blocks' incidence (the top 0.5 %,
which noise can flag at the image's edge, do not decide)."""


def fit_geometry(of: OrientationField, width: int, height: int, block: int, x0: np.ndarray, fit_fov: bool, coherence_sigmas: float = 4.0, weighting: str = "scatter",
                 fov_starts: tuple[float, ...] = (25.0, 40.0, 55.0, 70.0), rounds: int = 0, *, pane_model: PaneModelFactory) -> GeometryFit:
    """Gauss-Newton of (tilt, azimuth[, fov]) on the block orientation field (module docstring, step 3).

    ``weighting``: ``scatter`` (default) weighs each block by 1 / (its measured orientation variance
    (:func:`block_orientation_variance`) + a misfit floor) and leaves out blocks whose modulation sits in a quarter
    of their pixels or fewer; ``floor`` does the same with the pure-noise scale q / (32 |s4|^2), which holds the
    signal's power and so weighs every strongly modulating block alike (on the stress set it left theta 1-8 deg
    off: weak blocks biased towards a fixed angle pulled the fov-tilt valley); ``snr2`` weighs each block by its information about the angle,
    |sum z4|^2 / q (the inverse variance of psi_b: 1 / Var psi_b is proportional to the squared
    signal-to-noise ratio of s4), so that the weak second-order curvature of the field, the only thing
    in it that separates the field of view from the tilt, is read where it is measured precisely;
    ``s4`` weighs by |sum z4| (the matched-filter weight of the self-calibration).
    ``fov_starts``: extra starts (degrees) of a fitted field of view; ``rounds``: robust re-weighting rounds.
    """
    from reconstruct.pane.levenberg import gauss_newton
    from reconstruct.pane.orientation import block_orientation_variance

    s4, q = of.s4, of.q
    coherent = np.abs(s4) > coherence_sigmas * np.sqrt(0.5 * np.maximum(q, 1e-300))
    # every block with some signal takes part; noise blocks have random phases and large noise variance (small weights)
    mask = np.abs(s4) > 1.0 * np.sqrt(0.5 * np.maximum(q, 1e-300))
    if mask.sum() < 4:
        raise ConfigError(f"only {int(mask.sum())} blocks carry any modulation: too few to fit the pane geometry (need 4)")
    if weighting not in ("scatter", "floor", "snr2", "s4"):
        raise ConfigError(f"unknown geometry weighting {weighting!r}; use scatter, floor, snr2 or s4")
    if weighting == "scatter":
        v_all, n_eff = block_orientation_variance(s4, of.s4_px, block)
        # a block whose modulation comes from a few of its pixels (a hot pixel, the pane's edge) has no
        # scatter to measure its noise with: it is left out
        mask &= (n_eff >= 0.25 * block * block) & (v_all > 0)
        if mask.sum() < 4:
            raise ConfigError(f"only {int(mask.sum())} blocks carry a measurable modulation: too few to fit the pane geometry (need 4)")
        v_noise = v_all[mask]
    else:
        # noise variance of psi_b (rad^2) under pure noise: Im(s4 e^{-4i phi}) has variance q / 2, and 4 |s4| dpsi = that
        # (q also holds the signal's power: where the pane modulates this overstates the noise, up to 100-fold)
        v_noise = (np.maximum(q, 1e-300) / (32.0 * np.maximum(np.abs(s4), 1e-300) ** 2))[mask]
    snr_top = v_noise <= np.quantile(v_noise, 0.25)  # the best-measured quarter of the blocks

    def _weights(sys2: float) -> np.ndarray:
        if weighting == "s4":
            w_ = np.abs(s4)[mask]
        elif weighting == "snr2":
            w_ = 1.0 / v_noise
        else:
            w_ = 1.0 / (v_noise + sys2)
        return w_ / w_.sum() * w_.size  # mean weight 1

    sys2 = math.radians(1.0) ** 2
    w = _weights(sys2)
    sw = np.sqrt(w)
    psi = of.psi[mask]
    pm = pane_model(width, height, "single", block=block)  # phi_perp depends on the geometry only
    wrt = (0, 1, 2) if fit_fov else (0, 1)
    x_full = np.asarray(x0, np.float64).copy()

    def full(xs):
        x = x_full.copy()
        x[list(wrt)] = xs
        return x

    def fun_w(xs, u):
        """Residuals with robust weights u (per block), and the angle residuals for re-weighting."""
        m, J = pm.maps_and_jacobian(full(xs), wrt)
        d = psi - m["phi_perp"][mask]
        su = sw * np.sqrt(u)
        r = 0.5 * su * np.sin(2 * d)
        Jr = -(su * np.cos(2 * d))[:, None] * J["phi_perp"][:, mask].T
        return r, Jr, _wrap90(d)

    def _robust_gn(f, xs0, lb_, ub_):
        """Cauchy-weighted IRLS around Gauss-Newton: blocks whose orientation the planar model does not
        explain (moving content, a second reflector) lose weight; the self-calibration is robust likewise.
        """
        nonlocal w, sw, sys2
        u = np.ones(psi.size)
        xs = xs0
        for _ in range(rounds or _ROUNDS):
            res = gauss_newton(lambda z: f(z, u)[:2], xs, lb_, ub_, max_iter=40)
            xs = res.x
            d = np.abs(f(xs, u)[2])
            if weighting in ("floor", "scatter"):
                # misfit floor: the best-measured blocks scatter by more than their noise (content moving through
                # the harmonic fit); every block's variance is its noise plus that floor (CHI2_1_MEDIAN)
                sys2 = max(math.radians(0.1) ** 2, float(np.median(d[snr_top] ** 2)) / CHI2_1_MEDIAN - float(np.median(v_noise[snr_top])))
                w = _weights(sys2)
                sw = np.sqrt(w)
                u = 1.0 / (1.0 + (d / (_ROBUST_C * np.sqrt(v_noise + sys2))) ** 2)  # Cauchy on standardised residuals
            else:
                c = max(math.radians(2.0), _ROBUST_C * _wmedian(d, w))
                u = 1.0 / (1.0 + (d / c) ** 2)
        res.robust_weights = u
        return res

    lb = np.array([0.0, x0[1] - math.pi, math.radians(FOV_BOUNDS_DEG[0])])[list(wrt)]
    ub = np.array([math.radians(89.5), x0[1] + math.pi, math.radians(FOV_BOUNDS_DEG[1])])[list(wrt)]
    t0 = time.perf_counter()
    # multi-start: the self-calibration's pane, and (fov fitted) the same normal at other fields of view,
    # since tilt and fov trade off along a shallow valley of the orientation cost
    starts = [x_full[list(wrt)]]
    if fit_fov:
        starts += [np.array([x0[0], x0[1], math.radians(f)]) for f in fov_starts if abs(math.radians(f) - x0[2]) > math.radians(7.0)]
    best, tried = None, []
    for xs0 in starts:
        res = _robust_gn(fun_w, np.clip(xs0, lb, ub), lb, ub)
        d = fun_w(res.x, np.ones(psi.size))[2]
        score = float(np.sum(w * (1.0 - np.cos(4.0 * d))))  # bounded per block: comparable across starts
        tried.append({"start": np.degrees(xs0).tolist(), "end": np.degrees(res.x).tolist(), "cost": score, "degenerate": _degenerate_view(full(res.x), fit_fov)})
        if best is None or score < best[0]:
            best = (score, res)
    res = best[1]
    cov = res.cov * (res.chi2 / res.dof) / max(1.0, res.chi2 / res.dof)  # weights are relative: noise scale from the residuals
    x = full(res.x)
    x[1] = x[1] % (2 * math.pi)
    m, J = pm.maps_and_jacobian(x, wrt)
    # neighbouring blocks share content and motion: their residuals correlate, so the blocks are fewer
    # independent samples than they look; inflate the covariance by the lag-1 factor (1 + 2 rho_x)(1 + 2 rho_y)
    rfield = np.where(mask, _wrap90(of.psi - m["phi_perp"]), np.nan)
    rho = []
    for a, b in ((rfield[:, 1:], rfield[:, :-1]), (rfield[1:, :], rfield[:-1, :])):
        ok = np.isfinite(a) & np.isfinite(b)
        rho.append(float(np.corrcoef(a[ok], b[ok])[0, 1]) if ok.sum() > 10 else 0.0)
    rho = [max(0.0, r) if np.isfinite(r) else 0.0 for r in rho]
    inflate = (1 + 2 * rho[0]) * (1 + 2 * rho[1])
    cov = cov * inflate
    d = np.degrees(np.abs(_wrap90(of.psi - m["phi_perp"])))
    # propagate to the maps: sigma of theta and phi_perp per block
    sig_theta = np.sqrt(np.maximum(np.einsum("ihw,ij,jhw->hw", J["theta"], cov, J["theta"]), 0.0))
    sig_phi = np.sqrt(np.maximum(np.einsum("ihw,ij,jhw->hw", J["phi_perp"], cov, J["phi_perp"]), 0.0))
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    full_sig = np.zeros(4)
    full_sig[list(wrt)] = sig
    return GeometryFit(
        x=x, sigma=full_sig, cov=cov, wrt=wrt, mask=mask, coherent=coherent, score=float(best[0]), chi2=res.chi2, dof=res.dof, converged=res.converged,
        history=res.history, starts=tried, residual_deg_blocks=d, residual_deg_median=_wmedian(d[mask], np.abs(s4)[mask]), residual_lag1_correlation=rho,
        covariance_inflation=inflate, sigma_theta_deg_max=float(np.degrees(sig_theta[mask].max())), sigma_theta_deg_median=float(np.degrees(np.median(sig_theta[mask]))),
        sigma_phi_perp_deg_max=float(np.degrees(sig_phi[mask].max())), sigma_phi_perp_deg_median=float(np.degrees(np.median(sig_phi[mask]))),
        corr=(cov / np.outer(sig, sig)).tolist() if np.all(sig > 0) else None, seconds=time.perf_counter() - t0,
    )


# --------------------------------------------------------------------------- fov from the modulation depth
def _sigma_maps(geo: GeometryFit, pm, cov: np.ndarray, wrt: tuple[int, ...]) -> dict:
    """Theta / phi_perp 1-sigma on the block grid for covariance ``cov`` of the parameters ``wrt`` (GeometryFit's sigma_* fields)."""
    _, J = pm.maps_and_jacobian(geo.x, wrt)
    mask = geo.mask
    st_ = np.sqrt(np.maximum(np.einsum("ihw,ij,jhw->hw", J["theta"], cov, J["theta"]), 0.0))[mask]
    sp_ = np.sqrt(np.maximum(np.einsum("ihw,ij,jhw->hw", J["phi_perp"], cov, J["phi_perp"]), 0.0))[mask]
    return {"sigma_theta_deg_max": float(np.degrees(st_.max())), "sigma_theta_deg_median": float(np.degrees(np.median(st_))),
            "sigma_phi_perp_deg_max": float(np.degrees(sp_.max())), "sigma_phi_perp_deg_median": float(np.degrees(np.median(sp_)))}


# --------------------------------------------------------------------------- the 90 deg twin
def _turned_against(of: OrientationField, width: int, height: int, block: int, x_best: np.ndarray, *, pane_model: PaneModelFactory):
    """A test of whether a pane ``x`` belongs to ``x_best``'s 90 deg twin family: its phi_perp field turned against
    ``x_best``'s (the orientation field's weighted mean of cos 2 delta below 0).
    """
    pm = pane_model(width, height, "single", block=block)
    p1 = pm.maps(x_best)["phi_perp"]
    w = np.abs(of.s4)
    return lambda x: float(np.sum(w * np.cos(2.0 * (pm.maps(x)["phi_perp"] - p1)))) < 0


def _angles_deg(x: np.ndarray) -> dict:
    """A pane's tilt, azimuth and fov in degrees, as the report lists them."""
    return {"tilt_deg": math.degrees(x[0]), "azimuth_deg": math.degrees(x[1]), "fov_deg": math.degrees(x[2])}


def find_twin(of: OrientationField, width: int, height: int, block: int, x_best: np.ndarray, fit_fov: bool, *, pane_model: PaneModelFactory) -> GeometryFit | None:
    """The best pane whose phi_perp field runs along ``x_best``'s p-directions (its 90 deg twin: modulo 90 deg
    the two fields agree up to the field's curvature), as a :func:`fit_geometry` result, or None.
    """
    turned = _turned_against(of, width, height, block, x_best, pane_model=pane_model)
    found = None
    for tl in sorted({float(x_best[0]), math.radians(30.0), math.radians(55.0), math.radians(75.0)}):
        for da in (0.5 * math.pi, -0.5 * math.pi):
            xs = np.asarray(x_best, np.float64).copy()
            xs[0], xs[1] = tl, x_best[1] + da
            g = fit_geometry(of, width, height, block, xs, fit_fov, fov_starts=(), rounds=1, pane_model=pane_model)
            if turned(g.x) and (found is None or g.score < found.score):
                found = g
    if found is None:
        return None
    return fit_geometry(of, width, height, block, found.x, fit_fov, pane_model=pane_model)
