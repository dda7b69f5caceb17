"""Checkpoints of :class:`reconstruct.net.network.PolSpikeNet`: save, load, validate.

A checkpoint is a ``torch.save`` dict (loaded with ``weights_only=True``: plain
data only, no pickled code) with keys

``format`` ("polspike-ckpt/1"), ``net`` and ``solver`` (plain config dicts),
``state_dict``, ``param_count``, and for training checkpoints ``train``
(config dict), ``optimizer``, ``step``, ``metrics``.

Any problem (missing file, not a checkpoint, wrong format, config or tensors
that do not fit the network) raises :class:`polinfra.errors.CheckpointError`
with one line saying what and what to do.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import torch

from polinfra.atomic import atomic_path
from polinfra.config import from_dict, to_dict
from polinfra.errors import CheckpointError, ConfigError
from reconstruct.net.network import GAIN_SPREAD_AUTO, GAIN_SPREAD_ESTIMATE, NetConfig, PolSpikeNet
from reconstruct.physics.solvers import SolverConfig

__all__ = ["CKPT_FORMAT", "DEFAULT_WEIGHTS", "V1_WEIGHTS", "V2_WEIGHTS", "V2_MEAN_WEIGHTS", "V3_WEIGHTS", "V4_WEIGHTS", "V5_WEIGHTS", "V6_WEIGHTS", "V7_WEIGHTS", "save_checkpoint", "read_checkpoint", "load_model", "export_weights", "set_stream_gain_spread", "gain_spread_option", "floor_overrides", "FLOOR_ANCHORS", "FAST_WEIGHTS", "NAMED_WEIGHTS", "resolve_weights"]

CKPT_FORMAT = "polspike-ckpt/1"
V1_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v1.pt"
"""The first shipped checkpoint (v1 architecture), kept for comparison."""
V2_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v2.pt"
"""The v2 checkpoint trained on the weak-reflection paper_v1 data (issue 19), the default before issue 16."""
V2_MEAN_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v2_mean.pt"
"""v2 with the long spike mean as a refinement input (issue 16, first round), the default before v3."""
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v12.pt"
"""The shipped checkpoint (see ``docs/MODEL_CARD.md``): v12, v7 fine-tuned with RIR in the loop on camera motion, sensor
randomisation and bright light, its T decoder kept at v7's."""
V7_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v7.pt"
"""v7: v6 with the difference R - T moved toward the first harmonic of the whole long span of spikes where that span
identifies it (``span_level``; on an external zeta only); the default before v12."""
FAST_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_fast.pt"
"""The real-time checkpoint (``--weights fast``, docs/realtime.md): the default's design with about a quarter of its
channels, trained with RIR on camera motion and sensor randomisation; for ``polspike reconstruct --weights fast --fast
--compile --bf16 --rir chained``."""
NAMED_WEIGHTS = {"default": DEFAULT_WEIGHTS, "fast": FAST_WEIGHTS}
"""Shipped checkpoints by the name ``--weights`` takes in place of a path."""


def resolve_weights(weights: str | os.PathLike | None) -> Path:
    """The checkpoint file of ``--weights``: a path, a name of :data:`NAMED_WEIGHTS` (where no file of that name
    exists), or None / "" (the default).
    """
    if weights is None or str(weights) == "":
        return DEFAULT_WEIGHTS
    p = Path(weights)
    return p if p.exists() else NAMED_WEIGHTS.get(str(weights), p)


V6_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v6.pt"
"""The default before v7 (issue 16, fifth round): v5's weights with T's and R's low frequencies taken from the solver on
the wide windows (every spike between the N windows' centres; ``t_level_px``, ``r_level_from = wide``); v7's levels too."""
V5_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v5.pt"
"""The default before v6 (issue 16, fourth round): v4 whose R decoder alone was fine-tuned with the R term weighted by
the reflected share (every other weight frozen, so T is exactly v4's); v6's weights."""
V4_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v4.pt"
"""The default before v5 (issue 16, third round): the v3 network (the refinement correcting the physics anchored to the
long spike mean, ``base = anchored``, trained on paper.toml for its own and an external ``--zeta self`` zeta) trained
further with a structure (SSIM) term and picked on a validation split apart from the test groups; v5's T path."""
V3_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "polspike_v3.pt"
"""The default before v4 (issue 16, second round), kept for comparison."""


def save_checkpoint(path: str | os.PathLike, model: PolSpikeNet, *, extra: dict[str, Any] | None = None) -> Path:
    """Write ``model`` (and optional training state in ``extra``) atomically to ``path``."""
    data: dict[str, Any] = {
        "format": CKPT_FORMAT,
        "net": to_dict(model.cfg),
        "solver": to_dict(model.solver_cfg_in),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "param_count": sum(p.numel() for p in model.parameters()),  # all of them, also those a run froze (trainable)
    }
    if extra:
        data.update(extra)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return Path(path)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load and validate the raw checkpoint dict (CPU tensors); ``path`` may name a shipped one (:func:`resolve_weights`)."""
    p = resolve_weights(path)
    if not p.is_file():
        raise CheckpointError(f"checkpoint not found: {p}; pass --weights PATH (or {' / '.join(NAMED_WEIGHTS)}) or train one with `polspike train`")
    try:
        data = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt files
        raise CheckpointError(f"{p} is not a readable checkpoint ({type(exc).__name__}: {str(exc).splitlines()[0][:120]}); re-download or retrain it") from None
    if not isinstance(data, dict) or data.get("format") != CKPT_FORMAT:
        seen = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise CheckpointError(f"{p}: format {seen!r} is not {CKPT_FORMAT!r}; this file is not a polspike checkpoint")
    for key in ("net", "solver", "state_dict"):
        if key not in data:
            raise CheckpointError(f"{p}: checkpoint lacks {key!r}; it is truncated or from another tool")
    return data


def load_model(path: str | os.PathLike = DEFAULT_WEIGHTS, device: str | torch.device = "cpu", **overrides: Any) -> tuple[PolSpikeNet, dict[str, Any]]:
    """Build the network recorded in a checkpoint and load its weights.

    Args:
        path: checkpoint file.
        device: torch device for the model.
        overrides: NetConfig fields to change at load time (ablation-neutral
            ones such as ``use_rir``); architecture fields must match.

    Returns:
        (model in eval mode, raw checkpoint dict).
    """
    data = read_checkpoint(path)
    try:
        net_d = dict(data["net"])
        net_d.setdefault("arch", "v1")  # written before NetConfig.arch existed: the v1 network
        net = from_dict(NetConfig, {**net_d, **overrides}, where=f"{path} [net]")
        solver = from_dict(SolverConfig, data["solver"], where=f"{path} [solver]")
    except ConfigError as exc:
        raise CheckpointError(f"incompatible checkpoint: {exc}") from None
    model = PolSpikeNet(net, solver)
    try:
        model.load_state_dict(data["state_dict"], strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not fit the network ({str(exc).splitlines()[0][:160]}); the checkpoint is from an incompatible version") from None
    return model.to(device).eval(), data


def export_weights(src: str | os.PathLike, dest: str | os.PathLike, *, note: dict[str, Any] | None = None) -> Path:
    """Copy a training checkpoint without its optimizer state (a shippable few-MB file)."""
    data = read_checkpoint(src)
    data.pop("optimizer", None)
    if note:
        data["note"] = note
    with atomic_path(dest) as tmp:
        torch.save(data, tmp)
    return Path(dest)


def set_stream_gain_spread(model: torch.nn.Module, spread: float) -> torch.nn.Module:
    """Tell every :class:`PolSpikeNet` in ``model`` (an ensemble too) the per-pixel gain spread of the stream it is
    about to read (:func:`spike_sim.config.pixel_gain_spread` of a stored simulation; 0 where it is unknown).  The data
    floor allows for it where ``NetConfig.floor_gain_spread`` is -1 (``--gain-spread auto``); a value >= 0 there wins.
    """
    if spread < 0 or spread > 0.5:
        raise ValueError(f"gain spread {spread}: a relative sd in [0, 0.5]")
    for m in model.modules():
        if isinstance(m, PolSpikeNet):
            m.stream_gain_spread = float(spread)
    return model


def gain_spread_option(text: str | None, flag: str = "--gain-spread") -> float | None:
    """``NetConfig.floor_gain_spread`` from a command-line value: None or "" -> None (the checkpoint's), "auto" -> -1
    (the stream's own sensor), else a relative sd in [0, 0.5]; a :class:`ConfigError` naming ``flag`` otherwise.
    """
    if text is None or text == "":
        return None
    if text == "auto":
        return GAIN_SPREAD_AUTO
    if text == "estimate":
        return GAIN_SPREAD_ESTIMATE
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not 0.0 <= v <= 0.5:
        raise ConfigError(f"{flag} {text!r}: auto (the stream's own sensor), estimate (from the data) or a relative sd in [0, 0.5] (0.0735 for the simulator's default sensor)")
    return v


FLOOR_ANCHORS: tuple[str, ...] = tuple(next(f for f in dataclasses.fields(NetConfig) if f.name == "floor_anchor").metadata["choices"])
"""Values of ``NetConfig.floor_anchor`` (``--floor-anchor``)."""


def floor_overrides(floor: bool = True, anchor: str | None = None, gain_spread: str | None = None, layers: bool | None = None) -> dict[str, Any]:
    """The :class:`NetConfig` overrides of the data floor from command-line values (None or "": the checkpoint's):
    ``floor`` off, or its fallback ``anchor``, its ``gain_spread`` (:func:`gain_spread_option`) and its layer checks;
    a :class:`ConfigError` naming the flag for a bad ``anchor`` or ``gain_spread``.
    """
    if anchor and anchor not in FLOOR_ANCHORS:
        raise ConfigError(f"--floor-anchor {anchor!r}: use one of {', '.join(FLOOR_ANCHORS)}")
    gs = gain_spread_option(gain_spread)
    if not floor:
        return {"floor": False}
    out: dict[str, Any] = {} if not anchor else {"floor_anchor": anchor}
    if layers is not None:
        out["floor_layers"] = layers
    if gs is not None:
        out["floor_gain_spread"] = gs
    return out
