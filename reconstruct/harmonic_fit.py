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

from polspike.errors import ShapeError

__all__ = ["harmonic_fit", "harmonic_eval", "dop", "aolp"]

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
    ph = _angles_like(phi.to(I.dtype), I)
    c = torch.cos(2.0 * ph)
    s = torch.sin(2.0 * ph)
    one = torch.ones_like(c)
    w = torch.ones_like(I) if weights is None else torch.broadcast_to(weights.to(I.dtype), I.shape)
    basis = [one, c, s]
    shape = torch.broadcast_shapes(I.shape, c.shape)
    # Normal matrix G_ij = sum_k w b_i b_j, right side h_i = sum_k w b_i I   (supp. Eq. (1), weighted LS)
    G = torch.stack([torch.stack([(w * bi * bj).expand(shape).sum(-3) for bj in basis], -1) for bi in basis], -2)
    h = torch.stack([(w * bi * I).expand(shape).sum(-3) for bi in basis], -1)
    tr = G.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True)[..., None]
    eye = torch.eye(3, dtype=I.dtype, device=I.device)
    tiny = torch.finfo(I.dtype).tiny ** 0.5
    if ridge is None:
        ridge = 1e-10 if I.dtype == torch.float64 else 1e-5
    G = G + (ridge * tr + tiny) * eye
    coef = torch.linalg.solve(G, h[..., None])[..., 0]
    return coef[..., 0], coef[..., 1], coef[..., 2]


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
