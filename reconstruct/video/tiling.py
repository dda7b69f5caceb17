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

from polinfra.errors import ConfigError

log = logging.getLogger(__name__)


def _pad4(x: torch.Tensor, multiple: int = 4) -> tuple[torch.Tensor, tuple[int, int]]:
    H, W = x.shape[-2:]
    ph, pw = (-H) % multiple, (-W) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (H, W)


_KEYS = ("T", "R", "T_base", "R_base")


def _given(**kw) -> dict:
    """The keywords that are not None (optional inputs passed on to a model only when a caller has them)."""
    return {k: v for k, v in kw.items() if v is not None}


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


def run_model_on_windows(model, I: np.ndarray, phi: np.ndarray, device: str | torch.device = "cpu", tile: int = 128, margin: int = 16, *, precision: str = "float32", max_batch: int = 4,
                         zeta: np.ndarray | None = None, I_mean: np.ndarray | None = None, I_harm: np.ndarray | None = None,
                         I_wide: np.ndarray | None = None, exposure: float | None = None, span_steps: int | None = None) -> dict[str, np.ndarray]:
    """Network on windows I (B, N, H, W) radiance units, phi (B, N) -> dict of (B, H, W) T, R, T_base, R_base.

    ``model`` is any object with ``cfg.n_obs`` that maps ``(I (B, N, H, W), phi (B, N))`` float32
    tensors to an object with ``T``, ``R``, ``T_base``, ``R_base`` (B, H, W) tensors (optional
    ``pad_multiple``: H and W are replicate-padded to a multiple of it, default 4).
    Frames larger than ``tile`` (> 0) are cut into tile x tile pieces with a ``margin``-pixel
    overlap whose border is discarded (bounded memory; the network is fully convolutional, the
    per-pixel solver is exact per tile); all tiles of all windows go through the model as one
    batch (at most ``max_batch`` tiles or windows per call: bounded memory, ~0.2 GB per v1 activation).  ``tile <= 0``: whole frames.  RIR, when
    enabled, aligns each tile separately.  ``precision``: "float32" or "bfloat16" (autocast).
    ``zeta``: optional (B, N, H, W) mixing coefficients used instead of the network's own
    (``--zeta self``: the pane fitted to the stream); the network's solver and refinement then run
    on them (``model(I, phi, zeta_gt=zeta, alpha=1)``; its reliability weights stay learned).
    ``I_mean``: optional (B, H, W) long spike mean around each window's centre frame, passed on as
    ``model(..., I_mean=...)`` (required by a ``use_mean`` network), tiled like the frames; ``I_harm``: likewise
    the (B, 2, H, W) first harmonic of the same spans (a ``use_harm`` network); ``I_wide``: the (B, N, H, W)
    observations over the wide window (a network with ``cfg.wide_input``), tiled like the frames; ``exposure``,
    ``span_steps``: the stream's exposure and I_mean's span in steps (a ``span_level`` network; passed on when given).
    """
    dev = torch.device(device)
    x = torch.as_tensor(I, dtype=torch.float32, device=dev)
    p = torch.as_tensor(phi, dtype=torch.float32, device=dev)
    B, N, H, W = x.shape
    z = None if zeta is None else torch.as_tensor(zeta, dtype=torch.float32, device=dev)
    if z is not None and z.shape != x.shape:
        raise ConfigError(f"zeta must have the windows' shape {tuple(x.shape)}; got {tuple(z.shape)}")
    mult = _multiple(model)

    m_ = None if I_mean is None else torch.as_tensor(I_mean, dtype=torch.float32, device=dev)[:, None]
    if m_ is not None and m_.shape != (B, 1, H, W):
        raise ConfigError(f"I_mean must be (B, H, W) = {(B, H, W)}; got {tuple(I_mean.shape)}")

    h_ = None if I_harm is None else torch.as_tensor(I_harm, dtype=torch.float32, device=dev)
    if h_ is not None and h_.shape != (B, 2, H, W):
        raise ConfigError(f"I_harm must be (B, 2, H, W) = {(B, 2, H, W)}; got {tuple(h_.shape)}")

    w_ = None if I_wide is None else torch.as_tensor(I_wide, dtype=torch.float32, device=dev)
    if w_ is not None and w_.shape != x.shape:
        raise ConfigError(f"I_wide must have the windows' shape {tuple(x.shape)}; got {tuple(w_.shape)}")

    span_kw = _given(exposure=exposure, span_steps=span_steps)

    def zkw(zz, i, mm=None, hh=None, ww=None):
        kw = {} if zz is None else {"zeta_gt": zz[i : i + max_batch], "alpha": 1.0}
        kw.update(span_kw)
        if ww is not None:
            kw["I_wide"] = ww[i : i + max_batch]
        if mm is not None:
            kw["I_mean"] = mm[i : i + max_batch, 0]
        if hh is not None:
            kw["I_harm"] = hh[i : i + max_batch]
        return kw

    with torch.inference_mode(), _autocast(dev, precision):
        if tile <= 0 or (H <= tile and W <= tile):
            xp, zp, mp, hp, wp = (None if t is None else _pad4(t, mult)[0] for t in (x, z, m_, h_, w_))
            outs = [model(xp[i : i + max_batch], p[i : i + max_batch], **zkw(zp, i, mp, hp, wp)) for i in range(0, B, max_batch)]
            return {k: torch.cat([getattr(o, k) for o in outs])[..., :H, :W].float().cpu().numpy() for k in _KEYS}
        # a network that blurs its output (r_level_px: R's level from the base) needs that blur's radius inside the margin
        from reconstruct.net.network import gaussian_radius

        mc = getattr(model, "cfg", None)
        margin = max(margin, *(gaussian_radius(float(getattr(mc, k, 0.0) or 0.0)) for k in ("r_level_px", "t_level_px")),
                     gaussian_radius(float(mc.span_level_px)) if getattr(mc, "span_level", False) else 0)
        ts = tile + 2 * margin
        ts += (-ts) % mult
        ny, nx = -(-H // tile), -(-W // tile)
        # replicate-pad the frame so every tile with its margin has the same size ts x ts
        padding = (margin, nx * tile - W + ts - tile - margin, margin, ny * tile - H + ts - tile - margin)
        pos = [(ty * tile, tx * tile) for ty in range(ny) for tx in range(nx)]
        def cut(t):  # (B, C, H, W) -> the (B * tiles, C, ts, ts) tiles with their margins; None stays None
            if t is None:
                return None
            tp = F.pad(t, padding, mode="replicate")
            return torch.stack([tp[..., y0 : y0 + ts, x0 : x0 + ts] for (y0, x0) in pos], 1).reshape(B * len(pos), t.shape[1], ts, ts)

        tiles, ztiles, mtiles, htiles, wtiles = (cut(t) for t in (x, z, m_, h_, w_))
        pt = p.repeat_interleave(len(pos), 0)
        # a v2 network normalises brightness by the window's scale: give every tile the whole frame's
        kw = {}
        if getattr(getattr(model, "cfg", None), "arch", "v1") == "v2":
            from reconstruct.net.network import window_scale

            kw = {"scale": window_scale(_pad4(x, mult)[0]).reshape(B).repeat_interleave(len(pos), 0)}
        res = {k: [] for k in _KEYS}
        for i in range(0, tiles.shape[0], max_batch):
            o = model(tiles[i : i + max_batch], pt[i : i + max_batch], **{k: v[i : i + max_batch] for k, v in kw.items()}, **zkw(ztiles, i, mtiles, htiles, wtiles))
            for k in _KEYS:
                res[k].append(getattr(o, k)[:, margin : margin + tile, margin : margin + tile].float())
        out = {}
        for k in _KEYS:
            t = torch.cat(res[k]).reshape(B, ny, nx, tile, tile).permute(0, 1, 3, 2, 4).reshape(B, ny * tile, nx * tile)
            out[k] = t[:, :H, :W].cpu().numpy()
        return out


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

    def run(self, I: np.ndarray, phi: np.ndarray, idx: np.ndarray, I_mean: np.ndarray | None = None, I_harm: np.ndarray | None = None,
            I_wide: np.ndarray | None = None, exposure: float | None = None, span_steps: int | None = None) -> dict[str, np.ndarray]:
        """Windows I (B, N, H, W), phi (B, N), frame indices idx (B, N) -> dict of (B, H, W) maps (``I_mean``,
        ``I_harm``, ``I_wide``, ``exposure``, ``span_steps``: as :func:`run_model_on_windows`).
        """
        from reconstruct.net.network import window_scale

        dev = self.device
        x = torch.as_tensor(I, dtype=torch.float32, device=dev)
        p = torch.as_tensor(phi, dtype=torch.float32, device=dev)
        B, N, H, W = x.shape
        xp, _ = _pad4(x, _multiple(self.model))
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
            mk = {k: _pad4(torch.as_tensor(v, dtype=torch.float32, device=dev), _multiple(self.model))[0] for k, v in _given(I_harm=I_harm, I_wide=I_wide).items()}
            if I_mean is not None:
                mk["I_mean"] = _pad4(torch.as_tensor(I_mean, dtype=torch.float32, device=dev)[:, None], _multiple(self.model))[0][:, 0]
            mk.update(_given(exposure=exposure, span_steps=span_steps))
            out = self.model(xp, p, feats=(torch.stack(fs), torch.stack(gs)), **mk)
            res = {k: getattr(out, k)[..., :H, :W].float().cpu().numpy() for k in _KEYS}
        lo = int(idx[:, 0].max()) + 1  # windows advance: the next one starts after this batch's last first frame
        for key in [k for k in self.store if k < lo]:  # the next window starts one frame later
            del self.store[key]
        return res


def standin_inputs(model, I) -> dict[str, Any]:
    """Keyword inputs of the long span a network reads (``I_mean``, ``I_harm``, ``I_wide``, and for a ``span_level``
    network the exposure and span length), made up from its windows
    ``I`` (B, N, H, W), numpy or torch alike, for timing and FLOP counts (the content does not change the cost).
    """
    cfg = getattr(model, "cfg", None)
    kw: dict[str, Any] = {}
    if getattr(cfg, "use_mean", False):
        kw["I_mean"] = 0.5 * I.mean(1)
    if getattr(cfg, "harm_input", False):
        shape = (I.shape[0], 2, *I.shape[2:])
        kw["I_harm"] = I.new_full(shape, 0.01) if torch.is_tensor(I) else np.full(shape, 0.01, np.float32)
    if getattr(cfg, "wide_input", False):
        kw["I_wide"] = I
    if getattr(cfg, "span_level", False):
        kw.update(exposure=1.0, span_steps=350)
    return kw


def bench_full_network(model, height: int = 250, width: int = 400, frames: int = 2, device: str | torch.device = "cpu", tile: int = 128, seed: int = 0) -> dict[str, Any]:
    """Output frames per second of the full network (RWPS + both branches) at height x width.

    Random windows in radiance units (content does not change the cost);
    one warm-up pass, then ``frames`` timed single-frame passes.
    """
    g = np.random.default_rng(seed)
    N = model.cfg.n_obs
    I = (0.1 + 0.3 * g.random((1, N, height, width))).astype(np.float32)
    phi = (np.arange(N, dtype=np.float32) - N // 2)[None] * np.float32(math.radians(31.5))
    kw = standin_inputs(model, I)
    run_model_on_windows(model, I, phi, device, tile, **kw)
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(frames):
        run_model_on_windows(model, I, phi, device, tile, **kw)
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
    dt = (time.perf_counter() - t0) / frames
    return {"device": str(device), "height": height, "width": width, "tile": tile, "seconds_per_frame": dt, "frames_per_second": 1.0 / dt, "threads": torch.get_num_threads()}
