"""Data-parallel training through the console script: ``polspike train --nproc N`` (torchrun, gloo).

Oracle: one process on the whole global batch.  N ranks on batch_size / N windows each with averaged
gradients take the same steps up to float rounding; Adam turns the rounding of a gradient that is zero in
exact arithmetic (an attention key bias: softmax ignores a shift) into a step of up to lr, so the tolerance
is on the whole weight update: ||w_N - w_1|| <= 5e-3 ||w_1 - w_0|| (measured 6e-4 at 6 steps; a rank on
the wrong shard or a learning rate scaled with N moves it by order 1).
"""

from __future__ import annotations

import csv
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from reconstruct.net.checkpoint import read_checkpoint

TOML = """
seed = 3
epochs = 2
steps_per_epoch = 3
batch_size = 4
ckpt_every = 2
log_every = 1
train_items = 16
val_items = 2
curriculum_fracs = [0.25, 0.5]
[net]
feat_ch = 8
lr_ch = 8
w_ch = 4
ref_ch = [8, 8, 8]
dec_ch = [8, 8, 8]
use_rir = false
[window]
crop = 16
"""
STEPS = 6
REL_TOL = 5e-3


def _script() -> str:
    cand = Path(sys.executable).with_name("polspike")
    return str(cand) if cand.exists() else "polspike"


def _env(**extra) -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", **extra}


def _train(cfg: Path, data: Path, out: Path, nproc: int | None, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    cmd = [_script(), "train", str(cfg), "--data", str(data), "--out", str(out), "--threads", "1", "--workers", "0", "--quiet"]
    if nproc is not None:
        cmd += ["--nproc", str(nproc)]
    return subprocess.run(cmd, env=env or _env(), capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "tiny.toml"
    p.write_text(TOML)
    return p


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """Two tiny stored spike groups (train / test), as reconstruct's window tests build them."""
    from tests.recon.test_windows import _dataset

    return _dataset(tmp_path_factory.mktemp("ddp_data"))


@pytest.fixture(scope="module")
def runs(config, data, tmp_path_factory) -> dict[int, Path]:
    """Uninterrupted runs on one and on two processes."""
    root = tmp_path_factory.mktemp("ddp_runs")
    out = {}
    for n in (1, 2):
        r = _train(config, data, root / f"n{n}", n)
        assert r.returncode == 0, r.stderr[-3000:]
        out[n] = root / f"n{n}"
    return out


def _initial_weights(config: Path) -> dict[str, torch.Tensor]:
    from polinfra.config import from_dict, load_toml
    from reconstruct.net.network import PolSpikeNet, init_weights
    from reconstruct.net.train import TrainConfig

    cfg = from_dict(TrainConfig, load_toml(config))
    m = PolSpikeNet(cfg.net, cfg.solver)
    init_weights(m, torch.Generator().manual_seed(cfg.seed))
    return m.state_dict()


def _rel_distance(a: dict, b: dict, w0: dict) -> float:
    """||a - b|| / ||a - w0|| over every tensor: the difference of two runs relative to the update they made."""
    num = sum(float(((a[k].double() - b[k].double()) ** 2).sum()) for k in a)
    den = sum(float(((a[k].double() - w0[k].double()) ** 2).sum()) for k in a)
    return math.sqrt(num / den)


def _losses(run: Path) -> list[float]:
    return [float(r["loss"]) for r in csv.DictReader(open(run / "log.csv")) if r["loss"]]


@pytest.mark.slow
def test_two_processes_match_one_at_equal_global_batch(runs, config):
    a, b = (read_checkpoint(runs[n] / "last.pt") for n in (1, 2))
    assert a["step"] == b["step"] == STEPS
    w0 = _initial_weights(config)
    assert _rel_distance(a["state_dict"], w0, w0) == pytest.approx(1.0)  # the runs moved the weights
    d = _rel_distance(a["state_dict"], b["state_dict"], w0)
    assert d <= REL_TOL, d
    # the logged losses are the global batch's (the ranks' mean), as one process logs them
    la, lb = _losses(runs[1]), _losses(runs[2])
    assert len(la) == len(lb) == STEPS
    assert lb == pytest.approx(la, rel=1e-4)
    # rank 0 alone writes: one log, one config, the checkpoints
    assert {p.name for p in runs[2].iterdir()} >= {"last.pt", "best.pt", "log.csv", "config.json"}
    assert not list(runs[2].glob(".*tmp*"))


@pytest.mark.slow
def test_rank_killed_mid_run_resumes_to_the_same_weights(runs, config, data, tmp_path):
    """Kill -9 of rank 1 after its 3rd step (polinfra.faults point train.step.rank1): torchrun stops the other
    rank, the CLI exits non-zero, last.pt holds step 2; the same command on one process continues from there
    to the weights of the uninterrupted runs.
    """
    run = tmp_path / "killed"
    r = _train(config, data, run, 2, env=_env(POLSPIKE_FAULT_AT="train.step.rank1@3"))
    assert r.returncode == 1, r.stderr[-3000:]
    assert f"exitcode  : -{int(signal.SIGKILL)}" in r.stderr  # torchrun's report: the rank died of SIGKILL
    assert "the same command resumes" in r.stderr.strip().splitlines()[-1]
    assert read_checkpoint(run / "last.pt")["step"] == 2  # mid-run: not 0, not the end
    r = _train(config, data, run, None)  # another world size: one process
    assert r.returncode == 0, r.stderr[-3000:]
    c = read_checkpoint(run / "last.pt")
    assert c["step"] == STEPS
    w0 = _initial_weights(config)
    for n in (1, 2):
        d = _rel_distance(read_checkpoint(runs[n] / "last.pt")["state_dict"], c["state_dict"], w0)
        assert d <= REL_TOL, (n, d)
    assert _losses(run) == pytest.approx(_losses(runs[2]), rel=1e-4)


@pytest.mark.parametrize("nproc, msg", [(0, "--nproc 0"), (3, "does not divide the global batch_size 4")])
def test_bad_world_size_is_one_line_and_exit_2(config, tmp_path, nproc, msg):
    r = subprocess.run([_script(), "train", str(config), "--out", str(tmp_path / "o"), "--nproc", str(nproc)], env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and msg in lines[0], r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "o").exists()


def test_python_m_polspike_runs_the_cli():
    r = subprocess.run([sys.executable, "-m", "polspike", "train", "--help"], env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "--nproc" in r.stdout
