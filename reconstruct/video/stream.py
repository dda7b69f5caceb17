"""Streaming reconstruction of a spike stream into T and R video (paper Sec. 3, supp. Eq. (16)-(18)).

The stream is read chunk by chunk; paper Eq. (3) frames I(i) are aggregated
over ``window_steps`` steps centred where the polarizer has turned by
multiples of the angular stride (:func:`spike_sim.aggregate.frame_centres`);
every run of N = 2K+1 consecutive frames goes through the network, which
returns the centre frame's T and R.  Output cadence 360 f / stride
(10800 / 31.5 = 342.9 FPS at 30 rev/s).  Memory is bounded by one chunk plus
N frames: a long recording never needs to fit in memory.

Outputs in ``out_dir``: ``T.mp4``, ``R.mp4`` (H.264 via imageio-ffmpeg, at the
output cadence), ``preview.mp4`` (side by side: 2 x centre observation | T | R; ``preview``),
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
import logging
import os
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polinfra.atomic import atomic_path, ensure_dir, write_json
from polinfra.config import opt
from polinfra.errors import ConfigError
from reconstruct.physics.rir import ChainedRir
from reconstruct.stream.display import DisplayHistogram, _to8, display_gain
from reconstruct.stream.groups import SpikeMeanSums, spike_mean_steps, wide_window_steps, window_means
from reconstruct.stream.motion_span import SPAN_PARTS, auto_span_shifts, compensate_part_sums, part_shifts_from_windows
from reconstruct.stream.sources import SpikeSource
from reconstruct.stream.window_inputs import WindowInputs, inputs_of
from reconstruct.video.tiling import FeatureCache, auto_tile, run_model_on_windows, window_shifts

__all__ = ["ReconstructConfig", "reconstruct_stream", "cpu_threads"]

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
    preview: bool = opt(True, "with video: also preview.mp4 (input | T | R side by side)")
    chunk_steps: int = opt(2000, "spike steps read per chunk", lo=16, hi=10**8)
    max_frames: int = opt(0, "stop after this many output frames (0 = all)", lo=0, hi=10**9)
    tile: int = opt(-1, "tile side for bounded memory (0 = whole frames, -1 = auto: whole frames for v2 networks and on CUDA, 128 for v1 on CPU)", lo=-1, hi=1 << 16)
    precision: str = opt("float32", "float32 | bfloat16 (autocast; the solver stays float32)", choices=("float32", "bfloat16"))
    threads: int = opt(0, "torch threads on the CPU (0 = torch's setting as it is; cpu_threads() gives the idle cores)", lo=0, hi=4096)
    cache: bool = opt(True, "reuse per-observation features across overlapping windows (v2 networks, RIR off, whole frames)")
    span: str = opt("plain", "the long span a network reads: plain (every spike of its 17.5 ms summed) | compensated (cut into 7 parts registered onto the centre part before they are summed, reconstruct.stream.motion_span: a panning camera no longer smears it) | rir (the same parts moved by the 7 windows' RIR shifts interpolated in time: no registration of its own) | auto (per window, reconstruct.stream.motion_span.auto_span_shifts: rir where the windows register and their velocity smears the span by span_auto_px or more, plain where they register and it smears less, the parts' own registration where the windows do not register and it shows a smear)", choices=("plain", "compensated", "rir", "auto"))
    span_auto_px: float = opt(1.0, "span auto: the plain span's smear in pixels (the windows' fitted speed times the span's steps) from which the rir span is used", lo=0.0, hi=1e6)
    rir: str = opt("window", "how the windows' RIR shifts are estimated, once per window for the model and the span: window (reconstruct.physics.rir.estimate_shifts on each window: 6 masked phase correlations and a Gauss-Newton refinement, what the network does itself) | chained (reconstruct.physics.rir.ChainedRir: each frame registered once onto the previous one, the window's shifts their running sums)", choices=("window", "chained"))




@dataclasses.dataclass(frozen=True)
class _Pending:
    """A window waiting for its batch: the window's inputs without the batch axis, and the indices of its N Eq. (3) frames."""

    window: WindowInputs
    frames: np.ndarray


class _Writers:
    """Output files of a stream.  EXR frames are written as they come (linear, unclipped); MP4s and
    PNG frames need the whole video's display gain, so their linear frames are spooled to a
    float16 file beside the outputs (bounded memory) and encoded at the end.
    """

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
                prev = np.concatenate([_to8(I2, gP), _to8(T, gP), _to8(R, gP)], 1) if self.cfg.preview else None
                for name, img in (("T", _to8(T, gT)), ("R", _to8(R, gR)), ("preview", prev)):
                    if img is None:
                        continue
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


def cpu_threads(requested: int = 0) -> int:
    """The torch threads of a CPU run: ``requested`` when > 0, else the cores idle now (core count minus the 1-minute load
    average, rounded), at least 1.  On a busy machine more threads than idle cores wait on each other at every
    parallel operation (measured in docs/realtime.md).
    """
    if requested > 0:
        return int(requested)
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:  # no load average on this platform: all cores
        load = 0.0
    return max(1, min(cores, int(round(cores - load))))


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
        model: :class:`reconstruct.net.network.PolSpikeNet` (eval mode), or any object following the
            protocol of :func:`run_model_on_windows` (``cfg.n_obs``, ``cfg.inputs``; ``model(I, phi, **inputs)`` -> ``T``,
            ``R``, ``T_base``, ``R_base``), e.g. a physics-only reconstructor.  The stream builds what ``cfg.inputs`` names
            (the long spike mean, its harmonic, the wide windows, the exposure and span length) beside each window.  Models with
            ``cacheable = True`` must also provide ``encode_obs(frames, scales)`` and accept
            ``feats=`` (:class:`FeatureCache`); others run window by window.
        out_dir: output directory (created).
        cfg: options; ``exposure`` is overridden by the source's own when it has one.
        device: torch device.
        progress: optional (done, total) callback over output frames.
        meta: extra entries for the summary (e.g. how the exposure was found).

    On the CPU the stream runs on ``cfg.threads`` torch threads when > 0 (e.g. :func:`cpu_threads`), restored after;
    the number used is the summary's ``torch_threads``.

    Returns:
        the summary written to ``reconstruct.json``.
    """
    if torch.device(device).type != "cpu":
        return _reconstruct_stream(source, model, out_dir, cfg, device=device, progress=progress, meta=meta)
    before = torch.get_num_threads()
    n = cfg.threads if cfg.threads > 0 else before
    torch.set_num_threads(n)
    try:
        return _reconstruct_stream(source, model, out_dir, cfg, device=device, progress=progress, meta={**(meta or {}), "torch_threads": n})
    finally:
        torch.set_num_threads(before)


def _reconstruct_stream(source: SpikeSource, model, out_dir, cfg: ReconstructConfig, *, device, progress: ProgressFn | None, meta: dict[str, Any] | None) -> dict[str, Any]:
    """:func:`reconstruct_stream` on the threads it set."""
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
    t0, p0 = time.perf_counter(), time.process_time()
    frames_I: deque[np.ndarray] = deque(maxlen=N)
    need = inputs_of(model)
    wide = "I_wide" in need
    n_total = source.phi_step_rad.size
    widths = (cfg.window_steps, wide_window_steps(source.rate_hz, source.polarizer_rev_s, cfg.stride_deg)) if wide else (cfg.window_steps,)
    reach = max(w // 2 for w in widths)  # steps a frame needs on each side of its centre
    frames_W: deque[np.ndarray] = deque(maxlen=N)
    pending: list[_Pending] = []
    stats = {"nan_frames": 0, "tfp_corr": [], "tfp_psnr": []}
    done = 0
    next_c = 0  # index into centres of the next Eq. (3) frame to aggregate
    tail = np.zeros((0, source.height, source.width), np.uint8)
    tail_start = 0

    mean_steps = spike_mean_steps(source.rate_hz) if "I_mean" in need else 0
    use_harm = "I_harm" in need
    span_kw = {"exposure": exposure if "exposure" in need else None, "span_steps": mean_steps if "span_steps" in need else None}
    comp = cfg.span in ("compensated", "rir", "auto") and mean_steps > 0
    # the windows' RIR shifts, estimated once per window for the model (which would otherwise estimate them itself) and the span
    aligns = bool(getattr(model, "accepts_shifts", False))
    if cfg.rir == "chained" and not aligns and getattr(model.cfg, "use_rir", False):
        raise ConfigError("--rir chained: this model estimates its own shifts (a symmetry ensemble does, per mirrored window); use --rir window")
    want_shifts = aligns or (comp and cfg.span in ("rir", "auto"))
    chained = ChainedRir() if cfg.rir == "chained" else None
    cpu = {"rir": 0.0, "span": 0.0, "model": 0.0}  # process CPU seconds per stage
    n_auto = {"plain": 0, "rir": 0, "parts": 0}
    prefix = SpikeMeanSums(centres, mean_steps, source.phi_step_rad.size, (source.height, source.width), source.phi_step_rad if (use_harm or comp) else None,
                           n_sub=SPAN_PARTS if comp else 1) if mean_steps else None
    tile = auto_tile(model, device) if cfg.tile < 0 else cfg.tile
    cache = FeatureCache(model, device, cfg.precision) if (cfg.cache and tile == 0 and getattr(model, "cacheable", False)) else None

    def flush(writers: _Writers) -> None:
        nonlocal done
        if not pending:
            return
        x = WindowInputs.batch([p.window for p in pending], **span_kw)
        I = x.I
        c0 = time.process_time()
        if cache is not None:
            res = cache.run(x, np.stack([p.frames for p in pending]))
        else:
            res = run_model_on_windows(model, x, device, tile, precision=cfg.precision)
        cpu["model"] += time.process_time() - c0
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
                    Iw, pw, idx = np.stack(frames_I), phi_i[next_c - N : next_c], np.arange(next_c - N, next_c)
                    wsh = None
                    if want_shifts:
                        c0 = time.process_time()
                        wsh = window_shifts(model, Iw, pw) if chained is None else chained.window_shifts(torch.from_numpy(Iw), torch.from_numpy(np.asarray(pw, np.float64)), idx).numpy()
                        cpu["rir"] += time.process_time() - c0
                    if comp:  # the span's parts registered onto its centre part, then summed
                        c0 = time.process_time()
                        sums, parts = prefix.part_sums(j)
                        sh = None
                        if cfg.span == "rir":  # the windows' own registration, interpolated to the parts' times
                            sh = part_shifts_from_windows(wsh, centres[next_c - N : next_c], parts)
                        elif cfg.span == "auto":  # the windows' velocity, the parts' own where the windows do not register, or plain
                            spw = float(exposure * Iw.mean() * cfg.window_steps)  # spikes per pixel per window
                            sh, how = auto_span_shifts(wsh, centres[next_c - N : next_c], sums, parts, source.phi_step_rad, spw, cfg.span_auto_px)
                            n_auto[how] += 1
                        mj, hj, _ = compensate_part_sums(sums, parts, source.phi_step_rad, exposure, use_harm, shifts=sh)
                        prefix.release(j)
                        cpu["span"] += time.process_time() - c0
                    else:
                        hj = prefix.harmonic(j, exposure) if use_harm else None  # before mean(j), which frees older sums
                        mj = prefix.mean(j, exposure) if prefix is not None else None
                    window = WindowInputs(Iw, pw, mj, hj, np.stack(frames_W) if wide else None, shifts=wsh if aligns else None)
                    pending.append(_Pending(window, idx))
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
        "rir_shifts": (cfg.rir if want_shifts else None),
        "span_auto": n_auto if cfg.span == "auto" else None,
        "cpu_s_per_frame": {**{k: v / done for k, v in cpu.items()}, "total": (time.process_time() - p0) / done} if done else None,
        **(meta or {}),
    }
    write_json(out / "reconstruct.json", summary)
    return summary

