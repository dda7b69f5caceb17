"""Polarizer calibration from spikes: phase phi0 and rotation rate, as on the real rig.

Supp. "Hardware calibration": a polarized flat target (a smartphone screen) is
filmed; the darkest observed state gives the polarizer orientation, the motor
speed maps timestamps to angles.  Here, behind an ideal polarizer, the response
of a target polarized at angle psi is ``I ~ a + b cos(2 phi(t) - 2 psi)`` with
phi(t) = phi0 + 2 pi f t, darkest at phi = psi + pi/2.  We estimate

* the rate f from the modulation itself: the frequency 2f maximising the
  summed power sum_b |A_b(f)|^2 of spatially binned spike counts (incoherent
  over bins, so it works on ANY modulated scene, whatever its AoLP);
* the phase from the complex amplitude at 2f: ``A ~ b e^{i (2 phi0 - 2 psi)}``,
  so ``phi0 = psi + arg(sum_b A_b e^{2 i psi_b}) / 2`` (mod pi) for a flat
  target (:func:`calibrate_flat_target`), and, for a general scene whose
  per-pixel polarization axis psi_p is known only up to a 90 deg flip (glass:
  reflection along the s-direction phi_perp, transmission across it),
  ``4 phi0 = arg(sum_b (A_b e^{2 i psi_b})^2)`` with the pi/2 ambiguity broken by
  a prior (:func:`calibrate_from_modulation`).

The darkest-window estimate the rig uses is :func:`darkest_phase` (coarse, for
comparison).  Errors against the true phi(t) come from :func:`phase_error`.
Angles in radians; the polarizer is pi-periodic, so phases are reported mod pi.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polinfra.errors import ConfigError, ShapeError

__all__ = [
    "PolarizerCalibration",
    "binned_counts",
    "estimate_rate",
    "calibrate_flat_target",
    "calibrate_from_modulation",
    "darkest_phase",
    "phase_error",
    "calibrate_group",
    "isi_cv",
]


def isi_cv(spikes: np.ndarray, min_spikes: int = 4) -> np.ndarray:
    """Per-pixel coefficient of variation of the inter-spike intervals (std / mean).

    Args:
        spikes: (T, P) 0/1 array, time first.
        min_spikes: pixels with fewer spikes get NaN.

    Returns:
        (P,) CV; 0 for a perfectly regular pixel (the noise-free integrate-and-fire
        at constant light), ~1/sqrt(Q) with Q photoelectrons per threshold under shot noise.
    """
    x = np.asarray(spikes)
    out = np.full(x.shape[1], np.nan)
    for j in range(x.shape[1]):
        t = np.flatnonzero(x[:, j])
        if t.size >= min_spikes:
            d = np.diff(t)
            out[j] = d.std() / d.mean()
    return out


@dataclasses.dataclass(frozen=True)
class PolarizerCalibration:
    """Result: phi(t) = phi0_rad + 2 pi rate_hz t (mod pi)."""

    phi0_rad: float
    rate_hz: float
    method: str
    modulation: float

    def phi(self, t_s) -> np.ndarray:
        """Calibrated angle at times ``t_s``."""
        return self.phi0_rad + 2.0 * np.pi * self.rate_hz * np.asarray(t_s, dtype=np.float64)


def _wrap_pi(a):
    """Wrap to (-pi/2, pi/2]: the polarizer angle is defined mod pi."""
    return (np.asarray(a) + np.pi / 2) % np.pi - np.pi / 2


def binned_counts(source, bin_px: int = 10, chunk_steps: int = 2000) -> np.ndarray:
    """Spike counts per step summed over ``bin_px`` x ``bin_px`` blocks.

    Args:
        source: (T, H, W) 0/1 array or a :class:`~spike_sim.store.SpikeGroup`.
        bin_px: block size (edge blocks dropped).

    Returns:
        (T, nb) float32, nb = (H // bin_px) * (W // bin_px).
    """
    if hasattr(source, "iter_chunks"):
        parts = [_bin(chunk, bin_px) for _, chunk in source.iter_chunks(chunk_steps)]
        return np.concatenate(parts, axis=0)
    arr = np.asarray(source)
    if arr.ndim != 3:
        raise ShapeError(f"spikes must be (T, H, W), got {arr.shape}", arr.shape, "(T, H, W)")
    return np.concatenate([_bin(arr[i : i + chunk_steps], bin_px) for i in range(0, arr.shape[0], chunk_steps)], axis=0)


def _bin(x: np.ndarray, b: int) -> np.ndarray:
    T, H, W = x.shape
    hb, wb = H // b, W // b
    if hb == 0 or wb == 0:
        raise ShapeError(f"bin_px = {b} is larger than the {H}x{W} frame", x.shape, f"(T, >= {b}, >= {b})")
    y = x[:, : hb * b, : wb * b].reshape(T, hb, b, wb, b).sum(axis=(2, 4), dtype=np.int32)
    return y.reshape(T, hb * wb).astype(np.float32)


def _amplitudes(y: np.ndarray, t: np.ndarray, f_hz) -> np.ndarray:
    """Complex amplitudes A = b e^{i theta} of ``y ~ a + b cos(4 pi f t + theta)``, least squares: (n_f, nb).

    A least-squares fit of [1, cos, sin] (not a plain DFT) so that a window
    holding a non-integer number of periods does not leak the -2f component.
    """
    f = np.atleast_1d(np.asarray(f_hz, dtype=np.float64))
    y64 = y.astype(np.float64)
    out = np.empty((f.size, y.shape[1]), np.complex128)
    for i, fi in enumerate(f):
        w = 4.0 * np.pi * fi * t
        X = np.stack([np.ones_like(t), np.cos(w), np.sin(w)], axis=1)
        coef = np.linalg.solve(X.T @ X, X.T @ y64)  # (3, nb)
        out[i] = coef[1] - 1j * coef[2]
    return out


def estimate_rate(y: np.ndarray, dt_s: float, rate_guess_hz: float = 30.0, search_frac: float = 0.1) -> float:
    """Rotation rate: the grid frequency of largest binned modulation power at 2 f, refined
    by the phase drift between consecutive one-turn segments (unbiased, any scene).

    Args:
        y: (T, nb) binned counts (:func:`binned_counts`).
        dt_s: step length.
        rate_guess_hz: nominal rate; the search spans +-search_frac around it.
    """
    T = y.shape[0]
    t = (np.arange(T) + 0.5) * dt_s
    dur = T * dt_s
    if rate_guess_hz * dur < 1.0:
        raise ConfigError(f"{dur:.3f} s of stream holds less than one polarizer turn at {rate_guess_hz} rev/s; record longer")
    lo, hi = rate_guess_hz * (1 - search_frac), rate_guess_hz * (1 + search_frac)
    # grid finer than the spectral resolution 1 / (2 dur) of the 2f line
    n = max(9, int(np.ceil((hi - lo) / (0.25 / (2.0 * dur)))) + 1)
    grid = np.linspace(lo, hi, min(n, 401))

    def power(f):
        return float(np.sum(np.abs(_amplitudes(y, t, f)) ** 2))

    p = np.array([power(g) for g in grid])
    f = float(grid[int(np.argmax(p))])
    # refine by the phase drift between consecutive segments (about one turn each):
    # at trial f0 the phase of every bin advances by 4 pi (f - f0) per second
    n_seg = int(np.clip(np.floor(dur * f), 2, 64))
    edges = np.linspace(0, T, n_seg + 1).astype(int)
    centres = np.array([(t[a] + t[b - 1]) / 2 for a, b in zip(edges[:-1], edges[1:])])
    for _ in range(3):
        A = np.stack([_amplitudes(y[a:b], t[a:b], f)[0] for a, b in zip(edges[:-1], edges[1:])])  # (n_seg, nb)
        prod = np.sum(A[1:] * np.conj(A[:-1]))
        f = f + float(np.angle(prod)) / (4.0 * np.pi * float(np.mean(np.diff(centres))))
    return f


def calibrate_flat_target(
    source, dt_s: float, target_aolp_rad: float = 0.0, rate_hz: float | None = None, rate_guess_hz: float = 30.0, bin_px: int = 10
) -> PolarizerCalibration:
    """phi0 and rate from a stream of a flat target linearly polarized at ``target_aolp_rad``.

    Args:
        source: (T, H, W) spikes or a SpikeGroup of the target.
        dt_s: step length in seconds.
        target_aolp_rad: polarization angle of the target (image frame).
        rate_hz: known rate (skip the search) or None to estimate it.
    """
    y = binned_counts(source, bin_px)
    f = rate_hz if rate_hz is not None else estimate_rate(y, dt_s, rate_guess_hz)
    t = (np.arange(y.shape[0]) + 0.5) * dt_s
    A = _amplitudes(y.sum(axis=1, keepdims=True), t, f)[0, 0]
    phi0 = target_aolp_rad + 0.5 * np.angle(A)  # A ~ b exp(i(2 phi0 - 2 psi))
    mod = float(np.abs(A) / max(y.sum(axis=1).mean(), 1e-12))
    return PolarizerCalibration(float(_wrap_pi(phi0)), float(f), "flat-target fit", mod)


def calibrate_from_modulation(
    source,
    dt_s: float,
    axis_rad,
    prior_phi0_rad: float = 0.0,
    rate_hz: float | None = None,
    rate_guess_hz: float = 30.0,
    bin_px: int = 10,
) -> PolarizerCalibration:
    """phi0 and rate from the modulation of a scene whose polarization AXIS is known up to 90 deg.

    Args:
        source: (T, H, W) spikes or a SpikeGroup.
        dt_s: step length.
        axis_rad: scalar or (H, W) polarization axis per pixel, modulo pi/2
            (e.g. the pane's phi_perp map).
        prior_phi0_rad: a rough phase (e.g. the nominal one) choosing among the
            four solutions phi0 + k pi/2 (mod pi: two candidates).
        rate_hz: known rate or None to estimate it.
    """
    y = binned_counts(source, bin_px)
    f = rate_hz if rate_hz is not None else estimate_rate(y, dt_s, rate_guess_hz)
    t = (np.arange(y.shape[0]) + 0.5) * dt_s
    A = _amplitudes(y, t, f)[0]  # (nb,)
    ax = np.asarray(axis_rad, dtype=np.float64)
    if ax.ndim == 2:
        if hasattr(source, "height"):
            H, W = source.height, source.width
        else:
            H, W = np.asarray(source).shape[1:]
        if ax.shape != (H, W):
            raise ShapeError(f"axis map is {ax.shape}, the stream is {H}x{W}", ax.shape, f"({H}, {W})")
        b = bin_px
        hb, wb = H // b, W // b
        # average the axis over each block on the doubled-angle circle
        z = np.exp(2j * ax[: hb * b, : wb * b]).reshape(hb, b, wb, b).mean(axis=(1, 3)).ravel()
        psi = 0.5 * np.angle(z)
    else:
        psi = np.full(A.shape, float(ax))
    r = A * np.exp(2j * psi)  # ~ +-|b| exp(2 i phi0)
    base = 0.25 * np.angle(np.sum(r * r))  # 4 phi0 known, phi0 mod pi/2
    cands = base + np.array([0.0, np.pi / 2])
    k = int(np.argmin(np.abs(_wrap_pi(cands - prior_phi0_rad))))
    mod = float(np.sqrt(np.abs(np.sum(r * r))) / max(y.sum(axis=1).mean(), 1e-12))
    return PolarizerCalibration(float(_wrap_pi(cands[k])), float(f), "modulation fit", mod)


def darkest_phase(source, dt_s: float, rate_hz: float, target_aolp_rad: float = 0.0, window_steps: int = 13) -> PolarizerCalibration:
    """The rig's method: the angle at the darkest (smoothed) frame of the first turn is psi + pi/2."""
    y = binned_counts(source, 10).sum(axis=1)
    n_turn = int(round(0.5 / (rate_hz * dt_s)))  # half a turn covers a full intensity period
    y = y[: max(n_turn, window_steps)]
    sm = np.convolve(y, np.ones(window_steps) / window_steps, mode="same")
    h = window_steps // 2
    k = h + int(np.argmin(sm[h : len(sm) - h]))
    t_dark = (k + 0.5) * dt_s
    phi0 = target_aolp_rad + np.pi / 2 - 2.0 * np.pi * rate_hz * t_dark
    return PolarizerCalibration(float(_wrap_pi(phi0)), float(rate_hz), "darkest window", float("nan"))


def phase_error(cal: PolarizerCalibration, t_s, phi_true_rad) -> dict[str, float]:
    """Error of the calibrated phi(t) against the true angles (mod pi), degrees.

    Returns:
        {"phi0_err_deg": error at t = first sample, "rms_deg", "max_abs_deg"}.
    """
    e = _wrap_pi(cal.phi(t_s) - np.asarray(phi_true_rad))
    return {"phi0_err_deg": float(np.rad2deg(e[0])), "rms_deg": float(np.rad2deg(np.sqrt(np.mean(e**2)))), "max_abs_deg": float(np.rad2deg(np.max(np.abs(e))))}


def calibrate_group(group, target_aolp_rad: float | None = None, rate_hz: float | None = None, bin_px: int = 10) -> dict:
    """Calibrate the polarizer of a stored spike group and report the error against its true phi(t).

    Args:
        group: a :class:`spike_sim.store.SpikeGroup` (or its folder).
        target_aolp_rad: AoLP of a flat polarized target filmed in the group
            (:func:`calibrate_flat_target`); None = a glass scene, using the
            group's ``phi_perp`` map as the polarization axis
            (:func:`calibrate_from_modulation`, nominal phase as the prior).
        rate_hz: known rotation rate, or None to estimate it (search around the
            group's nominal rate).

    Returns:
        dict with the estimate (``phi0_deg`` mod 180, ``rate_hz``, ``method``,
        ``modulation``), the nominal polarizer (``nominal_phase_deg``,
        ``nominal_rate_hz``) and the errors of the calibrated phi(t) against the
        stored true angle per step (``phi0_err_deg``, ``rms_deg``, ``max_abs_deg``).
    """
    from spike_sim.store import SpikeGroup, open_group

    g = group if isinstance(group, SpikeGroup) else open_group(group)
    pol = g.json_attr("polarizer_json") or {}
    nom_rate = float(pol.get("rate_hz", 30.0))
    nom_phase = float(np.deg2rad(pol.get("phase_deg", 0.0)))
    if target_aolp_rad is not None:
        cal = calibrate_flat_target(g, g.dt_s, float(target_aolp_rad), rate_hz=rate_hz, rate_guess_hz=nom_rate, bin_px=bin_px)
    else:
        maps = g.maps()
        if "phi_perp" not in maps:
            raise ConfigError(f"{g.path} has no phi_perp map (render without maps.exr?); give the flat target's AoLP (--target-aolp-deg)")
        cal = calibrate_from_modulation(g, g.dt_s, maps["phi_perp"], prior_phi0_rad=nom_phase, rate_hz=rate_hz, rate_guess_hz=nom_rate, bin_px=bin_px)
    t = (np.arange(g.n_steps) + 0.5) * g.dt_s
    err = phase_error(cal, t, g.phi_true_rad)
    return {
        "phi0_deg": float(np.rad2deg(cal.phi0_rad) % 180.0),
        "rate_hz": cal.rate_hz,
        "method": cal.method,
        "modulation": cal.modulation,
        "nominal_phase_deg": float(pol.get("phase_deg", 0.0)),
        "nominal_rate_hz": nom_rate,
        **err,
    }
