"""The real-time physics stream: packed reads, a fused solver, background encoding; also on a growing .dat.

:func:`reconstruct_live` gives the output of :func:`reconstruct.video.stream.reconstruct_stream` for a
:class:`reconstruct.video.physics.PhysicsModel` on pane maps (the same Eq. (3) frames, centres, zeta and solver;
linear T and R equal to float32 rounding, tested), by a path that keeps up with the camera:

* Eq. (3) counts summed on the packed bits straight into radiance units (:mod:`reconstruct.stream.packed`), reading
  only the steps inside windows;
* zeta (paper Eq. (2)) once per Eq. (3) frame, not once per window it appears in;
* ``ls`` without RIR as one fused pass per pixel on zeta's closed form, no zeta frames
  (:func:`reconstruct.physics.fused.ls_fused_harmonic`); ``rwps`` with the
  physics constants as fused passes with the RIR shifts applied while reading
  (:func:`reconstruct.physics.fused_rwps.rwps_fused`); other solvers (or ``solver = "torch"``) through the torch
  solver on batches of windows; RIR by the chained whole-frame alignment
  (:class:`reconstruct.physics.rir.ChainedRir`: each frame registered once onto the one before; the shifts
  differ from :func:`reconstruct.physics.rir.estimate_shifts`'s, the quality change is measured in
  docs/realtime.md); torch on one thread;
* the fused ``rwps`` as two stages (``pipeline``): the solve and write of a window on a solve thread while the
  stream's thread reads, aggregates and registers the next frame (made beside the ring, copied in once the pixel pass
  before is done: the same numbers as one thread); that frame made, the stream's thread takes the pixel-pass rows of
  the window in hand the solve thread has not reached (``share_pixels``,
  :class:`reconstruct.physics.fused_rwps.RwpsWindow`; the same numbers);
* display gains from the running histogram of the first ``gain_frames`` frames (the whole video when it is
  shorter; a longer one keeps those gains: the display can be shown live), 8-bit conversion by a table and
  encoding on a background thread (H.264 by default, ``video_codec``; the 8-bit images by one numba pass,
  :func:`reconstruct.video.display8.to8_frames`; CRF by ``video_quality``); T.mp4 and R.mp4, the side-by-side
  preview.mp4 only with ``preview`` (it holds three times the pixels of T: more encoder CPU than T and R together).

With ``follow`` the .dat may still be growing: frames are made as their last step arrives, and the latency (the
time from the arrival of a window's last step to its output) is measured per frame.  ``stop`` (an event, set by
Ctrl-C) ends the run between frames; every output file is still completed (atomic writes).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from polinfra.atomic import atomic_path, ensure_dir, write_json
from polinfra.config import opt
from polinfra.errors import ConfigError
from reconstruct.stream.display import DisplayHistogram, display_gain
from reconstruct.stream.window_inputs import inputs_of

__all__ = ["LiveConfig", "reconstruct_live", "StageTimes", "to8_table"]

log = logging.getLogger(__name__)


VIDEO_CRF = {"fast": 23, "high": 10}
"""x264 constant rate factor of the live videos per ``LiveConfig.video_quality`` (imageio's quality 8 = CRF 10)."""


@dataclasses.dataclass(frozen=True)
class LiveConfig:
    """Options of :func:`reconstruct_live`."""

    window_steps: int = opt(13, "Eq. (3) window in steps, odd", lo=1, hi=255)
    stride_deg: float = opt(31.5, "polarizer rotation between output frames, degrees", lo=0.01, hi=360.0)
    batch: int = opt(8, "windows per torch solver call (solvers other than plain ls, or RIR on)", lo=1, hi=1024)
    frames: str = opt("none", "also write frames: none | png | exr", choices=("none", "png", "exr"))
    video: bool = opt(True, "write T.mp4 and R.mp4 (and preview.mp4 with preview)")
    preview: bool = opt(False, "also write preview.mp4 (input | T | R side by side: three times the pixels of T, more x264 CPU than T and R together)")
    max_frames: int = opt(0, "stop after this many output frames (0 = all)", lo=0, hi=10**9)
    gain_frames: int = opt(64, "display gains from the histogram of the first this many frames, then kept", lo=1, hi=10**9)
    solver: str = opt("fused", "fused numba kernels where one exists (ls, physics rwps; RIR shifts applied inside) or torch (the streaming path's solver)", choices=("fused", "torch"))
    preset: str = opt("ultrafast", "x264 preset of the videos", choices=("ultrafast", "superfast", "veryfast", "faster", "fast", "medium"))
    video_quality: str = opt("fast", "videos: fast (x264 CRF 23, one encoder thread per video) | high (CRF 10, the streaming path's level; more encoder CPU)", choices=tuple(VIDEO_CRF))
    video_codec: str = opt("h264", "videos: h264 (T.mp4, R.mp4: yuv420p, plays everywhere) | h264-gray (4:0:0 .mp4: less encoder CPU, not for browsers) | y4m (raw 8-bit .y4m: no encoder, 100 kB per 400 x 250 frame)", choices=("h264", "h264-gray", "y4m"))
    threads: int = opt(1, "numba threads of the fused RWPS passes (bands of rows in parallel; the same numbers; 0 = all cores)", lo=0, hi=256)
    rir_finest: int = opt(1, "RIR: finest level of the chained fit, 1 = full resolution, 2 = 2 x 2 blocks (cheaper; error measured in docs/realtime.md)", lo=1, hi=2)
    poll_s: float = opt(0.01, "follow: wait between looks at the growing file, seconds", lo=0.0, hi=10.0)
    idle_s: float = opt(5.0, "follow: stop when the file has not grown for this long, seconds (0 = only Ctrl-C stops)", lo=0.0, hi=1e6)
    pipeline: bool = opt(True, "fused rwps: the solve and write of a window on a second thread while the stream's thread reads, aggregates and registers the next frame (the same numbers)")
    share_pixels: bool = opt(True, "fused rwps with the pipeline and one numba thread: the stream's thread, its frame made, takes chunks of rows of the window's pixel pass the solve thread has not taken yet (the same numbers)")


class StageTimes:
    """Wall-clock and CPU seconds per stage (CPU: this thread's, so a loaded machine does not inflate it)."""

    def __init__(self):
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        w, c = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - w
            self.cpu[name] = self.cpu.get(name, 0.0) + time.thread_time() - c

    def add(self, name: str, wall: float, cpu: float) -> None:
        self.wall[name] = self.wall.get(name, 0.0) + wall
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu


_TABLE_N = 1 << 16


def to8_table() -> np.ndarray:
    """8-bit display values of linear x = i / (2^16 - 1) after the gain: the 1/2.2 gamma of
    :func:`reconstruct.stream.display._to8`, tabulated (one level at most apart from the exact mapping).
    """
    x = np.arange(_TABLE_N, dtype=np.float64) / (_TABLE_N - 1)
    return (x ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


_TO8 = to8_table()


_TO8_LIMITED = None


def _to8_table(limited: bool) -> np.ndarray:
    """The display table, or with ``limited`` its studio-range luma (``LIMITED[_TO8]``, what the encoder takes)."""
    global _TO8_LIMITED
    if not limited:
        return _TO8
    if _TO8_LIMITED is None:
        from reconstruct.video.live_video import LIMITED

        _TO8_LIMITED = LIMITED[_TO8]
    return _TO8_LIMITED


def _to8_fast(x: np.ndarray, gain: float) -> np.ndarray:
    idx = np.clip(x * np.float32(gain * (_TABLE_N - 1)) + np.float32(0.5), 0, _TABLE_N - 1).astype(np.uint16)
    return _TO8[idx]


class _LiveWriters:
    """Outputs of a live stream: EXR frames at once, display outputs (videos, PNG frames) on a background thread: it
    also keeps the display histogram of the first ``gain_frames`` frames (held until the gains are known, then encoded;
    or at the end), so the stream's thread never waits for it.
    """

    def __init__(self, out: Path, fps: float, cfg: LiveConfig, times: StageTimes):
        self.out, self.fps, self.cfg, self.times = out, fps, cfg, times
        self.display = cfg.video or cfg.frames == "png"
        self.hist = {k: DisplayHistogram() for k in ("T", "R", "input")}
        self.gain: dict[str, float] | None = None
        self.held: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
        self.q: queue.Queue = queue.Queue(maxsize=64)
        self.stack = contextlib.ExitStack()
        self.vw: dict[str, Any] = {}
        self.err: BaseException | None = None
        self.thread: threading.Thread | None = None
        self.n = 0
        if self.display:
            self.thread = threading.Thread(target=self._encode_loop, name="polspike-encode", daemon=True)
            self.thread.start()

    def _open(self, name: str, shape: tuple[int, int]):
        from reconstruct.video.live_video import VIDEO_CODECS, open_video

        tmp = self.stack.enter_context(atomic_path(self.out / f"{name}{VIDEO_CODECS[self.cfg.video_codec]}"))
        extra = ["-threads", "1"] if self.cfg.video_quality == "fast" else []  # one x264 thread per video: less sync work
        w = open_video(tmp, self.cfg.video_codec, shape[0], shape[1], self.fps, ["-preset", self.cfg.preset, "-crf", str(VIDEO_CRF[self.cfg.video_quality]), *extra])
        self.stack.callback(w.close)
        return w

    def _encode_loop(self) -> None:
        """Frames from the queue until None (the end: frames still held are encoded on the gains of their histogram) or
        False (a failed run: nothing more is encoded).
        """
        cpu = 0.0
        wall = 0.0
        try:
            while True:
                item = self.q.get()
                w0, c0 = time.perf_counter(), time.thread_time()
                if item is None or item is False:
                    if item is None and self.gain is None and self.held:
                        self._release()
                    break
                if self.gain is None:
                    _, I2, T, R = item
                    self.hist["input"].add(I2)
                    self.hist["T"].add(T)
                    self.hist["R"].add(R)
                    self.held.append(item)
                    if len(self.held) >= self.cfg.gain_frames:
                        self._release()
                else:
                    self._encode(*item)
                wall += time.perf_counter() - w0
                cpu += time.thread_time() - c0
        except BaseException as e:  # noqa: BLE001 - handed to the main thread in close()
            self.err = e
            while self.q.get() not in (None, False):  # drain so the producer never blocks
                pass
        finally:
            self.times.add("encode", wall, cpu)

    def _encode(self, i: int, I2: np.ndarray, T: np.ndarray, R: np.ndarray) -> None:
        g = self.gain
        from reconstruct.video.display8 import to8_frames

        # yuv420p H.264 without PNG frames: the table gives the studio-range luma the encoder takes, in the same pass
        limited = self.cfg.video and self.cfg.video_codec == "h264" and self.cfg.frames != "png"
        t8, r8, prev = to8_frames(T if I2 is None else I2, T, R, g, _to8_table(limited), preview=self.cfg.video and self.cfg.preview)  # the table lookup of _to8_fast, in one pass
        if self.cfg.video:
            for name, img in (("T", t8), ("R", r8), ("preview", prev)):
                if img is None:
                    continue
                if name not in self.vw:
                    self.vw[name] = self._open(name, img.shape)
                self.vw[name].append(img, limited)
        if self.cfg.frames == "png":
            import imageio.v3 as iio3

            d = ensure_dir(self.out / "frames")
            for name, img in (("T", t8), ("R", r8)):
                with atomic_path(d / f"{name}_{i:06d}.png") as tmp:
                    iio3.imwrite(tmp, img, extension=".png")

    def _release(self) -> None:
        """The gains from the histogram so far; the held frames encoded on them."""
        gT, gR, gI = (display_gain(self.hist[k]) for k in ("T", "R", "input"))
        self.gain = {"T": gT, "R": gR, "preview": min(gT, gR, gI)}
        for item in self.held:
            self._encode(*item)
        self.held.clear()

    def write(self, Ic: np.ndarray, T: np.ndarray, R: np.ndarray) -> None:
        if self.cfg.frames == "exr":
            from polinfra.exr import write_exr

            d = ensure_dir(self.out / "frames")
            write_exr(d / f"{self.n:06d}.exr", {"T": T.astype(np.float32), "R": R.astype(np.float32)}, {"units": "linear radiance, 1.0 = brightest layer"})
        if self.display:
            # the input (x 2) only for its histogram (the first gain_frames) and the preview; it is copied here
            keep_input = self.n < self.cfg.gain_frames or (self.cfg.video and self.cfg.preview)
            self.q.put((self.n, 2 * Ic if keep_input else None, T, R))
            if self.err is not None:
                raise self.err
        self.n += 1

    def close(self, ok: bool) -> None:
        try:
            if self.thread is not None:
                self.q.put(None if ok else False)
                self.thread.join()
            if self.err is not None and ok:
                raise self.err
        finally:
            exc = (None, None, None) if ok else (RuntimeError, RuntimeError("stream failed"), None)
            self.stack.__exit__(*exc)


class _Centres:
    """Eq. (3) frame centres of a stream whose length grows: those of
    :func:`spike_sim.aggregate.frame_centres` on the calibrated angle phi0 + 2 pi f t, which do not depend on
    how far the stream goes (computed on a horizon that doubles).
    """

    def __init__(self, phi0_rad: float, rev_per_s: float, rate_hz: float, agg):
        self.phi0, self.rev, self.rate, self.agg = phi0_rad, rev_per_s, rate_hz, agg
        self.horizon = 0
        self.c = np.zeros(0, np.int64)
        self.phi = np.zeros(0)

    def ready(self, n_steps: int) -> int:
        """How many frames have their whole window inside the first ``n_steps`` steps."""
        from spike_sim.aggregate import frame_centres

        if n_steps + self.agg.half + 2 > self.horizon:
            self.horizon = max(2 * self.horizon, n_steps + int(self.rate), 4 * self.agg.window_steps)
            t = (np.arange(self.horizon) + 0.5) / self.rate
            self.c, self.phi = frame_centres(self.phi0 + 2 * math.pi * self.rev * t, self.agg)
        return int(np.searchsorted(self.c + self.agg.half, n_steps - 1, side="right"))


class _SolveThread:
    """The second stage of the fused rwps path: ``fn(*job)`` (the solve and write of a window) on a thread of its
    own, one job at a time, in the order given, while the stream's thread makes the next frame.  :meth:`wait`
    returns once every job given is done (the ring they read may change then) and raises what a job raised (later
    jobs are then skipped).
    """

    def __init__(self, fn: Callable[..., None]):
        self.fn = fn
        self.jobs: queue.Queue = queue.Queue(maxsize=1)
        self.err: BaseException | None = None
        self.thread = threading.Thread(target=self._loop, name="polspike-solve", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while (job := self.jobs.get()) is not None:
            try:
                if self.err is None:
                    self.fn(*job)
            except BaseException as e:  # noqa: BLE001 - handed to the stream's thread in wait()
                self.err = e
            finally:
                self.jobs.task_done()

    def check(self) -> None:
        """Raise what a job raised."""
        if self.err is not None:
            raise self.err

    def wait(self) -> None:
        self.jobs.join()
        self.check()

    def submit(self, *job, wait: bool = True) -> None:
        """Hand a job over, once every job before is done (``wait``) or once the one waiting before it is taken."""
        if wait:
            self.wait()
        self.check()
        self.jobs.put(job)

    def close(self) -> None:
        """Let the job in hand finish, then end the thread."""
        self.jobs.put(None)
        self.thread.join()


class _LiveWindow(NamedTuple):
    """A window waiting for its batch: the N Eq. (3) frames (N, H, W), their zeta (N, H, W) and angles (N,), when its
    last step arrived (None: not timed), and the indices of its frames.
    """

    I: np.ndarray
    Z: np.ndarray
    phi: np.ndarray
    arrived: float | None
    frames: np.ndarray


def reconstruct_live(
    reader,
    model,
    out_dir: str | os.PathLike,
    cfg: LiveConfig,
    *,
    phi0_rad: float,
    rev_per_s: float,
    rate_hz: float,
    exposure: float,
    name: str = "stream",
    follow: bool = False,
    stop: threading.Event | None = None,
    on_frame: Callable[[int, float | None], None] | None = None,
    meta: dict[str, Any] | None = None,
    times: StageTimes | None = None,
) -> dict[str, Any]:
    """Reconstruct a packed spike stream with a physics model on pane maps (module docstring).

    Args:
        reader: :class:`reconstruct.stream.packed.PackedDat` (also a growing one) or another packed reader
            (``refresh()`` -> steps available, ``counts(a, b)`` -> upright (H, W) counts, ``height``, ``width``).
        model: :class:`reconstruct.video.physics.PhysicsModel` with pane maps (no learned zeta, no mean anchor).
        out_dir: output directory (created).
        cfg: options.
        phi0_rad, rev_per_s, rate_hz: polarizer calibration and camera rate.
        exposure: thresholds per step per unit radiance.
        follow: wait for the stream to grow (until ``stop``, or ``cfg.idle_s`` without growth).
        stop: an event that ends the run between frames (outputs completed).
        on_frame: called (frames done, latency seconds or None) after each output frame.
        meta: extra summary entries.
        times: stage timer to fill (read, aggregate, zeta, rir, solve, write, encode).

    Returns:
        the summary written to ``reconstruct.json``.
    """
    from spike_sim.aggregate import AggregateConfig, output_fps

    if getattr(model, "maps", None) is None or "I_mean" in inputs_of(model):
        raise ConfigError("the real-time path takes a physics solver on pane maps (--zeta self, gt, physics or --pane) without --anchor mean")

    out = ensure_dir(out_dir)
    times = times if times is not None else StageTimes()
    N = model.cfg.n_obs
    K = N // 2
    agg = AggregateConfig(window_steps=cfg.window_steps, stride_deg=cfg.stride_deg, n_obs=N)
    cen = _Centres(phi0_rad, rev_per_s, rate_hz, agg)
    fps = output_fps(rev_per_s, cfg.stride_deg) if rev_per_s > 0 else 1.0
    H, W = reader.height, reader.width
    fused = cfg.solver == "fused" and model.method == "ls" and not model.rir
    fused_rwps = False
    if cfg.solver == "fused" and model.method == "rwps":
        from reconstruct.physics.fused_rwps import rwps_fused, rwps_fused_supports

        fused_rwps = rwps_fused_supports(model.solver_cfg)
    maps = model.maps
    zeta_of = _ZetaFrames(maps, model.span_rad)
    chained = None
    if model.rir:
        from reconstruct.physics.rir import ChainedRir

        chained = ChainedRir(finest=cfg.rir_finest, fused=cfg.solver == "fused")
    scale = np.float32(cfg.window_steps * exposure)
    ring_I = np.zeros((N, H, W), np.float32)  # Eq. (3) frame j in slot j % N
    ring_Z = np.zeros((N, H, W), np.float32)
    ring_phi = np.zeros(N, np.float32)
    arrived: dict[int, float] = {}  # Eq. (3) frame -> when its last step was seen
    pending: list[_LiveWindow] = []
    lat: list[float] = []
    stats = {"nan_frames": 0, "shared_chunks": 0}
    done = 0  # frames written
    made = 0  # windows complete: written, in the solve thread or waiting for their batch
    nxt = 0
    stopped = "end of stream"
    t0 = time.perf_counter()
    last_growth = time.perf_counter()
    n_seen = -1

    def emit(writers, Ic, T, R, arr):
        nonlocal done
        if not (np.isfinite(T).all() and np.isfinite(R).all()):
            stats["nan_frames"] += 1
            T, R = np.nan_to_num(T), np.nan_to_num(R)
        with times("write"):
            writers.write(Ic, T, R)
        done += 1
        la = None if arr is None else time.perf_counter() - arr
        if la is not None:
            lat.append(la)
        if on_frame is not None:
            on_frame(done, la)

    def flush(writers):
        if not pending:
            return
        I = torch.from_numpy(np.stack([p.I for p in pending]))
        Z = torch.from_numpy(np.stack([p.Z for p in pending]))
        ph = torch.from_numpy(np.stack([p.phi for p in pending]))
        if model.rir and N > 1:
            from reconstruct.physics.rir import warp

            with times("rir"):
                sh = torch.stack([chained.window_shifts(I[b], ph[b], p.frames) for b, p in enumerate(pending)]).to(I.dtype)
                I = warp(I, sh)
                Z = warp(Z, sh)
        from reconstruct.physics.solvers import solve

        with times("solve"):
            r = solve(model.method, Z, I, config=model.solver_cfg)
            T, R = r.T.clamp_min(0.0).numpy(), r.R.clamp_min(0.0).numpy()
        for b, p in enumerate(pending):
            emit(writers, p.I[K], T[b], R[b], p.arrived)
        pending.clear()

    def solve_rwps(sh, centre, arr):  # on the solve thread with the pipeline: the ring stays as it is until it is done
        with times("solve"):
            T, R = rwps_fused(ring_Z, ring_I, model.solver_cfg, sh, threads=cfg.threads)
        emit(writers, ring_I[centre] if pipe else ring_I[centre].copy(), T, R, arr)  # the writers copy what they keep

    def solve_shared(win, Ic, arr):  # on the solve thread: the pixel rows the stream's thread has not taken, the maps passes
        with times("solve"):
            T, R = win.finish()
        emit(writers, Ic, T, R, arr)

    pipe = fused_rwps and cfg.pipeline
    share = pipe and cfg.share_pixels and cfg.threads == 1
    if share:
        from reconstruct.physics.fused_rwps import RwpsWindow

        sums = (np.empty((9, H, W)), np.empty((9, H, W)))  # the pixel sums of two windows in flight (pixel pass of one, maps of the one before)
    win = None  # the window in hand (share)
    new_I = np.zeros((H, W), np.float32) if pipe else None  # the newest frame, kept out of the ring while the solve reads it
    new_Z = np.zeros((H, W), np.float32) if pipe else None
    writers = _LiveWriters(out, fps, cfg, times)
    solver = _SolveThread(solve_shared if share else solve_rwps) if pipe else None
    ok = False
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small per-frame tensors: one thread (more spin-wait on a shared machine and gain nothing)
    try:
        while True:
            if stop is not None and stop.is_set():
                stopped = "interrupt"
                break
            with times("read"):
                n = reader.refresh()
            now = time.perf_counter()
            if n != n_seen:
                n_seen, last_growth = n, now
            with times("centres"):
                m = cen.ready(n)
            if follow:
                for j in range(nxt, m):
                    arrived.setdefault(j, now)
            progressed = False
            while nxt < m and (cfg.max_frames == 0 or made < cfg.max_frames):
                if stop is not None and stop.is_set():
                    break
                c = int(cen.c[nxt])
                slot = nxt % N
                fI, fZ = (new_I, new_Z) if pipe else (ring_I[slot], ring_Z[slot])
                with times("aggregate"):
                    _radiance(reader, c - agg.half, c + agg.half + 1, scale, fI)  # Eq. (3), radiance units
                ring_phi[slot] = np.float32(cen.phi[nxt])
                if not fused:  # the fused LS pass takes zeta's closed form, not the frames of zeta
                    with times("zeta"):
                        zeta_of(float(ring_phi[slot]), fZ)  # paper Eq. (2)
                nxt += 1
                progressed = True
                if pipe and nxt < N:
                    ring_I[slot], ring_Z[slot] = fI, fZ  # no window yet: nothing is being solved
                if nxt >= N:
                    made += 1
                    arr = arrived.pop(nxt - 1, None) if follow else None
                    for k in [k for k in arrived if k < nxt - 1]:
                        arrived.pop(k)
                    centre = (nxt - 1 - K) % N
                    if fused:  # the least-squares sums do not depend on the order of the frames: the ring as it is
                        with times("solve"):
                            T, R = zeta_of.ls(ring_I, ring_phi)
                        emit(writers, ring_I[centre], T, R, arr)  # the writers copy what they keep of the input
                    elif fused_rwps:  # nor do RWPS's (per-pixel sums, min and mean over the window); shifts follow the ring
                        sh = None
                        if model.rir and N > 1:
                            order = [(nxt - N + k) % N for k in range(N)]
                            views = [fI if o == slot else ring_I[o] for o in order]  # the new frame: the ring's or its own
                            with times("rir"):
                                sw = chained.window_shifts(views, torch.from_numpy(ring_phi[order]), np.arange(nxt - N, nxt)).numpy()
                            sh = np.empty_like(sw)
                            sh[order] = sw
                        if share:  # the window before: its pixel rows not taken yet, here; then the ring is free
                            if win is not None:
                                with times("solve_shared"):
                                    stats["shared_chunks"] += win.pixels()
                                with times("wait"):
                                    win.wait_pixels()
                            solver.check()
                            ring_I[slot], ring_Z[slot] = fI, fZ
                            win = RwpsWindow(ring_Z, ring_I, model.solver_cfg, sh, sums=sums[made % 2])
                            with times("wait"):  # the queue holds one window: the one before is taken, the maps of the one before it done
                                solver.submit(win, ring_I[centre].copy(), arr, wait=False)
                        elif pipe:  # the window before is solved by now: the new frame into the ring, this window to the solve thread
                            with times("wait"):
                                solver.wait()
                            ring_I[slot], ring_Z[slot] = fI, fZ
                            solver.submit(sh, centre, arr)
                        else:
                            solve_rwps(sh, centre, arr)
                    else:
                        order = [(nxt - N + k) % N for k in range(N)]
                        pending.append(_LiveWindow(ring_I[order], ring_Z[order], ring_phi[order], arr, np.arange(nxt - N, nxt)))
                        if len(pending) >= (1 if follow else cfg.batch):
                            flush(writers)
            if stop is not None and stop.is_set():  # set while the frames were made
                stopped = "interrupt"
                break
            if cfg.max_frames and made >= cfg.max_frames:
                stopped = "max frames"
                break
            if not follow:
                break
            if not progressed:
                if cfg.idle_s > 0 and time.perf_counter() - last_growth > cfg.idle_s:
                    stopped = "idle"
                    break
                if stop is not None:
                    stop.wait(cfg.poll_s)
                else:
                    time.sleep(cfg.poll_s)
        if solver is not None:
            with times("wait"):
                solver.wait()  # the last window written (or the solve thread's error raised here)
        flush(writers)
        ok = True
    finally:
        torch.set_num_threads(threads)
        if win is not None and not ok:  # the solve thread may wait on rows the stream's thread will no longer make
            win.cancel()
        if solver is not None:
            solver.close()
        reader.close()
        writers.close(ok)
    if done == 0:
        raise ConfigError(f"{name}: no output frame (the stream holds fewer than the N = {N} Eq. (3) frames a window needs)")
    secs = time.perf_counter() - t0
    la = np.asarray(lat) if lat else None
    summary = {
        "input": name,
        "frames": done,
        "fps": fps,
        "size": [H, W],
        "exposure": exposure,
        "window_steps": cfg.window_steps,
        "stride_deg": cfg.stride_deg,
        "n_obs": N,
        "nan_frames": stats["nan_frames"],
        "seconds": secs,
        "frames_per_second_processed": done / secs if secs > 0 else None,
        "outputs": sorted(p.name for p in out.iterdir() if p.is_file() and p.suffix in (".mp4", ".y4m")),
        "display_gain": writers.gain,
        "display_gain_frames": min(cfg.gain_frames, done),
        "path": "live",
        "follow": follow,
        "stopped": stopped,
        "latency_s": None if la is None else {"mean": float(la.mean()), "median": float(np.median(la)), "p95": float(np.quantile(la, 0.95)), "max": float(la.max()), "frames": int(la.size)},
        "pipeline": pipe,
        "pixel_chunks_on_stream_thread": stats["shared_chunks"] if share else None,
        "stage_seconds": {"wall": dict(times.wall), "cpu": dict(times.cpu)},
        **(meta or {}),
    }
    write_json(out / "reconstruct.json", summary)
    return summary


class _ZetaFrames:
    """zeta (paper Eq. (2), window-averaged) of one Eq. (3) frame at angle phi, as
    :func:`reconstruct.physics.zeta.zeta_eq2` computes it, by the angle-sum identity on maps prepared once:
    zeta = mean + f amp (cos 2 phi cos 2 phi_perp + sin 2 phi sin 2 phi_perp) (float32; agrees to rounding).
    """

    def __init__(self, maps, span_rad: float):
        from reconstruct.physics.zeta import _span_factor

        rp, rl, pp = (np.asarray(a, np.float64) for a in (maps.R_perp, maps.R_par, maps.phi_perp))
        a = 0.5 * (rp - rl) * _span_factor(span_rad)
        self.mean = (0.5 * (rp + rl)).astype(np.float32)
        self.ac = (a * np.cos(2 * pp)).astype(np.float32)
        self.as_ = (a * np.sin(2 * pp)).astype(np.float32)

    def __call__(self, phi: float, out: np.ndarray) -> np.ndarray:
        np.multiply(self.ac, np.float32(math.cos(2 * phi)), out=out)
        out += np.float32(math.sin(2 * phi)) * self.as_
        out += self.mean
        return out


    def ls(self, I: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Least-squares T, R of the window I (N, H, W) at angles phi (N,) on this zeta, without its frames
        (:func:`reconstruct.physics.fused.ls_fused_harmonic`).
        """
        from reconstruct.physics.fused import ls_fused_harmonic

        ph = 2 * np.asarray(phi, np.float64)
        return ls_fused_harmonic(I, np.cos(ph), np.sin(ph), self.mean, self.ac, self.as_)


def _radiance(reader, a: int, b: int, scale: np.float32, out: np.ndarray) -> None:
    """Eq. (3) frame of steps a..b-1 in radiance units into ``out``: ``counts(a, b).astype(float32) / scale``, by the
    reader's one-pass kernel where it has one (the same values).
    """
    if hasattr(reader, "radiance"):
        reader.radiance(a, b, scale, out)
    else:
        out[...] = reader.counts(a, b).astype(np.float32) / scale
