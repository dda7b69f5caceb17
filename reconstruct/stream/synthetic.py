"""A closed-form synthetic test set, made in-process (no generator, no spike simulator).

Used when no built dataset is available, for tests and for the solver-ordering
study.  Per group:

* layers: two grayscale pictures bundled with scikit-image (T and a defocused
  R), radiance in [0.03, 1], each translating slowly (sub-pixel per frame, so
  RIR has work to do);
* pane: a pinhole camera looking through a tilted plane; per-pixel incidence
  theta(p) and s-direction phi_perp(p) from :mod:`polphysics.geometry`,
  Fresnel R_perp, R_par of a single interface (:mod:`polphysics.fresnel`);
* polarizer: 30 rev/s; output frame i is centred where it has turned by
  i * stride; zeta(i) is paper Eq. (2) averaged over the aggregation window;
* observation: I(i) = 1/2 (zeta R + (1 - zeta) T) (paper Eq. (1)), then spike
  counts over the window ~ Poisson(exposure * I * window_steps), I(i) =
  counts / (exposure * window_steps) (paper Eq. (3) in radiance units).
  Poisson counts are much noisier than a real integrate-and-fire pixel (whose
  ISI CV is 0.03-0.09): a pessimistic, spike-like noise model.  The
  ``integrate_fire`` option instead counts threshold crossings of a noiseless
  accumulator with a random phase (pure quantization noise, +-1 spike).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polinfra.config import opt
from reconstruct.physics.zeta import PaneMaps
from reconstruct.stream.groups import EvalGroup, spike_mean_steps, wide_window_steps

__all__ = ["SyntheticConfig", "make_group", "make_groups", "PICTURES"]

PICTURES = ("camera", "astronaut", "coffee", "chelsea", "rocket", "brick", "coins", "horse", "clock", "cat", "moon", "gravel")
"""scikit-image pictures used as layers (all shipped with the package, no download)."""


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """Synthetic closed-form test set parameters."""

    width: int = opt(200, "image width W in pixels", lo=8, hi=4000)
    height: int = opt(125, "image height H in pixels", lo=8, hi=4000)
    n_groups: int = opt(4, "number of groups (scenes)", lo=1, hi=1000)
    n_frames: int = opt(20, "output frames per group (observation frames, before the 2K window margin)", lo=1, hi=100000)
    rate_hz: float = opt(20000.0, "spike camera readout rate", lo=1.0, hi=1e8)
    polarizer_rate_hz: float = opt(30.0, "polarizer revolutions per second", lo=0.01, hi=1e4)
    window_steps: int = opt(13, "aggregation window dt in steps (13 = 0.65 ms)", lo=1, hi=100000)
    stride_deg: float = opt(31.5, "polarizer rotation between output frames, degrees", lo=0.01, hi=360.0)
    exposure: float = opt(1.0, "spikes per step per unit intensity behind the polarizer", lo=1e-6, hi=1e6)
    motion_px_per_frame: float = opt(0.25, "layer translation speed, pixels per output frame", lo=0.0, hi=100.0)
    n_glass: float = opt(1.5, "refractive index of the pane", lo=1.0, hi=4.0)
    noise: str = opt("poisson", "spike-count noise: poisson (pessimistic), integrate_fire (quantization of a regular pixel with random phase), none", choices=("poisson", "integrate_fire", "none"))
    seed: int = opt(0, "random seed", lo=0, hi=2**31 - 1)


def _picture(name: str, H: int, W: int) -> np.ndarray:
    import skimage.data
    from skimage.color import rgb2gray, rgba2rgb
    from skimage.transform import resize

    im = getattr(skimage.data, name)()
    if im.ndim == 3 and im.shape[-1] == 4:
        im = rgba2rgb(im)
    if im.ndim == 3:
        im = rgb2gray(im)
    im = im.astype(np.float64)
    im = (im - im.min()) / max(im.max() - im.min(), 1e-12)
    # crop to the aspect ratio, then resize with margin for motion
    h, w = im.shape
    ar = W / H
    if w / h > ar:
        cw = int(h * ar)
        im = im[:, (w - cw) // 2 : (w - cw) // 2 + cw]
    else:
        ch = int(w / ar)
        im = im[(h - ch) // 2 : (h - ch) // 2 + ch]
    return resize(im, (H, W), anti_aliasing=True)


def _shifted(img: np.ndarray, dy: float, dx: float) -> np.ndarray:
    from scipy.ndimage import shift

    return shift(img, (dy, dx), order=3, mode="reflect")


def make_group(cfg: SyntheticConfig, index: int) -> EvalGroup:
    """Group ``index`` of the synthetic set (deterministic in cfg.seed and index)."""
    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import PinholeCamera, Plane, incidence_geometry

    rng = np.random.default_rng([cfg.seed, index])
    H, W = cfg.height, cfg.width
    names = rng.choice(len(PICTURES), 2, replace=False)
    T0 = 0.03 + 0.97 * _picture(PICTURES[names[0]], H, W)
    from scipy.ndimage import gaussian_filter

    R0 = 0.03 + 0.97 * gaussian_filter(_picture(PICTURES[names[1]], H, W), rng.uniform(0.5, 2.0))
    # pane: tilted about a random in-plane axis so the incidence plane (phi_perp) varies across the image
    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=60.0, width=W, height=H)
    tilt = np.deg2rad(rng.uniform(35.0, 65.0))
    az = rng.uniform(0, 2 * np.pi)
    normal = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
    geo = incidence_geometry(cam, Plane(np.array([0.0, 0.0, 1.0]), normal))
    co = pane_coefficients(geo["theta"], cfg.n_glass, model="single")
    maps = PaneMaps(R_perp=co["R_perp"], R_par=co["R_par"], phi_perp=geo["phi_perp"])
    # polarizer and frames
    stride = np.deg2rad(cfg.stride_deg)
    span = 2 * np.pi * cfg.polarizer_rate_hz * cfg.window_steps / cfg.rate_hz
    phi0 = rng.uniform(0, np.pi)
    M = cfg.n_frames
    phi = phi0 + stride * np.arange(M)
    vT = rng.normal(0, 1, 2)
    vT *= cfg.motion_px_per_frame / max(np.linalg.norm(vT), 1e-12)
    vR = rng.normal(0, 1, 2)
    vR *= cfg.motion_px_per_frame / max(np.linalg.norm(vR), 1e-12)
    sinc = np.sin(span) / span if span > 0 else 1.0
    Ts, Rs, Is, Zs, Iws = [], [], [], [], []
    steps = cfg.window_steps * cfg.exposure
    steps_w = wide_window_steps(cfg.rate_hz, cfg.polarizer_rate_hz, cfg.stride_deg) * cfg.exposure
    for i in range(M):
        Ti = _shifted(T0, *(vT * (i - M / 2)))
        Ri = _shifted(R0, *(vR * (i - M / 2)))
        d = phi[i] - maps.phi_perp
        z = 0.5 * (maps.R_perp + maps.R_par) + 0.5 * (maps.R_perp - maps.R_par) * sinc * np.cos(2 * d)  # paper Eq. (2), window mean
        Ii = 0.5 * (z * Ri + (1 - z) * Ti)  # paper Eq. (1)
        Iw = Ii  # the wide window (the whole stride): the same light with the noise of its steps (zeta's averaging kept)
        if cfg.noise == "poisson":
            Ii = rng.poisson(np.clip(Ii, 0, None) * steps) / steps  # paper Eq. (3): counts / dt, radiance units
            Iw = rng.poisson(np.clip(Iw, 0, None) * steps_w) / steps_w
        elif cfg.noise == "integrate_fire":
            acc0 = rng.uniform(0.0, 1.0, Ii.shape)  # accumulator phase at the window start
            Ii = (np.floor(acc0 + np.clip(Ii, 0, None) * steps) - 0.0) / steps
            Iw = np.floor(rng.uniform(0.0, 1.0, Iw.shape) + np.clip(Iw, 0, None) * steps_w) / steps_w
        Ts.append(Ti)
        Rs.append(Ri)
        Is.append(Ii)
        Iws.append(Iw)
        Zs.append(z)
    # the long spike mean (17.5 ms, ~6 strides: about half a polarizer turn): the light averaged over the neighbouring
    # frames with the turn's mean zeta (the modulation averages out, motion blurs), noise of its 350 steps
    zbar = 0.5 * (maps.R_perp + maps.R_par)
    L = spike_mean_steps(cfg.rate_hz) * cfg.exposure
    half = 3
    Im = []
    for i in range(M):
        js = range(max(0, i - half), min(M, i + half + 1))
        m_ = np.mean([0.5 * (zbar * Rs[j] + (1 - zbar) * Ts[j]) for j in js], 0)
        if cfg.noise in ("poisson", "integrate_fire"):
            m_ = rng.poisson(np.clip(m_, 0, None) * L) / L
        Im.append(m_)
    # its first harmonic: fitted to the neighbouring noisy frames at their angles (the windows stand in for the span)
    from reconstruct.physics.span import harmonic_of

    Ih = []
    for i in range(M):
        js = list(range(max(0, i - half), min(M, i + half + 1)))
        _, hb, hc = harmonic_of(np.stack([Is[j] for j in js]), phi[js])
        Ih.append(np.stack([hb, hc]))
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return EvalGroup(
        name=f"synthetic-{cfg.seed}-{index:03d}",
        I=f32(Is),
        phi_nominal=phi,
        phi_true=phi.copy(),
        span_rad=float(span),
        T=f32(Ts),
        R=f32(Rs),
        maps=maps,
        theta=geo["theta"],
        has_gt=np.ones(M, bool),
        gt_zeta=f32(Zs),
        I_mean=f32(Im),
        I_harm=f32(Ih),
        I_wide=f32(Iws),
        fov_deg=60.0,
        exposure=float(cfg.exposure),
        span_steps=spike_mean_steps(cfg.rate_hz),
    )


def make_groups(cfg: SyntheticConfig):
    """Iterate over the cfg.n_groups synthetic groups."""
    for g in range(cfg.n_groups):
        yield make_group(cfg, g)
