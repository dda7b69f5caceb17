"""The 8 symmetries of the square image grid with the polarization angles carried along.

A symmetry ``code`` in 0..7: bit 0 = mirror left-right, bit 1 = mirror up-down, bit 2 = transpose (applied in that
order).  A mirror maps every image-plane direction at angle a to -a (mod pi, the period of linear polarization:
the polarizer angles and the plane-of-incidence map phi_perp alike); a transpose maps a to pi/2 - a.  paper Eq. (2)
depends on phi_k - phi_perp only through cos 2(phi_k - phi_perp), which both maps keep, so zeta, T and R are the
same numbers at the moved pixels.  Used by the training augmentation (:func:`reconstruct.net.onthefly.flip_item`) and
the test-time self-ensemble (:class:`reconstruct.net.network.SymmetryEnsemble`).
"""

from __future__ import annotations

import math

import torch

__all__ = ["angle_map", "symmetry_image", "symmetry_angles", "harmonic_signs", "symmetry_harmonic"]


def angle_map(code: int) -> tuple[float, float]:
    """(sign, offset): symmetry ``code`` maps an image-plane angle a to sign * a + offset (mod pi)."""
    sign, offset = 1.0, 0.0
    for bit in (1, 2):
        if code & bit:
            sign, offset = -sign, -offset
    if code & 4:
        sign, offset = -sign, math.pi / 2 - offset
    return sign, offset


def symmetry_image(x: torch.Tensor, code: int, inverse: bool = False) -> torch.Tensor:
    """Apply symmetry ``code`` to the last two dims of ``x`` (any leading dims); ``inverse`` undoes it."""
    dims = [d for bit, d in ((1, -1), (2, -2)) if code & bit]

    def mirrors(y):
        return torch.flip(y, dims) if dims else y

    if inverse:
        return mirrors(x.transpose(-1, -2) if code & 4 else x)
    y = mirrors(x)
    return y.transpose(-1, -2) if code & 4 else y


def symmetry_angles(phi: torch.Tensor, code: int) -> torch.Tensor:
    """Polarizer angles (B, N) of windows seen through symmetry ``code`` (:func:`angle_map`); each window's centre
    angle is brought back into [0, pi).
    """
    sign, offset = angle_map(code)
    a = sign * phi.double() + offset
    c = a[:, a.shape[1] // 2 : a.shape[1] // 2 + 1]
    return (a - torch.floor(c / math.pi) * math.pi).to(phi.dtype)


def harmonic_signs(code: int) -> tuple[float, float]:
    """Factors on the (cos 2 phi, sin 2 phi) coefficients of a first harmonic of the polarizer angle seen through
    symmetry ``code``: with phi' = s phi + o (:func:`angle_map`, 2 o a multiple of pi), cos 2 phi = e cos 2 phi' and
    sin 2 phi = e s sin 2 phi', e = cos 2 o; so (b, c) -> (e b, e s c).  Its own inverse.
    """
    sign, offset = angle_map(code)
    e = float(round(math.cos(2 * offset)))
    return e, e * sign


def symmetry_harmonic(x: torch.Tensor, code: int) -> torch.Tensor:
    """Symmetry ``code`` applied to (..., 2, H, W) first-harmonic maps (cos, sin): moved as an image, signs by
    :func:`harmonic_signs`.
    """
    fc, fs = harmonic_signs(code)
    y = symmetry_image(x, code)
    return torch.stack([fc * y[..., 0, :, :], fs * y[..., 1, :, :]], -3)
