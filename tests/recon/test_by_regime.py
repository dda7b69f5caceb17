"""Per-regime evaluation (``polspike evaluate --by-regime``) and the RWPS fit (``polspike fit-rwps``):
group names parse into regimes, rows average exactly the groups of each level, every zeta source is
taken by name, the fit picks the grid point with the best objective on known windows.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from polinfra.errors import ConfigError
from reconstruct.evaluate.harness import REGIME_FACTORS, EvalConfig
from reconstruct.evaluate.regimes import evaluate_by_regime, regime_of
from reconstruct.stream.synthetic import SyntheticConfig, make_group

REPO = Path(__file__).resolve().parents[2]


def test_regime_of_parses_names_and_ignores_the_rest():
    assert regime_of("refl-weak_motion-fast_light-dim_inc-brewster_pane-slab") == {"refl": "weak", "motion": "fast", "light": "dim", "inc": "brewster", "pane": "slab"}
    assert regime_of("test_000") == {}
    assert regime_of("refl-purple_inc-normal") == {"inc": "normal"}


@pytest.fixture(scope="module")
def groups():
    cfg = SyntheticConfig(width=24, height=16, n_groups=3, n_frames=9, seed=3)
    gs = [make_group(cfg, i) for i in range(3)]
    names = ["refl-weak_inc-normal", "refl-strong_inc-normal", "refl-strong_inc-glancing"]
    return [dataclasses.replace(g, name=n) for g, n in zip(gs, names)]


def test_by_regime_rows_are_means_of_their_groups(groups):
    cfg = EvalConfig(methods="ls,rwps", max_frames=2, rir=False)
    res = evaluate_by_regime(groups, cfg, zetas=("gt",), network=False)
    assert res["columns"] == ["tfp", "best_frame", "spike_mean", "ls@gt", "rwps@gt"]
    per = {g["group"]: g for g in res["groups"]}
    rows = {r["regime"]: r for r in res["rows"]}
    assert set(rows) == {"refl=weak", "refl=strong", "inc=normal", "inc=glancing"}
    for col in res["columns"]:
        assert rows["refl=strong"][col] == pytest.approx(np.mean([per["refl-strong_inc-normal"][col], per["refl-strong_inc-glancing"][col]]))
        assert rows["inc=glancing"][col] == pytest.approx(per["refl-strong_inc-glancing"][col])
    assert rows["refl=strong"]["n_groups"] == 2
    assert set(REGIME_FACTORS) == {"refl", "motion", "light", "inc", "pane"}


def test_by_regime_rejects_an_unknown_zeta_source(groups):
    with pytest.raises(ConfigError, match="oracle"):
        evaluate_by_regime(groups, EvalConfig(methods="ls"), zetas=("oracle",), network=False)


def test_fit_picks_the_best_grid_point():
    """On windows with known truth the fit's table is consistent: best = the one-SE rule's pick, margins vs LS / ridge."""
    import torch

    from reconstruct.evaluate.rwps_fit import fit_rwps, group_scores
    from reconstruct.physics.solvers import SolverConfig

    sys.path.insert(0, str(Path(__file__).parent))
    from test_rwps_adaptive import _regime_windows

    win = {}
    for reg in ("normal_dim", "brewster_bright"):
        z, I, T = _regime_windows(reg, B=2, H=16, W=16)
        win[reg] = [(z[j], I[j], T[j]) for j in range(2)]
    grid = {"snr_kappa": (0.3, 30.0), "lambda_low": (0.0,), "lambda_high": (0.1,), "rwps_irls_iters": (0,)}
    res = fit_rwps(win, grid=grid)
    assert len(res["table"]) == 2
    top = max(res["table"], key=lambda r: r["objective"])
    near = [r for r in res["table"] if r["objective"] >= top["objective"] - top["objective_se"]]
    best = min(near, key=lambda r: r["snr_kappa"])  # lambda_high is fixed: least snr_kappa within one SE
    assert res["best"]["snr_kappa"] == best["snr_kappa"]
    ls, ridge = group_scores(win, "ls", SolverConfig()), group_scores(win, "ridge", SolverConfig())
    rw = group_scores(win, "rwps", SolverConfig(lambda_map="adaptive", snr_kappa=best["snr_kappa"], lambda_low=0.0, lambda_high=0.1, rwps_irls_iters=0))
    m = np.array([rw[g] - max(ls[g], ridge[g]) for g in win])
    assert best["mean_margin"] == pytest.approx(m.mean()) and best["min_margin"] == pytest.approx(m.min())
    assert torch.is_tensor(win["normal_dim"][0][0])


def test_fit_rwps_refuses_the_test_split(tmp_path):
    r = subprocess.run([sys.executable, "-c", "from polspike.cli import app; app()", "fit-rwps", str(tmp_path), "--split", "test", "--quiet"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "training groups" in r.stderr and "Traceback" not in r.stderr


def test_share_tables_are_means_of_their_groups_and_render(groups):
    """R where the reflection is >= 20 % of the light: per-regime rows average the groups' masked scores and
    fractions; the table leads with the fraction and the bound (n/a without a stored group's noise).
    """
    from reconstruct.evaluate.regimes import regime_markdown, regime_report

    cfg = EvalConfig(methods="ls", max_frames=2, rir=False)
    res = evaluate_by_regime(groups, cfg, zetas=("gt",), network=False)
    rows = {r["regime"]: r for r in res["rows_R_share"]}
    gs, gr = res["groups_share"], res["groups_R_share"]
    names = ["refl-strong_inc-normal", "refl-strong_inc-glancing"]
    assert rows["refl=strong"]["share_frac"] == pytest.approx(np.mean([gs[n]["share_frac"] for n in names]))
    vals = [gr[n]["ls@gt"][0] for n in names if gr[n]["ls@gt"][0] is not None]
    assert vals and rows["refl=strong"]["ls@gt"] == pytest.approx(np.mean(vals))
    assert rows["refl=strong"]["psnr_R_bound"] is None  # synthetic groups carry no simulator noise
    md = regime_markdown(res, "rows_R_share")
    assert md.splitlines()[0].startswith("| regime | groups | rho>=0.2 frac | R bound (LS, true zeta) | groups with bound >= 22 dB | rho>=0.2 px with bound >= 22 dB | flat R (oracle level) | ls@gt |")
    assert rows["refl=strong"]["n_bound"] == 0 and "| n/a | n/a | n/a |" in md
    assert "tfp" not in md.splitlines()[0]  # the baselines estimate no R
    assert "PSNR of R where the reflection is >= 20 % of the light" in regime_report(res)


def test_share_rows_count_the_groups_whose_bound_reaches_22_db(groups, monkeypatch):
    """With a known window noise (the synthetic set's Poisson counts, exposure 1, 13 steps) every group gets an R
    bound; each level counts the groups whose bound is >= 22 dB and averages the bounds.
    """
    import reconstruct.evaluate.harness as ev

    monkeypatch.setattr(ev, "group_noise", lambda g, cfg: {"exposure": 1.0, "window_steps": 13, "model": "poisson"})
    res = evaluate_by_regime(groups, EvalConfig(methods="ls", max_frames=2, rir=False), zetas=("gt",), network=False)
    b = {n: v["psnr_R_bound"] for n, v in res["groups_share"].items()}
    for r in res["rows_R_share"]:
        f, lv = r["regime"].split("=")
        mine = [b[n] for n in b if regime_of(n).get(f) == lv and b[n] is not None]
        assert r["n_bound"] == len(mine) and r["n_bound_ge_22"] == sum(x >= 22.0 for x in mine)
        if mine:
            assert r["psnr_R_bound"] == pytest.approx(np.mean(mine))
    assert any(v is not None for v in b.values())
