"""zeta and reliability weights from a checkpoint's parameter branch."""

from __future__ import annotations

import torch

from polinfra.errors import ShapeError
from reconstruct.physics.zeta import _pad4


@torch.no_grad()
def zeta_learned(model, I: torch.Tensor, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``learned`` source: zeta_hat and reliability weights w of the network's parameter branch.

    zeta_k = sigmoid(a0 + ac cos 2phi_k + as sin 2phi_k) (supp. Eq. (19)), w = softmax over the window.

    Args:
        model: :class:`reconstruct.net.network.PolSpikeNet` (e.g. from :func:`reconstruct.net.checkpoint.load_model`).
        I: (B, N, H, W) windows, already RIR-aligned, radiance units; any H, W (replicate-padded here to
            the network's ``pad_multiple``, 4 for v1).
        phi: (B, N) polarizer angles (window centres), radians.

    Returns:
        (zeta, w), each (B, N, H, W) on I's device and dtype.
    """
    from reconstruct.net.network import predict_parameters

    if I.dim() != 4 or phi.shape != I.shape[:2]:
        raise ShapeError(f"zeta_learned needs I (B, N, H, W) and phi (B, N); got {tuple(I.shape)} and {tuple(phi.shape)}", actual_shape=tuple(I.shape), expected_shape="(B, N, H, W)")
    H, W = I.shape[-2:]
    dev = next(model.parameters()).device
    mult = int(getattr(model, "pad_multiple", 4))  # v1: 4; v2: its pixel-unshuffle factor
    z, w = predict_parameters(model, _pad4(I.to(dev, torch.float32), mult), phi.to(dev, torch.float32))
    return z[..., :H, :W].to(I.device, I.dtype), w[..., :H, :W].to(I.device, I.dtype)
