"""Where is the reflection R identifiable from one window?  The reflected share and a noise floor for R.

Paper Eq. (1) in the solvers' units: b_k = 2 I_k = (1 - zeta_k) T + zeta_k R, k = 1..N (N = 7 windows
of one output frame, zeta_k the true mixing coefficient of window k).  Two quantities answer the
"R >= 22 dB where the reflection is at least 20 % of the light":

* the **reflected share** of the light, rho = zbar R / (zbar R + (1 - zbar) T) (:func:`reflected_share`),
  with zbar the half-turn mean of zeta, (R_perp + R_par) / 2: the share of reflection in what the
  camera receives averaged over the polarizer angle (a property of the scene, not of the polarizer's
  phase at one frame, so the masked pixels do not flicker from frame to frame);
* the **noise floor of R**: the variance of the unbiased least-squares estimate of (T, R) from the N
  observations with the TRUE zeta and the window's spike noise (:func:`ls_layer_variance`), and the
  PSNR it implies (:func:`bound_psnr`).  It depends only on the modulation of zeta over the window
  (var(R^) ~ 4 sigma^2 / (N var_k zeta_k) for small zeta) and on the noise of the Eq. (3) window mean.

Noise of an Eq. (3) window mean (:func:`window_mean_variance`), in radiance units, I^ = counts /
(exposure * L) over L steps.  The simulator (:mod:`spike_sim.integrate_fire`) is an integrate-and-fire
pixel with a subtractive reset: the accumulator keeps its residue, so over L steps with m = exposure
I L expected thresholds the count is floor(u + m) for a residue u spread over [0, 1), i.e. floor(m) or
floor(m) + 1 with probability f = frac(m): var = f (1 - f) (quantization, <= 1/4 whatever m), plus the
charge noise accumulated over the window, m / Q (shot noise, Q photoelectrons per threshold) and
sigma_reset^2 per spike.  The per-pixel gain / threshold mismatch (a few %) spreads m across pixels, so
the quantization term is averaged over that spread (Gauss-Hermite, ``rel_sigma``).  A Poisson count
(``model="poisson"``, var = m, the synthetic set's pessimistic noise) is far noisier for m > 1: at the
stress set's exposure 3 and L = 13, a pixel with I = 0.1 gets m = 3.9, Poisson var 3.9, integrate-and-
fire var 0.09 + 0.004.  Tests check the integrate-and-fire formula against the simulator itself and
the LS variance against a Monte-Carlo.

The bound is for the unclipped, unbiased estimate from one window; the scores clip R^ to [0, 1], so
where the bound is far below 0 dB the clipped scores can exceed it (they then reflect the clipping,
not information about R).  The fixed per-pixel gain mismatch biases T^ and R^ alike and is not in it.
"""

from __future__ import annotations

import math

import numpy as np

from polinfra.errors import ConfigError, ShapeError

__all__ = ["SHARE_MIN", "NOISE_MODELS", "reflected_share", "count_variance", "window_mean_variance", "ls_layer_variance", "bound_psnr"]

SHARE_MIN = 0.2
"""Issue 16's threshold on the reflected share: "where the reflection is at least 20 % of the light"."""

NOISE_MODELS = ("integrate_fire", "poisson")
"""Count-noise models of :func:`count_variance`."""

_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(9)  # probabilists' Gauss-Hermite: E[g(z)], z ~ N(0, 1)
_GH_W = _GH_W / _GH_W.sum()


def reflected_share(T, R, zbar) -> np.ndarray:
    """Rho = zbar R / (zbar R + (1 - zbar) T), elementwise (0 where no light arrives)."""
    T = np.clip(np.asarray(T, np.float64), 0.0, None)
    R = np.clip(np.asarray(R, np.float64), 0.0, None)
    zb = np.asarray(zbar, np.float64)
    refl = zb * R
    tot = refl + (1.0 - zb) * T
    return np.divide(refl, tot, out=np.zeros(np.broadcast(refl, tot).shape), where=tot > 0)


def _frac_var(m: np.ndarray) -> np.ndarray:
    f = m - np.floor(m)
    return f * (1.0 - f)


def count_variance(m, model: str = "integrate_fire", photons_per_threshold: float = math.inf, reset_sigma: float = 0.0, rel_sigma: float = 0.0) -> np.ndarray:
    """Variance of the spike count of one window with ``m`` expected thresholds (module docstring).

    Args:
        m: expected count, exposure * I * L (array; negatives count as 0).
        model: ``integrate_fire`` (the simulator's pixel: frac(m)(1 - frac(m)) + m / Q + m sigma_reset^2)
            or ``poisson`` (var = m).
        photons_per_threshold: Q of the shot noise (inf: no shot noise).
        reset_sigma: reset-noise std per spike, thresholds.
        rel_sigma: relative spread of m across pixels (gain and threshold mismatch); the quantization term
            is averaged over m (1 + rel_sigma z), z ~ N(0, 1).
    """
    m = np.clip(np.asarray(m, np.float64), 0.0, None)
    if model == "poisson":
        return m
    if model != "integrate_fire":
        raise ConfigError(f"unknown count-noise model {model!r}; choose from {list(NOISE_MODELS)}")
    if rel_sigma > 0:
        q = sum(w * _frac_var(np.clip(m * (1.0 + rel_sigma * x), 0.0, None)) for x, w in zip(_GH_X, _GH_W))
    else:
        q = _frac_var(m)
    return q + m / photons_per_threshold + m * reset_sigma**2


def window_mean_variance(I, exposure: float, window_steps: int, **noise) -> np.ndarray:
    """Variance of the Eq. (3) window mean I^ = counts / (exposure L) in radiance^2, at true radiance ``I``
    behind the polarizer (keywords: :func:`count_variance`).
    """
    if exposure <= 0 or window_steps < 1:
        raise ConfigError(f"window noise needs exposure > 0 and window_steps >= 1; got {exposure}, {window_steps}")
    s = float(exposure) * int(window_steps)
    return count_variance(np.asarray(I, np.float64) * s, **noise) / (s * s)


def ls_layer_variance(zeta, var_I, weighted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Variances of (T^, R^) of the least-squares solution of b_k = (1 - zeta_k) T + zeta_k R (b = 2 I).

    Args:
        zeta: (N, ...) true mixing coefficients of the window's observations.
        var_I: (N, ...) variance of each observation's window mean I^ (var b = 4 var I), independent.
        weighted: False: ordinary LS (what the ``ls`` solver computes), its exact sandwich covariance
            (A'A)^-1 A' diag(var b) A (A'A)^-1; True: the generalized (inverse-variance weighted) LS,
            (A' diag(var b)^-1 A)^-1, the smallest variance of any unbiased linear estimate (the
            Cramer-Rao bound for Gaussian noise).

    Returns:
        (var T^, var R^), each (...); inf where zeta does not modulate (singular normal equations).
    """
    z = np.asarray(zeta, np.float64)
    vb = 4.0 * np.asarray(var_I, np.float64)
    if z.shape != vb.shape or z.ndim < 1:
        raise ShapeError(f"zeta and var_I must be (N, ...) of one shape; got {z.shape} and {vb.shape}", actual_shape=vb.shape, expected_shape=z.shape)
    a_t, a_r = 1.0 - z, z
    if weighted:
        w = 1.0 / np.maximum(vb, 1e-300)
        s_tt, s_tr, s_rr = (w * a_t * a_t).sum(0), (w * a_t * a_r).sum(0), (w * a_r * a_r).sum(0)
        det = s_tt * s_rr - s_tr * s_tr
        ok = det > 1e-14 * np.maximum(s_tt * s_rr, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(ok, s_rr / det, np.inf), np.where(ok, s_tt / det, np.inf)
    s_tt, s_tr, s_rr = (a_t * a_t).sum(0), (a_t * a_r).sum(0), (a_r * a_r).sum(0)
    det = s_tt * s_rr - s_tr * s_tr  # = N^2 var_k(zeta_k) (Lagrange's identity)
    ok = det > 1e-14 * np.maximum(s_tt * s_rr, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        c_t = (s_rr * a_t - s_tr * a_r) / det  # rows of (A'A)^-1 A'
        c_r = (s_tt * a_r - s_tr * a_t) / det
        return np.where(ok, (c_t * c_t * vb).sum(0), np.inf), np.where(ok, (c_r * c_r * vb).sum(0), np.inf)


def bound_psnr(var_R, mask=None, data_range: float = 1.0) -> float | None:
    """PSNR (dB) implied by a per-pixel estimate variance: 10 log10(range^2 / mean var) over ``mask``
    (None: all pixels); None for an empty mask; clamped to [-100, 100] dB (+100 like :func:`reconstruct.evaluate.metrics.psnr`;
    -100 where zeta does not modulate at some pixel, infinite variance: R unidentifiable).
    """
    v = np.asarray(var_R, np.float64)
    if mask is not None:
        v = v[np.asarray(mask, bool)]
    if v.size == 0:
        return None
    mse = float(np.mean(v))
    if not np.isfinite(mse):
        return -100.0
    return float(np.clip(10.0 * math.log10(data_range**2 / mse), -100.0, 100.0)) if mse > 0 else 100.0
