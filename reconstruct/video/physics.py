"""Physics-only streaming reconstruction: a solver (ls, ridge, irls, rwps) on a zeta source, no network.

:class:`PhysicsModel` follows the model protocol of :func:`reconstruct.video.tiling.run_model_on_windows`
(``cfg.n_obs``; ``model(I (B, N, H, W), phi (B, N))`` -> ``T``, ``R``, ``T_base``, ``R_base``),
so :func:`reconstruct.video.stream.reconstruct_stream` streams it exactly as it streams the network.  Its
zeta maps are per full-frame pixel, so it asks for whole frames (``stream_tile = 0``) and no
padding (``pad_multiple = 1``).  Per window: RIR (optional; shifts estimated on the frames, applied
to frames and zeta alike, as the evaluation harness does), then :func:`reconstruct.physics.solvers.solve`.

zeta sources (:func:`build_physics_model`):

* ``self``: the pane fitted to the first ``span_s`` of the stream itself
  (:func:`calibrate_source`, :mod:`reconstruct.pane.selfcal`); where nothing modulates, the
  learned zeta of a checkpoint instead (a warning says so);
* ``physics``: a group store's incidence-angle and phi_perp maps with a calibrated index and
  pane model (as ``polspike evaluate --zeta physics``); a raw .dat has no pane description;
* ``gt``: a group store's true pane maps (R_perp, R_par, phi_perp), at the calibrated angles;
* ``learned``: zeta and reliability weights of a checkpoint's parameter branch
  (:func:`reconstruct.net.learned_zeta.zeta_learned`).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch

from polinfra.errors import ConfigError
from reconstruct.net.learned_zeta import zeta_learned
from reconstruct.pane.selfcal import SelfCalConfig
from reconstruct.pane.source import calibrate_stream
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, SOLVERS, SolverConfig, solve
from reconstruct.physics.span import anchor_to_mean, zbar_of
from reconstruct.physics.zeta import PaneMaps, zeta_from_maps

__all__ = ["PHYSICS_METHODS", "STREAM_ZETA_SOURCES", "PhysicsModel", "PhysicsOutput", "group_pane_maps", "build_physics_model"]

log = logging.getLogger(__name__)

PHYSICS_METHODS = SOLVERS
"""Solver names usable for a physics-only stream."""

STREAM_ZETA_SOURCES = ("self", "learned", "physics", "gt")
"""zeta sources of a physics-only stream (module docstring)."""


@dataclasses.dataclass
class PhysicsOutput:
    """What :class:`PhysicsModel` returns: T, R (B, H, W); the solver output is also the base."""

    T: torch.Tensor
    R: torch.Tensor
    T_base: torch.Tensor
    R_base: torch.Tensor


@dataclasses.dataclass(frozen=True)
class _Cfg:
    n_obs: int
    use_mean: bool = False  # True: the stream passes the long spike mean (anchor = "mean")

    @property
    def inputs(self) -> frozenset[str]:
        """What the model reads beside its windows (:class:`reconstruct.stream.window_inputs.WindowInputs`)."""
        return frozenset({"I_mean"}) if self.use_mean else frozenset()


class PhysicsModel:
    """A solver on a zeta source, callable like the network (module docstring).

    Args:
        method: one of :data:`PHYSICS_METHODS`.
        n_obs: observations per output frame N (odd).
        maps: per-pixel pane maps (H, W) for ``self`` / ``physics`` / ``gt``, or None with ``learned_model``.
        span_rad: polarizer rotation during one Eq. (3) window (zeta is window-averaged).
        learned_model: a network whose parameter branch gives zeta and w (``learned``), or None.
        solver_cfg: solver parameters.
        rir: align each window (reflection-invariant registration) before solving.
        anchor: "mean" = anchor each output to the 17.5 ms spike mean the stream passes
            (:func:`reconstruct.physics.span.anchor_to_mean`: the level from the long mean, the difference
            R - T from the solver); "none" = the solver output as is.
    """

    stream_tile = 0  # zeta maps are per full-frame pixel: whole frames, never tiles
    pad_multiple = 1

    def __init__(self, method: str, n_obs: int = 7, maps: PaneMaps | None = None, span_rad: float = 0.0, learned_model=None,
                 solver_cfg: SolverConfig | None = None, rir: bool = True, anchor: str = "none"):
        if method not in PHYSICS_METHODS:
            raise ConfigError(f"unknown physics method {method!r}; choose one of {list(PHYSICS_METHODS)}")
        if n_obs < 1 or n_obs % 2 == 0:
            raise ConfigError(f"n_obs = {n_obs} must be odd (N = 2K + 1)")
        if (maps is None) == (learned_model is None):
            raise ConfigError("a physics model needs exactly one zeta source: pane maps or a learned model")
        if anchor not in ("none", "mean"):
            raise ConfigError(f"anchor {anchor!r}: choose none or mean")
        self.cfg = _Cfg(int(n_obs), anchor == "mean")
        self.method = method
        self.maps = maps
        self.span_rad = float(span_rad)
        self.learned_model = learned_model
        self.solver_cfg = solver_cfg if solver_cfg is not None else PHYSICS_SOLVER_CONFIG  # adaptive RWPS, fitted on training groups
        self.rir = bool(rir)

    def eval(self) -> PhysicsModel:
        return self

    @property
    def accepts_shifts(self) -> bool:
        """RIR on: the windows' ``shifts`` (B, N, 2) estimated once by the stream replace the model's own estimate."""
        return self.rir

    def __call__(self, I: torch.Tensor, phi: torch.Tensor, I_mean: torch.Tensor | None = None, shifts: torch.Tensor | None = None) -> PhysicsOutput:
        I = I.float()
        phi = phi.float()
        B, N, H, W = I.shape
        if N != self.cfg.n_obs:
            raise ConfigError(f"the physics model takes N = {self.cfg.n_obs} observations per window; got {N}")
        if self.maps is not None and tuple(self.maps.phi_perp.shape) != (H, W):
            raise ConfigError(f"pane maps are {self.maps.phi_perp.shape[1]}x{self.maps.phi_perp.shape[0]} but frames are {W}x{H}")
        Z = None
        if self.maps is not None:
            Z = zeta_from_maps(self.maps, phi.cpu().numpy().astype(np.float64), self.span_rad, dtype=torch.float32, device=I.device)  # paper Eq. (2)
        if self.rir and N > 1:
            from reconstruct.physics.rir import estimate_shifts, warp

            sh = (torch.stack([estimate_shifts(I[b], phi[b]) for b in range(B)]) if shifts is None else torch.as_tensor(shifts)).to(I.dtype)
            I = warp(I, sh)
            Z = None if Z is None else warp(Z, sh)
        w = None
        if Z is None:
            Z, w_learned = zeta_learned(self.learned_model, I, phi)
            w = w_learned if self.method == "rwps" else None
        r = solve(self.method, Z, I, weights=w, config=self.solver_cfg)
        T, R = r.T, r.R
        if self.cfg.use_mean:
            if I_mean is None:
                raise ConfigError("anchor = mean needs the stream's long spike mean (reconstruct_stream passes it)")
            T, R = anchor_to_mean(T, R, I_mean.to(T.dtype), zbar_of(Z, phi).to(T.dtype))
        T, R = T.clamp_min(0.0), R.clamp_min(0.0)
        return PhysicsOutput(T=T, R=R, T_base=T, R_base=R)


def group_pane_maps(group_dir, zeta: str, n: float = 1.5, model: str = "single") -> PaneMaps:
    """Pane maps of a stored group for ``gt`` (its true R_perp, R_par, phi_perp) or ``physics`` (its theta and
    phi_perp maps, Fresnel reflectances of the calibrated index and pane model).
    """
    from spike_sim.store import open_group

    with open_group(group_dir) as g:
        mp = g.maps()
    if zeta == "gt":
        if not {"R_perp", "R_par", "phi_perp"} <= set(mp):
            raise ConfigError(f"{group_dir}: no stored pane maps for --zeta gt; use --zeta self")
        return PaneMaps(R_perp=mp["R_perp"], R_par=mp["R_par"], phi_perp=mp["phi_perp"])
    if not {"theta", "phi_perp"} <= set(mp):
        raise ConfigError(f"{group_dir}: no incidence-angle / phi_perp maps for --zeta physics; use --zeta self")
    from polphysics.fresnel import pane_coefficients

    co = pane_coefficients(mp["theta"], n, model=model)
    return PaneMaps(R_perp=co["R_perp"], R_par=co["R_par"], phi_perp=mp["phi_perp"])


def calibrated_pane_maps(path, height: int, width: int) -> PaneMaps:
    """The pane maps of ``polspike calibrate-pane`` or of a self-calibrating ``polspike reconstruct`` (its output
    directory, or that directory's maps.exr) for a stream of ``height`` x ``width``: R_perp, R_par and phi_perp as fitted (geometry, index and model are in them).

    Raises:
        ConfigError: no maps there (calibrate-pane refused that recording: its report.json says why), channels
            missing, or maps of another frame size (one line, what to fix).
    """
    from polinfra.errors import DataFormatError
    from polinfra.exr import read_exr

    p = Path(path)
    if not p.exists():
        raise ConfigError(f"--pane {path}: no such directory or file; give a calibrate-pane (or self-calibrated reconstruct) output directory or its maps.exr")
    f = p / "maps.exr" if p.is_dir() else p
    if not f.is_file():
        why = (" (calibrate-pane wrote no maps: its report.json says why it did not calibrate)" if (f.parent / "report.json").is_file()
               else " (that reconstruction did not self-calibrate: its zeta.json or physics.json says why)" if (f.parent / "reconstruct.json").is_file() else "")
        raise ConfigError(f"--pane {path}: no {f.name} there{why}; give a calibrate-pane (or self-calibrated reconstruct) output directory or its maps.exr")
    try:
        mp = read_exr(f, ["R_perp", "R_par", "phi_perp"])
    except DataFormatError as e:
        raise ConfigError(f"--pane {path}: {e} (calibrate-pane's maps.exr has R_perp, R_par and phi_perp)") from None
    if mp["phi_perp"].shape != (height, width):
        h, w = mp["phi_perp"].shape
        raise ConfigError(f"--pane {path}: maps of {w} x {h} for a stream of {width} x {height}; calibrate a recording of this camera's frame size")
    if not all(np.all(np.isfinite(v)) for v in mp.values()):
        raise ConfigError(f"--pane {path}: the maps hold NaN or Inf; calibrate the recording again")
    return PaneMaps(R_perp=mp["R_perp"], R_par=mp["R_par"], phi_perp=mp["phi_perp"])


def build_physics_model(
    method: str,
    zeta: str,
    source,
    *,
    group_dir=None,
    n_obs: int = 7,
    window_steps: int = 13,
    exposure: float | None = None,
    rir: bool = True,
    load_learned=None,
    selfcal: SelfCalConfig | None = None,
    pane_n: float | None = None,
    pane_model: str | None = None,
    anchor: str = "none",
) -> tuple[PhysicsModel, dict]:
    """A :class:`PhysicsModel` for ``method`` on zeta source ``zeta`` for this stream (``anchor``: as the model's).

    Args:
        method: solver name.
        zeta: one of :data:`STREAM_ZETA_SOURCES`.
        source: the :class:`reconstruct.stream.sources.SpikeSource`.
        group_dir: the stored group's directory (``physics`` and ``gt`` need it), or None for a raw .dat.
        n_obs, window_steps, exposure: window geometry (as the stream's).
        rir: RIR alignment per window.
        load_learned: callable () -> network, for ``learned`` and for the ``self`` fallback.
        selfcal: self-calibration settings (``self``); its field of view defaults to the group's scene.
        pane_n, pane_model: the pane's index and model where known. ``physics``: default 1.5 and single; ``self``:
            default fitted where the data constrain them (:func:`calibrate_stream`); ``pane_model`` "auto" = not given.

    Returns:
        (model, info) with info = {"zeta": source used, "selfcal": summary or None}.

    Raises:
        ConfigError: a source this input cannot provide (one line).
    """
    if zeta not in STREAM_ZETA_SOURCES:
        raise ConfigError(f"unknown zeta source {zeta!r}; choose one of {list(STREAM_ZETA_SOURCES)}")
    if zeta in ("gt", "physics") and group_dir is None:
        raise ConfigError(f"--zeta {zeta} needs a stored group (its pane maps); a raw .dat has none: use --zeta self or learned")
    span = source.window_span_rad(window_steps)
    info: dict = {"zeta": zeta, "selfcal": None}
    if zeta == "learned":
        return PhysicsModel(method, n_obs, learned_model=_need(load_learned), rir=rir, anchor=anchor), info
    if zeta in ("gt", "physics"):
        pm = "single" if pane_model in (None, "auto") else pane_model
        return PhysicsModel(method, n_obs, maps=group_pane_maps(group_dir, zeta, 1.5 if pane_n is None else pane_n, pm), span_rad=span, rir=rir, anchor=anchor), info
    res = calibrate_stream(source, group_dir, window_steps, exposure, selfcal, pane_n, pane_model)
    info["selfcal"] = res.summary()
    if res.ok:
        return PhysicsModel(method, n_obs, maps=res.maps, span_rad=span, rir=rir, anchor=anchor), info
    info["zeta"] = "learned (no self-calibration: " + res.reason.split(":")[0] + ")"
    return PhysicsModel(method, n_obs, learned_model=_need(load_learned), rir=rir, anchor=anchor), info


def _need(load_learned):
    if load_learned is None:
        raise ConfigError("the learned zeta needs a checkpoint (--weights)")
    return load_learned()
