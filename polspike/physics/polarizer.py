"""The rotating linear polarizer in front of the spike camera.

phi(t) = phi0 + 2 pi f t (radians, image-plane convention of
:mod:`polspike.physics.stokes`).  Defaults: f = 30 rev/s, so the output cadence
at a 31.5 deg stride is 10800 / 31.5 = 342.9 frames/s.
"""

from __future__ import annotations

import dataclasses

from polspike.config import opt

__all__ = ["PolarizerConfig"]


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
