"""Running a model on Eq. (3) windows: tiles, padding, autocast, cached per-frame features, stand-in inputs."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from polinfra.errors import ShapeError
from reconstruct.net.network import NetConfig, window_scale
from reconstruct.stream.window_inputs import MAP_INPUTS, WindowInputs, inputs_of

log = logging.getLogger(__name__)


def _pad4(x: torch.Tensor, multiple: int = 4) -> tuple[torch.Tensor, tuple[int, int]]:
    H, W = x.shape[-2:]
    ph, pw = (-H) % multiple, (-W) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (H, W)


_KEYS = ("T", "R", "T_base", "R_base")


def _multiple(model) -> int:
    return int(getattr(model, "pad_multiple", 4))


def _autocast(device: torch.device, precision: str):
    """bf16 autocast context for ``precision == "bfloat16"`` (CPU or CUDA), else a no-op."""
    if precision == "bfloat16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def auto_tile(model, device: str | torch.device = "cpu") -> int:
    """Default tile side: the model's own ``stream_tile`` when it has one (0 = whole frames, e.g. a
    physics model with per-frame-pixel zeta maps), else whole frames (0) for cacheable (v2)
    networks and on CUDA, 128 otherwise (v1 on CPU).
    """
    own = getattr(model, "stream_tile", None)
    if own is not None:
        return int(own)
    return 0 if (getattr(model, "cacheable", False) or torch.device(device).type == "cuda") else 128


def _net_cfg(model) -> NetConfig | None:
    """The model's network configuration, or None for another model (a solver, a stand-in): no blur reach, no shared scale."""
    return model.cfg if isinstance(model.cfg, NetConfig) else None


def _float32(dev: torch.device):
    return lambda a: torch.as_tensor(a, dtype=torch.float32, device=dev)


def run_model_on_windows(model, x: WindowInputs, device: str | torch.device = "cpu", tile: int = 128, margin: int = 16, *, precision: str = "float32", max_batch: int = 4,
                         zeta: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Network on windows ``x`` (I (B, N, H, W) radiance units, phi (B, N), and what the model reads beside them) -> dict of
    (B, H, W) T, R, T_base, R_base.

    ``model`` is any object with ``cfg.n_obs`` and ``cfg.inputs`` (:class:`reconstruct.stream.window_inputs.ReadsInputs`)
    that maps ``(I (B, N, H, W), phi (B, N), **inputs beside the windows)`` float32 tensors to an object with ``T``, ``R``,
    ``T_base``, ``R_base`` (B, H, W) tensors (optional ``pad_multiple``: H and W are replicate-padded to a multiple of it,
    default 4).  ``x`` must carry exactly what ``cfg.inputs`` names (:meth:`WindowInputs.check`, a ShapeError otherwise);
    its maps (I_mean, I_harm, I_wide) are padded and tiled like the frames, exposure and span_steps passed on.
    Frames larger than ``tile`` (> 0) are cut into tile x tile pieces with a ``margin``-pixel
    overlap whose border is discarded (bounded memory; the network is fully convolutional, the
    per-pixel solver is exact per tile); all tiles of all windows go through the model as one
    batch (at most ``max_batch`` tiles or windows per call: bounded memory, ~0.2 GB per v1 activation).  ``tile <= 0``: whole frames.  RIR, when
    enabled, aligns each tile separately, unless ``x.shifts`` gives the windows' shifts (:func:`window_shifts`): a model
    that ``accepts_shifts`` then gets them, every tile of a frame the frame's.  ``precision``: "float32" or "bfloat16" (autocast).
    ``zeta``: optional (B, N, H, W) mixing coefficients used instead of the network's own
    (``--zeta self``: the pane fitted to the stream); the network's solver and refinement then run
    on them (``model(I, phi, zeta_gt=zeta, alpha=1)``; its reliability weights stay learned).
    """
    dev = torch.device(device)
    x = x.check(model.cfg).map_arrays(_float32(dev))
    B, N, H, W = x.I.shape
    if zeta is not None and tuple(zeta.shape) != (B, N, H, W):
        raise ShapeError(f"zeta must have the windows' shape {(B, N, H, W)}; got {tuple(zeta.shape)}", actual_shape=tuple(zeta.shape), expected_shape=(B, N, H, W))
    mult = _multiple(model)
    # the per-pixel inputs as (B, C, H, W) stacks, padded and tiled alike
    maps = {"I": x.I, "zeta": None if zeta is None else _float32(dev)(zeta), "I_mean": None if x.I_mean is None else x.I_mean[:, None], "I_harm": x.I_harm, "I_wide": x.I_wide}
    maps = {k: v for k, v in maps.items() if v is not None}
    scalars = {k: v for k, v in x.extras().items() if k not in MAP_INPUTS}
    shifts = x.shifts if (x.shifts is not None and getattr(model, "accepts_shifts", False)) else None

    def call(m: dict[str, torch.Tensor], p: torch.Tensor, i: int, sh: torch.Tensor | None = None, **kw):
        s = slice(i, i + max_batch)
        if "zeta" in m:
            kw.update(zeta_gt=m["zeta"][s], alpha=1.0)
        if sh is not None:
            kw["shifts"] = sh[s]
        kw.update({k: m[k][s, 0] if k == "I_mean" else m[k][s] for k in MAP_INPUTS if k in m})
        return model(m["I"][s], p[s], **kw, **scalars)

    with torch.inference_mode(), _autocast(dev, precision):
        if tile <= 0 or (H <= tile and W <= tile):
            padded = {k: _pad4(v, mult)[0] for k, v in maps.items()}
            outs = [call(padded, x.phi, i, shifts) for i in range(0, B, max_batch)]
            return {k: torch.cat([getattr(o, k) for o in outs])[..., :H, :W].float().cpu().numpy() for k in _KEYS}
        net = _net_cfg(model)
        margin = max(margin, net.reach_px if net is not None else 0)  # a network that blurs its output needs that blur's radius inside the margin
        ts = tile + 2 * margin
        ts += (-ts) % mult
        ny, nx = -(-H // tile), -(-W // tile)
        # replicate-pad the frame so every tile with its margin has the same size ts x ts
        padding = (margin, nx * tile - W + ts - tile - margin, margin, ny * tile - H + ts - tile - margin)
        pos = [(ty * tile, tx * tile) for ty in range(ny) for tx in range(nx)]

        def cut(t):  # (B, C, H, W) -> the (B * tiles, C, ts, ts) tiles with their margins
            tp = F.pad(t, padding, mode="replicate")
            return torch.stack([tp[..., y0 : y0 + ts, x0 : x0 + ts] for (y0, x0) in pos], 1).reshape(B * len(pos), t.shape[1], ts, ts)

        tiles = {k: cut(v) for k, v in maps.items()}
        pt = x.phi.repeat_interleave(len(pos), 0)
        st = None if shifts is None else shifts.repeat_interleave(len(pos), 0)  # tiles of a frame share its shifts
        # a v2 network normalises brightness by the window's scale: give every tile the whole frame's
        sc = None
        if net is not None and net.arch == "v2":
            sc = window_scale(_pad4(x.I, mult)[0]).reshape(B).repeat_interleave(len(pos), 0)
        res = {k: [] for k in _KEYS}
        for i in range(0, tiles["I"].shape[0], max_batch):
            o = call(tiles, pt, i, st, **({} if sc is None else {"scale": sc[i : i + max_batch]}))
            for k in _KEYS:
                res[k].append(getattr(o, k)[:, margin : margin + tile, margin : margin + tile].float())
        out = {}
        for k in _KEYS:
            t = torch.cat(res[k]).reshape(B, ny, nx, tile, tile).permute(0, 1, 3, 2, 4).reshape(B, ny * tile, nx * tile)
            out[k] = t[:, :H, :W].cpu().numpy()
        return out


def window_shifts(model, I: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """RIR shifts (N, 2) float64 of one window ``I`` (N, H, W), ``phi`` (N,), estimated as ``model`` would estimate them
    itself (:func:`reconstruct.physics.rir.estimate_shifts` on the float32 frames replicate-padded to its
    ``pad_multiple``, as :func:`run_model_on_windows` pads them), so passing them (``WindowInputs.shifts``) changes
    nothing but the time.
    """
    from reconstruct.physics.rir import estimate_shifts

    It, _ = _pad4(torch.as_tensor(np.asarray(I), dtype=torch.float32)[None], _multiple(model))
    return estimate_shifts(It[0].double(), torch.as_tensor(np.asarray(phi), dtype=torch.float32).double()).numpy()


class FeatureCache:
    """Per-observation features of a v2 network kept across the overlapping windows of a stream.

    Consecutive output frames share N - 1 of their N observations; each Eq. (3) frame is
    encoded once (:meth:`reconstruct.net.network.PolSpikeNet.encode_obs`) at the window's scale
    (:func:`reconstruct.net.network.window_scale`, a power of two, so neighbouring windows almost
    always agree; a frame is re-encoded when it does not) and dropped once no later window uses it.
    Output is identical to running the model on each window (tests/recon/test_reconstruct_cli.py).
    """

    def __init__(self, model, device: str | torch.device = "cpu", precision: str = "float32"):
        self.model, self.device, self.precision = model, torch.device(device), precision
        self.store: dict[int, tuple[float, torch.Tensor, torch.Tensor]] = {}
        self.encoded = 0
        self.reused = 0

    def run(self, x: WindowInputs, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Windows ``x`` (I (B, N, H, W), phi (B, N), and what the model reads beside them, as :func:`run_model_on_windows`),
        frame indices idx (B, N) -> dict of (B, H, W) maps.
        """
        dev = self.device
        x = x.check(self.model.cfg).map_arrays(_float32(dev))
        B, N, H, W = x.I.shape
        mult = _multiple(self.model)
        xp, _ = _pad4(x.I, mult)
        with torch.inference_mode(), _autocast(dev, self.precision):
            sc = window_scale(xp).reshape(B)
            need: dict[int, tuple[int, int]] = {}
            for b in range(B):
                for k in range(N):
                    key = int(idx[b, k])
                    hit = self.store.get(key)
                    if (hit is None or hit[0] != float(sc[b])) and key not in need:
                        need[key] = (b, k)
            if need:
                keys = list(need)
                frames = torch.stack([xp[b, k] for b, k in need.values()])
                scales = torch.stack([sc[b] for b, _ in need.values()])
                f, g = self.model.encode_obs(frames, scales)
                for j, key in enumerate(keys):
                    self.store[key] = (float(scales[j]), f[j], g[j])
                self.encoded += len(keys)
            # a frame whose cached scale differs from this window's (rare) is encoded for this window only
            fs, gs = [], []
            for b in range(B):
                for k in range(N):
                    s_, f_, g_ = self.store[int(idx[b, k])]
                    if s_ != float(sc[b]):
                        f_, g_ = (t[0] for t in self.model.encode_obs(xp[b, k][None], sc[b][None]))
                        self.encoded += 1
                    fs.append(f_)
                    gs.append(g_)
            self.reused += B * N - len(need)
            mk = {k: _pad4(v, mult)[0] for k, v in (("I_harm", x.I_harm), ("I_wide", x.I_wide)) if v is not None}
            if x.I_mean is not None:
                mk["I_mean"] = _pad4(x.I_mean[:, None], mult)[0][:, 0]
            mk.update({k: v for k, v in x.extras().items() if k not in MAP_INPUTS})
            out = self.model(xp, x.phi, feats=(torch.stack(fs), torch.stack(gs)), **mk)
            res = {k: getattr(out, k)[..., :H, :W].float().cpu().numpy() for k in _KEYS}
        lo = int(idx[:, 0].max()) + 1  # windows advance: the next one starts after this batch's last first frame
        for key in [k for k in self.store if k < lo]:  # the next window starts one frame later
            del self.store[key]
        return res


def standin_inputs(model, I, phi) -> WindowInputs:
    """Windows ``I`` (B, N, H, W), ``phi`` (B, N), numpy or torch alike, with stand-ins for what ``model`` reads beside them
    (``I_mean``, ``I_harm``, ``I_wide``, and for a ``span_level`` network the exposure and span length), made up from
    the windows, for timing and FLOP counts (the content does not change the cost).
    """
    need = inputs_of(model)
    kw: dict[str, Any] = {}
    if "I_mean" in need:
        kw["I_mean"] = 0.5 * I.mean(1)
    if "I_harm" in need:
        shape = (I.shape[0], 2, *I.shape[2:])
        kw["I_harm"] = I.new_full(shape, 0.01) if torch.is_tensor(I) else np.full(shape, 0.01, np.float32)
    if "I_wide" in need:
        kw["I_wide"] = I
    if "exposure" in need:
        kw["exposure"] = 1.0
    if "span_steps" in need:
        kw["span_steps"] = 350
    return WindowInputs(I, phi, **kw)


def bench_full_network(model, height: int = 250, width: int = 400, frames: int = 2, device: str | torch.device = "cpu", tile: int = 128, seed: int = 0) -> dict[str, Any]:
    """Output frames per second of the full network (RWPS + both branches) at height x width.

    Random windows in radiance units (content does not change the cost);
    one warm-up pass, then ``frames`` timed single-frame passes.
    """
    g = np.random.default_rng(seed)
    N = model.cfg.n_obs
    I = (0.1 + 0.3 * g.random((1, N, height, width))).astype(np.float32)
    phi = (np.arange(N, dtype=np.float32) - N // 2)[None] * np.float32(math.radians(31.5))
    x = standin_inputs(model, I, phi)
    run_model_on_windows(model, x, device, tile)
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(frames):
        run_model_on_windows(model, x, device, tile)
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
    dt = (time.perf_counter() - t0) / frames
    return {"device": str(device), "height": height, "width": width, "tile": tile, "seconds_per_frame": dt, "frames_per_second": 1.0 / dt, "threads": torch.get_num_threads()}
