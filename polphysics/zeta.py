"""The mixing coefficient zeta and the mixed radiance: paper Eq. (1)-(2) and their Stokes form.

Paper Eq. (2): zeta(phi) = R_perp cos^2(phi - phi_perp) + R_par sin^2(phi - phi_perp).
Paper Eq. (1): L_M(phi) = 1/2 (zeta L_R + (1 - zeta) L_T)   (the 1/2 is the ideal polarizer).

Stokes form (what the generator writes): the light in front of the polarizer is
the reflected R layer plus the transmitted T layer, each linearly polarized along
(or across) the s-direction phi_perp:

    S0 = L_R (R_perp + R_par)/2 + L_T (T_perp + T_par)/2
    S1 = [L_R (R_perp - R_par)/2 + L_T (T_perp - T_par)/2] cos 2 phi_perp
    S2 = [L_R (R_perp - R_par)/2 + L_T (T_perp - T_par)/2] sin 2 phi_perp

With T = 1 - R per polarization, 1/2 (S0 + S1 cos 2phi + S2 sin 2phi) equals
Eq. (1) exactly (tested).  Shapes broadcast; angles in radians, camera frame.
"""

from __future__ import annotations

import numpy as np

__all__ = ["zeta", "transmission_fraction", "mix_eq1", "stokes_from_layers"]


def zeta(phi_rad, R_perp, R_par, phi_perp_rad):
    """Reflected fraction behind a polarizer at phi, paper Eq. (2).

    Returns values in [min(R_perp, R_par), max(R_perp, R_par)].
    """
    d = np.asarray(phi_rad) - np.asarray(phi_perp_rad)
    c2 = np.cos(d) ** 2
    return R_perp * c2 + R_par * (1.0 - c2)  # Eq. (2)


def transmission_fraction(phi_rad, T_perp, T_par, phi_perp_rad):
    """Transmitted fraction tau(phi) = T_perp cos^2 + T_par sin^2 (= 1 - zeta when T = 1 - R)."""
    return zeta(phi_rad, T_perp, T_par, phi_perp_rad)


def mix_eq1(L_R, L_T, zeta_val):
    """Mixed intensity behind an ideal polarizer, paper Eq. (1): 1/2 (zeta L_R + (1 - zeta) L_T)."""
    return 0.5 * (zeta_val * L_R + (1.0 - zeta_val) * L_T)  # Eq. (1)


def stokes_from_layers(L_T, L_R, R_perp, R_par, T_perp, T_par, phi_perp_rad, L_R_ghost=None, G_perp=None, G_par=None):
    """Stokes (S0, S1, S2) of the light in front of the polarizer.

    Args:
        L_T, L_R: layer radiances (H, W) (any broadcastable shape), linear.
        R_perp, R_par, T_perp, T_par: pane coefficients (total, ghost included).
        phi_perp_rad: image-plane angle of the s-direction (radians).
        L_R_ghost, G_perp, G_par: optional displaced ghost image of the R layer
            and the part of R_perp / R_par it carries (thick slab); the primary
            image then carries R - G.

    Returns:
        Array (3, ...) float64: S0, S1, S2 in the camera frame.
    """
    if L_R_ghost is not None:
        rs_img = (R_perp - G_perp) * L_R + G_perp * L_R_ghost
        rp_img = (R_par - G_par) * L_R + G_par * L_R_ghost
    else:
        rs_img, rp_img = R_perp * L_R, R_par * L_R
    ts_img, tp_img = T_perp * L_T, T_par * L_T
    s0 = 0.5 * (rs_img + rp_img + ts_img + tp_img)
    lin = 0.5 * (rs_img - rp_img + ts_img - tp_img)
    two = 2.0 * np.asarray(phi_perp_rad)
    return np.stack(np.broadcast_arrays(s0, lin * np.cos(two), lin * np.sin(two)))
