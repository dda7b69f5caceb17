"""Training windows generated on the fly: the item format and the map-style dataset.

An **item** is one window of N = 2K+1 spike frames around an output frame,
with its centre-frame ground truth.  Stored windows (``reconstruct.net.windows``)
and on-the-fly windows share this format, built by :func:`item_from_stream`
from a spike stream exactly as :func:`reconstruct.stream.groups.load_store_group`
reads a stored group:

``I``         (N, H, W) float32  paper Eq. (3) frames / exposure (radiance units, I = 1/2 mix of paper Eq. (1))
``phi``       (N,)      float32  window-mean *nominal* (calibrated) polarizer angle, rad
``T``, ``R``  (H, W)    float32  centre-frame GT layers (float16-rounded, as a group store keeps them)
``zeta``      (N, H, W) float32  paper Eq. (2) at the window-mean *true* angle, averaged over
                                 the polarizer sweep of one window (sinc factor, :func:`reconstruct.physics.zeta.zeta_eq2`)
``R_perp``, ``R_par``, ``phi_perp`` (H, W) float32  pane maps
``exposure``  ()        float32  thresholds per step per unit radiance of the stream
``I_mean``    (H, W)    float32  only with ``WindowConfig.mean_steps``: spikes per step / exposure over that many
                                 steps centred on the output frame (the long spike mean, a use_mean network's input)
``I_wide``    (N, H, W) float32  with ``WindowConfig.wide_steps``: the observations over the wide window (the input of a network with NetConfig.wide_input)
``I_harm``    (2, H, W) float32  with ``I_mean``: the first harmonic (cos 2 phi, sin 2 phi) of the same span's spikes
                                 at the nominal angles (:func:`reconstruct.stream.groups.span_harmonic`; a use_harm network's input)
``span_steps`` ()     float32  with ``I_mean``: the number of steps of its span (clipped to the stream)

On-the-fly items come from a :data:`WindowSource` callable ``(seed, index) ->
item``.  ``reconstruct`` never imports ``generator``: the CLI
(its pipeline module ``train_windows``) wires in a source that renders the
crop with the generator's analytic tier and simulates only the window's steps
with :func:`spike_sim.simulate` (integrate-and-fire, seeded per item), i.e. the
same code that builds stores, and then calls :func:`item_from_stream`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import torch

from polinfra.config import opt
from polinfra.errors import ConfigError, ShapeError
from reconstruct.physics.symmetry import angle_map, symmetry_harmonic, symmetry_image
from reconstruct.stream.groups import harmonic_design, span_harmonic, spike_mean_span, window_means

__all__ = ["WindowConfig", "ITEM_KEYS", "WindowSource", "window_centres", "item_from_stream", "OnTheFlyWindows", "flip_item"]

ITEM_KEYS = ("I", "phi", "T", "R", "zeta", "R_perp", "R_par", "phi_perp", "T_perp", "T_par", "exposure")
"""Keys of a window item (module docstring)."""


@dataclasses.dataclass(frozen=True)
class WindowConfig:
    """Window geometry (paper Sec. 3.5) and the per-item simulation knobs of on-the-fly windows."""

    n_obs: int = opt(7, "observations per window N = 2K+1 (odd)", lo=3, hi=31)
    crop: int = opt(32, "square crop side, pixels (multiple of 4)", lo=4, hi=4096)
    window_steps: int = opt(13, "paper Eq. (3) window in simulator steps (13 = 0.65 ms at 20 kHz; odd)", lo=1, hi=10001)
    stride_deg: float = opt(31.5, "polarizer rotation between consecutive observations, degrees", lo=0.1, hi=180.0)
    keyframe_hz: float = opt(2000.0, "on-the-fly: Stokes keyframes per second rendered inside the window (linear in between)", lo=1.0, hi=20000.0)
    exposure_range: tuple[float, float] = opt((0.8, 1.8), "on-the-fly: spike_sim exposure (thresholds per step per unit radiance), drawn per item", lo=1e-3, hi=100.0)
    sim_preset: str = opt("default", "on-the-fly: spike_sim noise preset (ideal | default | noisy; group = each manifest group's own preset)", choices=("ideal", "default", "noisy", "group"))
    exposure_source: str = opt("range", "on-the-fly: range = exposure drawn from exposure_range; group = the manifest group's own exposure (its light level) times a log-uniform factor in exposure_jitter", choices=("range", "group"))
    exposure_jitter: tuple[float, float] = opt((1.0, 1.0), "on-the-fly, exposure_source = group: range of the log-uniform factor on the group's exposure", lo=1e-3, hi=1000.0)
    bright_prob: float = opt(0.0, "on-the-fly, exposure_source = group: probability that an item's light level is redrawn log-uniformly in bright_rate (spikes per pixel per step of the mean T content, the sampler's light formula) instead of the group's own; a manifest whose groups are all dim still trains for bright light", lo=0.0, hi=1.0)
    bright_rate: tuple[float, float] = opt((0.03, 0.3), "on-the-fly: range of the redrawn light level of bright_prob, spikes per pixel per step (the sampler's bright light)", lo=1e-4, hi=10.0)
    mean_steps: int = opt(0, "steps of the long spike mean I_mean given to a use_mean network, centred on the output frame (350 = 17.5 ms at 20 kHz, about half a polarizer turn); 0 = none", lo=0, hi=100001)
    wide_steps: int = opt(0, "also give each item its N observations over the wide window of this many steps (odd; 57 = the whole 31.5 deg stride at 20 kHz and 30 rev/s, reconstruct.stream.groups.wide_window_steps): the input I_wide of a network with NetConfig.wide_input; 0 = none", lo=0, hi=10001)
    assumed_n: float = opt(0.0, "also give each item the window's zeta under an assumed glass of this index (the self-calibration's prior, 1.5) for each pane model it can assume, zeta_a_single and zeta_a_thin_slab (paper Eq. (2) from the maps' theta and phi_perp): training for the errors of --zeta self, whose index and model are assumed where the spikes do not identify them; 0 = off", lo=0.0, hi=4.0)
    flips: bool = opt(False, "on-the-fly: random mirror / transpose of each item (one of the 8 symmetries of the square crop; polarizer and phi_perp angles mirrored with the image, so the physics stays exact)")

    def __post_init__(self) -> None:
        if self.n_obs % 2 == 0:
            raise ConfigError(f"window.n_obs = {self.n_obs} must be odd (N = 2K + 1); use {self.n_obs + 1}")
        if self.window_steps % 2 == 0:
            raise ConfigError(f"window.window_steps = {self.window_steps} must be odd (centred windows); use {self.window_steps + 1}")
        if self.wide_steps and self.wide_steps % 2 == 0:
            raise ConfigError(f"window.wide_steps = {self.wide_steps} must be odd (centred windows); use {self.wide_steps - 1}")
        if self.exposure_jitter[0] > self.exposure_jitter[1]:
            raise ConfigError(f"window.exposure_jitter = {list(self.exposure_jitter)} must be [low, high] with low <= high")
        if self.bright_rate[0] > self.bright_rate[1]:
            raise ConfigError(f"window.bright_rate = {list(self.bright_rate)} must be [low, high] with low <= high")
        if self.bright_prob > 0 and self.exposure_source != "group":
            raise ConfigError("window.bright_prob redraws the group's light level: it needs window.exposure_source = 'group'")
        if (self.sim_preset == "group") != (self.exposure_source == "group"):
            raise ConfigError("window.sim_preset = 'group' and window.exposure_source = 'group' go together (both take the manifest group's sensor)")
        if self.crop % 4:
            raise ConfigError(f"window.crop = {self.crop} must be a multiple of 4 (the refinement downsamples twice)")


WindowSource = Callable[[int, int], dict[str, torch.Tensor]]
"""(seed, index) -> item dict (keys :data:`ITEM_KEYS`); a pure function of its arguments."""


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)


def window_centres(phi_nominal_rad: np.ndarray, centre_step: int, n_obs: int, stride_rad: float) -> np.ndarray:
    """Centre steps c_k (N,) of the observations around ``centre_step``: where the nominal angle has
    turned by k * stride (k = -K..K) from its value at ``centre_step``, rounded to a step (c_0 = c).
    """
    K = n_obs // 2
    phi = np.asarray(phi_nominal_rad, dtype=np.float64)
    c = np.rint(np.interp(phi[int(centre_step)] + stride_rad * np.arange(-K, K + 1), phi, np.arange(phi.size, dtype=np.float64))).astype(np.int64)
    c[K] = int(centre_step)
    return c


def item_from_stream(
    spikes: np.ndarray,
    obs_steps: np.ndarray,
    phi_nominal_step: np.ndarray,
    phi_true_step: np.ndarray,
    gt: tuple[np.ndarray, np.ndarray],
    maps: dict[str, np.ndarray],
    exposure: float,
    cfg: WindowConfig,
) -> dict[str, torch.Tensor]:
    """Build a window item from a spike stream, the way a stored group is read.

    Args:
        spikes: (T, H, W) 0/1 stream (step 0 = stream start).
        obs_steps: (N,) centre steps c_k of the observations k = -K..K: the stream's
            output frames (:func:`spike_sim.aggregate.frame_centres`) around the centre one,
            or :func:`window_centres` for a window centred on any step.
        phi_nominal_step: (T,) nominal mid-step polarizer angle, rad (observation placement and ``phi``).
        phi_true_step: (T,) true mid-step angle, rad (GT zeta).
        gt: (T, R) ground-truth layers (H, W) at the centre step c_0 (as stored: float16-rounded).
        maps: ``R_perp``, ``R_par``, ``phi_perp`` and optionally ``T_perp``, ``T_par`` (H, W).
        exposure: stream exposure (I = counts / (window_steps exposure)).
        cfg: window geometry.

    Returns:
        item dict (module docstring); ``phi`` is shifted by a multiple of pi so that the
        centre angle lies in [0, pi) (every quantity has period pi in phi).
    """
    h = cfg.window_steps // 2
    ck = np.asarray(obs_steps, dtype=np.int64)
    if ck.shape != (cfg.n_obs,):
        raise ShapeError(f"obs_steps must be ({cfg.n_obs},); got {ck.shape}", ck.shape, (cfg.n_obs,))
    if ck.min() - h < 0 or ck.max() + h > spikes.shape[0] - 1:
        raise ShapeError(f"windows {ck.min() - h}..{ck.max() + h} leave the stream of {spikes.shape[0]} steps", spikes.shape, "a longer stream")
    idx = ck[:, None] + np.arange(-h, h + 1)[None]
    counts = spikes[idx.ravel()].reshape(idx.shape + spikes.shape[1:]).sum(1, dtype=np.int32)
    I = counts / (cfg.window_steps * exposure)  # paper Eq. (3), radiance units
    phi_nom = np.asarray(phi_nominal_step, np.float64)
    phi_tr = np.asarray(phi_true_step, np.float64)
    phi = phi_nom[idx].mean(1)
    phi = phi - math.floor(phi[len(phi) // 2] / math.pi) * math.pi  # period pi: centre angle in [0, pi)
    a = float(np.mean(np.diff(phi_tr))) if phi_tr.size > 1 else 0.0
    sinc = math.sin(a) / a if a != 0 else 1.0  # rotation inside one step (either sense: sin(a)/a is even)
    pt = phi_tr[idx]
    C = sinc * np.cos(2 * pt).mean(1)
    Sn = sinc * np.sin(2 * pt).mean(1)
    Rp, Rs, pp = (np.asarray(maps[k], np.float32).astype(np.float64) for k in ("R_perp", "R_par", "phi_perp"))

    def eq2(rp, rs):  # paper Eq. (2) averaged over each window at the true per-step angles: mean + amp <cos 2(phi - phi_perp)>
        return 0.5 * (rp + rs)[None] + 0.5 * (rp - rs)[None] * (C[:, None, None] * np.cos(2 * pp)[None] + Sn[:, None, None] * np.sin(2 * pp)[None])

    zeta = eq2(Rp, Rs)
    Tp = np.asarray(maps["T_perp"], np.float32) if "T_perp" in maps else (1.0 - Rp).astype(np.float32)
    Ts = np.asarray(maps["T_par"], np.float32) if "T_par" in maps else (1.0 - Rs).astype(np.float32)
    T_, R_ = (np.asarray(x, np.float16).astype(np.float64) for x in gt)
    item = {
        "I": _t(I), "phi": _t(phi), "T": _t(T_), "R": _t(R_), "zeta": _t(zeta), "R_perp": _t(Rp), "R_par": _t(Rs), "phi_perp": _t(pp),
        "T_perp": _t(Tp), "T_par": _t(Ts), "exposure": torch.tensor(float(exposure), dtype=torch.float32),
    }
    if cfg.assumed_n > 0:
        if "theta" not in maps:
            raise ConfigError("window.assumed_n needs the maps' incidence angle theta; this source gives none")
        from polphysics.fresnel import pane_coefficients

        th = np.asarray(maps["theta"], np.float64)
        for model in ASSUMED_MODELS:
            co = pane_coefficients(th, cfg.assumed_n, model=model)
            item[f"zeta_a_{model}"] = _t(eq2(np.asarray(co["R_perp"], np.float64), np.asarray(co["R_par"], np.float64)))
    if cfg.wide_steps:  # the same observations over the wide window, clipped to the stream
        item["I_wide"] = _t(window_means(lambda a, b: spikes[a:b], ck, (cfg.wide_steps,), spikes.shape[0], exposure)[0])
    if cfg.mean_steps:  # the long spike mean around the centre frame, clipped to the stream
        a, b = (int(v) for v in spike_mean_span(int(ck[len(ck) // 2]), cfg.mean_steps, spikes.shape[0]))
        item["I_mean"] = _t(spikes[a:b].sum(0, dtype=np.int64) / ((b - a) * exposure))
        sums = np.tensordot(harmonic_design(phi_nom[a:b]), spikes[a:b].astype(np.float64), axes=(1, 0))
        item["I_harm"] = _t(span_harmonic(sums, phi_nom[a:b], exposure))  # the span's first harmonic, as a stored group's
        item["span_steps"] = torch.tensor(float(b - a))  # the span's length, clipped to the stream (a span_level network's noise)
    return item


ASSUMED_MODELS = ("single", "thin_slab")
"""Pane models whose zeta under the assumed index an item carries (window.assumed_n): the self-calibration's
(:data:`reconstruct.pane.cone.CONE_MODELS`)."""

_IMAGE_KEYS = ("I", "T", "R", "zeta", "R_perp", "R_par", "phi_perp", "T_perp", "T_par", "I_mean", "I_wide", *(f"zeta_a_{m}" for m in ASSUMED_MODELS))
_ANGLE_KEYS = ("phi", "phi_perp")


def flip_item(item: dict[str, torch.Tensor], code: int) -> dict[str, torch.Tensor]:
    """One of the 8 symmetries of a square crop applied to an item, angles carried along (:mod:`reconstruct.physics.symmetry`:
    ``code`` in 0..7, bit 0 = mirror left-right, bit 1 = mirror up-down, bit 2 = transpose).  Both the polarizer
    angles ``phi`` and the plane-of-incidence map ``phi_perp`` move with the image, so zeta, T and R are the same
    numbers at the moved pixels (tested against Eq. (2)).
    """
    if not 0 <= code < 8:
        raise ConfigError(f"flip code {code} must be in 0..7")
    if code == 0:
        return item
    out = dict(item)
    for k in _IMAGE_KEYS:
        if k in out:
            out[k] = symmetry_image(out[k], code).contiguous()
    if "I_harm" in out:  # a first harmonic of the angle: moved, and its coefficients change sign with the angles
        out["I_harm"] = symmetry_harmonic(out["I_harm"], code).contiguous()
    sign, offset = angle_map(code)
    for k in _ANGLE_KEYS:
        if k in out:
            a = sign * out[k].double() + offset
            if k == "phi":  # keep the centre angle in [0, pi) as item_from_stream does
                a = a - math.floor(float(a[len(a) // 2]) / math.pi) * math.pi
            else:
                a = torch.remainder(a, math.pi)
            out[k] = a.float()
    return out


class OnTheFlyWindows(torch.utils.data.Dataset):
    """Map-style dataset of ``length`` windows; item i = ``source(seed, i)``, a pure function of (seed, i)."""

    def __init__(self, source: WindowSource, *, length: int = 100000, seed: int = 0):
        if length < 1:
            raise ConfigError(f"length = {length} must be >= 1")
        self.source, self.length, self.seed = source, int(length), int(seed)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < self.length:
            raise IndexError(index)
        return self.source(self.seed, int(index))
