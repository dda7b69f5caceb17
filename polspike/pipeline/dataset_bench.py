"""``polspike bench dataset``: seconds per 1 s group per tier, bytes per group, peak memory.

Each tier builds one group of the ``brewster`` scene at ``width x height``
through :func:`polspike.pipeline.dataset.build_group` (the dataset task
function: render, simulate, store, checksums) in a fresh spawned process, so
the peak resident memory (``ru_maxrss``) is that group's alone.  A group shorter
than 1 s may be measured (``duration_s``); its time is scaled to 1 s as::

    s_per_1s_group = setup_s + (total_s - setup_s) / duration_s

(CPU seconds of all threads are scaled alike: ``cpu_s_per_1s_group``; on a
busy machine the wall time is inflated by other processes, the CPU time much
less), where ``setup_s`` (coefficient maps, layer content, Mitsuba scene/maps render)
is paid once per group and everything else (keyframes, spikes, GT, compression,
checksums) grows with the duration.  Bytes are scaled the same way (linear in
duration).  The JSON says which numbers were measured and which scaled.
"""

from __future__ import annotations

import logging
import math
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from polinfra.atomic import ensure_dir, write_json
from polinfra.errors import ConfigError

__all__ = ["run_dataset_bench", "BENCH_TIERS"]

log = logging.getLogger(__name__)

BENCH_TIERS = ("analytic", "maps", "full")
GOAL_ANALYTIC_S = 60.0
"""Goal: an analytic 1 s group of 400 x 250 in at most 60 s on 2 cores."""


def _spec(tier: str, width: int, height: int, duration_s: float, spp: int) -> dict:
    from polspike.pipeline.manifest import parse_manifest

    g = {
        "name": f"bench_{tier}",
        "split": "train",
        "scene": "brewster",
        "tier": tier,
        "seed": 1,
        "duration_s": duration_s,
        "camera": {"width": width, "height": height},
        "render": {"spp": spp},
    }
    m = parse_manifest({"name": "bench", "groups": [g]}, where="bench")
    return m.groups[0].build_spec()


def _child(spec: dict, out: str, q) -> None:  # pragma: no cover - runs in a spawned process
    import resource

    from polspike.pipeline.dataset import build_group

    try:
        rec = build_group(spec, out, progress=lambda *a: None)
        rss_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        q.put({"ok": True, "record": rec, "peak_rss_mib": rss_kib / 1024.0})
    except BaseException as exc:  # report, never hang the parent
        q.put({"ok": False, "error": f"{type(exc).__name__}: {exc}"})


def run_dataset_bench(
    out_dir: str | os.PathLike,
    tiers: tuple[str, ...] = ("analytic",),
    width: int = 400,
    height: int = 250,
    duration_s: dict[str, float] | float = 0.25,
    spp: int = 4,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Time one group per tier; write ``out_dir/bench_dataset.json`` and return it.

    Args:
        out_dir: where the JSON (and, temporarily, the groups) go.
        tiers: any of analytic, maps, full.
        width, height: image size in pixels.
        duration_s: measured stream length (s), one value or one per tier; scaled to 1 s.
        spp: samples per pixel of the maps/full tiers.
        progress: (done, total) over tiers.
    """
    import multiprocessing as mp

    bad = [t for t in tiers if t not in BENCH_TIERS]
    if bad:
        raise ConfigError(f"unknown tier {bad[0]!r}; choose from {list(BENCH_TIERS)}")
    out = ensure_dir(out_dir)
    work = Path(tempfile.mkdtemp(prefix=".bench-", dir=out))
    rows = []
    ctx = mp.get_context("spawn")
    try:
        for i, tier in enumerate(tiers):
            d = float(duration_s[tier] if isinstance(duration_s, dict) else duration_s)
            spec = _spec(tier, width, height, d, spp)
            q = ctx.Queue()
            t0 = time.perf_counter()
            p = ctx.Process(target=_child, args=(spec, str(work), q))
            p.start()
            res = q.get()
            p.join()
            wall = time.perf_counter() - t0
            if not res["ok"]:
                rows.append({"tier": tier, "error": res["error"]})
                log.warning("tier %s failed: %s", tier, res["error"])
            else:
                rec = res["record"]
                t = rec["timings"]
                setup = float(t.get("setup_s", 0.0))
                kf = t.get("render_frames_s", 0.0)
                kf_scale = (math.ceil(1.0 * spec["keyframe_fps"] - 1e-9) + 1) / max(1.0, t.get("n_keyframes", 1.0))
                per = setup + kf * kf_scale + (t["total_s"] - setup - kf) / d
                cset = float(t.get("setup_cpu_s", 0.0))
                per_cpu = cset + kf * kf_scale + (t["cpu_s"] - cset - kf) / d
                rows.append(
                    {
                        "tier": tier,
                        "width": width,
                        "height": height,
                        "measured_duration_s": d,
                        "measured_s": t["total_s"],
                        "process_wall_s": wall,
                        "setup_s": setup,
                        "simulate_s": t.get("simulate_s"),
                        "kernel_s": t.get("kernel_s"),
                        "checksum_s": t.get("checksum_s"),
                        "s_per_1s_group": per,
                        "cpu_s_per_1s_group": per_cpu,
                        "scaled": d != 1.0,
                        "bytes_measured": rec["bytes"],
                        "bytes_per_1s_group": int(rec["bytes"] / d),
                        "peak_rss_mib": res["peak_rss_mib"],
                        "spp": spp if tier != "analytic" else None,
                    }
                )
            shutil.rmtree(work / "groups", ignore_errors=True)
            if progress:
                progress(i + 1, len(tiers))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    an = next((r for r in rows if r.get("tier") == "analytic" and "s_per_1s_group" in r), None)
    result = {
        "benchmark": "dataset",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(), "load_avg_1min": os.getloadavg()[0]},
        "scene": "brewster",
        "rows": rows,
        "goal": {"analytic_s_per_1s_group_400x250": GOAL_ANALYTIC_S, "met": (an["s_per_1s_group"] <= GOAL_ANALYTIC_S) if an and (width, height) == (400, 250) else None},
        "notes": "s_per_1s_group = setup_s + render_frames_s * K(1 s) / K(d) + (measured_s - setup_s - render_frames_s) / d "
        "(one-off setup, keyframe renders scaled by the keyframe count K, the rest linear in duration d); cpu_s_per_1s_group alike "
        "(keyframe render counted as CPU); "
        "bytes scaled linearly; peak_rss_mib = ru_maxrss of a fresh process that built the group",
    }
    write_json(out / "bench_dataset.json", result)
    return result
