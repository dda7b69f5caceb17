"""Stokes-vector helpers in the camera frame.

Convention (pinned by tests): Stokes (S0, S1, S2) are expressed per pixel in the
camera frame; S1 > 0 means linear polarization along image +x, S2 > 0 along the
+45 deg diagonal (bottom-left to top-right); angles phi are measured in the
image plane from +x toward image up (counter-clockwise as the viewer sees the
image), in radians.  This is Mitsuba 3's ``stokes`` integrator frame.
"""

from __future__ import annotations

import numpy as np

__all__ = ["polarizer_intensity", "dop", "aolp", "EPS"]

EPS = 1e-12
"""Guard for divisions by S0 (radiance units)."""


def polarizer_intensity(s0, s1, s2, phi_rad, extinction_ratio: float | None = None):
    """Intensity behind a linear polarizer at angle ``phi_rad``.

    Ideal: ``I = 1/2 (S0 + S1 cos 2phi + S2 sin 2phi)``.  With a finite
    extinction ratio ``ER = k_max / k_min`` (principal transmittances k_max = 1,
    k_min = 1/ER), ``I = 1/2 ((k1 + k2) S0 + (k1 - k2)(S1 cos 2phi + S2 sin 2phi)) / 1``
    with k1 = 1, k2 = 1/ER, i.e. the diattenuator's Mueller first row.

    Args:
        s0, s1, s2: arrays broadcastable together, linear radiance.
        phi_rad: polarizer angle(s), broadcastable.
        extinction_ratio: None for an ideal polarizer, else ER >= 1.

    Returns:
        Intensity, same broadcast shape, >= 0 for physical Stokes input.
    """
    c, s = np.cos(2.0 * phi_rad), np.sin(2.0 * phi_rad)
    if extinction_ratio is None:
        return 0.5 * (s0 + s1 * c + s2 * s)
    k2 = 1.0 / float(extinction_ratio)
    return 0.5 * ((1.0 + k2) * s0 + (1.0 - k2) * (s1 * c + s2 * s))


def dop(s0, s1, s2):
    """Degree of linear polarization sqrt(S1^2 + S2^2) / S0, in [0, 1]; 0 where S0 ~ 0."""
    s0 = np.asarray(s0, dtype=np.float64)
    lin = np.hypot(s1, s2)
    out = np.divide(lin, s0, out=np.zeros(np.broadcast(s0, lin).shape), where=s0 > EPS)
    return np.clip(out, 0.0, 1.0)


def aolp(s1, s2):
    """Angle of linear polarization 1/2 atan2(S2, S1), wrapped to [0, pi)."""
    return np.mod(0.5 * np.arctan2(s2, s1), np.pi)
