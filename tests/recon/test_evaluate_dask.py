"""``polspike evaluate`` on a Dask cluster gives the tables of the in-process evaluation.

Oracle: the in-process run of the same command.  Each group's scores depend on that group alone, so the
per-group rows, the overall rows (recomputed from the merged per-frame scores) and the configuration must
be equal to the last bit; only the timings may differ.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ARGS = ["synthetic:5", "--synthetic-groups", "3", "--synthetic-frames", "10", "--synthetic-size", "48x32", "--method", "ls,ridge,rwps", "--quiet"]


def _script() -> str:
    cand = Path(sys.executable).with_name("polspike")
    return str(cand) if cand.exists() else "polspike"


def _evaluate(out: Path, *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    return subprocess.run([_script(), "evaluate", *ARGS, "--out", str(out), *extra], env=env, capture_output=True, text=True, timeout=900)


def _tables(out: Path) -> tuple[str, list, dict, str]:
    res = json.loads((out / "results.json").read_text())
    md = (out / "results.md").read_text().split("\nTimings (s):")[0]
    return (out / "results.csv").read_text(), res["rows"], res["config"], md


@pytest.mark.slow
def test_dask_tables_equal_in_process_tables(tmp_path):
    distributed = pytest.importorskip("distributed")
    r = _evaluate(tmp_path / "local")
    assert r.returncode == 0, r.stderr[-3000:]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        r = _evaluate(tmp_path / "dask", "--scheduler", cluster.scheduler_address)
    assert r.returncode == 0, r.stderr[-3000:]
    a, b = _tables(tmp_path / "local"), _tables(tmp_path / "dask")
    assert len(a[1]) == 3 * 6 + 6  # 3 groups x (3 solvers, tfp, best_frame, spike_mean), then the overall rows
    assert [x["group"] for x in a[1]][-1] == "overall" and a[2]["groups"] == ["synthetic-5-000", "synthetic-5-001", "synthetic-5-002"]
    assert a == b
    assert (tmp_path / "dask" / "figure.png").is_file()


def test_bad_executor_is_one_line_and_exit_2(tmp_path):
    r = _evaluate(tmp_path / "x", "--executor", "spark")
    assert r.returncode == 2, r.stderr[-2000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "--executor 'spark'" in lines[0], r.stderr


def test_merged_per_group_reports_equal_the_whole_report():
    """merge_reports of one evaluate_groups per group (what the Dask tasks return) equals evaluate_groups of all."""
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups, group_loaders
    from reconstruct.evaluate.parallel import merge_reports
    from reconstruct.stream.synthetic import SyntheticConfig

    cfg = EvalConfig(methods="ls,rwps", figure_frames=2)
    loaders = group_loaders("synthetic:5", "test", cfg, SyntheticConfig(n_groups=3, n_frames=9, width=32, height=24))
    whole = evaluate_groups([load() for load in loaders], cfg)
    merged = merge_reports([evaluate_groups([load()], cfg) for load in loaders], cfg)
    assert merged.rows == whole.rows and merged.frames == whole.frames and merged.order == whole.order
    assert merged.config == whole.config
    assert merged.figure["frames"] == whole.figure["frames"] and len(merged.figure["frames"]) == 2
    assert merged.figure["columns"] == whole.figure["columns"]
    assert set(merged.timings) == set(whole.timings)
