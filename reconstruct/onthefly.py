"""Training windows generated on the fly from closed-form physics (no stored dataset).

An item is one window of N = 2K+1 spike frames (paper Eq. (3)) with its
centre-frame ground truth, made from

* a **scene sample** (:class:`SceneSample`): layer radiances T, R per
  observation, the pane coefficient maps (R_perp, R_par, phi_perp) and the
  window's polarizer angles.  It comes from a :data:`SceneProvider` callable,
  so ``reconstruct`` never imports ``generator``: the CLI wires generator
  content in (``polspike train --on-the-fly``); :class:`ImageLayerProvider`
  builds samples from any list of grey images with random pane geometry from
  :mod:`polspike.physics.fresnel` (shared physics);
* a **spike model** (:data:`SpikeModel` callable) turning the mean photocurrent
  of each aggregation window into spike counts.  The default,
  :func:`window_count_model`, is the closed form of a noise-free
  integrate-and-fire pixel over ``n_steps`` steps with a uniformly random
  residue at the window start plus a Gaussian term for shot / thermal noise:
  ``count = clip(floor(u + n g + sigma eps), 0, n)``, g = exposure L_M
  thresholds per step.  The full simulator (spike_sim) can be passed instead.

Mixed light per observation (paper Eq. (1)-(2)), averaged over the polarizer
sweep of one window (sinc factor, exact for constant rotation):
``L_M,k = 1/2 (zeta_k R_k + (1 - zeta_k) T_k)``; the frame in radiance units
is ``I_k = count_k / (n_steps exposure)``.

Every item is a pure function of (seed, index): ``np.random.default_rng([seed, index])``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from scipy import ndimage

from polspike.config import opt
from polspike.errors import ConfigError, ShapeError
from polspike.physics.fresnel import pane_coefficients

__all__ = ["WindowConfig", "SceneSample", "SceneProvider", "SpikeModel", "window_count_model", "ImageLayerProvider", "make_item", "OnTheFlyWindows"]


@dataclasses.dataclass(frozen=True)
class WindowConfig:
    """Window geometry and the closed-form spike model."""

    n_obs: int = opt(7, "observations per window N = 2K+1", lo=3, hi=31)
    crop: int = opt(16, "square crop side, pixels (multiple of 4)", lo=4, hi=4096)
    dt_s: float = opt(0.65e-3, "aggregation window, s (paper: 0.65 ms)", lo=1e-5, hi=0.1)
    step_s: float = opt(50e-6, "spike camera step, s (20 kHz)", lo=1e-7, hi=1e-2)
    rate_hz: float = opt(30.0, "polarizer rotation rate, rev/s", lo=0.1, hi=1000.0)
    stride_deg: float = opt(31.5, "polarizer angle between consecutive observations, degrees", lo=0.1, hi=180.0)
    exposure_range: tuple[float, float] = opt((0.6, 1.4), "photocurrent per unit radiance behind the polarizer, thresholds per step, drawn per item", lo=1e-3, hi=100.0)
    noise_std: float = opt(0.15, "Gaussian count noise per window (shot + thermal), spikes, times sqrt(n_steps g)", lo=0.0, hi=10.0)

    @property
    def n_steps(self) -> int:
        """Steps per aggregation window (0.65 ms / 50 us = 13)."""
        return max(1, int(round(self.dt_s / self.step_s)))

    @property
    def span_rad(self) -> float:
        """Polarizer rotation during one aggregation window, rad."""
        return 2 * math.pi * self.rate_hz * self.n_steps * self.step_s


@dataclasses.dataclass
class SceneSample:
    """One window's physics; maps (H, W) float, per-observation layers (N, H, W) or (H, W).

    Attributes:
        T, R: layer radiances (linear, 1.0 = brightest); (N, H, W) when the
            scene moves inside the window, else (H, W).  The centre index is the GT.
        R_perp, R_par: pane reflectances (totals), phi_perp: s-direction (rad).
        phi: (N,) polarizer angle at each window centre, rad.
    """

    T: np.ndarray
    R: np.ndarray
    R_perp: np.ndarray
    R_par: np.ndarray
    phi_perp: np.ndarray
    phi: np.ndarray


SceneProvider = Callable[[np.random.Generator, WindowConfig], SceneSample]
"""(rng, window config) -> :class:`SceneSample` for a crop x crop window."""

SpikeModel = Callable[[np.ndarray, int, np.random.Generator], np.ndarray]
"""(g (N, H, W) thresholds per step, n_steps, rng) -> spike counts (N, H, W)."""


def window_count_model(noise_std: float = 0.15) -> SpikeModel:
    """Closed-form integrate-and-fire count over a window (module docstring)."""

    def model(g: np.ndarray, n_steps: int, rng: np.random.Generator) -> np.ndarray:
        x = n_steps * np.clip(g, 0.0, 1.0)
        u = rng.random(g.shape)  # residue at the window start, U[0, 1) of a threshold
        noise = noise_std * np.sqrt(np.maximum(x, 0.0)) * rng.standard_normal(g.shape) if noise_std > 0 else 0.0
        return np.clip(np.floor(u + x + noise), 0, n_steps)

    return model


def make_item(sample: SceneSample, cfg: WindowConfig, rng: np.random.Generator, spike_model: SpikeModel | None = None) -> dict[str, torch.Tensor]:
    """Turn a scene sample into a training item (float32 tensors).

    Returns:
        dict with ``I`` (N, H, W) radiance units, ``phi`` (N,), ``T``, ``R`` (H, W)
        centre-frame GT, ``zeta`` (N, H, W) window-averaged paper Eq. (2),
        ``R_perp``, ``R_par``, ``phi_perp`` (H, W), ``exposure`` ().
    """
    N = cfg.n_obs
    phi = np.asarray(sample.phi, dtype=np.float64)
    if phi.shape != (N,):
        raise ShapeError(f"scene sample phi must be ({N},); got {phi.shape}", actual_shape=phi.shape, expected_shape=(N,))
    T = np.broadcast_to(sample.T, (N,) + np.shape(sample.R_perp)).astype(np.float64)
    R = np.broadcast_to(sample.R, (N,) + np.shape(sample.R_perp)).astype(np.float64)
    sinc = math.sin(cfg.span_rad) / cfg.span_rad if cfg.span_rad > 0 else 1.0
    mean = 0.5 * (sample.R_perp + sample.R_par)
    amp = 0.5 * (sample.R_perp - sample.R_par)
    zeta = mean[None] + amp[None] * sinc * np.cos(2 * (phi[:, None, None] - sample.phi_perp[None]))  # paper Eq. (2), window average
    L_M = 0.5 * (zeta * R + (1 - zeta) * T)  # paper Eq. (1)
    lo, hi = cfg.exposure_range
    exposure = float(rng.uniform(lo, hi))
    model = spike_model or window_count_model(cfg.noise_std)
    counts = model(exposure * L_M, cfg.n_steps, rng)  # paper Eq. (3): count over dt
    I = counts / (cfg.n_steps * exposure)
    c = N // 2
    f = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)  # noqa: E731
    return {"I": f(I), "phi": f(phi), "T": f(T[c]), "R": f(R[c]), "zeta": f(zeta), "R_perp": f(sample.R_perp), "R_par": f(sample.R_par), "phi_perp": f(sample.phi_perp), "exposure": torch.tensor(exposure, dtype=torch.float32)}


class ImageLayerProvider:
    """Scene samples from a list of grey images with random pane geometry and motion.

    Per item: two different images (T and R layers), random crops, flips and
    scales, brightness in ``t_gain`` / ``r_gain``, an optional defocus blur of
    the R layer; the pane is a linear field of incidence angle theta (deg range
    ``theta_deg``) and s-direction phi_perp across the crop, index n in
    ``n_range``, model single or thin_slab (Fresnel from :mod:`polspike.physics.fresnel`);
    the layers drift by up to ``drift_px`` pixels per observation.
    """

    def __init__(
        self,
        images: Sequence[np.ndarray],
        *,
        t_gain: tuple[float, float] = (0.4, 1.0),
        r_gain: tuple[float, float] = (0.3, 1.0),
        theta_deg: tuple[float, float] = (15.0, 80.0),
        n_range: tuple[float, float] = (1.45, 1.65),
        blur_px: tuple[float, float] = (0.0, 2.0),
        drift_px: float = 0.3,
        zoom: tuple[float, float] = (0.5, 1.5),
    ):
        imgs = [np.asarray(im, dtype=np.float64) for im in images]
        if len(imgs) < 2 or any(im.ndim != 2 for im in imgs):
            raise ConfigError(f"ImageLayerProvider needs at least two (H, W) grey images; got {len(imgs)}")
        self.images = imgs
        self.t_gain, self.r_gain, self.theta_deg, self.n_range = t_gain, r_gain, theta_deg, n_range
        self.blur_px, self.drift_px, self.zoom = blur_px, drift_px, zoom

    def _layer(self, img: np.ndarray, rng: np.random.Generator, S: int, N: int, gain: float, blur: float) -> np.ndarray:
        z = rng.uniform(*self.zoom)
        span = S * z
        H, W = img.shape
        y0 = rng.uniform(0, max(H - span - 2, 0))
        x0 = rng.uniform(0, max(W - span - 2, 0))
        v = rng.normal(0, self.drift_px, 2)
        yy, xx = np.mgrid[0:S, 0:S].astype(np.float64) * z
        if rng.random() < 0.5:
            xx = xx[:, ::-1]
        out = np.empty((N, S, S))
        for k in range(N):
            d = (k - N // 2) * v
            out[k] = ndimage.map_coordinates(img, [yy + y0 + d[0], xx + x0 + d[1]], order=1, mode="reflect")
        if blur > 0:
            out = ndimage.gaussian_filter(out, sigma=(0, blur, blur))
        return np.clip(out, 0.0, None) * gain

    def __call__(self, rng: np.random.Generator, cfg: WindowConfig) -> SceneSample:
        S, N = cfg.crop, cfg.n_obs
        i, j = rng.choice(len(self.images), size=2, replace=False)
        T = self._layer(self.images[i], rng, S, N, rng.uniform(*self.t_gain), 0.0)
        R = self._layer(self.images[j], rng, S, N, rng.uniform(*self.r_gain), rng.uniform(*self.blur_px))
        yy, xx = (np.mgrid[0:S, 0:S] - (S - 1) / 2.0) / S
        th0 = rng.uniform(*self.theta_deg)
        gth = rng.normal(0, 8.0, 2)
        theta = np.radians(np.clip(th0 + gth[0] * yy + gth[1] * xx, 1.0, 88.0))
        pp0 = rng.uniform(0, math.pi)
        gpp = rng.normal(0, 0.3, 2)
        phi_perp = pp0 + gpp[0] * yy + gpp[1] * xx
        model = "single" if rng.random() < 0.5 else "thin_slab"
        co = pane_coefficients(theta, rng.uniform(*self.n_range), model)
        phi_c = rng.uniform(0, 2 * math.pi)
        phi = phi_c + math.radians(cfg.stride_deg) * (np.arange(N) - N // 2)
        return SceneSample(T=T, R=R, R_perp=np.asarray(co["R_perp"]), R_par=np.asarray(co["R_par"]), phi_perp=phi_perp, phi=phi)


class OnTheFlyWindows(torch.utils.data.Dataset):
    """Map-style dataset of ``length`` windows, item i a pure function of (seed, i)."""

    def __init__(self, provider: SceneProvider, cfg: WindowConfig = WindowConfig(), *, length: int = 100000, seed: int = 0, spike_model: SpikeModel | None = None):
        if cfg.crop % 4:
            raise ConfigError(f"crop = {cfg.crop} must be a multiple of 4 (the refinement downsamples twice)")
        self.provider, self.cfg, self.length, self.seed, self.spike_model = provider, cfg, int(length), int(seed), spike_model

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < self.length:
            raise IndexError(index)
        rng = np.random.default_rng([self.seed, int(index)])
        return make_item(self.provider(rng, self.cfg), self.cfg, rng, self.spike_model)
