"""Fresnel coefficients of a dielectric interface and of glass panes.

All functions are pure numpy, vectorised over broadcastable arrays, finite on
the whole closed interval theta in [0, pi/2] for any relative index n > 0,
including n < 1 (total internal reflection) and n = 1 (no interface).

Conventions: ``theta_rad`` is the angle of incidence from the surface normal;
``n`` is the relative index n2 / n1 (transmitted over incident medium).  "s" =
"perp" (electric field perpendicular to the plane of incidence), "p" = "par".
Power reflectances R and transmittances T are energy fractions with R + T = 1
per polarization for a lossless interface (radiance compression by n^2 across a
single interface is a separate, documented factor: :func:`radiance_scale`).

References: Hecht, *Optics*, 5th ed., Sec. 4.6 (Fresnel equations);
paper Eq. (2) uses R_perp = R_s, R_par = R_p.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "fresnel_amplitudes",
    "fresnel_power",
    "brewster_angle",
    "critical_angle",
    "slab_coefficients",
    "pane_coefficients",
    "radiance_scale",
    "PANE_MODELS",
    "GLASSES",
    "glass_index",
]

PANE_MODELS = ("single", "thin_slab", "thick_slab")
"""Pane models a scene may name (see :func:`pane_coefficients`)."""

GLASSES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    # Sellmeier coefficients (B1, B2, B3), (C1, C2, C3 in um^2): SCHOTT data sheets.
    "BK7": ((1.03961212, 0.231792344, 1.01046945), (0.00600069867, 0.0200179144, 103.560653)),
    "FUSED_SILICA": ((0.6961663, 0.4079426, 0.8974794), (0.0684043**2, 0.1162414**2, 9.896161**2)),
    "SF11": ((1.73759695, 0.313747346, 1.89878101), (0.013188707, 0.0623068142, 155.23629)),
}
"""Named dispersive glasses (Sellmeier form), usable as ``pane.glass`` in scenes."""


def glass_index(name: str, wavelength_nm: float | np.ndarray = 550.0) -> np.ndarray:
    """Refractive index of a named glass by the Sellmeier equation.

    Args:
        name: a key of :data:`GLASSES` (case-insensitive).
        wavelength_nm: wavelength(s) in nm.

    Returns:
        n(lambda), same shape as ``wavelength_nm``.
    """
    from polinfra.errors import ConfigError

    key = name.upper()
    if key not in GLASSES:
        raise ConfigError(f"unknown glass {name!r}; choose one of {sorted(GLASSES)} or give pane.n")
    b, c = GLASSES[key]
    l2 = (np.asarray(wavelength_nm, dtype=np.float64) / 1000.0) ** 2
    n2 = 1.0 + sum(bi * l2 / (l2 - ci) for bi, ci in zip(b, c))
    return np.sqrt(n2)


def _cos_t(theta_rad, n):
    """Complex cosine of the transmission angle (imaginary beyond the critical angle)."""
    sin_i = np.sin(theta_rad)
    return np.sqrt((1.0 - (sin_i / n) ** 2).astype(np.complex128))


def fresnel_amplitudes(theta_rad, n):
    """Complex amplitude coefficients (r_s, r_p, t_s, t_p) at an interface.

    Uses r_s = (cos_i - n cos_t) / (cos_i + n cos_t), r_p = (n cos_i - cos_t) /
    (n cos_i + cos_t), t_s = 2 cos_i / (cos_i + n cos_t), t_p = 2 cos_i /
    (n cos_i + cos_t) (Hecht Eq. 4.42-4.45 with mu = 1).  Where a denominator
    vanishes (n = 1 at grazing incidence, the only such point) the limit of a
    matched interface is returned: r = 0, t = 1.

    Args:
        theta_rad: incidence angle(s) in [0, pi/2].
        n: relative index(es) n2/n1 > 0.

    Returns:
        Four complex128 arrays of the broadcast shape.
    """
    theta = np.asarray(theta_rad, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    theta, n = np.broadcast_arrays(theta, n)
    cos_i = np.cos(theta).astype(np.complex128)
    cos_t = _cos_t(theta, n)
    matched = np.abs(n - 1.0) < 1e-12
    out = []
    for num, den, limit in (
        (cos_i - n * cos_t, cos_i + n * cos_t, 0.0),
        (n * cos_i - cos_t, n * cos_i + cos_t, 0.0),
        (2.0 * cos_i, cos_i + n * cos_t, 1.0),
        (2.0 * cos_i, n * cos_i + cos_t, 1.0),
    ):
        ok = np.abs(den) > 1e-300
        safe = np.where(ok, den, 1.0)
        out.append(np.where(ok & ~matched, num / safe, limit))
    return tuple(out)


def fresnel_power(theta_rad, n):
    """Power reflectances and transmittances (R_s, R_p, T_s, T_p) of one interface.

    R = |r|^2, T = 1 - R (energy conservation per polarization; lossless).
    Beyond the critical angle (n < 1) R = 1 exactly.

    Args:
        theta_rad: incidence angle(s) in [0, pi/2] (radians).
        n: relative index(es) n2/n1 > 0.

    Returns:
        Four float64 arrays of the broadcast shape, each in [0, 1].
    """
    rs, rp, _, _ = fresnel_amplitudes(theta_rad, n)
    Rs = np.clip(np.abs(rs) ** 2, 0.0, 1.0)
    Rp = np.clip(np.abs(rp) ** 2, 0.0, 1.0)
    return Rs, Rp, 1.0 - Rs, 1.0 - Rp


def brewster_angle(n):
    """Brewster angle arctan(n) in radians (R_p = 0 there)."""
    return np.arctan(np.asarray(n, dtype=np.float64))


def critical_angle(n):
    """Critical angle arcsin(n) for n < 1 (radians); pi/2 where n >= 1 (no TIR)."""
    n = np.asarray(n, dtype=np.float64)
    return np.where(n < 1.0, np.arcsin(np.clip(n, 0.0, 1.0)), np.pi / 2)


def slab_coefficients(R1, internal_transmittance=1.0):
    """Incoherent two-interface slab (parallel faces, same medium both sides).

    With single-interface reflectance R1 (per polarization) and single-pass
    internal transmittance a = exp(-alpha d / cos theta_t):
    R = R1 + (1 - R1)^2 R1 a^2 / (1 - R1^2 a^2),  T = (1 - R1)^2 a / (1 - R1^2 a^2).
    Lossless (a = 1): R = 2 R1 / (1 + R1), T = (1 - R1) / (1 + R1).

    Returns:
        (R, T, G) where G = R - R1 is the part reflected by the second surface
        and beyond (the displaced ghost of a thick slab).
    """
    R1 = np.asarray(R1, dtype=np.float64)
    a = np.asarray(internal_transmittance, dtype=np.float64)
    den = 1.0 - (R1 * a) ** 2
    den = np.where(den > 1e-15, den, 1e-15)  # R1 = a = 1: TIR slab reflects all
    G = (1.0 - R1) ** 2 * R1 * a**2 / den
    T = (1.0 - R1) ** 2 * a / den
    return R1 + G, T, G


def _transmission_cos(theta_rad, n):
    return np.real(_cos_t(np.asarray(theta_rad, dtype=np.float64), n))


def pane_coefficients(theta_rad, n, model: str = "single", thickness_m: float = 0.0, absorption_per_m: float = 0.0):
    """Per-polarization reflectance and transmittance of a named pane model.

    Models:
        ``single``: one interface, (R_s, R_p) = Fresnel, T = 1 - R.
        ``thin_slab``: two interfaces, incoherent interreflection
            (:func:`slab_coefficients`), optional absorption.
        ``thick_slab``: as ``thin_slab``; the second-surface part G is also
            returned so the caller can displace it (the ghost image).

    Args:
        theta_rad: incidence angle(s), radians.
        n: relative index of the glass (> 0; slabs need n >= 1 in air).
        model: one of :data:`PANE_MODELS`.
        thickness_m: slab thickness in metres (used with absorption).
        absorption_per_m: absorption coefficient alpha in 1/m.

    Returns:
        dict with float64 arrays ``R_perp, R_par, T_perp, T_par, G_perp, G_par``
        (G = 0 for ``single``).
    """
    from polinfra.errors import ConfigError

    if model not in PANE_MODELS:
        raise ConfigError(f"unknown pane model {model!r}; choose one of {list(PANE_MODELS)}")
    Rs, Rp, Ts, Tp = fresnel_power(theta_rad, n)
    zero = np.zeros_like(Rs)
    if model == "single":
        return {"R_perp": Rs, "R_par": Rp, "T_perp": Ts, "T_par": Tp, "G_perp": zero, "G_par": zero}
    cos_t = np.maximum(_transmission_cos(theta_rad, n), 1e-6)
    a = np.exp(-absorption_per_m * thickness_m / cos_t)
    Rs2, Ts2, Gs = slab_coefficients(Rs, a)
    Rp2, Tp2, Gp = slab_coefficients(Rp, a)
    return {"R_perp": Rs2, "R_par": Rp2, "T_perp": Ts2, "T_par": Tp2, "G_perp": Gs, "G_par": Gp}


def radiance_scale(n, model: str) -> float:
    """Factor on transmitted radiance from radiance compression (basic radiance L/n^2).

    A ``single`` interface seen from the glass side compresses radiance by 1/n^2
    (Mitsuba applies this); slabs return to air so the factor is 1.  The
    analytic tier follows paper Eq. (1), which omits it: it is reported here so
    comparisons against renderers can include it explicitly.
    """
    return 1.0 / float(n) ** 2 if model == "single" else 1.0
