"""`polspike evaluate-paper`: Table 1 / supp. Table 3 layout from per-checkpoint evaluations.

Oracles: a column is the mean of its checkpoints' own evaluate_groups scores (computed here
independently); Table 3's RWPS "final" row of a checkpoint trained with RWPS is its Table 1 "Ours"
(the solver swap is the identity); the RWPS solver-only row is the network's T_base.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, V1_WEIGHTS

pytestmark = pytest.mark.skipif(not (DEFAULT_WEIGHTS.is_file() and V1_WEIGHTS.is_file()), reason="shipped checkpoints not present")


@pytest.fixture(scope="module")
def groups():
    from reconstruct.stream.synthetic import SyntheticConfig, make_group

    cfg = SyntheticConfig(width=24, height=16, n_groups=2, n_frames=9, seed=7)
    return [make_group(cfg, i) for i in range(2)]


def test_columns_are_means_of_their_checkpoints(groups):
    import torch

    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups
    from reconstruct.evaluate.paper_table import paper_csv, paper_markdown, paper_tables

    torch.set_num_threads(1)
    cfg = EvalConfig(zeta="gt", max_frames=1)
    cks = [str(DEFAULT_WEIGHTS), str(V1_WEIGHTS)]
    res = paper_tables(groups, {"full": cks}, cfg, solvers=("rwps",))
    own = []
    for ck in cks:
        rep = evaluate_groups(groups, dataclasses.replace(cfg, methods="full", zeta="learned", checkpoint=ck, figure_frames=0))
        lab = rep.config["network"]["label"]
        own.append({r["method"]: r for r in rep.rows if r["group"] == "overall"}[lab])
    ours = res["table1"]["Ours"]
    assert len(ours["runs"]) == 2
    assert ours["mean"]["psnr_T"] == pytest.approx(np.mean([o["psnr_T"] for o in own]))
    assert ours["mean"]["ssim_R"] == pytest.approx(np.mean([o["ssim_R"] for o in own]))
    # both checkpoints were trained with RWPS: swapping in RWPS changes nothing
    assert res["table3"]["rwps"]["final"]["mean"]["psnr_T"] == pytest.approx(ours["mean"]["psnr_T"])
    assert "w/o conf (test-time)" in res["table1"] and "w/o Angle attention" not in res["table1"]
    assert res["table1"]["TFP"]["mean"]["psnr_R"] is None
    md = paper_markdown(res)
    assert "| PSNR T (dB) |" in md and "Supp. Table 3" in md and "27.06" in md
    rows = paper_csv(res)
    assert rows[0][:4] == ["table", "column", "stage", "checkpoint"] and sum(r[3] == "mean" for r in rows[1:]) == len(res["table1"]) + 2


def test_network_on_another_zeta(groups):
    """--net-zeta gt: the Ours column is the network's full@gt row of evaluate_groups."""
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups
    from reconstruct.evaluate.paper_table import paper_tables

    cfg = EvalConfig(zeta="gt", max_frames=1)
    res = paper_tables(groups, {"full": [str(DEFAULT_WEIGHTS)]}, cfg, solvers=(), net_zeta="gt")
    rep = evaluate_groups(groups, dataclasses.replace(cfg, methods="full", net_zeta="gt", figure_frames=0))
    lab = rep.config["network"]["label"] + "@gt"
    own = {r["method"]: r for r in rep.rows if r["group"] == "overall"}[lab]
    assert res["table1"]["Ours"]["mean"]["psnr_T"] == pytest.approx(own["psnr_T"]) and res["config"]["net_zeta"] == "gt"


def test_cli_writes_md_csv_json(tmp_path, polspike_main):
    r = polspike_main("evaluate-paper", "synthetic:3", "--synthetic-size", "24x16", "--max-frames", "1", "--solvers", "", "--out", tmp_path, "--quiet", "--zeta", "gt")
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "paper_table.json").read_text())
    assert set(doc["table1"]) >= {"TFP", "RWPS (zeta gt)", "Ours"} and doc["table3"] == {}
    assert (tmp_path / "paper_table.csv").read_text().startswith("table,column,stage,checkpoint")
    assert "## Table 1" in (tmp_path / "paper_table.md").read_text()


def test_needs_a_known_column_and_existing_checkpoints(tmp_path, groups, polspike_main):
    from polinfra.errors import ConfigError
    from reconstruct.evaluate.paper_table import paper_tables

    with pytest.raises(ConfigError, match="no_magic"):
        paper_tables(groups, {"full": [str(DEFAULT_WEIGHTS)], "no_magic": ["x"]})
    r = polspike_main("evaluate-paper", "synthetic:3", "--full", tmp_path / "missing.pt", "--out", tmp_path / "o")
    polspike_main.one_line_exit_2(r, "missing.pt")
