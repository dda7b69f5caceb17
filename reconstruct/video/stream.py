"""Streaming reconstruction of a spike stream into T and R video (paper Sec. 3, supp. Eq. (16)-(18)).

The stream is read chunk by chunk; paper Eq. (3) frames I(i) are aggregated
over ``window_steps`` steps centred where the polarizer has turned by
multiples of the angular stride (:func:`spike_sim.aggregate.frame_centres`);
every run of N = 2K+1 consecutive frames goes through the network, which
returns the centre frame's T and R.  Output cadence 360 f / stride
(10800 / 31.5 = 342.9 FPS at 30 rev/s).  Memory is bounded by one chunk plus
N frames: a long recording never needs to fit in memory.

Outputs in ``out_dir``: ``T.mp4``, ``R.mp4`` (H.264 via imageio-ffmpeg, at the
output cadence), ``preview.mp4`` (side by side: 2 x centre observation | T | R),
optional ``frames/T_NNNNNN.png`` or ``frames/NNNNNN.exr`` (linear T, R), and
``reconstruct.json`` (counts, fps, timing, NaN check, agreement with the plain
TFP image).  All files are written atomically.

Display mapping (MP4s and PNG frames): linear radiance x gain, clipped to [0, 1],
sRGB-like gamma 1/2.2, 8 bit.  One gain per video, chosen over all its frames so
that at most 0.1 % of its pixels clip (:data:`DISPLAY_CLIP_FRACTION`; T and R
each their own, the preview the smallest of T's, R's and the input's), so the
video does not flicker and highlights keep their detail; the frames are spooled
(float16, beside the outputs) until the gain is known.  EXR frames are linear
and unclipped (values above 1 stay).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import time
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from polinfra.atomic import atomic_path, ensure_dir, write_json
from polinfra.config import opt
from polinfra.errors import ConfigError, DataFormatError

from reconstruct.groups import SpikeMeanSums, spike_mean_steps, wide_window_steps, window_means

__all__ = ["DISPLAY_CLIP_FRACTION", "DisplayHistogram", "display_gain", "ReconstructConfig", "SpikeSource", "FeatureCache", "auto_tile", "dat_source", "group_source", "reconstruct_stream", "run_model_on_windows", "standin_inputs"]

log = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]


@dataclasses.dataclass(frozen=True)
class ReconstructConfig:
    """Options of :func:`reconstruct_stream`."""

    window_steps: int = opt(13, "Eq. (3) window in steps (13 = 0.65 ms at 20 kHz), odd", lo=1, hi=100001)
    stride_deg: float = opt(31.5, "polarizer rotation between output frames, degrees", lo=0.01, hi=360.0)
    exposure: float = opt(1.0, "thresholds per step per unit radiance (I radiance = spikes per step / exposure)", lo=1e-6, hi=1e6)
    batch: int = opt(2, "output frames per forward pass", lo=1, hi=1024)
    frames: str = opt("none", "also write frames: none | png | exr", choices=("none", "png", "exr"))
    video: bool = opt(True, "write T.mp4, R.mp4 and preview.mp4")
    chunk_steps: int = opt(2000, "spike steps read per chunk", lo=16, hi=10**8)
    max_frames: int = opt(0, "stop after this many output frames (0 = all)", lo=0, hi=10**9)
    tile: int = opt(-1, "tile side for bounded memory (0 = whole frames, -1 = auto: whole frames for v2 networks and on CUDA, 128 for v1 on CPU)", lo=-1, hi=1 << 16)
    precision: str = opt("float32", "float32 | bfloat16 (autocast; the solver stays float32)", choices=("float32", "bfloat16"))
    cache: bool = opt(True, "reuse per-observation features across overlapping windows (v2 networks, RIR off, whole frames)")


@dataclasses.dataclass
class SpikeSource:
    """A spike stream: chunk iterator, per-step polarizer angles and metadata.

    Attributes:
        chunks: callable returning an iterator of (first step, (n, H, W) uint8 spikes).
        phi_step_rad: (T,) mid-step polarizer angle, unwrapped, radians.
        height, width, rate_hz (steps per second), polarizer_rev_s, name.
        exposure: thresholds per step per unit radiance, when the source knows it.
    """

    chunks: Callable[[], Iterator[tuple[int, np.ndarray]]]
    phi_step_rad: np.ndarray
    height: int
    width: int
    rate_hz: float
    polarizer_rev_s: float
    name: str
    exposure: float | None = None

    def window_span_rad(self, window_steps: int) -> float:
        """Polarizer rotation during one Eq. (3) window of ``window_steps`` steps, radians (zeta is averaged over it)."""
        return 2 * math.pi * self.polarizer_rev_s * window_steps / self.rate_hz


def dat_source(path: str | os.PathLike, height: int, width: int, phi0_rad: float, rev_per_s: float, rate_hz: float = 20000.0, chunk_steps: int = 2000) -> SpikeSource:
    """A raw Vidar ``.dat`` with the polarizer calibrated as phi(t) = phi0 + 2 pi f t (t at mid-step)."""
    from spike_sim.vidar_dat import dat_frame_count, iter_dat

    n = dat_frame_count(path, height, width)
    t = (np.arange(n) + 0.5) / rate_hz
    phi = phi0_rad + 2 * math.pi * rev_per_s * t

    def chunks():
        s = 0
        for c in iter_dat(path, height, width, chunk_frames=chunk_steps):
            yield s, c
            s += c.shape[0]

    return SpikeSource(chunks, phi, height, width, rate_hz, rev_per_s, Path(path).name)


def array_source(spikes: np.ndarray, phi0_rad: float, rev_per_s: float, rate_hz: float = 20000.0, name: str = "array", chunk_steps: int = 2000) -> SpikeSource:
    """An in-memory (T, H, W) 0/1 stream (e.g. a real .npz capture) with a calibrated polarizer."""
    sp = np.asarray(spikes)
    if sp.ndim != 3:
        raise DataFormatError(f"spike array must be (T, H, W); got shape {sp.shape}")
    t = (np.arange(sp.shape[0]) + 0.5) / rate_hz
    phi = phi0_rad + 2 * math.pi * rev_per_s * t
    return SpikeSource(lambda: ((s, sp[s : s + chunk_steps]) for s in range(0, sp.shape[0], chunk_steps)), phi, sp.shape[1], sp.shape[2], rate_hz, rev_per_s, name)


def group_source(path: str | os.PathLike, chunk_steps: int = 2000) -> SpikeSource:
    """A stored spike group (``polspike simulate`` output); nominal (calibrated) angles, its exposure."""
    from spike_sim.store import open_group

    g = open_group(path)
    cfg = g.json_attr("config_json") or {}
    pol = g.json_attr("polarizer_json") or {}
    return SpikeSource(
        lambda: g.iter_chunks(chunk_steps), g.phi_nominal_rad, g.height, g.width, g.rate_hz, float(pol.get("rate_hz", 30.0)), Path(path).name,
        exposure=float(cfg["exposure"]) if "exposure" in cfg else None,
    )


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
    networks and on CUDA, 128 otherwise (v1 on CPU)."""
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
        from reconstruct.network import gaussian_radius

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
            from reconstruct.network import window_scale

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
    encoded once (:meth:`reconstruct.network.PolSpikeNet.encode_obs`) at the window's scale
    (:func:`reconstruct.network.window_scale`, a power of two, so neighbouring windows almost
    always agree; a frame is re-encoded when it does not) and dropped once no later window uses it.
    Output is identical to running the model on each window (tests/reconstruct/test_reconstruct_cli.py).
    """

    def __init__(self, model, device: str | torch.device = "cpu", precision: str = "float32"):
        self.model, self.device, self.precision = model, torch.device(device), precision
        self.store: dict[int, tuple[float, torch.Tensor, torch.Tensor]] = {}
        self.encoded = 0
        self.reused = 0

    def run(self, I: np.ndarray, phi: np.ndarray, idx: np.ndarray, I_mean: np.ndarray | None = None, I_harm: np.ndarray | None = None,
            I_wide: np.ndarray | None = None, exposure: float | None = None, span_steps: int | None = None) -> dict[str, np.ndarray]:
        """Windows I (B, N, H, W), phi (B, N), frame indices idx (B, N) -> dict of (B, H, W) maps (``I_mean``,
        ``I_harm``, ``I_wide``, ``exposure``, ``span_steps``: as :func:`run_model_on_windows`)."""
        from reconstruct.network import window_scale

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


def _to8(x: np.ndarray, gain: float) -> np.ndarray:
    return (np.clip(x * gain, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


DISPLAY_CLIP_FRACTION = 1e-3
"""At most this fraction of a video's pixels (all its frames together) reach white (module docstring)."""

DISPLAY_WHITE = 0.99
"""The clip quantile is mapped to this linear value (below 0.9957, the lowest that rounds to 255 after the 1/2.2 gamma)."""

_HIST_LO, _HIST_HI, _HIST_BINS = -6.0, 6.0, 12 * 1024  # log10 range and bins of the display histograms (0.23 % per bin)


class DisplayHistogram:
    """Streaming histogram of a video's pixel values on a log scale, for :func:`display_gain`.

    Values <= 10^-6 (also zero and negative ones, which display black) fall into the first bin;
    the upper edge of the bin holding the quantile bounds the exact quantile from above, so the
    gain chosen from it never clips more than the requested fraction."""

    def __init__(self):
        self.counts = np.zeros(_HIST_BINS + 1, np.int64)
        self.n = 0

    def add(self, x: np.ndarray) -> None:
        v = np.asarray(x, np.float64).ravel()
        v = v[np.isfinite(v)]
        lg = np.log10(np.maximum(v, 10.0**_HIST_LO))
        idx = np.clip(np.ceil((lg - _HIST_LO) / (_HIST_HI - _HIST_LO) * _HIST_BINS).astype(np.int64), 0, _HIST_BINS)
        self.counts += np.bincount(idx, minlength=_HIST_BINS + 1)
        self.n += v.size

    def upper_quantile(self, fraction_above: float) -> float:
        """A value q with at most ``fraction_above`` of the values above it (the bin's upper edge)."""
        if self.n == 0:
            return 1.0
        allowed = math.floor(fraction_above * self.n)
        above = self.n - np.cumsum(self.counts)  # values in bins after bin i
        i = int(np.argmax(above <= allowed))
        return float(10.0 ** (_HIST_LO + (_HIST_HI - _HIST_LO) * i / _HIST_BINS))


def display_gain(hist: DisplayHistogram, clip_fraction: float = DISPLAY_CLIP_FRACTION) -> float:
    """Display gain of one video: at most ``clip_fraction`` of its pixels map to white (8-bit 255)."""
    return DISPLAY_WHITE / max(hist.upper_quantile(clip_fraction), 1e-6)


class _Writers:
    """Output files of a stream.  EXR frames are written as they come (linear, unclipped); MP4s and
    PNG frames need the whole video's display gain, so their linear frames are spooled to a
    float16 file beside the outputs (bounded memory) and encoded at the end."""

    def __init__(self, out: Path, fps: float, cfg: ReconstructConfig, n_frames: int = 0, shape: tuple[int, int] = (0, 0)):
        self.out, self.fps, self.cfg = out, fps, cfg
        self.stack = contextlib.ExitStack()
        self.vw: dict[str, Any] = {}
        self.gain: dict[str, float] | None = None
        self.hist = {k: DisplayHistogram() for k in ("T", "R", "input")}
        self.n = 0
        self.display = cfg.video or cfg.frames == "png"
        self.spool = None
        self.spool_path = out / ".display_spool.npy"
        if self.display and n_frames > 0:
            self.spool = np.lib.format.open_memmap(self.spool_path, mode="w+", dtype=np.float16, shape=(n_frames, 3, *shape))

    def __enter__(self):
        return self

    def _open(self, name: str):
        import imageio.v2 as iio

        tmp = self.stack.enter_context(atomic_path(self.out / f"{name}.mp4"))
        w = iio.get_writer(str(tmp), format="FFMPEG", mode="I", fps=self.fps, codec="libx264", quality=8, macro_block_size=1, pixelformat="yuv420p", ffmpeg_log_level="error")
        self.stack.callback(w.close)  # closes before the atomic rename (LIFO)
        return w

    def write(self, Ic: np.ndarray, T: np.ndarray, R: np.ndarray) -> None:
        if self.display:
            if self.spool is None or self.n >= self.spool.shape[0]:
                raise RuntimeError("display spool overflow: more frames than announced")  # pragma: no cover - internal invariant
            lim = float(np.finfo(np.float16).max)
            for j, a in enumerate((2 * Ic, T, R)):
                self.spool[self.n, j] = np.clip(a, -lim, lim)
            self.hist["input"].add(2 * Ic)
            self.hist["T"].add(T)
            self.hist["R"].add(R)
        if self.cfg.frames == "exr":
            from polinfra.exr import write_exr

            d = ensure_dir(self.out / "frames")
            write_exr(d / f"{self.n:06d}.exr", {"T": T.astype(np.float32), "R": R.astype(np.float32)}, {"units": "linear radiance, 1.0 = brightest layer"})
        self.n += 1

    def finish(self) -> None:
        """Choose the display gains over all frames and encode the MP4s / PNG frames."""
        if not self.display or self.n == 0:
            return
        gT, gR, gI = (display_gain(self.hist[k]) for k in ("T", "R", "input"))
        self.gain = {"T": gT, "R": gR, "preview": min(gT, gR, gI)}
        even = lambda a: a[: a.shape[0] // 2 * 2, : a.shape[1] // 2 * 2]  # noqa: E731  (yuv420p needs even sizes)
        gP = self.gain["preview"]
        for i in range(self.n):
            I2, T, R = (np.asarray(self.spool[i, j], np.float32) for j in range(3))
            if self.cfg.video:
                for name, img in (("T", _to8(T, gT)), ("R", _to8(R, gR)), ("preview", np.concatenate([_to8(I2, gP), _to8(T, gP), _to8(R, gP)], 1))):
                    if name not in self.vw:
                        self.vw[name] = self._open(name)
                    self.vw[name].append_data(even(img))
            if self.cfg.frames == "png":
                import imageio.v3 as iio3

                d = ensure_dir(self.out / "frames")
                for name, img in (("T", _to8(T, gT)), ("R", _to8(R, gR))):
                    with atomic_path(d / f"{name}_{i:06d}.png") as tmp:
                        iio3.imwrite(tmp, img, extension=".png")

    def __exit__(self, *exc):
        try:
            if exc[0] is None:
                self.finish()
            self.stack.__exit__(*exc)
        finally:
            if self.spool is not None:
                del self.spool
                self.spool = None
            with contextlib.suppress(FileNotFoundError):
                self.spool_path.unlink()


def reconstruct_stream(
    source: SpikeSource,
    model,
    out_dir: str | os.PathLike,
    cfg: ReconstructConfig = ReconstructConfig(),
    *,
    device: str | torch.device = "cpu",
    progress: ProgressFn | None = None,
    meta: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Reconstruct every output frame of ``source`` with ``model``; write videos/frames.

    Args:
        source: spike stream and calibrated polarizer angles.
        model: :class:`reconstruct.network.PolSpikeNet` (eval mode), or any object following the
            protocol of :func:`run_model_on_windows` (``cfg.n_obs``; ``model(I, phi)`` -> ``T``, ``R``,
            ``T_base``, ``R_base``), e.g. a physics-only reconstructor.  Models with
            ``cacheable = True`` must also provide ``encode_obs(frames, scales)`` and accept
            ``feats=`` (:class:`FeatureCache`); others run window by window.
        out_dir: output directory (created).
        cfg: options; ``exposure`` is overridden by the source's own when it has one.
        device: torch device.
        progress: optional (done, total) callback over output frames.
        meta: extra entries for the summary (e.g. how the exposure was found).

    Returns:
        the summary written to ``reconstruct.json``.
    """
    from spike_sim.aggregate import AggregateConfig, frame_centres, output_fps

    out = ensure_dir(out_dir)
    N = model.cfg.n_obs
    K = N // 2
    agg = AggregateConfig(window_steps=cfg.window_steps, stride_deg=cfg.stride_deg, n_obs=N)
    centres, phi_i = frame_centres(source.phi_step_rad, agg)
    n_out = max(0, centres.size - 2 * K)
    if cfg.max_frames:
        n_out = min(n_out, cfg.max_frames)
    if n_out == 0:
        raise ConfigError(
            f"{source.name}: {source.phi_step_rad.size} steps give {centres.size} Eq. (3) frames, fewer than the N = {N} a window needs; "
            f"use a longer recording, a smaller --stride-deg or the true --rev-per-s"
        )
    exposure = source.exposure if source.exposure is not None else cfg.exposure
    fps = output_fps(source.polarizer_rev_s, cfg.stride_deg) if source.polarizer_rev_s > 0 else 1.0
    t0 = time.perf_counter()
    frames_I: deque[np.ndarray] = deque(maxlen=N)
    wide = bool(getattr(model.cfg, "wide_input", False))
    n_total = source.phi_step_rad.size
    widths = (cfg.window_steps, wide_window_steps(source.rate_hz, source.polarizer_rev_s, cfg.stride_deg)) if wide else (cfg.window_steps,)
    reach = max(w // 2 for w in widths)  # steps a frame needs on each side of its centre
    frames_W: deque[np.ndarray] = deque(maxlen=N)
    pending: list[tuple[np.ndarray, np.ndarray]] = []
    stats = {"nan_frames": 0, "tfp_corr": [], "tfp_psnr": []}
    done = 0
    next_c = 0  # index into centres of the next Eq. (3) frame to aggregate
    tail = np.zeros((0, source.height, source.width), np.uint8)
    tail_start = 0

    mean_steps = spike_mean_steps(source.rate_hz) if getattr(model.cfg, "use_mean", False) else 0
    use_harm = bool(getattr(model.cfg, "harm_input", False))
    span_kw = {"exposure": exposure, "span_steps": mean_steps} if getattr(model.cfg, "span_level", False) else {}
    prefix = SpikeMeanSums(centres, mean_steps, source.phi_step_rad.size, (source.height, source.width), source.phi_step_rad if use_harm else None) if mean_steps else None
    tile = auto_tile(model, device) if cfg.tile < 0 else cfg.tile
    cache = FeatureCache(model, device, cfg.precision) if (cfg.cache and tile == 0 and getattr(model, "cacheable", False)) else None

    def flush(writers: _Writers) -> None:
        nonlocal done
        if not pending:
            return
        I = np.stack([p[0] for p in pending])
        ph = np.stack([p[1] for p in pending])
        im = np.stack([p[3] for p in pending]) if prefix is not None else None
        ih = np.stack([p[4] for p in pending]) if use_harm else None
        iw = np.stack([p[5] for p in pending]) if wide else None
        if cache is not None:
            res = cache.run(I, ph, np.stack([p[2] for p in pending]), I_mean=im, I_harm=ih, I_wide=iw, **span_kw)
        else:
            res = run_model_on_windows(model, I, ph, device, tile, precision=cfg.precision, I_mean=im, I_harm=ih, I_wide=iw, **span_kw)
        for b in range(I.shape[0]):
            T, R = res["T"][b], res["R"][b]
            if not (np.isfinite(T).all() and np.isfinite(R).all()):
                stats["nan_frames"] += 1
                T, R = np.nan_to_num(T), np.nan_to_num(R)
            tfp = 2.0 * I[b].mean(0)
            if tfp.std() > 0 and T.std() > 0:
                stats["tfp_corr"].append(float(np.corrcoef(T.ravel(), tfp.ravel())[0, 1]))
            writers.write(I[b, K], T, R)
            done += 1
            if progress is not None:
                progress(done, n_out)
        pending.clear()

    with _Writers(out, fps, cfg, n_out, (source.height, source.width)) as writers:
        for s0, chunk in source.chunks():
            buf = np.concatenate([tail, chunk]) if tail.size else chunk
            b0 = tail_start if tail.size else s0
            b1 = b0 + buf.shape[0]
            if prefix is not None:
                prefix.feed(s0, chunk)
            while next_c < centres.size and min(int(centres[next_c]) + reach, n_total - 1) < b1 and done + len(pending) < n_out:
                # Eq. (3) in radiance units, and the wide window clipped to the stream, as a stored group's
                got = window_means(lambda a, b: buf[a - b0 : b - b0], [int(centres[next_c])], widths, n_total, exposure)
                frames_I.append(got[0][0])
                if wide:
                    frames_W.append(got[1][0])
                next_c += 1
                if len(frames_I) == N:
                    j = next_c - 1 - K
                    hj = prefix.harmonic(j, exposure) if use_harm else None  # before mean(j), which frees older sums
                    pending.append((np.stack(frames_I), phi_i[next_c - N : next_c], np.arange(next_c - N, next_c), prefix.mean(j, exposure) if prefix is not None else None, hj,
                                    np.stack(frames_W) if wide else None))
                    if len(pending) >= cfg.batch:
                        flush(writers)
            if done + len(pending) >= n_out:
                break
            keep = b1 - max(0, int(centres[next_c]) - reach) if next_c < centres.size else 0
            keep = max(0, min(keep, buf.shape[0]))
            tail = buf[buf.shape[0] - keep :] if keep else np.zeros((0, source.height, source.width), np.uint8)
            tail_start = b1 - keep
        flush(writers)
    secs = time.perf_counter() - t0
    summary = {
        "input": source.name,
        "frames": done,
        "fps": fps,
        "size": [source.height, source.width],
        "exposure": exposure,
        "window_steps": cfg.window_steps,
        "stride_deg": cfg.stride_deg,
        "n_obs": N,
        "nan_frames": stats["nan_frames"],
        "tfp_corr_mean": float(np.mean(stats["tfp_corr"])) if stats["tfp_corr"] else None,
        "seconds": secs,
        "frames_per_second_processed": done / secs if secs > 0 else None,
        "outputs": sorted(p.name for p in out.iterdir() if p.is_file() and p.suffix == ".mp4"),
        "display_gain": writers.gain,
        "tile": tile,
        "precision": cfg.precision,
        "feature_cache": None if cache is None else {"encoded_frames": cache.encoded, "reused": cache.reused},
        **(meta or {}),
    }
    write_json(out / "reconstruct.json", summary)
    return summary


def standin_inputs(model, I) -> dict[str, Any]:
    """Keyword inputs of the long span a network reads (``I_mean``, ``I_harm``, ``I_wide``, and for a ``span_level``
    network the exposure and span length), made up from its windows
    ``I`` (B, N, H, W), numpy or torch alike, for timing and FLOP counts (the content does not change the cost)."""
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
