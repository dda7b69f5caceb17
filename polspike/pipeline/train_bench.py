"""``polspike bench train-ddp``: training throughput of data-parallel processes against one process.

Every setting trains the same config (the v2 network on on-the-fly windows of sampled scenes, one global
batch) through ``polspike train`` in a subprocess, ``--nproc N`` for N > 1.  The throughput is read from
the run's own ``log.csv`` (seconds since the loop started, per step) between the end of the warm-up steps
and the last step, so the start-up of the processes (imports, torchrun, scene maps) is left out; the
wall time of the whole command is reported beside it.  The reference is one process on one thread,
measured in the same run.
"""

from __future__ import annotations

import csv
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

from polinfra.atomic import ensure_dir, write_text
from polinfra.errors import ConfigError, OutputError

__all__ = ["SETTINGS", "bench_config", "bench_train_ddp", "ddp_table"]

log = logging.getLogger(__name__)

SETTINGS = (("1 process, 1 thread", 1, 1), ("1 process, 2 threads", 1, 2), ("2 processes, 1 thread each", 2, 1))
"""(label, processes, torch threads per process); the first is the reference."""


def bench_config(steps: int, batch: int, crop: int) -> str:
    """The benchmark's training TOML: the cpu_v2 network, on-the-fly windows of 2 sampled scenes, one epoch."""
    return (
        f"seed = 0\nepochs = 1\nsteps_per_epoch = {steps}\nbatch_size = {batch}\nlr = 5e-4\nckpt_every = 1000000\nlog_every = 1\n"
        "val_items = 2\ntrain_scenes = 2\ntest_scenes = 1\ndevice = \"cpu\"\n\n[net]\narch = \"v2\"\nuse_rir = false\n\n"
        f"[window]\ncrop = {crop}\nkeyframe_hz = 1000.0\n"
    )


def _throughput(run: Path, warmup: int, batch: int) -> tuple[float, int]:
    rows = [r for r in csv.DictReader(open(run / "log.csv")) if r.get("loss")]
    sec = {int(r["step"]): float(r["seconds"]) for r in rows}
    last = max(sec)
    if last <= warmup or sec[last] <= sec[warmup]:
        raise OutputError(f"{run}: too few timed steps after the warm-up ({last} steps, warm-up {warmup}); raise --steps")
    return (last - warmup) * batch / (sec[last] - sec[warmup]), last - warmup


def bench_train_ddp(out_dir: str | os.PathLike, steps: int = 40, warmup: int = 5, batch: int = 8, crop: int = 32) -> dict:
    """Train each of :data:`SETTINGS` for ``steps`` steps; windows per second after ``warmup`` steps, ratios to the first."""
    if steps <= warmup + 1:
        raise ConfigError(f"--steps {steps} must exceed the warm-up ({warmup}) by at least 2")
    if batch % 2:
        raise ConfigError(f"--batch {batch} must be even (2 processes take half each)")
    root = ensure_dir(out_dir)
    cfg = write_text(root / "bench_train.toml", bench_config(steps, batch, crop))
    res: dict = {"config": {"steps": steps, "warmup": warmup, "batch": batch, "crop": crop, "net": "v2", "data": "on-the-fly windows, 2 sampled scenes"},
                 "cpu_count": os.cpu_count(), "load_avg_before": list(os.getloadavg()), "settings": []}
    for j, (label, nproc, threads) in enumerate(SETTINGS):
        run = root / f"run{j}"
        cmd = [sys.executable, "-m", "polspike", "train", str(cfg), "--out", str(run), "--threads", str(threads), "--workers", "0", "--quiet", "--nproc", str(nproc)]
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
        t0 = time.perf_counter()
        r = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise OutputError(f"benchmark run {label!r} failed (exit {r.returncode}): {(r.stderr.strip().splitlines() or [''])[-1]}")
        thr, timed = _throughput(run, warmup, batch)
        log.info("%s: %.2f windows/s (%d timed steps), %.1f s wall", label, thr, timed, wall)
        res["settings"].append({"label": label, "processes": nproc, "threads": threads, "windows_per_s": thr, "timed_steps": timed, "wall_s": wall})
    ref = res["settings"][0]["windows_per_s"]
    for s in res["settings"]:
        s["ratio"] = s["windows_per_s"] / ref
    res["ratio_2proc"] = res["settings"][-1]["ratio"]
    res["load_avg_after"] = list(os.getloadavg())
    return res


def ddp_table(res: dict) -> str:
    """Markdown table of :func:`bench_train_ddp`'s result."""
    c = res["config"]
    lines = [
        f"Training throughput, global batch {c['batch']} windows of {c['crop']}x{c['crop']} ({c['net']} network, {c['data']}); "
        f"{c['steps'] - c['warmup']} timed steps after {c['warmup']} warm-up steps; {res['cpu_count']} cores, load average {res['load_avg_before'][0]:.1f} before, {res['load_avg_after'][0]:.1f} after.",
        "",
        "| setting | processes | threads each | windows/s | ratio to 1 process, 1 thread | wall s (whole command) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for s in res["settings"]:
        lines.append(f"| {s['label']} | {s['processes']} | {s['threads']} | {s['windows_per_s']:.2f} | {s['ratio']:.2f} | {s['wall_s']:.1f} |")
    return "\n".join(lines) + "\n"
