"""Spike streams of glass-pane scenes under camera and layer motion, made in-process (closed form, per 20 kHz step).

What the motion bench (:mod:`reconstruct.evaluate.motion_bench`) reads.  Per scene:

* layers: two scikit-image pictures (:data:`reconstruct.stream.synthetic.PICTURES`; the transmitted one sharp, the
  reflected one slightly defocused) on a canvas twice the view, so the view can move without running out of picture;
* pane: a pinhole camera (60 deg horizontal field of view) behind a tilted thin glass slab of index 1.5 (both
  faces, Fresnel R_perp, R_par, the incidence plane's direction phi_perp per pixel, :mod:`polphysics`); the pane
  is fixed to the camera, so its maps do not move;
* motion per step t (seconds from the stream's middle): the view samples each layer's canvas at
  ``c + s(t) Rot(theta(t)) (p - c) + d(t)``; ``pan`` d = (v t, 0), ``shake`` d a random walk of velocity (rms
  ``speed`` views/s, seeded), ``rotate`` theta = omega t about the optical axis, ``zoom`` s = exp(kappa t), ``layers``
  the transmitted layer pans while the reflected one holds still (a camera that turns in front of a still mirror
  image does the reverse; either way one flow does not align both);
* light: paper Eq. (1) behind a polarizer at 30 rev/s, zeta per step from paper Eq. (2) (no window averaging: the
  simulator integrates every step); a plain integrate-and-fire pixel (threshold 1, subtractive reset, random initial
  charge, at most one spike per step) at the exposure that gives ``rate`` spikes per pixel per step on average;
* reflection strength: the reflected layer's gain sets the reflected share zbar R / (zbar R + (1 - zbar) T) of the
  mean light (weak 0.1, strong 0.35, dominant 0.6), then both layers are scaled so the brightest value is 1.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
import torch.nn.functional as F

from polinfra.config import opt
from polinfra.errors import ConfigError
from reconstruct.physics.zeta import PaneMaps

__all__ = ["MOTIONS", "REFLECTION_SHARES", "MotionSceneConfig", "MotionStream", "make_motion_stream"]

MOTIONS = ("pan", "shake", "rotate", "zoom", "layers")
"""Kinds of motion (module docstring)."""

REFLECTION_SHARES = {"weak": 0.1, "strong": 0.35, "dominant": 0.6}
"""Reflected share of the mean light for each reflection strength."""


@dataclasses.dataclass(frozen=True)
class MotionSceneConfig:
    """One stream of the motion bench."""

    width: int = opt(96, "image width W in pixels", lo=16, hi=4000)
    height: int = opt(64, "image height H in pixels", lo=16, hi=4000)
    steps: int = opt(560, "steps of the stream at rate_hz", lo=64, hi=10**7)
    rate_hz: float = opt(20000.0, "spike camera steps per second", lo=1.0, hi=1e8)
    rev_per_s: float = opt(30.0, "polarizer revolutions per second", lo=0.01, hi=1e4)
    motion: str = opt("pan", "kind of motion", choices=MOTIONS)
    speed: float = opt(0.0, "pan / shake / layers: view widths per second; rotate: degrees per second; zoom: scale rate per second (kappa)", lo=-1e4, hi=1e4)
    reflection: str = opt("weak", "reflection strength", choices=tuple(REFLECTION_SHARES))
    rate: float = opt(0.3, "mean spikes per pixel per step", lo=1e-4, hi=1.0)
    tilt_deg: float = opt(50.0, "the pane's tilt from facing the camera, degrees", lo=0.0, hi=85.0)
    seed: int = opt(0, "seed of the pictures, the pane's azimuth, the shake and the initial charges", lo=0, hi=2**31 - 1)


@dataclasses.dataclass
class MotionStream:
    """A simulated stream: spikes (S, H, W) uint8, per-step angles phi (S,) rad, the layers per step on request."""

    spikes: np.ndarray
    phi: np.ndarray
    exposure: float
    maps: PaneMaps
    fov_deg: float
    layers_at: object  # callable(steps array) -> (T (n, H, W), R (n, H, W)) float32
    phi0: float


def _picture(name: str, H: int, W: int) -> np.ndarray:
    from reconstruct.stream.synthetic import _picture as pic

    return pic(name, H, W)


def _affine_grids(cfg: MotionSceneConfig, t: np.ndarray, vel: np.ndarray | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Sampling grids (n, H, W, 2) in the canvas' normalised coordinates for the transmitted and reflected layers."""
    H, W = cfg.height, cfg.width
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    px, py = xs - (W - 1) / 2, ys - (H - 1) / 2  # view pixels about the optical axis
    n = t.size
    dT = np.zeros((n, 2))
    ang = np.zeros(n)
    sc = np.ones(n)
    v = cfg.speed * W  # px/s for the translating kinds
    if cfg.motion in ("pan", "layers"):
        dT[:, 0] = v * t
    elif cfg.motion == "shake":
        dT = vel
    elif cfg.motion == "rotate":
        ang = np.deg2rad(cfg.speed) * t
    elif cfg.motion == "zoom":
        sc = np.exp(cfg.speed * t)
    dR = np.zeros_like(dT) if cfg.motion == "layers" else dT

    def grid(d):
        c, s = np.cos(ang)[:, None, None], np.sin(ang)[:, None, None]
        qx = sc[:, None, None] * (c * px - s * py) + d[:, 0, None, None]
        qy = sc[:, None, None] * (s * px + c * py) + d[:, 1, None, None]
        # canvas 2W x 2H centred on the view: normalised coordinates (align_corners=False)
        gx = (qx + W) / W - 1.0 + 1.0 / (2 * W)
        gy = (qy + H) / H - 1.0 + 1.0 / (2 * H)
        return torch.from_numpy(np.stack([gx, gy], -1).astype(np.float32))

    return grid(dT), grid(dR)


def make_motion_stream(cfg: MotionSceneConfig) -> MotionStream:
    """Simulate the stream of ``cfg`` (module docstring); deterministic in ``cfg.seed``."""
    from scipy.ndimage import gaussian_filter

    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import PinholeCamera, Plane, incidence_geometry
    from reconstruct.stream.synthetic import PICTURES

    if cfg.motion not in MOTIONS:
        raise ConfigError(f"motion {cfg.motion!r}: choose one of {', '.join(MOTIONS)}")
    rng = np.random.default_rng([cfg.seed, 34])
    H, W = cfg.height, cfg.width
    names = rng.choice(len(PICTURES), 2, replace=False)
    T0 = 0.05 + 0.95 * _picture(PICTURES[names[0]], 2 * H, 2 * W)
    R0 = 0.05 + 0.95 * gaussian_filter(_picture(PICTURES[names[1]], 2 * H, 2 * W), 1.0)
    fov = 60.0
    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=fov, width=W, height=H)
    tilt, az = np.deg2rad(cfg.tilt_deg), rng.uniform(0, 2 * np.pi)
    normal = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
    geo = incidence_geometry(cam, Plane(np.array([0.0, 0.0, 1.0]), normal))
    co = pane_coefficients(geo["theta"], 1.5, model="thin_slab")
    maps = PaneMaps(R_perp=co["R_perp"], R_par=co["R_par"], phi_perp=geo["phi_perp"])
    zbar = 0.5 * (maps.R_perp + maps.R_par)
    rho = REFLECTION_SHARES[cfg.reflection]
    g = rho / (1 - rho) * float(((1 - zbar) * T0[H // 2 : H // 2 + H, W // 2 : W // 2 + W]).mean()) / float((zbar * R0[H // 2 : H // 2 + H, W // 2 : W // 2 + W]).mean())
    R0 = g * R0
    top = max(float(T0.max()), float(R0.max()))
    T0, R0 = T0 / top, R0 / top
    S = cfg.steps
    t = (np.arange(S) - S // 2) / cfg.rate_hz
    vel = None
    if cfg.motion == "shake":  # a random walk of the velocity, rms speed views/s, integrated to the offset
        a = np.cumsum(rng.normal(0.0, 1.0, (S, 2)), 0)
        a -= a.mean(0)
        a *= cfg.speed * W / max(float(np.sqrt((a * a).sum(1).mean())), 1e-12)
        vel = np.cumsum(a, 0) / cfg.rate_hz
        vel -= vel[S // 2]
    gT, gR = _affine_grids(cfg, t, vel)
    tT = torch.from_numpy(T0.astype(np.float32))[None, None]
    tR = torch.from_numpy(R0.astype(np.float32))[None, None]

    def layers_at(idx):
        idx = np.atleast_1d(np.asarray(idx, np.int64))
        T = F.grid_sample(tT.expand(idx.size, -1, -1, -1), gT[idx], mode="bilinear", padding_mode="border", align_corners=False)[:, 0]
        R = F.grid_sample(tR.expand(idx.size, -1, -1, -1), gR[idx], mode="bilinear", padding_mode="border", align_corners=False)[:, 0]
        return T.numpy(), R.numpy()

    phi0 = float(rng.uniform(0, np.pi))
    phi = phi0 + 2 * math.pi * cfg.rev_per_s * (np.arange(S) + 0.5) / cfg.rate_hz
    Rp, Rs, pp = (torch.from_numpy(np.asarray(m, np.float32)) for m in (maps.R_perp, maps.R_par, maps.phi_perp))
    # exposure from the mean light of the middle frame at the mean zeta
    Tm, Rm = layers_at([S // 2])
    mean_I = float((0.5 * (zbar * Rm[0] + (1 - zbar) * Tm[0])).mean())
    exposure = cfg.rate / max(mean_I, 1e-9)
    acc = rng.uniform(0.0, 1.0, (H, W)).astype(np.float32)
    spikes = np.zeros((S, H, W), np.uint8)
    for a0 in range(0, S, 128):
        idx = np.arange(a0, min(S, a0 + 128))
        T, R = (torch.from_numpy(x) for x in layers_at(idx))
        d = torch.from_numpy(phi[idx].astype(np.float32))[:, None, None] - pp
        z = 0.5 * (Rp + Rs) + 0.5 * (Rp - Rs) * torch.cos(2 * d)  # paper Eq. (2) at the step's angle
        charge = (exposure * 0.5 * (z * R + (1 - z) * T)).numpy()  # paper Eq. (1), thresholds per step
        for j in range(idx.size):
            acc += charge[j]
            s = acc >= 1.0
            acc[s] -= 1.0
            np.minimum(acc, 1.0, out=acc)  # at most one spike per step; the excess charge is lost
            spikes[idx[j]] = s
    return MotionStream(spikes=spikes, phi=phi, exposure=exposure, maps=maps, fov_deg=fov, layers_at=layers_at, phi0=phi0)
