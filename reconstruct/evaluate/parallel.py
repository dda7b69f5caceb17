"""The evaluation harness on a Dask cluster: one task per group, the same tables as in-process.

Each task loads its group where it runs (:func:`reconstruct.evaluate.harness.group_loaders`: the workers must see
the dataset directory, e.g. on a shared filesystem) and scores it with
:func:`reconstruct.evaluate.harness.evaluate_groups` on that one group.  Every group's scores depend on that group
alone, so the merged report equals the in-process one: the per-frame scores in group order, the per-group
and overall rows recomputed from them (:func:`reconstruct.evaluate.harness.summary_rows`), the figure's first
``figure_frames`` groups; only the timings (summed over the tasks) differ.

Cluster: ``scheduler`` = the address of a running scheduler (``tcp://HOST:8786``), else a
``LocalCluster`` of ``workers`` processes with one thread each; or an existing ``client``.
"""

from __future__ import annotations

import contextlib
import logging
import uuid
from collections import defaultdict
from collections.abc import Callable

from polinfra.dask_client import dask_client
from polinfra.errors import ConfigError, OutputError, PolspikeError
from reconstruct.evaluate.harness import EvalConfig, EvalReport, evaluate_groups, summary_rows
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, SolverConfig

__all__ = ["evaluate_groups_dask", "merge_reports"]

log = logging.getLogger(__name__)


def _evaluate_one(load: Callable, cfg: EvalConfig, solver_cfg: SolverConfig) -> EvalReport:  # pragma: no cover - runs on a worker
    return evaluate_groups([load()], cfg, solver_cfg)


def merge_reports(reports: list[EvalReport], cfg: EvalConfig) -> EvalReport:
    """One report from per-group reports (in group order), as :func:`evaluate_groups` gives for all groups at once."""
    if not reports:
        raise ConfigError("no group to evaluate")
    frames = [f for r in reports for f in r.frames]
    fig = {"frames": [], "columns": list(reports[0].figure["columns"]), "images": []}
    for r in reports:
        for name, img in zip(r.figure["frames"], r.figure["images"]):
            if len(fig["frames"]) < cfg.figure_frames:
                fig["frames"].append(name)
                fig["images"].append(img)
    timings: dict[str, float] = defaultdict(float)
    for r in reports:
        for k, v in r.timings.items():
            timings[k] += v
    conf = {k: v for k, v in reports[0].config.items() if k != "network"}
    conf["groups"] = [g for r in reports for g in r.config["groups"]]
    net = next((r.config["network"] for r in reports if "network" in r.config), None)
    if net is not None:
        conf["network"] = net
    order = reports[0].order
    return EvalReport(frames=frames, rows=summary_rows(frames, order), figure=fig, timings=dict(timings), config=conf, order=order)


def evaluate_groups_dask(
    loaders: list[Callable],
    cfg: EvalConfig = EvalConfig(),
    solver_cfg: SolverConfig = PHYSICS_SOLVER_CONFIG,
    *,
    scheduler: str | None = None,
    workers: int = 2,
    client=None,
    progress: Callable[[int, int], None] | None = None,
) -> EvalReport:
    """:func:`reconstruct.evaluate.harness.evaluate_groups` over the groups of ``loaders``, one Dask task per group.

    Args:
        loaders: :func:`reconstruct.evaluate.harness.group_loaders` of the dataset.
        cfg, solver_cfg: as for :func:`evaluate_groups`.
        scheduler: address of a running Dask scheduler; None = a LocalCluster of ``workers`` processes.
        client: an existing ``distributed.Client`` (overrides ``scheduler``).
        progress: optional (done, total) callback, counted in groups.

    Returns:
        the merged :class:`EvalReport` (:func:`merge_reports`).
    """
    if not loaders:
        raise ConfigError("no group to evaluate")
    with dask_client(scheduler, workers, client, what="a Dask evaluation") as c:
        import distributed

        tag = uuid.uuid4().hex[:8]
        futs = [c.submit(_evaluate_one, load, cfg, solver_cfg, key=f"polspike-evaluate-{tag}-{j}", pure=False) for j, load in enumerate(loaders)]
        pos = {f.key: j for j, f in enumerate(futs)}
        reports: list[EvalReport | None] = [None] * len(futs)
        try:
            for done, f in enumerate(distributed.as_completed(futs), 1):
                try:
                    reports[pos[f.key]] = f.result()
                except PolspikeError:
                    raise
                except Exception as exc:
                    raise OutputError(f"group {pos[f.key]} failed on a worker: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from exc
                if progress is not None:
                    progress(done, len(futs))
        finally:
            for f in futs:
                with contextlib.suppress(Exception):
                    f.cancel()
    log.info("evaluated %d groups on Dask", len(reports))
    return merge_reports([r for r in reports if r is not None], cfg)
