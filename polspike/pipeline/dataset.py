"""Build and verify datasets: manifest groups -> spike stores with ground truth.

``polspike dataset build MANIFEST --out DIR`` runs :func:`build_dataset`; each
group is one call of the task function :func:`build_group`, on a local process
pool or a Dask cluster (the same function either way):

1. render radiance through the group's tier.  ``analytic``: keyframes are
   computed lazily in memory (coefficient maps once, each keyframe's layers and
   Stokes on demand: memory is a few frames, never the clip).  ``maps`` /
   ``full``: :func:`generator.render.render` writes a render directory under
   ``DIR/.tmp`` that is streamed from disk and deleted afterwards;
2. simulate the 20 kHz spikes (:func:`spike_sim.simulate.simulate`), which
   streams spikes and GT frames to ``spikes.h5`` chunk by chunk;
3. write ``group_spec.json`` (the resolved scene and simulator config) and
   ``checksums.json``, then publish the folder with one atomic ``rename`` from
   ``DIR/.tmp/NAME.<token>`` to ``DIR/groups/NAME``.

Output layout::

    DIR/dataset.json            {"format": "polspike-dataset/1", "name", "manifest": "manifest.toml",
                                 "manifest_sha256", "complete", "checksums": <definition>,
                                 "groups": [{"name", "path": "groups/NAME", "split", "tier", "seed",
                                             "duration_s", "width", "height", "n_steps", "scene_hash",
                                             "spec_sha256", "content_sha256", "files": {FILE: {"sha256", "bytes"}}}]}
    DIR/manifest.toml           byte copy of the manifest
    DIR/build_log.json          wall-clock timings per group (not checksummed)
    DIR/groups/NAME/spikes.h5   spike_sim group store (spikes, angles, GT T/R, coefficient maps)
    DIR/groups/NAME/group.json  spike_sim summary
    DIR/groups/NAME/group_spec.json   resolved scene + simulator config
    DIR/groups/NAME/checksums.json    spec_sha256, content_sha256, sha256 + size of every file above

Checksums and byte identity.  ``files[...].sha256`` is the sha256 of each file's
bytes: it detects any changed byte (``verify``; resume).  Group files hold no
wall-clock data: spike_sim is asked to leave its timings and temporary path out
of ``summary_json`` and group.json (``store_timings=False``), and the HDF5 store
is written without object timestamps in a fixed layout (:mod:`spike_sim.store`).
So **the same manifest gives the same bytes**, file by file (every file except
``build_log.json``, which alone holds the timings), whatever the executor (in
process, process pool, Dask), worker or thread count, and after a kill -9 and
resume (tested).  ``content_sha256`` hashes every HDF5 dataset (name, dtype,
shape, values) and attribute, group.json and group_spec.json, leaving out the
keys :data:`VOLATILE_KEYS` (which older builds stored): it compares content
across builds made before byte identity, or after a re-compression.

Resume.  A build holds ``DIR/.lock``.  At start it deletes ``DIR/.tmp``
(partial groups of a killed build); a group under ``DIR/groups`` is skipped
only when its ``checksums.json`` matches the manifest's ``spec_sha256`` and
every listed file's sha256 is re-computed and matches; anything else there is
removed and rebuilt.  Since a group appears under its final name only by the
final rename, a kill at any moment leaves no partial group visible.

Executors.  ``local`` (default): ``workers == 1`` runs groups in this
process; ``workers > 1`` uses a ``concurrent.futures`` process pool (spawn
context; workers die with the parent).  ``dask``: a ``dask.distributed``
client, connected to ``scheduler`` (a real cluster, whose workers must see DIR
at the same path, e.g. a shared filesystem) or, without one, to a
``LocalCluster(n_workers=workers, threads_per_worker=1)``.  Progress of each
group reaches the client through a small JSON file in ``DIR/.tmp``, so it works
the same for every executor.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from polinfra.atomic import ensure_dir, write_bytes, write_json
from polinfra.dask_client import dask_client
from polinfra.errors import ConfigError, DataFormatError, OutputError, PolspikeError
from polinfra.faults import fault_point
from polspike.pipeline.dataset_checksums import (
    CHECKSUM_DEFINITION,
    CHECKSUMS_FILE,
    DATASET_FORMAT,
    SPEC_FILE,
    VOLATILE_KEYS,
    _file_table,
    content_sha256,
    file_sha256,
    verify_group_files,
)
from polspike.pipeline.manifest import Manifest, ResolvedGroup, load_manifest

__all__ = [
    "DATASET_FORMAT",
    "VOLATILE_KEYS",
    "BuildCallbacks",
    "build_group",
    "build_dataset",
    "verify_dataset",
    "verify_group_files",
    "content_sha256",
    "file_sha256",
    "estimate_group_bytes",
]

log = logging.getLogger(__name__)

# ---- one group (the task function) ----------------------------------------------------------------------

class _AnalyticSource:
    """Lazily computed analytic-tier keyframes (coefficient maps once; frames on demand, small cache)."""

    def __init__(self, scene, cache_frames: int = 8):
        from generator.analytic import analytic_maps
        from generator.layers import LayerContent

        self.scene = scene
        self.maps = analytic_maps(scene)
        hw = (scene.camera.height, scene.camera.width)
        self.tc = LayerContent(scene.layers.transmission, hw)
        self.rc = LayerContent(scene.layers.reflection, hw)
        self.cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.cache_frames = max(4, int(cache_frames))

    def frame(self, i: int, t_s: float):
        from generator.analytic import frame_stokes, sample_layers

        if i not in self.cache:
            if len(self.cache) >= self.cache_frames:
                self.cache.pop(min(self.cache))
            K = int(getattr(self.scene.render, "supersample", 0))
            if K > 0:  # the pixel's area (generator.analytic_area)
                from generator.analytic_area import area_frames

                S, L_T, L_R = area_frames(self.scene, [t_s], K)[0]
                S = S.astype(np.float32)
            else:
                L_T, L_R, L_G = sample_layers(self.maps, self.tc, self.rc, t_s)
                S = frame_stokes(self.maps, L_T, L_R, L_G).astype(np.float32)
            self.cache[i] = (S, L_T.astype(np.float32), L_R.astype(np.float32))
        return self.cache[i]


def _keyframe_source(scene, tier: str, duration_s: float, fps: float, work: Path, progress: Callable[[str, int, int], None] | None, chunk_s: float = 0.05):
    """A :class:`spike_sim.simulate.KeyframeSource` for the group's tier, and render timings.

    The analytic source caches the keyframes of about one simulation chunk (``chunk_s``
    seconds) plus 4, so the GT writer, which trails the spikes by up to a chunk, finds them.
    """
    from generator.objects3d import require_full_tier
    from generator.render import RenderOptions, frame_times, render
    from generator.scene import scene_hash
    from spike_sim.simulate import KeyframeSource, keyframes_from_render

    require_full_tier(scene, tier)  # 3-D object scenes: full tier only
    opts = RenderOptions(tier=tier, fps=fps, duration_s=duration_s, seed=scene.render.seed)
    if tier == "analytic":
        times = frame_times(scene, opts)
        a = _AnalyticSource(scene, cache_frames=min(64, int(np.ceil(chunk_s * fps)) + 4))
        src = KeyframeSource(
            times_s=times,
            stokes=lambda i: a.frame(i, float(times[i]))[0],
            height=scene.camera.height,
            width=scene.camera.width,
            layers=lambda i: a.frame(i, float(times[i]))[1:],
            maps=lambda: {k: v.astype(np.float32) for k, v in a.maps.channels().items()},
            polarizer=scene.polarizer,
            scene_hash=scene_hash(scene),
        )
        return src, {}
    rdir = work.with_name(work.name + ".render")
    meta = render(scene, rdir, opts, progress=(lambda d, t: progress("render", d, t)) if progress else None)
    return keyframes_from_render(rdir), dict(meta.get("timings", {}))


class _FileProgress:
    """Throttled (stage, done, total) writer to a JSON file the client polls."""

    def __init__(self, path: Path, min_interval_s: float = 0.5):
        self.path, self.dt, self.last = path, min_interval_s, 0.0

    def __call__(self, stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        if now - self.last < self.dt and done < total:
            return
        self.last = now
        tmp = self.path.with_name(self.path.name + f".{os.getpid()}")
        try:
            tmp.write_text(json.dumps({"stage": stage, "done": done, "total": total}))
            os.replace(tmp, self.path)
        except OSError:
            pass


def build_group(spec: dict, out_dir: str, chunk_steps: int = 1000, numba_threads: int = 0, progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Build one group into ``out_dir/groups/NAME`` (the task function of every executor).

    Args:
        spec: :meth:`ResolvedGroup.build_spec` (plain data: picklable, no paths needed
            on the worker except content files such as ``image:PATH``).
        out_dir: dataset folder DIR (must be visible to the worker at this path).
        chunk_steps: spike_sim chunk length (part of the byte layout; fixed per build).
        numba_threads: threads of the spike kernel in this worker (0 = numba's default).
        progress: optional (stage, done, total) callback; None = write
            ``DIR/.tmp/NAME.progress.json`` for the client to poll.

    Returns:
        the group's record for dataset.json (checksums included) plus ``timings``.
    """
    from generator.scene import scene_from_dict, scene_hash
    from polinfra.config import from_dict
    from spike_sim.config import SpikeSimConfig
    from spike_sim.simulate import simulate

    t0 = time.perf_counter()
    c0 = time.process_time()
    if numba_threads:
        import numba

        numba.set_num_threads(max(1, min(int(numba_threads), numba.config.NUMBA_NUM_THREADS)))
    root = Path(out_dir)
    name = spec["name"]
    tmp_root = ensure_dir(root / ".tmp")
    final = root / "groups" / name
    work = tmp_root / f"{name}.{uuid.uuid4().hex[:12]}"
    if progress is None:
        progress = _FileProgress(tmp_root / f"{name}.progress.json")
    scene = scene_from_dict(spec["scene"], where=f"group {name}")
    sim = from_dict(SpikeSimConfig, spec["spike_sim"], where=f"group {name} spike_sim")
    timings: dict[str, float] = {}
    try:
        ts = time.perf_counter()
        chunk_s = chunk_steps / float(sim.rate_hz)
        src, rt = _keyframe_source(scene, spec["tier"], float(spec["duration_s"]), float(spec["keyframe_fps"]), work, progress, chunk_s)
        timings.update({f"render_{k}": float(v) for k, v in rt.items() if isinstance(v, (int, float))})
        # one-off part: maps, layer content, Mitsuba scene; the keyframes' render grows with the duration
        timings["render_s"] = time.perf_counter() - ts
        timings["setup_s"] = timings["render_s"] - timings.get("render_frames_s", 0.0)
        timings["setup_cpu_s"] = time.process_time() - c0 - timings.get("render_frames_s", 0.0)
        timings["n_keyframes"] = float(src.times_s.size)
        ts = time.perf_counter()
        summ = simulate(src, float(spec["duration_s"]), int(spec["seed"]), config=sim, out=work, chunk_steps=chunk_steps, progress=lambda d, t: progress("simulate", d, t), store_timings=False)
        timings["simulate_s"] = time.perf_counter() - ts
        timings["kernel_s"] = summ.sim_seconds
        # group.json: the final location (the temporary one is random and left out by store_timings=False)
        gj = json.loads((work / "group.json").read_text())
        if isinstance(gj.get("summary"), dict):
            gj["summary"]["group_dir"] = f"groups/{name}"
        write_json(work / "group.json", gj)
        write_json(work / SPEC_FILE, spec)
        ts = time.perf_counter()
        files = _file_table(work)
        content = content_sha256(work)
        timings["checksum_s"] = time.perf_counter() - ts
        cs = {"format": "polspike-group-checksums/1", "name": name, "spec_sha256": spec["spec_sha256"], "content_sha256": content, "files": files, "definition": CHECKSUM_DEFINITION}
        write_json(work / CHECKSUMS_FILE, cs)
        _fsync_tree(work)  # data on disk before the name appears (a crash then leaves no torn group)
        ensure_dir(final.parent)
        fault_point("dataset.publish")  # test-only kill -9 injection (polinfra.faults)
        try:
            os.rename(work, final)  # atomic publish: the group appears complete or not at all
        except OSError as exc:
            same = False
            if final.exists() and not verify_group_files(final):
                with contextlib.suppress(OSError, json.JSONDecodeError, KeyError):
                    other = json.loads((final / CHECKSUMS_FILE).read_text())
                    same = other["spec_sha256"] == spec["spec_sha256"]
            if same:
                log.warning("group %s was published meanwhile by another builder with the same settings; keeping that copy", name)
                files, content = other["files"], other["content_sha256"]
                shutil.rmtree(work, ignore_errors=True)
            else:
                raise OutputError(f"cannot publish group {name} at {final}: {exc.strerror}; remove it and rebuild") from None
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(work.with_name(work.name + ".render"), ignore_errors=True)
    with contextlib.suppress(OSError):
        (tmp_root / f"{name}.progress.json").unlink()
    h = int(scene.camera.height)
    w = int(scene.camera.width)
    timings["total_s"] = time.perf_counter() - t0
    timings["cpu_s"] = time.process_time() - c0  # all threads of this process
    return {
        "name": name,
        "path": f"groups/{name}",
        "tier": spec["tier"],
        "seed": int(spec["seed"]),
        "duration_s": float(spec["duration_s"]),
        "width": w,
        "height": h,
        "n_steps": int(summ.n_steps),
        "scene_hash": scene_hash(scene),
        "spec_sha256": spec["spec_sha256"],
        "content_sha256": content,
        "files": files,
        "bytes": int(sum(f["bytes"] for f in files.values())),
        "timings": timings,
    }


def _fsync_tree(d: Path) -> None:
    for p in [*d.iterdir(), d]:
        with contextlib.suppress(OSError):
            fd = os.open(p, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def estimate_group_bytes(g: ResolvedGroup) -> int:
    """Upper bound of a group's disk use while it builds (raw spike bits, float16 GT, maps; render dir for maps/full)."""
    h, w = int(g.scene["camera"]["height"]), int(g.scene["camera"]["width"])
    steps = int(round(g.duration_s * float(g.spike_sim["rate_hz"])))
    frames = int(g.duration_s * 2 * 360.0 * float(g.scene["polarizer"]["rate_hz"]) / 31.5) + 2  # Eq. (3) outputs, generous
    n = steps * ((h * w + 7) // 8) + frames * h * w * 2 * 2 + 6 * h * w * 4 + (1 << 20)
    if g.tier != "analytic":
        n += (int(np.ceil(g.duration_s * g.keyframe_fps)) + 1) * h * w * 5 * 4
    return int(n)


def _record_from_group(final: Path, g: ResolvedGroup) -> dict:
    cs = json.loads((final / CHECKSUMS_FILE).read_text())
    spec = json.loads((final / SPEC_FILE).read_text())
    gj = json.loads((final / "group.json").read_text())
    cam = spec["scene"]["camera"]
    return {
        "name": g.name,
        "path": f"groups/{g.name}",
        "tier": g.tier,
        "seed": g.seed,
        "duration_s": g.duration_s,
        "width": int(cam["width"]),
        "height": int(cam["height"]),
        "n_steps": int(gj.get("summary", {}).get("n_steps", round(g.duration_s * float(spec["spike_sim"]["rate_hz"])))),
        "scene_hash": gj.get("scene_hash", ""),
        "spec_sha256": cs["spec_sha256"],
        "content_sha256": cs["content_sha256"],
        "files": cs["files"],
        "bytes": int(sum(f["bytes"] for f in cs["files"].values())),
        "timings": {},
    }


# ---- the whole dataset ---------------------------------------------------------------------------------

@dataclasses.dataclass
class BuildCallbacks:
    """Optional progress hooks of :func:`build_dataset` (the CLI draws rich bars with them).

    Attributes:
        group: (name, stage, done, total) while a group runs ("skipped" / "done" at its end).
        overall: (steps_done, steps_total) over all groups (ETA).
    """

    group: Callable[[str, str, int, int], None] | None = None
    overall: Callable[[int, int], None] | None = None


def _lock(root: Path):
    import fcntl

    fh = open(root / ".lock", "a+")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise OutputError(f"another build holds {root / '.lock'}; wait for it or choose another --out") from None
    return fh


def _worker_init(numba_threads: int) -> None:  # pragma: no cover - runs in pool workers
    """Pool worker setup: die with the parent (Linux), cap numba threads."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _dataset_doc(m: Manifest, records: dict[str, dict], complete: bool) -> dict:
    groups = []
    for g in m.groups:
        r = records.get(g.name)
        if r is None:
            continue
        groups.append({**{k: v for k, v in r.items() if k != "timings"}, "split": g.split})
    return {
        "format": DATASET_FORMAT,
        "name": m.name,
        "description": m.description,
        "manifest": "manifest.toml",
        "manifest_sha256": m.sha256,
        "complete": complete,
        "n_groups": len(m.groups),
        "checksums": CHECKSUM_DEFINITION,
        "groups": groups,
    }


def build_dataset(
    manifest: str | os.PathLike | Manifest,
    out_dir: str | os.PathLike,
    workers: int = 1,
    executor: str = "local",
    scheduler: str | None = None,
    client: Any = None,
    chunk_steps: int = 1000,
    groups: list[str] | None = None,
    callbacks: BuildCallbacks | None = None,
    poll_s: float = 0.5,
) -> dict:
    """Build every group of ``manifest`` into ``out_dir`` (deterministic, resumable; module docstring).

    Args:
        manifest: a manifest path / shipped name, or a loaded :class:`Manifest`.
        out_dir: dataset folder DIR.
        workers: groups built at once (local pool size / LocalCluster workers).
        executor: "local" or "dask".
        scheduler: dask scheduler address (tcp://host:8786) of a real cluster.
        client: an existing ``distributed.Client`` (tests); implies dask.
        chunk_steps: spike_sim chunk length (fixed per dataset: it shapes the HDF5 layout).
        groups: build only these group names (default: all).
        callbacks: progress hooks.
        poll_s: progress poll interval (s).

    Returns:
        {"dataset": dataset.json dict, "built": [names], "skipped": [names], "seconds": float,
         "timings": {name: timings}}.
    """
    if executor not in ("local", "dask"):
        raise ConfigError(f"--executor {executor!r} is unknown; choose local or dask")
    if workers < 1:
        raise ConfigError(f"--workers = {workers} must be >= 1")
    if scheduler and executor != "dask":
        raise ConfigError("--scheduler needs --executor dask")
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    sel = list(m.groups)
    if groups:
        sel = [m.group(n) for n in groups]
    cb = callbacks or BuildCallbacks()
    root = ensure_dir(out_dir)
    t0 = time.perf_counter()
    lock = _lock(root)
    try:
        shutil.rmtree(root / ".tmp", ignore_errors=True)  # partial groups of a killed build
        for stale in root.glob(".*.tmp-*"):  # temporaries of a killed atomic write (dataset.json, manifest.toml, build_log.json)
            stale.unlink(missing_ok=True)
        ensure_dir(root / "groups")
        write_bytes(root / "manifest.toml", m.source_text)
        records: dict[str, dict] = {}
        todo: list[ResolvedGroup] = []
        for g in m.groups:
            final = root / "groups" / g.name
            if not final.exists():
                if g in sel:
                    todo.append(g)
                continue
            problems = verify_group_files(final)
            if not problems:
                cs = json.loads((final / CHECKSUMS_FILE).read_text())
                if cs.get("spec_sha256") != g.spec_sha256:
                    problems = ["built from other settings (spec_sha256 differs)"]
            if not problems:
                records[g.name] = _record_from_group(final, g)
                if g in sel and cb.group:
                    cb.group(g.name, "skipped", 1, 1)
                continue
            if g not in sel:
                continue
            log.warning("group %s: %s; rebuilding it", g.name, "; ".join(problems))
            trash = root / ".tmp" / f"{g.name}.stale.{uuid.uuid4().hex[:8]}"
            ensure_dir(trash.parent)
            os.rename(final, trash)
            shutil.rmtree(trash, ignore_errors=True)
            todo.append(g)
        skipped = [g.name for g in sel if g.name in records]
        write_json(root / "dataset.json", _dataset_doc(m, records, complete=len(records) == len(m.groups)))
        steps = {g.name: int(round(g.duration_s * float(g.spike_sim["rate_hz"]))) for g in sel}
        steps_total = sum(steps.values())
        steps_done = {n: (steps[n] if n in records else 0) for n in steps}
        if cb.overall:
            cb.overall(sum(steps_done.values()), steps_total)
        timings: dict[str, dict] = {}

        def on_done(g: ResolvedGroup, rec: dict) -> None:
            records[g.name] = rec
            timings[g.name] = rec.get("timings", {})
            steps_done[g.name] = steps[g.name]
            if cb.group:
                cb.group(g.name, "done", steps[g.name], steps[g.name])
            if cb.overall:
                cb.overall(sum(steps_done.values()), steps_total)
            write_json(root / "dataset.json", _dataset_doc(m, records, complete=len(records) == len(m.groups)))
            log.info("group %s built in %.1f s", g.name, rec.get("timings", {}).get("total_s", float("nan")))

        if todo:
            need = max(estimate_group_bytes(g) for g in todo) * min(workers, len(todo))
            free = shutil.disk_usage(root).free
            if free < need:
                raise OutputError(f"{root}: {free / 1e9:.2f} GB free, but building {min(workers, len(todo))} group(s) at once needs up to {need / 1e9:.2f} GB; free space, lower --workers or choose another --out")
            n_thr = max(1, (os.cpu_count() or 1) // workers) if workers > 1 else 0
            if executor == "local" and workers == 1 and client is None:
                for g in todo:
                    def prog(stage, d, t, _n=g.name):
                        if stage == "simulate":
                            steps_done[_n] = d
                            if cb.overall:
                                cb.overall(sum(steps_done.values()), steps_total)
                        if cb.group:
                            cb.group(_n, stage, d, t)

                    on_done(g, build_group(g.build_spec(), str(root), chunk_steps, 0, progress=prog))
            else:
                _run_pool(todo, root, workers, executor, scheduler, client, chunk_steps, n_thr, cb, steps_done, steps_total, on_done, poll_s)
        doc = _dataset_doc(m, records, complete=len(records) == len(m.groups))
        write_json(root / "dataset.json", doc)
        log_path = root / "build_log.json"
        old = {}
        if log_path.is_file():
            with contextlib.suppress(json.JSONDecodeError, UnicodeDecodeError):
                old = json.loads(log_path.read_text()).get("groups", {})
        write_json(log_path, {"groups": {**old, **timings}, "executor": "dask" if (executor == "dask" or client is not None) else "local", "workers": workers})
        shutil.rmtree(root / ".tmp", ignore_errors=True)
        return {"dataset": doc, "built": [g.name for g in todo], "skipped": skipped, "seconds": time.perf_counter() - t0, "timings": timings}
    finally:
        lock.close()


def _run_pool(todo, root, workers, executor, scheduler, client, chunk_steps, n_thr, cb, steps_done, steps_total, on_done, poll_s) -> None:
    """Submit the groups to a process pool or a Dask client, poll progress files, collect results."""
    own = []
    if executor == "local" and client is None:
        import concurrent.futures as cf
        import multiprocessing as mp

        pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_worker_init, initargs=(n_thr,))
        own.append(pool.shutdown)
        futs = {pool.submit(build_group, g.build_spec(), str(root), chunk_steps, n_thr): g for g in todo}
    else:
        stack = contextlib.ExitStack()
        client = stack.enter_context(dask_client(scheduler, workers, client, what="--executor dask"))
        own.insert(0, stack.close)
        futs = {client.submit(build_group, g.build_spec(), str(root), chunk_steps, n_thr, key=f"polspike-group-{g.name}-{g.spec_sha256[:12]}-{uuid.uuid4().hex[:6]}", pure=False): g for g in todo}
    try:
        pending = dict(futs)
        while pending:
            for f in [f for f in pending if f.done()]:
                g = pending.pop(f)
                try:
                    rec = f.result()
                except PolspikeError:
                    raise
                except Exception as exc:
                    raise OutputError(f"group {g.name} failed on a worker: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from exc
                on_done(g, rec)
            for f, g in pending.items():
                p = root / ".tmp" / f"{g.name}.progress.json"
                try:
                    st = json.loads(p.read_text())
                except (OSError, json.JSONDecodeError, UnicodeDecodeError):
                    continue
                if st.get("stage") == "simulate":
                    steps_done[g.name] = int(st["done"])
                if cb.group:
                    cb.group(g.name, st.get("stage", ""), int(st["done"]), int(st["total"]))
            if cb.overall:
                cb.overall(sum(steps_done.values()), steps_total)
            if pending:
                time.sleep(poll_s)
    finally:
        for f in futs:
            with contextlib.suppress(Exception):
                f.cancel()
        for close in own:
            with contextlib.suppress(Exception):
                close()


# ---- verify -------------------------------------------------------------------------------------------

def verify_dataset(out_dir: str | os.PathLike, content: bool = True, progress: Callable[[int, int], None] | None = None, partial: bool = False) -> dict:
    """Re-check a built dataset: file sha256s, content checksums and metadata.

    Args:
        out_dir: dataset folder DIR.
        content: also recompute ``content_sha256`` (reads and decompresses every dataset).
        progress: (done, total) over groups.
        partial: accept a build that holds only some of the manifest's groups (``--group``).

    Returns:
        {"ok": bool, "bad": {group: [problems]}, "problems": [dataset-level problems], "n_groups": int}.

    Raises:
        DataFormatError: DIR has no readable dataset.json.
    """
    root = Path(out_dir)
    meta = root / "dataset.json"
    if not meta.is_file():
        raise DataFormatError(f"{root} has no dataset.json; build it with polspike dataset build")
    try:
        doc = json.loads(meta.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{meta} is not valid JSON ({exc})") from None
    problems: list[str] = []
    if doc.get("format") != DATASET_FORMAT:
        problems.append(f"dataset.json format {doc.get('format')!r} != {DATASET_FORMAT!r}")
    man = root / str(doc.get("manifest", "manifest.toml"))
    if not man.is_file():
        problems.append("manifest copy missing")
    elif file_sha256(man) != doc.get("manifest_sha256"):
        problems.append("manifest copy sha256 mismatch")
    groups = doc.get("groups") or []
    if not doc.get("complete") and not partial:
        problems.append(f"build incomplete ({len(groups)} of {doc.get('n_groups', '?')} groups)")
    bad: dict[str, list[str]] = {}
    spec_by_name: dict[str, dict] = {}
    if man.is_file():
        try:
            from polinfra.config import load_toml
            from polspike.pipeline.manifest import parse_manifest

            mm = parse_manifest(load_toml(man), where=str(man), base_dir=man.parent)
            spec_by_name = {g.name: {"split": g.split, "spec_sha256": g.spec_sha256, "tier": g.tier, "seed": g.seed} for g in mm.groups}
            missing = sorted(set(spec_by_name) - {g.get("name") for g in groups})
            if missing and doc.get("complete"):
                problems.append(f"groups of the manifest missing from dataset.json: {', '.join(missing)}")
        except PolspikeError as exc:
            problems.append(f"manifest copy does not load ({exc})")
    for i, rec in enumerate(groups):
        name = str(rec.get("name", f"#{i}"))
        gdir = root / str(rec.get("path", f"groups/{name}"))
        errs = verify_group_files(gdir, rec)
        exp = spec_by_name.get(name)
        if exp is not None:
            for k in ("split", "spec_sha256", "tier", "seed"):
                if rec.get(k) != exp[k]:
                    errs.append(f"{k} {rec.get(k)!r} differs from the manifest ({exp[k]!r})")
        if not errs and gdir.is_dir():
            try:
                spec = json.loads((gdir / SPEC_FILE).read_text())
                if spec.get("spec_sha256") != rec.get("spec_sha256"):
                    errs.append("group_spec.json spec_sha256 differs")
                from spike_sim.store import open_group

                with open_group(gdir) as sg:
                    if (sg.width, sg.height, sg.n_steps) != (rec.get("width"), rec.get("height"), rec.get("n_steps")):
                        errs.append(f"store size {sg.width}x{sg.height}x{sg.n_steps} differs from dataset.json")
                    if not sg.has("gt/T") or not sg.maps():
                        errs.append("ground truth (gt/T or maps) missing")
                if content and content_sha256(gdir) != rec.get("content_sha256"):
                    errs.append("content_sha256 mismatch")
            except (PolspikeError, OSError, json.JSONDecodeError, KeyError) as exc:
                errs.append(str(exc).splitlines()[0][:160])
        if errs:
            bad[name] = errs
        if progress:
            progress(i + 1, len(groups))
    return {"ok": not bad and not problems, "bad": bad, "problems": problems, "n_groups": len(groups)}
