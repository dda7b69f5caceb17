"""Per-pixel harmonic fit of a polarizer-modulated window, supp. Eq. (1)-(2).

Over a window of N observations I_k taken behind a polarizer at angle phi_k the
intensity of every pixel follows (supp. Eq. (1))

    I_k = a0 + ac cos 2 phi_k + as sin 2 phi_k .

With an ideal polarizer in front of Stokes light (S0, S1, S2) in the camera
frame this is I = 1/2 (S0 + S1 cos 2phi + S2 sin 2phi), so a0 = S0/2,
ac = S1/2, as = S2/2; DoP (supp. Eq. (2)) and AoLP follow.

Everything is PyTorch, batched over leading dimensions and pixels, works on any
device and dtype, and is differentiable (the 3x3 weighted normal equations are
solved with ``torch.linalg.solve`` after a tiny documented Tikhonov floor).
"""

from __future__ import annotations

import torch

from polinfra.errors import ShapeError

__all__ = ["harmonic_fit", "harmonic_eval", "dop", "aolp", "half_turn_frames"]

_DEF_EPS = 1e-6


def _angles_like(phi: torch.Tensor, I: torch.Tensor) -> torch.Tensor:
    """Broadcast phi (..., N) or (..., N, H, W) against I (..., N, H, W)."""
    if phi.dim() == I.dim():
        return phi
    if phi.dim() == I.dim() - 2:
        return phi[..., None, None]
    raise ShapeError(
        f"phi must have shape (..., N) or (..., N, H, W) matching I of shape {tuple(I.shape)}; got {tuple(phi.shape)}",
        actual_shape=tuple(phi.shape),
        expected_shape="(..., N) or (..., N, H, W)",
    )


def harmonic_fit(
    I: torch.Tensor,
    phi: torch.Tensor,
    weights: torch.Tensor | None = None,
    *,
    ridge: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted least-squares harmonic fit, supp. Eq. (1).

    Args:
        I: observations (..., N, H, W), any linear unit, N >= 3 for a unique fit.
        phi: polarizer angles in radians, (..., N) shared by all pixels or
            (..., N, H, W) per pixel.
        weights: optional non-negative weights broadcastable to (..., N, H, W).
        ridge: Tikhonov floor added to the 3x3 normal matrix, relative to its
            trace (default 1e-10 for float64, 1e-5 otherwise); keeps degenerate windows (N < 3, all angles equal, zero
            weights) finite: they return the minimum-norm-like solution.

    Returns:
        (a0, ac, as), each (..., H, W), same unit as I.
    """
    if I.dim() < 3:
        raise ShapeError(f"I must be (..., N, H, W); got shape {tuple(I.shape)}", actual_shape=tuple(I.shape), expected_shape="(..., N, H, W)")
    if ridge is None:
        ridge = 1e-10 if I.dtype == torch.float64 else 1e-5
    tiny = torch.finfo(I.dtype).tiny ** 0.25  # its cube (the 3x3 determinant) stays a normal number
    if weights is None and phi.dim() == I.dim() - 2:
        # angles shared by all pixels: one 3x3 system per window, applied to every pixel
        ph = phi.to(I.dtype)
        B = torch.stack([torch.ones_like(ph), torch.cos(2.0 * ph), torch.sin(2.0 * ph)], -1)  # (..., N, 3)
        G = B.transpose(-1, -2) @ B
        tr = G.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
        G = G + (ridge * tr + tiny) * torch.eye(3, dtype=I.dtype, device=I.device)
        P = torch.linalg.solve(G, B.transpose(-1, -2))  # (..., 3, N) pseudo-inverse rows
        coef = torch.einsum("...jn,...nhw->...jhw", P, I)  # supp. Eq. (1), least squares
        return coef[..., 0, :, :], coef[..., 1, :, :], coef[..., 2, :, :]
    ph = _angles_like(phi.to(I.dtype), I)
    c = torch.cos(2.0 * ph)
    s = torch.sin(2.0 * ph)
    w = torch.ones_like(I) if weights is None else torch.broadcast_to(weights.to(I.dtype), I.shape)
    wc, ws = w * c, w * s
    # weighted normal equations, supp. Eq. (1): G = sum_k w b b^T, h = sum_k w b I, b = [1, cos 2phi, sin 2phi]
    g00 = w.expand_as(I).sum(-3) if w.shape != I.shape else w.sum(-3)
    g01 = wc.expand_as(I).sum(-3)
    g02 = ws.expand_as(I).sum(-3)
    g11 = (wc * c).expand_as(I).sum(-3)
    g12 = (wc * s).expand_as(I).sum(-3)
    g22 = (ws * s).expand_as(I).sum(-3)
    h0 = (w * I).sum(-3)
    h1 = (wc * I).sum(-3)
    h2 = (ws * I).sum(-3)
    d = ridge * (g00 + g11 + g22) + tiny
    g00, g11, g22 = g00 + d, g11 + d, g22 + d
    # symmetric 3x3 solve by cofactors (elementwise over pixels: no batched LAPACK call)
    c00 = g11 * g22 - g12 * g12
    c01 = g02 * g12 - g01 * g22
    c02 = g01 * g12 - g02 * g11
    c11 = g00 * g22 - g02 * g02
    c12 = g01 * g02 - g00 * g12
    c22 = g00 * g11 - g01 * g01
    det = g00 * c00 + g01 * c01 + g02 * c02
    a0 = (c00 * h0 + c01 * h1 + c02 * h2) / det
    ac = (c01 * h0 + c11 * h1 + c12 * h2) / det
    as_ = (c02 * h0 + c12 * h1 + c22 * h2) / det
    return a0, ac, as_


def harmonic_eval(a0: torch.Tensor, ac: torch.Tensor, as_: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Evaluate supp. Eq. (1) at angles phi (..., N) -> (..., N, H, W)."""
    ph = phi[..., None, None] if phi.dim() == a0.dim() - 1 else phi
    return a0.unsqueeze(-3) + ac.unsqueeze(-3) * torch.cos(2.0 * ph) + as_.unsqueeze(-3) * torch.sin(2.0 * ph)


def dop(a0: torch.Tensor, ac: torch.Tensor, as_: torch.Tensor, eps: float = _DEF_EPS) -> torch.Tensor:
    """Degree of (linear) polarization, supp. Eq. (2): sqrt(ac^2 + as^2) / (|a0| + eps).

    ``eps`` (same unit as a0) keeps dark pixels finite; the square root gets a
    ``eps**2`` floor so its gradient is finite at ac = as = 0.
    """
    return torch.sqrt(ac * ac + as_ * as_ + eps * eps) / (a0.abs() + eps)  # supp. Eq. (2)


def aolp(ac: torch.Tensor, as_: torch.Tensor) -> torch.Tensor:
    """Angle of linear polarization 1/2 atan2(as, ac), radians in (-pi/2, pi/2], image convention."""
    return 0.5 * torch.atan2(as_, ac)


def half_turn_frames(phi) -> int:
    """Frames in a chunk of about half a polarizer turn (one cycle of 2 phi), at least 3, for frames at angles ``phi``
    (radians, a roughly constant step): the chunk length of every long-span harmonic fit (self-calibration, the DoP
    cone, the content test, calibrate-pane).
    """
    import math

    import numpy as np

    phi = np.asarray(phi, np.float64).ravel()
    step = float(np.median(np.abs(np.diff(phi)))) if phi.size > 1 else math.pi
    return max(3, int(math.ceil(math.pi / max(step, 1e-9) - 1e-6)))
