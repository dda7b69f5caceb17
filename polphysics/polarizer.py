"""The rotating linear polarizer in front of the spike camera.

Angle model (radians, image-plane convention of :mod:`polphysics.stokes`)::

    phi(t) = phi0 + 2 pi f [t + a (1 - cos(2 pi f_w t)) / (2 pi f_w)] + j_n

* ``phi0 = radians(phase_deg + calibration_offset_deg)`` is the TRUE phase at
  t = 0; the calibrated (nominal) phase that a reconstructor believes is
  ``radians(phase_deg)``, so ``calibration_offset_deg`` is "true minus calibrated".
* ``a = wobble_frac``, ``f_w = wobble_hz``: the instantaneous speed is
  ``f (1 + a sin(2 pi f_w t))`` (the integral above), phi(0) = phi0.
* ``j_n ~ N(0, jitter)``: one angle-jitter value per simulator step ``n``,
  constant within the step, drawn from a counter-based hash of (seed, n), so it
  does not depend on how a stream is chunked.

Defaults: f = 30 rev/s, so the output cadence at a 31.5 deg stride is
10800 / 31.5 = 342.9 frames/s (supp. Eq. (17)-(18)).

Step integral.  Inside one simulator step ``[t_a, t_b]`` the angle is taken as
linear in time between its exact end values (the step is 50 us; a wobble bends
it by at most 2 pi f a 2 pi f_w dt^2 / 8 rad: 1e-9 rad at a = 1 %, f_w = 2 Hz,
tested) and the intensity behind the polarizer
``I = 1/2 ((1 + k) S0 + (1 - k)(S1 cos 2phi + S2 sin 2phi))`` (k = 1/ER, ideal
k = 0) is integrated in CLOSED FORM.  With ``u in [0, 1]`` the fraction of the
step, ``2 phi(u) = alpha + beta u``, over a sub-range of mid ``u_m``, length
``L``, ``m = alpha + beta u_m``, ``h = beta L / 2``::

    int cos 2phi du   = L cos m sinc h
    int sin 2phi du   = L sin m sinc h
    int u cos 2phi du = u_m L cos m sinc h - L^2 sin m J(h)
    int u sin 2phi du = u_m L sin m sinc h + L^2 cos m J(h)
    J(h) = int_{-1/2}^{1/2} s sin(2 h s) ds = (sin h - h cos h) / (2 h^2)

The ``u``-weighted terms carry the LINEAR-IN-TIME interpolation of the Stokes
vector between keyframes: ``S(t) = (1 - w) S_k + w S_{k+1}``, ``w`` linear in
``t``, hence linear in ``u`` inside the step.  :func:`step_keyframe_weights`
turns all this into, per step, weights on the keyframes' (S0, S1, S2), so the
step mean of I is a weighted sum of keyframe Stokes images (exact for the
model, no sampling).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polinfra.config import opt

__all__ = [
    "PolarizerConfig",
    "phi_true",
    "phi_nominal",
    "step_jitter",
    "step_phi_edges",
    "step_moments",
    "step_mean_intensity",
    "step_keyframe_weights",
    "transmittances",
]


@dataclasses.dataclass(frozen=True)
class PolarizerConfig:
    """Rotating polarizer parameters (the ``[polarizer]`` table of a scene)."""

    rate_hz: float = opt(30.0, "rotation rate in revolutions per second", lo=0.0, hi=10000.0)
    phase_deg: float = opt(0.0, "polarizer angle at t = 0, degrees from image +x toward image up", lo=-360.0, hi=360.0)
    extinction_ratio: float | None = opt(None, "principal transmittance ratio k_max/k_min (None or absent = ideal)", lo=1.0, hi=1e12)
    jitter_deg: float = opt(0.0, "per-step Gaussian angle jitter, standard deviation in degrees", lo=0.0, hi=45.0)
    wobble_frac: float = opt(0.0, "relative sinusoidal speed modulation amplitude", lo=0.0, hi=0.5)
    wobble_hz: float = opt(1.0, "frequency of the speed modulation, Hz", lo=0.0, hi=10000.0)
    calibration_offset_deg: float = opt(0.0, "true phase minus the calibrated (nominal) phase, degrees", lo=-90.0, hi=90.0)


def transmittances(cfg: PolarizerConfig) -> tuple[float, float]:
    """(k_max, k_min) principal transmittances: (1, 0) ideal, (1, 1/ER) otherwise."""
    if cfg.extinction_ratio is None:
        return 1.0, 0.0
    return 1.0, 1.0 / float(cfg.extinction_ratio)


def _smooth_angle(t_s, cfg: PolarizerConfig, phase_rad: float) -> np.ndarray:
    t = np.asarray(t_s, dtype=np.float64)
    turn = t
    if cfg.wobble_frac > 0.0 and cfg.wobble_hz > 0.0:
        w = 2.0 * np.pi * cfg.wobble_hz
        turn = t + cfg.wobble_frac * (1.0 - np.cos(w * t)) / w
    return phase_rad + 2.0 * np.pi * cfg.rate_hz * turn


def phi_nominal(t_s, cfg: PolarizerConfig) -> np.ndarray:
    """Calibrated angle a reconstructor assumes: radians(phase_deg) + 2 pi f t (no wobble, no jitter)."""
    t = np.asarray(t_s, dtype=np.float64)
    return np.deg2rad(cfg.phase_deg) + 2.0 * np.pi * cfg.rate_hz * t


def phi_true(t_s, cfg: PolarizerConfig) -> np.ndarray:
    """True smooth angle (offset and wobble, no per-step jitter), radians, unwrapped."""
    return _smooth_angle(t_s, cfg, np.deg2rad(cfg.phase_deg + cfg.calibration_offset_deg))


_M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = (x + np.uint64(0x9E3779B97F4A7C15)) & _M64
        z = ((z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & _M64
        z = ((z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & _M64
        return z ^ (z >> np.uint64(31))


def step_jitter(steps: np.ndarray, cfg: PolarizerConfig, seed: int) -> np.ndarray:
    """Per-step angle jitter (radians), N(0, jitter_deg) from a counter hash of (seed, step).

    Depends only on (seed, step index), never on chunking.  Zeros when jitter is off.
    """
    steps = np.asarray(steps, dtype=np.int64)
    if cfg.jitter_deg <= 0.0:
        return np.zeros(steps.shape)
    key = np.uint64((int(seed) * 0x2545F4914F6CDD1D + 0x6A09E667) & 0xFFFFFFFFFFFFFFFF)
    with np.errstate(over="ignore"):
        base = _splitmix64(steps.astype(np.uint64) * np.uint64(2) ^ key)
        b2 = _splitmix64(base)
    u1 = ((base >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53
    u2 = (b2 >> np.uint64(11)).astype(np.float64) / 2.0**53
    z = np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)  # Box-Muller
    return np.deg2rad(cfg.jitter_deg) * z


def step_phi_edges(n0: int, n1: int, dt_s: float, cfg: PolarizerConfig, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """True polarizer angle at the start and end of steps ``n0 .. n1-1``.

    Step n covers [n dt, (n+1) dt).  The per-step jitter is added to both edges.

    Returns:
        (phi_a, phi_b), each (n1 - n0,) float64 radians.
    """
    n = np.arange(n0, n1, dtype=np.int64)
    edges = phi_true(np.arange(n0, n1 + 1, dtype=np.float64) * dt_s, cfg)
    j = step_jitter(n, cfg, seed)
    return edges[:-1] + j, edges[1:] + j


def _sinc(h):
    h = np.asarray(h, dtype=np.float64)
    out = np.ones_like(h)
    big = np.abs(h) > 1e-4
    out[big] = np.sin(h[big]) / h[big]
    hs = h[~big]
    out[~big] = 1.0 - hs * hs / 6.0
    return out


def _jfun(h):
    """J(h) = (sin h - h cos h) / (2 h^2) = h/6 - h^3/60 + ..."""
    h = np.asarray(h, dtype=np.float64)
    out = np.empty_like(h)
    big = np.abs(h) > 1e-2
    hb = h[big]
    out[big] = (np.sin(hb) - hb * np.cos(hb)) / (2.0 * hb * hb)
    hs = h[~big]
    out[~big] = hs / 6.0 - hs**3 / 60.0 + hs**5 / 2520.0
    return out


def step_moments(phi_a, phi_b, u0=0.0, u1=1.0) -> dict[str, np.ndarray]:
    """Closed-form integrals over the sub-range [u0, u1] of a step of the polarizer terms.

    Inside the step 2 phi(u) = alpha + beta u, alpha = 2 phi_a, beta = 2 (phi_b - phi_a),
    u in [0, 1] the fraction of the step.

    Returns:
        dict with keys ``1, u, c, s, uc, us``: the integrals du of 1, u, cos 2phi,
        sin 2phi, u cos 2phi, u sin 2phi (NOT divided by the step; for the full
        step [0, 1] they are step means).  Arrays broadcast from the inputs.
    """
    pa = np.asarray(phi_a, dtype=np.float64)
    pb = np.asarray(phi_b, dtype=np.float64)
    u0 = np.asarray(u0, dtype=np.float64)
    u1 = np.asarray(u1, dtype=np.float64)
    alpha, beta = 2.0 * pa, 2.0 * (pb - pa)
    L = u1 - u0
    um = 0.5 * (u0 + u1)
    m = alpha + beta * um
    h = beta * L / 2.0
    sh = np.broadcast_shapes(m.shape, h.shape)
    snc = _sinc(np.broadcast_to(h, sh))
    jj = _jfun(np.broadcast_to(h, sh))
    cm, sm = np.cos(m), np.sin(m)
    c = L * cm * snc
    s = L * sm * snc
    return {
        "1": np.broadcast_to(L, sh).astype(np.float64),
        "u": np.broadcast_to(L * um, sh).astype(np.float64),
        "c": c,
        "s": s,
        "uc": um * c - L * L * sm * jj,
        "us": um * s + L * L * cm * jj,
    }


def step_mean_intensity(s0, s1, s2, phi_a, phi_b, extinction_ratio: float | None = None):
    """Mean over one step of I(phi(t)) for a CONSTANT Stokes vector (closed form).

    ``<I> = 1/2 ((1+k) S0 + (1-k) (S1 <cos 2phi> + S2 <sin 2phi>))``, phi linear
    from ``phi_a`` to ``phi_b`` over the step, k = 1/ER (0 ideal).  Equals
    :func:`polphysics.stokes.polarizer_intensity` when phi_a == phi_b.
    """
    mo = step_moments(phi_a, phi_b)
    k = 0.0 if extinction_ratio is None else 1.0 / float(extinction_ratio)
    return 0.5 * ((1.0 + k) * np.asarray(s0) + (1.0 - k) * (np.asarray(s1) * mo["c"] + np.asarray(s2) * mo["s"]))


def step_keyframe_weights(
    n0: int,
    n1: int,
    dt_s: float,
    key_times_s: np.ndarray,
    cfg: PolarizerConfig,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-step weights on keyframe Stokes so that step-mean I = sum_k W[n, k, :] . S_k.

    Stokes is interpolated linearly in time between keyframes (held constant
    before the first and after the last); the polarizer term is integrated in
    closed form (module docstring).  Steps ``n0 .. n1-1``, step n covering
    [n dt, (n+1) dt).

    Args:
        n0, n1: step range.
        dt_s: step length in seconds (1 / 20 kHz).
        key_times_s: (K,) strictly increasing keyframe times, seconds.
        cfg: polarizer.
        seed: seed of the per-step angle jitter.

    Returns:
        (k_lo, W): ``k_lo`` (N,) int64, the first keyframe each step touches; ``W``
        (N, 3, 3) float64 weights on keyframes ``k_lo + 0..2`` and Stokes (S0, S1, S2).
        A step touches at most 3 keyframes when keyframes are >= 1 step apart.
    """
    kt = np.asarray(key_times_s, dtype=np.float64)
    K = kt.size
    N = n1 - n0
    phi_a, phi_b = step_phi_edges(n0, n1, dt_s, cfg, seed)
    kmax, kmin = transmittances(cfg)
    kp, km = 0.5 * (kmax + kmin), 0.5 * (kmax - kmin)
    ta = np.arange(n0, n1, dtype=np.float64) * dt_s
    tb = ta + dt_s
    W = np.zeros((N, 3, 3))
    if K == 1:
        mo = step_moments(phi_a, phi_b)
        W[:, 0, 0] = kp
        W[:, 0, 1] = km * mo["c"]
        W[:, 0, 2] = km * mo["s"]
        return np.zeros(N, dtype=np.int64), W
    # interval index j: [kt[j], kt[j+1]]; -1 before the first, K-1 after the last
    ja = np.searchsorted(kt, ta, side="right") - 1
    jb = np.searchsorted(kt, tb, side="left") - 1
    ja = np.clip(ja, -1, K - 1)
    jb = np.clip(jb, ja, K - 1)
    if np.any(jb - ja > 1):
        from polinfra.errors import ConfigError

        raise ConfigError(f"keyframes closer than one simulator step ({dt_s * 1e6:.1f} us) are not supported; min spacing seen {np.min(np.diff(kt)) * 1e6:.3f} us")
    k_lo = np.clip(ja, 0, max(K - 3, 0)).astype(np.int64)
    for part in range(2):
        # part 0: [ta, min(tb, kt[ja+1])] in interval ja ; part 1: rest in interval jb (only if jb > ja)
        j = ja if part == 0 else jb
        if part == 1:
            sel = jb > ja
        else:
            sel = np.ones(N, dtype=bool)
        if not np.any(sel):
            continue
        idx = np.flatnonzero(sel)
        jj = j[idx]
        t_lo = ta[idx] if part == 0 else kt[jj]
        t_hi = np.where(jb[idx] > ja[idx], kt[np.minimum(ja[idx] + 1, K - 1)], tb[idx]) if part == 0 else tb[idx]
        u0 = (t_lo - ta[idx]) / dt_s
        u1 = (t_hi - ta[idx]) / dt_s
        mo = step_moments(phi_a[idx], phi_b[idx], u0, u1)
        inside = (jj >= 0) & (jj < K - 1)
        jc = np.clip(jj, 0, K - 2)
        span = kt[jc + 1] - kt[jc]
        w0 = np.where(inside, (ta[idx] - kt[jc]) / span, 0.0)  # w at u = 0 (extrapolated line)
        dw = np.where(inside, dt_s / span, 0.0)
        # E[(1-w) g] and E[w g] for g in {1, c, s}; w = w0 + dw u
        for col, (g, ug) in enumerate((("1", "u"), ("c", "uc"), ("s", "us"))):
            coef = kp if col == 0 else km
            e_w = w0 * mo[g] + dw * mo[ug]
            e_1mw = mo[g] - e_w
            # keyframe of the interval's left end: jj (or clamp), right end: jj + 1
            left = np.where(jj < 0, 0, np.where(jj >= K - 1, K - 1, jj))
            right = np.where(inside, jj + 1, left)
            e_left = np.where(inside, e_1mw, mo[g])
            e_right = np.where(inside, e_w, 0.0)
            for kk, e in ((left, e_left), (right, e_right)):
                slot = kk - k_lo[idx]
                np.add.at(W, (idx, np.clip(slot, 0, 2), col), coef * e)
    return k_lo, W
