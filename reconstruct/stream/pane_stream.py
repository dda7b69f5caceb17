"""A step-level spike stream behind a glass pane, made chunk by chunk in constant memory (closed form).

Used by ``polspike bench realtime`` and the real-time tests: a 400 x 250, 20 kHz stream of any length
without the renderer or the spike simulator.  Per step:

* pane: a pinhole camera looking through a tilted plane; per-pixel incidence theta(p) and s-direction
  phi_perp(p) from :mod:`polphysics.geometry`, Fresnel R_perp, R_par of one interface
  (:mod:`polphysics.fresnel`); zeta(phi) = R_perp cos^2(phi - phi_perp) + R_par sin^2(phi - phi_perp)
  (paper Eq. (2));
* layers: T and R are sums of cosines with whole cycles per image (exactly shiftable); T translates
  at ``motion_px_s`` (updated every ``motion_block`` steps, a global motion), R stays;
* pixels: integrate and fire with a random initial phase: the accumulator gains
  exposure * 1/2 (zeta R + (1 - zeta) T) per step (paper Eq. (1)) and fires at 1.

:func:`pane_stream_packed` yields packed upright frames (``DatWriter.write_packed``'s layout: LSB first,
row-major), so a 60 s stream never exists in memory; :func:`write_pane_dat` writes one as a .dat.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from polinfra.config import opt

__all__ = ["PaneStreamConfig", "pane_stream_maps", "pane_stream_packed", "write_pane_dat"]


@dataclasses.dataclass(frozen=True)
class PaneStreamConfig:
    """Geometry, layers and camera of the closed-form pane stream."""

    height: int = opt(250, "frame height H", lo=8, hi=4000)
    width: int = opt(400, "frame width W (H W divisible by 8)", lo=8, hi=4000)
    rate_hz: float = opt(20000.0, "camera steps per second", lo=1.0, hi=1e7)
    rev_per_s: float = opt(30.0, "polarizer revolutions per second", lo=0.01, hi=1e4)
    phi0_rad: float = opt(0.4, "polarizer angle at t = 0, radians", lo=-100.0, hi=100.0)
    tilt_deg: float = opt(58.0, "pane normal's tilt from the optical axis", lo=0.0, hi=89.0)
    azimuth_deg: float = opt(130.0, "pane normal's image azimuth", lo=-360.0, hi=360.0)
    fov_deg: float = opt(60.0, "horizontal field of view", lo=1.0, hi=170.0)
    n_glass: float = opt(1.5, "refractive index", lo=1.0, hi=4.0)
    exposure: float = opt(1.0, "thresholds per step per unit radiance", lo=1e-6, hi=1e6)
    t_level: float = opt(0.25, "mean transmitted radiance", lo=0.0, hi=10.0)
    r_level: float = opt(1.2, "mean reflected radiance", lo=0.0, hi=10.0)
    motion_px_s: tuple = opt((0.0, 0.0), "T layer's translation (dy, dx), pixels per second")
    motion_block: int = opt(13, "steps between updates of the moving layer", lo=1, hi=10**6)
    seed: int = opt(0, "random seed", lo=0, hi=2**31 - 1)


def _texture_spectrum(rng: np.random.Generator, H: int, W: int, nwaves: int = 40, fmax: float = 0.15):
    ky = rng.integers(-int(fmax * H), int(fmax * H) + 1, nwaves)
    kx = rng.integers(-int(fmax * W), int(fmax * W) + 1, nwaves)
    ph = rng.uniform(0, 2 * np.pi, nwaves)
    amp = rng.uniform(0.5, 1.0, nwaves)
    return ky, kx, ph, amp / np.sqrt(0.5 * np.sum(amp**2))


def _texture(spec, H: int, W: int, shift=(0.0, 0.0)) -> np.ndarray:
    """tex(y - dy, x - dx): a sum of whole-cycle cosines, separable per wave (cheap for any shift)."""
    ky, kx, ph, amp = spec
    y = np.arange(H, dtype=np.float64)
    x = np.arange(W, dtype=np.float64)
    out = np.zeros((H, W))
    for i in range(ky.size):
        ey = np.exp(1j * (2 * np.pi * ky[i] * (y - shift[0]) / H + ph[i]))
        ex = np.exp(1j * 2 * np.pi * kx[i] * (x - shift[1]) / W)
        out += amp[i] * np.real(ey[:, None] * ex[None, :])
    return out


def pane_stream_maps(cfg: PaneStreamConfig = PaneStreamConfig()) -> dict[str, np.ndarray]:
    """The pane's true maps (H, W): R_perp, R_par, phi_perp, theta."""
    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import PinholeCamera, Plane, incidence_geometry

    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=cfg.fov_deg, width=cfg.width, height=cfg.height)
    t, a = math.radians(cfg.tilt_deg), math.radians(cfg.azimuth_deg)
    normal = math.sin(t) * math.cos(a) * cam.right + math.sin(t) * math.sin(a) * cam.up + math.cos(t) * cam.forward
    geo = incidence_geometry(cam, Plane(np.array([0.0, 0.0, 1.0]), normal))
    co = pane_coefficients(geo["theta"], cfg.n_glass)
    return {"R_perp": co["R_perp"], "R_par": co["R_par"], "phi_perp": geo["phi_perp"], "theta": geo["theta"]}


def _layers(cfg: PaneStreamConfig, spec_T, t_s: float) -> np.ndarray:
    dy, dx = (float(v) * t_s for v in cfg.motion_px_s)
    return np.clip(cfg.t_level * (1 + 0.4 * _texture(spec_T, cfg.height, cfg.width, (dy, dx))), 0.02 * max(cfg.t_level, 1e-3), None)


def pane_stream_packed(cfg: PaneStreamConfig, steps: int, chunk_steps: int = 1000) -> Iterator[np.ndarray]:
    """Packed upright spike frames (t, H W / 8) uint8, LSB first, ``chunk_steps`` at a time, ``steps`` in all."""
    H, W = cfg.height, cfg.width
    rng = np.random.default_rng(cfg.seed)
    mp = pane_stream_maps(cfg)
    spec_T = _texture_spectrum(np.random.default_rng([cfg.seed, 1]), H, W)
    spec_R = _texture_spectrum(np.random.default_rng([cfg.seed, 2]), H, W)
    R = np.clip(cfg.r_level * (1 + 0.5 * _texture(spec_R, H, W)), 0.02 * max(cfg.r_level, 1e-3), None)
    # zeta = A + B cos 2(phi - phi_perp) = A + Bc cos 2phi + Bs sin 2phi
    A = 0.5 * (mp["R_perp"] + mp["R_par"])
    B = 0.5 * (mp["R_perp"] - mp["R_par"])
    Bc, Bs = B * np.cos(2 * mp["phi_perp"]), B * np.sin(2 * mp["phi_perp"])
    moving = any(float(v) != 0.0 for v in cfg.motion_px_s)
    T = _layers(cfg, spec_T, 0.0)
    acc = rng.uniform(0, 1, (H, W)).astype(np.float32)
    e = 0.5 * cfg.exposure

    def coeffs(T):
        d = (R - T) * e
        return ((T * e + A * d).astype(np.float32), (Bc * d).astype(np.float32), (Bs * d).astype(np.float32))

    p0, pc, ps = coeffs(T)
    s = 0
    while s < steps:
        m = min(chunk_steps, steps - s)
        bits = np.empty((m, H, W), np.bool_)
        for j in range(m):
            k = s + j
            if moving and k % cfg.motion_block == 0 and k > 0:
                p0, pc, ps = coeffs(_layers(cfg, spec_T, k / cfg.rate_hz))
            phi = cfg.phi0_rad + 2 * math.pi * cfg.rev_per_s * (k + 0.5) / cfg.rate_hz
            acc += p0
            acc += np.float32(math.cos(2 * phi)) * pc
            acc += np.float32(math.sin(2 * phi)) * ps
            np.greater_equal(acc, 1.0, out=bits[j])
            acc -= bits[j]
        yield np.packbits(bits.reshape(m, H * W), axis=1, bitorder="little")
        s += m


def write_pane_dat(path, cfg: PaneStreamConfig, seconds: float, chunk_steps: int = 1000) -> Path:
    """Write ``seconds`` of the pane stream as a raw .dat (atomically)."""
    from spike_sim.vidar_dat import DatWriter

    steps = int(round(seconds * cfg.rate_hz))
    with DatWriter(path) as w:
        for pk in pane_stream_packed(cfg, steps, chunk_steps):
            w.write_packed(pk, cfg.height, cfg.width)
    return Path(path)
