"""The real-time path of ``polspike reconstruct`` (a physics solver on pane maps over a .dat, also one still being
written: ``--follow``), wired from :func:`polspike.commands.train_cmds.reconstruct_cmd`.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time
from pathlib import Path

import typer

from polinfra.errors import ConfigError


def wait_for_dat(path: Path, height: int, width: int, steps: int, idle_s: float):
    """A :class:`reconstruct.stream.packed.PackedDat` on ``path`` once it holds ``steps`` whole frames (the file may
    not exist yet); ConfigError when it does not grow for ``idle_s`` seconds (0 = wait for ever).
    """
    from reconstruct.stream.packed import PackedDat

    last, seen, t = -1, -1, time.perf_counter()
    while True:
        if path.is_file():
            rd = PackedDat(path, height, width, stored_w=width)
            n = rd.refresh()
            if n >= steps:
                return rd
            if n != seen:
                seen, t = n, time.perf_counter()
        if idle_s > 0 and time.perf_counter() - t > idle_s:
            raise ConfigError(f"--follow: {path} holds {max(seen, 0)} steps after {idle_s:g} s without growth; the start needs {steps} (self-calibration and exposure)")
        if last != seen:
            typer.echo(f"waiting for {path} ({max(seen, 0)} of {steps} steps to start)", err=True)
            last = seen
        time.sleep(0.05)


@contextlib.contextmanager
def sigint_event():
    """An event set by Ctrl-C (SIGINT) while the block runs (the previous handler restored after)."""
    ev = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield ev
        return
    prev = signal.signal(signal.SIGINT, lambda *a: ev.set())
    try:
        yield ev
    finally:
        signal.signal(signal.SIGINT, prev)


def run_live(reader, model, out: Path, cfg, *, phi0_rad: float, rev_per_s: float, rate_hz: float, exposure: float, name: str, follow: bool, meta: dict, quiet: bool) -> dict:
    """:func:`reconstruct.video.live.reconstruct_live` with Ctrl-C as its stop and a latency line on stderr each second."""
    from reconstruct.video.live import reconstruct_live

    state = {"t": time.perf_counter()}

    def on_frame(done: int, lat: float | None) -> None:
        now = time.perf_counter()
        if (follow or not quiet) and now - state["t"] >= 1.0:
            state["t"] = now
            msg = f"live: {done} frames" + (f", latency {1e3 * lat:.0f} ms" if lat is not None else "")
            print(msg, file=sys.stderr, flush=True)

    with sigint_event() as stop:
        s = reconstruct_live(reader, model, out, cfg, phi0_rad=phi0_rad, rev_per_s=rev_per_s, rate_hz=rate_hz, exposure=exposure, name=name,
                             follow=follow, stop=stop, on_frame=on_frame, meta=meta)
    la = s.get("latency_s")
    if la:
        print(f"latency: median {1e3 * la['median']:.0f} ms, p95 {1e3 * la['p95']:.0f} ms, max {1e3 * la['max']:.0f} ms over {la['frames']} frames ({s['stopped']})", file=sys.stderr, flush=True)
    return s
