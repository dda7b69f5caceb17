"""Closed-form evaluation groups behind a pane of known geometry (for the self-calibration tests).

Independent of reconstruct.pane.selfcal's estimator: the truth is built from polphysics (camera, plane,
Fresnel) and paper Eq. (1)-(2) directly; spike counts are Poisson (pessimistic) at ``exposure``.
"""

from __future__ import annotations

import math

import numpy as np

from polphysics.fresnel import pane_coefficients
from polphysics.geometry import PinholeCamera, Plane, incidence_geometry
from reconstruct.physics.zeta import PaneMaps
from reconstruct.stream.groups import EvalGroup

from ._synth import periodic_texture


def true_normal(tilt_deg: float, azimuth_deg: float, cam: PinholeCamera) -> np.ndarray:
    """Normal at tilt from the optical axis, its image projection at azimuth (deg, ccw from image +x to image up)."""
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    return math.sin(t) * math.cos(a) * cam.right + math.sin(t) * math.sin(a) * cam.up + math.cos(t) * cam.forward


def make_pane_group(
    tilt_deg: float,
    azimuth_deg: float,
    *,
    fov_deg: float = 60.0,
    H: int = 100,
    W: int = 160,
    M: int = 34,
    r_gain: float = 3.0,
    t_level: float = 0.5,
    exposure: float = 1.0,
    motion_px: float = 1.0,
    n_glass: float = 1.5,
    model: str = "single",
    noise: bool = True,
    seed: int = 0,
    record_fov: bool = True,
    contrast: float = 1.0,
) -> tuple[EvalGroup, np.ndarray]:
    """A group of M frames (stride 31.5 deg, 13-step windows at 20 kHz, 30 rev/s) and its true normal.

    T: textured, mean ``t_level``, sliding ``motion_px`` per frame; R: textured, mean ``r_gain`` * 0.5,
    sliding at half that speed the other way; ``contrast`` scales both textures (0: flat layers).  The camera looks
    along +z with up +y.
    """
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=fov_deg, width=W, height=H)
    N = true_normal(tilt_deg, azimuth_deg, cam)
    geo = incidence_geometry(cam, Plane(np.array([0.0, 0.0, 1.0]), N))
    co = pane_coefficients(geo["theta"], n_glass, model=model)
    maps = PaneMaps(R_perp=co["R_perp"], R_par=co["R_par"], phi_perp=geo["phi_perp"])
    stride = math.radians(31.5)
    span = 2 * math.pi * 30.0 * 13 / 20000.0
    phi = rng.uniform(0, math.pi) + stride * np.arange(M)
    sinc = math.sin(span) / span
    tex_T = np.random.default_rng([seed, 1])
    tex_R = np.random.default_rng([seed, 2])
    sT = tex_T.integers(0, 2**31)
    sR = tex_R.integers(0, 2**31)
    Is, Ts, Rs, Zs = [], [], [], []
    for i in range(M):
        T = np.clip(t_level * (1 + 0.4 * contrast * periodic_texture(np.random.default_rng(sT), H, W, shift=(0.0, motion_px * i))), 0.02, None)
        R = np.clip(0.5 * r_gain * (1 + 0.5 * contrast * periodic_texture(np.random.default_rng(sR), H, W, shift=(0.5 * motion_px * i, 0.0))), 0.02, None)
        z = 0.5 * (maps.R_perp + maps.R_par) + 0.5 * (maps.R_perp - maps.R_par) * sinc * np.cos(2 * (phi[i] - maps.phi_perp))  # paper Eq. (2), window mean
        I = 0.5 * (z * R + (1 - z) * T)  # paper Eq. (1)
        if noise:
            steps = 13 * exposure
            I = rng.poisson(I * steps) / steps  # paper Eq. (3)
        Is.append(I)
        Ts.append(T)
        Rs.append(R)
        Zs.append(z)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    g = EvalGroup(
        name=f"pane-t{tilt_deg:g}-a{azimuth_deg:g}-s{seed}",
        I=f32(Is),
        phi_nominal=phi,
        phi_true=phi.copy(),
        span_rad=span,
        T=f32(Ts),
        R=f32(Rs),
        maps=maps,
        theta=geo["theta"],
        has_gt=np.ones(M, bool),
        gt_zeta=f32(Zs),
        fov_deg=fov_deg if record_fov else None,
    )
    return g, N
