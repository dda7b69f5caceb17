"""Typed configuration of the spike camera simulator (``[spike_sim]`` in TOML).

Units.  The simulator works in *threshold units*: the accumulator fires when it
reaches the pixel's threshold theta_p (mean 1).  The radiance -> photocurrent
mapping (the exposure knob) is::

    x_p(n) = exposure * gain_p * <I>_n + dark_p        [threshold units per step]

where <I>_n is the mean over step n of the intensity behind the polarizer (linear
radiance, 1.0 = brightest layer value; an unpolarized S0 = 1 gives I = 1/2 behind
an ideal polarizer).  Noise-free (preset :data:`IDEAL`), a pixel at intensity g in
[0, 1] therefore fires exactly ``exposure * g`` spikes per step on average
(``exposure = 1``: g spikes per step, the SpikeCV / spikezoo convention).

Noise terms (each switchable; reference values from SCSim, Hu et al. ICME 2024,
rescaled from SCSim's absolute units to threshold units, see each field):

* photon shot noise: photoelectrons per step ~ Poisson(Q x); ``Q =
  photons_per_threshold`` electrons fill one threshold, so a constant pixel's
  ISI CV from shot noise alone is about 1/sqrt(Q).  Photons per unit radiance
  per step = Q * exposure.
* dark current: per-pixel dark_p ~ N(dark_mean, dark_std) (SCSim N(0.4442,
  0.1731): relative spread 0.39) plus a small fraction of hot pixels.
* fixed-pattern mismatch: threshold theta_p = (C_p / C) (1 + o_p) with
  capacitance C_p/C ~ N(1, 0.0128/4.348) and comparator offset o_p ~ N(0,
  0.0497/1.0924) (SCSim's V_s spread over 3.3 - 2.2 + V_s); gain_p ~ N(1,
  0.0584/1.0128).
* thermal noise: zero-mean Gaussian on the comparison at every step, SCSim
  N(0, 0.00636) over a threshold of 4.348 * 1.0924 = 4.75 -> 0.00134.
* reset noise: Gaussian kTC-like perturbation of the residue after each spike;
  leakage: the accumulator decays as exp(-leak_rate_hz * t).
* random initial accumulator: U[0, 1) of the threshold (else 0).
* multiplicative increment noise (off in every preset but ``plain_if``): each step's charge
  is scaled by ``1 + increment_sigma z``, z ~ N(0, 1), so its std grows with the photocurrent.
"""

from __future__ import annotations

import dataclasses

from polinfra.config import opt

__all__ = ["SpikeSimConfig", "IDEAL", "DEFAULT", "NOISY", "PLAIN_IF", "PRESETS", "preset", "pixel_gain_spread"]


@dataclasses.dataclass(frozen=True)
class SpikeSimConfig:
    """Spike camera simulator parameters (threshold units, see module docstring)."""

    width: int = opt(400, "sensor width in pixels (W)", lo=1, hi=100000)
    height: int = opt(250, "sensor height in pixels (H)", lo=1, hi=100000)
    rate_hz: float = opt(20000.0, "readout rate: one bit per pixel per step of 1/rate_hz seconds", lo=1.0, hi=1e8)
    exposure: float = opt(1.0, "photocurrent per unit intensity behind the polarizer, in thresholds per step (ISO-like knob)", lo=0.0, hi=1e6)
    shot_noise: bool = opt(True, "photon shot noise (Poisson photoelectron count per step)")
    photons_per_threshold: float = opt(1000.0, "photoelectrons that fill one threshold (shot-noise ISI CV ~ 1/sqrt of this)", lo=1.0, hi=1e9)
    dark_current: bool = opt(True, "dark current (per-pixel, with hot pixels)")
    dark_mean: float = opt(5e-4, "mean dark current, thresholds per step (5e-4 = 10 Hz dark rate at 20 kHz)", lo=0.0, hi=1.0)
    dark_std: float = opt(1.95e-4, "per-pixel spread of the dark current, thresholds per step (SCSim relative spread 0.39)", lo=0.0, hi=1.0)
    hot_pixel_fraction: float = opt(2e-4, "fraction of pixels with a hot (large) dark current", lo=0.0, hi=1.0)
    hot_pixel_dark: float = opt(0.05, "dark current of a hot pixel, thresholds per step", lo=0.0, hi=1.0)
    fixed_pattern: bool = opt(True, "per-pixel threshold / comparator offset / gain mismatch")
    threshold_sigma: float = opt(0.00294, "relative spread of the integration capacitance (SCSim 0.0128/4.348)", lo=0.0, hi=0.5)
    offset_sigma: float = opt(0.0455, "comparator offset spread, fraction of the threshold (SCSim 0.0497/1.0924)", lo=0.0, hi=0.5)
    gain_sigma: float = opt(0.0577, "relative photo-gain spread (SCSim 0.0584/1.0128)", lo=0.0, hi=0.5)
    thermal_noise: bool = opt(True, "Gaussian noise on the comparison at every step")
    thermal_sigma: float = opt(0.00134, "thermal noise std, thresholds (SCSim 0.00636/4.75)", lo=0.0, hi=1.0)
    reset_noise: bool = opt(True, "Gaussian reset (kTC) noise on the residue after each spike")
    reset_sigma: float = opt(0.005, "reset noise std, thresholds", lo=0.0, hi=1.0)
    leakage: bool = opt(True, "accumulator leakage between spikes")
    leak_rate_hz: float = opt(1.0, "leak rate: the accumulator decays as exp(-leak_rate_hz t)", lo=0.0, hi=1e6)
    random_init: bool = opt(True, "random initial accumulator U[0,1) of the threshold (else 0)")
    increment_sigma: float = opt(0.0, "multiplicative increment noise: each step's charge is scaled by 1 + sigma z, z ~ N(0, 1) (0 = off)", lo=0.0, hi=1.0, omit_if_default=True)

    @property
    def dt_s(self) -> float:
        """Step length in seconds."""
        return 1.0 / self.rate_hz

    @property
    def n_pixels(self) -> int:
        """H * W."""
        return self.width * self.height


DEFAULT = SpikeSimConfig()
"""Full noise model calibrated against the real captures (tests/spike_sim/test_real_stats.py)."""

IDEAL = dataclasses.replace(
    DEFAULT,
    shot_noise=False,
    dark_current=False,
    fixed_pattern=False,
    thermal_noise=False,
    reset_noise=False,
    leakage=False,
    random_init=False,
)
"""Noise-free integrate-and-fire, zero initial state: exactly floor(n g) spikes in n steps at constant g."""

NOISY = dataclasses.replace(DEFAULT, photons_per_threshold=100.0, reset_sigma=0.02)
"""A deliberately noisier camera (10x fewer photoelectrons per threshold), for robustness studies."""

PLAIN_IF = dataclasses.replace(IDEAL, random_init=True, increment_sigma=0.2)
"""A plain integrate-and-fire pixel (no shot noise, dark current, fixed pattern, thermal or reset noise,
no leak; random initial charge) whose per-step charge carries multiplicative noise of 20 %: the simpler
sensor model of other spike simulators."""

PRESETS: dict[str, SpikeSimConfig] = {"ideal": IDEAL, "default": DEFAULT, "noisy": NOISY, "plain_if": PLAIN_IF}


def preset(name: str) -> SpikeSimConfig:
    """Named preset; ConfigError listing the names when unknown."""
    from polinfra.errors import ConfigError

    if name not in PRESETS:
        raise ConfigError(f"unknown spike_sim preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]


def pixel_gain_spread(sim: dict) -> float:
    """The relative sd of a pixel's spike count against its light from the fixed pattern of a stored configuration
    (``config_json`` of a group, a :class:`SpikeSimConfig` as a dict): the photo-gain, the comparator offset and the
    capacitance each scale a pixel's counts alike at every step, so they add in quadrature (0.0735 for ``default``);
    0 without the fixed pattern.
    """
    if not bool(sim.get("fixed_pattern", True)):
        return 0.0
    return float(sum(float(sim.get(k, 0.0)) ** 2 for k in ("gain_sigma", "offset_sigma", "threshold_sigma")) ** 0.5)
