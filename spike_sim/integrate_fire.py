"""Integrate-and-fire spike camera pixel: fast numba kernel and a plain numpy reference.

Model (threshold units, see :mod:`spike_sim.config`), per pixel p and step n::

    x     = dark_p + sum_j coef[n, j] * basis[j, p]          photocurrent (basis has exposure*gain_p folded in)
    incr  = Poisson(Q max(x, 0)) / Q                        shot noise (or x when off)
    incr  = incr (1 + sigma_m z_m)                          multiplicative increment noise (sigma_m = 0: off)
    V     = V * leak + incr                                 integrate (leak = exp(-leak_rate / rate))
    fire  = V + sigma_th * z_th >= theta_p                  comparison with thermal noise
    V     = V - theta_p + sigma_reset * z_reset   if fire   subtract the threshold, keep the residue

The output is one bit per pixel per step, bit-packed LSB first per frame
(``np.packbits(frame.ravel(), bitorder="little")``), frames upright.

Fast kernel (:func:`run_numba`): parallel over blocks of 128 pixels, each block
stepping through time with its state in L1, inner loop over pixels vectorised
(AVX2).  Randomness is COUNTER-BASED: every per-step variate comes from a 32-bit
hash of (pixel key, step key), the keys being hashes of (seed, pixel index) and
(seed, step index).  The result depends on (seed, pixel, step) only, so it is
identical for any chunking in time and any thread count.  Statistically
equivalent reformulation (tested against the numpy reference in
tests/spike_sim/test_integrate_fire.py): the Poisson count of a step is replaced
by its Gaussian approximation ``x + sqrt(x / Q) z`` (Q >= ~100 photoelectrons per
threshold, so every inter-spike interval sums >= 100 photoelectrons and only the
mean and variance per step matter), and the unit normals z are triangular
variates (difference of two uniform bytes, scaled to unit variance).  The 32-bit
hash repeats for random, unstructured pairs of (pixel, step) about once per 2^32.

Reference (:func:`run_numpy`): the same model with exact Poisson counts and
normals from ``np.random.Generator``, one vectorised numpy update per step.
"""

from __future__ import annotations

import dataclasses
import logging

import numba as nb
import numpy as np
from numba import prange

from polinfra.errors import ShapeError
from spike_sim.config import SpikeSimConfig

__all__ = [
    "PixelParams",
    "make_pixel_params",
    "step_keys",
    "noise_scalars",
    "run_numba",
    "run_numpy",
    "simulate_currents",
    "simulate_constant",
    "packed_frame_bytes",
    "BLOCK",
]

log = logging.getLogger(__name__)

BLOCK = 128
"""Pixels per parallel block (multiple of 8 so blocks own whole output bytes)."""

_TRI_SCALE = np.float32(0.009568205)
"""Scale of the triangular variate (a - b), a, b uniform bytes: 1 / sqrt(2 (256^2 - 1) / 12) = 0.0095684 would give it
unit variance; the kernel has always used this value, 2e-5 lower (variance 0.99996), and keeps it so that every
stream it made stays bit for bit the same."""


def packed_frame_bytes(n_pixels: int) -> int:
    """Bytes per bit-packed frame of ``n_pixels`` (ceil(P / 8))."""
    return (n_pixels + 7) // 8


@dataclasses.dataclass(frozen=True)
class PixelParams:
    """Per-pixel fixed parameters, all (P,) with P = H * W (row-major).

    Attributes:
        gain: photo-gain times exposure (thresholds per step per unit intensity), float32.
        theta: threshold, float32 (mean 1).
        dark: dark current, thresholds per step, float32.
        key: uint32 counter-hash key of the pixel.
        v0: initial accumulator, float32.
    """

    gain: np.ndarray
    theta: np.ndarray
    dark: np.ndarray
    key: np.ndarray
    v0: np.ndarray


def _mix32_np(h: np.ndarray) -> np.ndarray:
    h = h.astype(np.uint32)
    h ^= h >> np.uint32(16)
    h *= np.uint32(0x7FEB352D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x846CA68B)
    h ^= h >> np.uint32(16)
    return h


def _seed32(seed: int, stream: int) -> np.uint32:
    s = np.array([(int(seed) * 0x9E3779B1 + stream * 0x85EBCA77) & 0xFFFFFFFF], dtype=np.uint32)
    return _mix32_np(_mix32_np(s) ^ np.uint32((int(seed) >> 32) & 0xFFFFFFFF))[0]


def step_keys(n0: int, n1: int, seed: int) -> np.ndarray:
    """uint32 hash keys of steps ``n0 .. n1-1`` for ``seed`` (independent of chunking)."""
    n = np.arange(n0, n1, dtype=np.uint64) & np.uint64(0xFFFFFFFF)
    return _mix32_np(n.astype(np.uint32) * np.uint32(0x9E3779B9) ^ _seed32(seed, 2))


def make_pixel_params(cfg: SpikeSimConfig, seed: int) -> PixelParams:
    """Draw the fixed pattern of a sensor (deterministic in ``seed``).

    Uses ``np.random.default_rng([seed, 0x5EED])`` for the per-pixel maps (drawn
    once for the whole sensor, so independent of chunking).
    """
    P = cfg.n_pixels
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, 0x5EED])
    gain = np.full(P, cfg.exposure, dtype=np.float64)
    theta = np.ones(P)
    if cfg.fixed_pattern:
        cap = rng.normal(1.0, cfg.threshold_sigma, P)
        off = rng.normal(0.0, cfg.offset_sigma, P)
        theta = np.clip(cap * (1.0 + off), 0.5, 2.0)
        gain = cfg.exposure * np.clip(rng.normal(1.0, cfg.gain_sigma, P), 0.1, 3.0)
    dark = np.zeros(P)
    if cfg.dark_current:
        dark = np.clip(rng.normal(cfg.dark_mean, cfg.dark_std, P), 0.0, None)
        hot = rng.random(P) < cfg.hot_pixel_fraction
        dark[hot] = cfg.hot_pixel_dark
    v0 = rng.random(P) * theta if cfg.random_init else np.zeros(P)
    key = _mix32_np(np.arange(P, dtype=np.uint32) * np.uint32(0x27D4EB2F) ^ _seed32(seed, 1))
    return PixelParams(gain.astype(np.float32), theta.astype(np.float32), dark.astype(np.float32), key, v0.astype(np.float32))


def noise_scalars(cfg: SpikeSimConfig) -> tuple[float, float, float, float, float]:
    """(1/Q or 0, thermal sigma or 0, reset sigma or 0, per-step leak factor, increment sigma) for the kernels."""
    invq = 1.0 / cfg.photons_per_threshold if cfg.shot_noise else 0.0
    sth = cfg.thermal_sigma if cfg.thermal_noise else 0.0
    sres = cfg.reset_sigma if cfg.reset_noise else 0.0
    leak = float(np.exp(-cfg.leak_rate_hz / cfg.rate_hz)) if cfg.leakage else 1.0
    return invq, sth, sres, leak, float(cfg.increment_sigma)


@nb.njit(parallel=True, nogil=True, fastmath=False, error_model="numpy", cache=True)
def _kernel(basis, coef, stepkey, pkey, dark, theta, V, invq, sth, sres, leak, smul, out):  # pragma: no cover - jitted
    P = basis.shape[1]
    NS = coef.shape[0]
    BS = BLOCK
    nblk = (P + BS - 1) // BS
    tri = _TRI_SCALE
    zero = np.float32(0.0)
    for b in prange(nblk):
        p0 = b * BS
        p1 = min(P, p0 + BS)
        n = p1 - p0
        v = V[p0:p1].copy()
        b0 = basis[0, p0:p1].copy()
        b1 = basis[1, p0:p1].copy()
        b2 = basis[2, p0:p1].copy()
        b3 = basis[3, p0:p1].copy()
        b4 = basis[4, p0:p1].copy()
        b5 = basis[5, p0:p1].copy()
        th = theta[p0:p1].copy()
        dk = dark[p0:p1].copy()
        pk = pkey[p0:p1].copy()
        bits = np.zeros(BS, np.uint8)
        b64 = bits.view(np.uint64)
        ob = p0 // 8
        nbytes = (n + 7) // 8
        for s in range(NS):
            c0 = coef[s, 0]
            c1 = coef[s, 1]
            c2 = coef[s, 2]
            c3 = coef[s, 3]
            c4 = coef[s, 4]
            c5 = coef[s, 5]
            sk = stepkey[s]
            for i in range(n):
                x = dk[i] + c0 * b0[i] + c1 * b1[i] + c2 * b2[i] + c3 * b3[i] + c4 * b4[i] + c5 * b5[i]
                lam = max(x, zero)
                h = np.uint32(pk[i] + sk)
                h = np.uint32(h ^ (h >> 16))
                h = np.uint32(h * np.uint32(0x7FEB352D))
                h = np.uint32(h ^ (h >> 15))
                h = np.uint32(h * np.uint32(0x846CA68B))
                h = np.uint32(h ^ (h >> 16))
                g = np.uint32(h ^ (h >> 13))
                g = np.uint32(g * np.uint32(0x5BD1E995))
                g = np.uint32(g ^ (g >> 15))
                z1 = np.float32(np.int32(h & 255) - np.int32((h >> 8) & 255)) * tri
                z2 = np.float32(np.int32((h >> 16) & 255) - np.int32(h >> 24)) * tri
                z3 = np.float32(np.int32((g >> 16) & 255) - np.int32(g >> 24)) * tri
                vi = v[i] * leak + lam + np.sqrt(lam * invq + smul * smul * lam * lam) * z1
                t = th[i]
                f = np.float32(vi + sth * z2 >= t)
                v[i] = vi - f * (t - sres * z3)
                bits[i] = np.uint8(f)
            # pack 8 one-byte flags (little endian) into one LSB-first byte: the
            # multiplier moves flag i (bit 8 i) to bit 56 + i without carries
            for k in range(nbytes):
                out[s, ob + k] = np.uint8((b64[k] * np.uint64(0x0102040810204080)) >> np.uint64(56))
        V[p0:p1] = v


def _check(basis, coef, P):
    if basis.ndim != 2 or basis.shape[0] != 6 or basis.shape[1] != P:
        raise ShapeError(f"basis must be (6, {P}) float32, got {basis.shape}", basis.shape, f"(6, {P})")
    if coef.ndim != 2 or coef.shape[1] != 6:
        raise ShapeError(f"coef must be (n_steps, 6), got {coef.shape}", coef.shape, "(n_steps, 6)")


def run_numba(basis, coef, stepkey, params: PixelParams, V, scalars, out) -> None:
    """Advance the sensor through ``len(coef)`` steps with the fast kernel (in place).

    Args:
        basis: (6, P) float32 per-pixel images whose step-weighted sum is the
            photocurrent (exposure * gain already folded in).
        coef: (NS, 6) float32 per-step weights.
        stepkey: (NS,) uint32 counter keys of these steps (:func:`step_keys`).
        params: the fixed pattern.
        V: (P,) float32 accumulator state, updated.
        scalars: :func:`noise_scalars` tuple.
        out: (NS, ceil(P/8)) uint8, receives the packed frames.
    """
    P = params.theta.size
    _check(basis, coef, P)
    if len(coef) == 0:
        return
    invq, sth, sres, leak, smul = (np.float32(s) for s in scalars)
    _kernel(
        np.ascontiguousarray(basis, dtype=np.float32),
        np.ascontiguousarray(coef, dtype=np.float32),
        np.ascontiguousarray(stepkey, dtype=np.uint32),
        params.key,
        params.dark,
        params.theta,
        V,
        invq,
        sth,
        sres,
        leak,
        smul,
        out,
    )


def run_numpy(basis, coef, params: PixelParams, V, scalars, out, rng: np.random.Generator) -> None:
    """Reference: the same model, exact Poisson and Gaussian draws, one numpy update per step.

    Same arguments as :func:`run_numba` (no step keys: randomness from ``rng``).
    """
    P = params.theta.size
    _check(basis, coef, P)
    invq, sth, sres, leak, smul = scalars
    basis64 = np.asarray(basis, dtype=np.float64)
    theta = params.theta.astype(np.float64)
    dark = params.dark.astype(np.float64)
    v = V.astype(np.float64)
    for s in range(len(coef)):
        x = dark + coef[s].astype(np.float64) @ basis64
        lam = np.maximum(x, 0.0)
        incr = rng.poisson(lam / invq) * invq if invq > 0 else lam
        if smul > 0:
            incr = incr * (1.0 + smul * rng.standard_normal(P))
        v = v * leak + incr
        cmp = v + sth * rng.standard_normal(P) if sth > 0 else v
        fire = cmp >= theta
        v = v - fire * theta
        if sres > 0:
            v = v + fire * (sres * rng.standard_normal(P))
        out[s] = np.packbits(fire, bitorder="little")
    V[:] = v.astype(np.float32)


def simulate_currents(
    intensity: np.ndarray,
    cfg: SpikeSimConfig,
    seed: int,
    engine: str = "numba",
    step0: int = 0,
    V: np.ndarray | None = None,
    params: PixelParams | None = None,
) -> np.ndarray:
    """Simulate a stream from per-step intensities behind the polarizer (small inputs, tests).

    Args:
        intensity: (T, H, W) or (H, W) (constant over ``T = cfg`` steps is not
            implied: a 2-D input means one step) mean intensity per step.
        cfg: simulator config (its width/height must match).
        seed: seed.
        engine: "numba" (fast kernel) or "numpy" (reference).
        step0: global index of the first step (for chunked calls).
        V, params: state / fixed pattern to continue from (fresh when None).

    Returns:
        (T, H, W) uint8 spikes.
    """
    arr = np.asarray(intensity, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[None]
    T, H, W = arr.shape
    if (H, W) != (cfg.height, cfg.width):
        raise ShapeError(f"intensity frames are {H}x{W} but the config says {cfg.height}x{cfg.width}", arr.shape, "(T, height, width)")
    params = params or make_pixel_params(cfg, seed)
    if V is None:
        V = params.v0.copy()
    P = H * W
    out = np.zeros((T, packed_frame_bytes(P)), np.uint8)
    scal = noise_scalars(cfg)
    rng = np.random.default_rng([seed, 0xB0B])
    for s in range(T):
        basis = np.zeros((6, P), np.float32)
        basis[0] = arr[s].ravel() * params.gain
        coef = np.zeros((1, 6), np.float32)
        coef[0, 0] = 1.0
        if engine == "numba":
            run_numba(basis, coef, step_keys(step0 + s, step0 + s + 1, seed), params, V, scal, out[s : s + 1])
        else:
            run_numpy(basis, coef, params, V, scal, out[s : s + 1], rng)
    bits = np.unpackbits(out, axis=1, bitorder="little", count=P)
    return bits.reshape(T, H, W)


def simulate_constant(
    intensity: np.ndarray,
    n_steps: int,
    cfg: SpikeSimConfig,
    seed: int,
    engine: str = "numba",
    packed: bool = False,
) -> np.ndarray:
    """Simulate ``n_steps`` of a constant intensity image (H, W) behind the polarizer.

    Returns:
        (n_steps, H, W) uint8 spikes, or the packed (n_steps, ceil(H W / 8)) frames
        when ``packed``.
    """
    arr = np.asarray(intensity, dtype=np.float32)
    if arr.shape != (cfg.height, cfg.width):
        raise ShapeError(f"intensity is {arr.shape} but the config says ({cfg.height}, {cfg.width})", arr.shape, "(height, width)")
    params = make_pixel_params(cfg, seed)
    V = params.v0.copy()
    P = arr.size
    basis = np.zeros((6, P), np.float32)
    basis[0] = arr.ravel() * params.gain
    coef = np.zeros((n_steps, 6), np.float32)
    coef[:, 0] = 1.0
    out = np.zeros((n_steps, packed_frame_bytes(P)), np.uint8)
    scal = noise_scalars(cfg)
    if engine == "numba":
        run_numba(basis, coef, step_keys(0, n_steps, seed), params, V, scal, out)
    elif engine == "numpy":
        run_numpy(basis, coef, params, V, scal, out, np.random.default_rng([seed, 0xB0B]))
    else:
        from polinfra.errors import ConfigError

        raise ConfigError(f"unknown engine {engine!r}; choose 'numba' or 'numpy'")
    if packed:
        return out
    return np.unpackbits(out, axis=1, bitorder="little", count=P).reshape(n_steps, cfg.height, cfg.width)
