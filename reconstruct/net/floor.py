"""The network's data-consistency floor: its output checked against the physics on the same aligned windows.

:func:`network_floor` is what :meth:`reconstruct.net.network.PolSpikeNet.data_floor` runs after the refinement at
inference: (T, R) against the physics-only RWPS (``polspike reconstruct --method rwps`` on this zeta, layers >= 0;
:func:`reconstruct.physics.solvers.solve` clamped at 0) through :mod:`reconstruct.physics.consistency` or, with an
anchor, :mod:`reconstruct.physics.anchor`.
"""

from __future__ import annotations

import torch

from reconstruct.physics.anchor import AnchorFloorConfig, anchored_floor
from reconstruct.physics.consistency import FloorConfig, consistency_floor, spike_noise_bounds, window_counts
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, solve
from reconstruct.physics.span import zbar_of

__all__ = ["network_floor"]


@torch.no_grad()
def network_floor(cfg, T: torch.Tensor, R: torch.Tensor, zeta: torch.Tensor, I: torch.Tensor, exposure=None, I_mean=None, phi=None,
                  external: bool = True, gain_spread: float | None = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The floor of a network configuration ``cfg`` (:class:`reconstruct.net.network.NetConfig`) -> (T, R, T's kept fraction).

    Given the stream's ``exposure``, the noise is capped at the windows' Poisson noise, var(2 I) = 4 I / (exposure L)
    with L = 13 steps (0.65 ms at 20 kHz: the windows the network reads), so misalignment or a wrong zeta in the
    residual does not widen the allowance; and bounded from below by the noise of counts under one spike per window
    (:func:`reconstruct.physics.consistency.count_quantum_variance` at the brighter of the windows' and the span's
    mean), which a dark pool's all-zero windows cannot show.  ``floor_anchor = "blend"`` (default): the same check,
    falling back per pixel to the RWPS and the best closed-form physics weighed by their error powers, ``"best"`` to
    the latter alone (:func:`reconstruct.physics.anchor.anchored_floor`, with the long span's ``I_mean`` at the
    polarizer-cycle mean zeta of ``phi``); ``floor_layers`` adds its layer checks.  Only on an ``external`` zeta
    (self-calibrated or given): least squares on the unchecked learned zeta can be far off (the anchor's T erred by
    0.8-1.2 on a 0.3-0.7 layer).  ``gain_spread``: the sensor's photo-gain spread the check allows for
    (:func:`reconstruct.physics.consistency.move_excess`); None: estimated from the windows, its pixel-white part
    (:func:`reconstruct.physics.consistency.estimate_gain_spread`).
    """
    z, Iw = zeta.detach().float(), I.detach().float()
    Im = None if I_mean is None else I_mean.detach().float()
    mv, qf = spike_noise_bounds(Iw, exposure, Im)
    ph = solve("rwps", z, Iw, None, PHYSICS_SOLVER_CONFIG)
    ref = (ph.T.clamp_min(0.0), ph.R.clamp_min(0.0))
    if cfg.floor_anchor in ("best", "blend") and external:
        g = anchored_floor(T.float(), R.float(), z, Iw, Im, None if Im is None else zbar_of(z, phi.float()),
                           AnchorFloorConfig(tol=cfg.floor_tol, layers=cfg.floor_layers), mv, reference=ref, noise_floor=qf,
                           counts=window_counts(Iw, exposure), gain_spread=gain_spread, fallback="blend" if cfg.floor_anchor == "blend" else "anchor")
        return g.T.to(T.dtype), g.R.to(R.dtype), g.keep_T
    f = consistency_floor(T.float(), R.float(), *ref, z, Iw, FloorConfig(tol=cfg.floor_tol, mode=cfg.floor_mode), mv, "min", noise_floor=qf, gain_spread=gain_spread)
    return f.T.to(T.dtype), f.R.to(R.dtype), f.keep
