"""The network on a zeta it did not estimate itself: ``polspike reconstruct --method net --zeta self``.

The network's parameter branch estimates zeta (and the reliability weights w) per window.  With
``--zeta self`` the pane is instead fitted to the stream itself (:mod:`reconstruct.pane.selfcal`, the
same fit the physics methods use) and that zeta (paper Eq. (2), window-averaged) replaces the
learned one in the network's solver and refinement: ``model(I, phi, zeta_gt=zeta, alpha=1)``
(the teacher-forcing path of :class:`reconstruct.net.network.PolSpikeNet`); w stays learned.  Where
nothing modulates (no pane can be fitted) the network runs on zeta = 0 (no separable reflection, T is the whole
light) or, where the refused stream still modulates (:data:`NET_FALLBACK_ZETA` ``auto``), on its own zeta; the info
says which.

:class:`MapsZetaNet` follows the model protocol of :func:`reconstruct.video.tiling.run_model_on_windows`
and of the stream's feature cache, so :func:`reconstruct.video.stream.reconstruct_stream` runs it as it
runs the network.  Its zeta maps are per full-frame pixel: whole frames only (``stream_tile = 0``).
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as F

from polinfra.errors import ConfigError
from reconstruct.physics.zeta import PaneMaps, zeta_from_maps

__all__ = ["MapsZetaNet", "ZeroZetaNet", "NET_ZETA_SOURCES", "NET_DEFAULT_ZETA", "NET_FALLBACK_ZETA", "NET_FALLBACKS", "FALLBACK_LEARNED_PX", "fallback_for", "build_net_zeta_model"]

log = logging.getLogger(__name__)

NET_ZETA_SOURCES = ("learned", "self", "none")
"""zeta sources of the network in ``polspike reconstruct`` (``learned``: its own parameter branch; ``none``: zeta = 0,
no separable reflection, T is the whole light, the network still denoises)."""

NET_DEFAULT_ZETA = "self"
"""The network's zeta when ``--zeta`` is not given (``polspike reconstruct``, ``evaluate-real``, ``evaluate-paper``,
the demo): the better of the two, measured (``polspike evaluate ... --by-regime --net-zetas learned,self``).
The shipped network (v3 and v4) is trained for it (half its steps ran on a jittered external zeta): on the stress
set self beats learned on every regime level (docs/MODEL_CARD.md).  Where the stream does not calibrate (nothing
modulates, or shorter than half a polarizer turn) the network runs on :data:`NET_FALLBACK_ZETA`, and the run's info
says so."""

NET_FALLBACK_ZETA = "auto"
"""The network's zeta where ``self`` cannot calibrate the stream (:func:`fallback_for`): ``auto`` takes its learned
zeta where the refused calibration still shows polarization (at least :data:`FALLBACK_LEARNED_PX` of the pixels
modulating above noise: a pane the planar fit cannot follow, e.g. under a camera pan) and zeta = 0 elsewhere
(``none``: nothing modulates, so the spikes cannot separate a reflection and a learned zeta invents one; T is the
whole light).  Measured (docs/MODEL_CARD.md): on the real recordings without a polarizer zeta = 0 is far better
(the REDS stream's 48 px crops: T within 30.3 dB of the TFP image against 20.3), on the validation groups whose
calibration fails under a camera pan (17-18 % of pixels modulating) the learned zeta is (T +2.7 and +5.2 dB)."""

FALLBACK_LEARNED_PX = 0.05
"""``auto`` fallback: share of pixels modulating above noise (``SelfCalResult.diagnostics["modulating_px"]``) from
which a refused stream runs on the learned zeta rather than zeta = 0 (the refusing groups measured: 0-1.7 % where
zeta = 0 is as good or better, 17-18 % where the learned zeta is better)."""

NET_FALLBACKS = ("auto", "none", "learned")
"""Choices of the network's fallback zeta (``--zeta-fallback``)."""


def fallback_for(result, fallback: str = NET_FALLBACK_ZETA) -> str:
    """The zeta source (``none`` or ``learned``) the network falls back to where the self-calibration ``result``
    (a :class:`reconstruct.pane.selfcal.SelfCalResult`, or None where none was possible) refused.
    """
    if fallback not in NET_FALLBACKS:
        raise ConfigError(f"zeta fallback {fallback!r}: choose one of {', '.join(NET_FALLBACKS)}")
    if fallback != "auto":
        return fallback
    px = None if result is None else (result.diagnostics or {}).get("modulating_px")
    return "learned" if (px is not None and px >= FALLBACK_LEARNED_PX) else "none"


class _ExternalZetaNet:
    """A :class:`reconstruct.net.network.PolSpikeNet` whose solver and refinement run on a zeta it did not estimate.

    Follows the model protocol of :func:`reconstruct.video.tiling.run_model_on_windows` and of the stream's feature cache;
    subclasses give :meth:`zeta` (B, N, H, W) for the window angles ``phi``.
    """

    def __init__(self, net):
        self.net = net
        self.cfg = net.cfg

    @property
    def pad_multiple(self) -> int:
        return int(getattr(self.net, "pad_multiple", 4))

    @property
    def cacheable(self) -> bool:
        return bool(getattr(self.net, "cacheable", False))

    @property
    def accepts_shifts(self) -> bool:
        """The network aligns its windows and takes their RIR ``shifts`` estimated once by the stream."""
        return bool(getattr(self.net, "accepts_shifts", False))

    def encode_obs(self, I, scale):
        return self.net.encode_obs(I, scale)

    def eval(self):
        self.net.eval()
        return self

    def parameters(self):
        return self.net.parameters()

    def zeta(self, I: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def __call__(self, I: torch.Tensor, phi: torch.Tensor, **kw):
        return self.net(I, phi, zeta_gt=self.zeta(I, phi), alpha=1.0, **kw)


class ZeroZetaNet(_ExternalZetaNet):
    """The network on zeta = 0 (source ``none``): the solver returns the whole light as T; tiles allowed."""

    def zeta(self, I: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
        return torch.zeros(I.shape, dtype=torch.float32, device=I.device)


class MapsZetaNet(_ExternalZetaNet):
    """The network on zeta from pane maps (source ``self``).

    Args:
        net: the network (eval mode).
        maps: per-pixel pane maps (H, W) of the stream's frames.
        span_rad: polarizer rotation during one Eq. (3) window (zeta is window-averaged).
    """

    stream_tile = 0

    def __init__(self, net, maps: PaneMaps, span_rad: float):
        super().__init__(net)
        self.maps, self.span_rad = maps, float(span_rad)

    def zeta(self, I: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
        H0, W0 = self.maps.phi_perp.shape
        H, W = I.shape[-2:]
        if H < H0 or W < W0 or H - H0 >= self.pad_multiple or W - W0 >= self.pad_multiple:
            raise ConfigError(f"--zeta self runs on whole frames: the pane maps are {W0}x{H0}, the network got {W}x{H} (set tile = 0)")
        Z = zeta_from_maps(self.maps, phi.detach().cpu().numpy().astype(np.float64), self.span_rad, dtype=torch.float32, device=I.device)  # paper Eq. (2)
        if (H, W) != (H0, W0):
            Z = F.pad(Z, (0, W - W0, 0, H - H0), mode="replicate")
        return Z


def build_net_zeta_model(net, zeta: str, source, *, group_dir=None, window_steps: int = 13, exposure: float | None = None, pane_n: float | None = None,
                         pane_model: str | None = None, fallback: str = NET_FALLBACK_ZETA, selfcal=None):
    """The network on zeta source ``zeta`` (:data:`NET_ZETA_SOURCES`) for this stream -> (model, info).

    ``pane_n`` / ``pane_model``: the pane's index and model where known (None or "auto": fitted where the data
    constrain them, else n 1.5 and a thin slab; :func:`reconstruct.pane.source.calibrate_stream`).
    ``selfcal``: self-calibration settings (a :class:`reconstruct.pane.selfcal.SelfCalConfig`, e.g. a known field of
    view; None: the defaults, with a stored group's scene fov).

    info = {"zeta": source used, "selfcal": summary or None}; ``self`` falls back to ``fallback``
    (:data:`NET_FALLBACK_ZETA`, or ``learned``) when the pane cannot be fitted (info["zeta"] says why).
    """
    if zeta not in NET_ZETA_SOURCES:
        raise ConfigError(f"--zeta {zeta!r} for the network: choose one of {', '.join(NET_ZETA_SOURCES)}")
    if fallback not in NET_FALLBACKS:
        raise ConfigError(f"zeta fallback {fallback!r}: choose one of {', '.join(NET_FALLBACKS)}")
    info: dict = {"zeta": zeta, "selfcal": None}
    if zeta == "learned":
        return net, info
    if zeta == "none":
        return ZeroZetaNet(net), info
    from reconstruct.pane.source import calibrate_stream
    from reconstruct.stream.sources import StreamTooShortError

    def fall(why: str, res=None):
        fb = fallback_for(res, fallback)
        info["zeta"] = f"{fb} (no self-calibration: {why})"
        return (ZeroZetaNet(net) if fb == "none" else net), info

    try:
        res = calibrate_stream(source, group_dir, window_steps, exposure, selfcal, pane_n, pane_model)
    except StreamTooShortError as e:  # e.g. a 15 ms .dat at 30 rev/s: nothing measured, as where nothing modulates
        log.warning("%s; the network runs on zeta %s", e, fallback_for(None, fallback))
        return fall("the stream is shorter than half a polarizer turn")
    info["selfcal"] = res.summary()
    if not res.ok:
        return fall(res.reason.split(":")[0], res)
    return MapsZetaNet(net, res.maps, source.window_span_rad(window_steps)), info
