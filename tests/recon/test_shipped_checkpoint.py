"""The shipped default checkpoint: its stored scores reproduce, the model card quotes them, and the
exact parameter count of every architecture is pinned.

The scores live beside the weights in ``<stem>.scores.json`` (written by ``polspike
checkpoint-scores``, see :mod:`polspike.pipeline.checkpoint_scores`), so the model card cannot drift
from the weights: a new checkpoint without a fresh scores file, a reduced evaluation that no longer
reproduces, or a card quoting other numbers fails here.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from polspike.pipeline.checkpoint_scores import REPRODUCE_TOL_DB, compare_reduced, evaluate_setting, scores_path, sha256_file, summary_line
from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
from reconstruct.net.network import NetConfig, PolSpikeNet, count_parameters

REPO = Path(__file__).resolve().parents[2]
CARD = REPO / "docs" / "MODEL_CARD.md"

#: Exact trainable-parameter count per architecture (NetConfig defaults).  Changing the
#: architecture means updating this number on purpose (and the model card).
EXPECTED_PARAMS = {"v1": 510_454, "v2": 395_230}
#: Exact trainable-parameter count of each shipped default checkpoint (by file name).
EXPECTED_SHIPPED = {"polspike_v1.pt": 510_454, "polspike_v2.pt": 395_230, "polspike_v2_mean.pt": 395_806, "polspike_v3.pt": 395_806, "polspike_v4.pt": 395_806, "polspike_v5.pt": 395_806, "polspike_v6.pt": 395_806, "polspike_v7.pt": 395_806, "polspike_v12.pt": 395_806}  # v2_mean: + 2 x 32 x 3 x 3 refinement inputs; v3-v12: same layers

pytestmark = [pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason=f"shipped checkpoint {DEFAULT_WEIGHTS} not present"), pytest.mark.usefixtures("one_thread")]


def _scores() -> dict:
    sp = scores_path(DEFAULT_WEIGHTS)
    assert sp.is_file(), f"{sp} missing: run `polspike checkpoint-scores {DEFAULT_WEIGHTS.relative_to(REPO)} --threads 1` and commit it"
    return json.loads(sp.read_text())


def test_scores_file_belongs_to_the_default_weights():
    doc = _scores()
    assert doc["format"] == "polspike-scores/1" and doc["weights"] == DEFAULT_WEIGHTS.name
    assert doc["weights_sha256"] == sha256_file(DEFAULT_WEIGHTS), f"the scores are of other weights: rerun `{doc['command']}`"
    assert doc["command"].startswith(f"polspike checkpoint-scores {DEFAULT_WEIGHTS.relative_to(REPO)} ")
    assert (REPO / doc["manifest"]).is_file(), doc["manifest"]


def test_reduced_evaluation_reproduces_the_stored_scores():
    """8 windows of 32x32 of the test split, one thread: every PSNR within 0.05 dB of the stored one."""
    doc = _scores()
    stored = doc["reduced"]["metrics"]
    assert {"psnr_T", "psnr_T_base", "psnr_T_oracle", "psnr_T_tfp", "psnr_R", "ssim_T"} <= set(stored)
    setting = {**doc["reduced"]["setting"], "manifest": str(REPO / doc["reduced"]["setting"]["manifest"])}  # any cwd
    fresh = evaluate_setting(DEFAULT_WEIGHTS, setting, threads=1)
    bad = compare_reduced(stored, fresh, REPRODUCE_TOL_DB)
    assert not bad, "the shipped checkpoint no longer reproduces its stored scores (rerun `" + doc["command"] + "` if the change is intended):\n" + "\n".join(bad)


def test_stored_scores_match_psnr_computed_here_by_hand():
    """The stored reduced scores by an independent path: the same held-out windows, PSNR written out here in
    numpy (per window 10 log10(1 / MSE) with the estimate clipped to [0, 1], then the mean), for TFP from its
    closed form (2 x the mean of the N observations, no network) and for the network's T from one forward pass;
    both within the reproduction tolerance of the stored numbers.
    """
    import numpy as np

    from polspike.commands.train_cmds import heldout_inputs, heldout_test_set
    from reconstruct.net.train import batch_inputs, collate

    doc = _scores()
    st, stored = doc["reduced"]["setting"], doc["reduced"]["metrics"]
    model, _ = load_model(DEFAULT_WEIGHTS, "cpu")
    ds = heldout_test_set(st["crop"], st["items"], st["seed"], str(REPO / st["manifest"]), light=st.get("light", "range"), **heldout_inputs(model))
    b = collate([ds[i] for i in range(len(ds))])
    with torch.no_grad():
        x = batch_inputs(b, "cpu", model.cfg)
        out = model.eval()(x.I, x.phi, **x.extras())
    T = b["T"].double().numpy()

    def psnr(est):
        mse = ((np.clip(est, 0, 1) - T) ** 2).reshape(len(T), -1).mean(1)
        return float(np.mean(10 * np.log10(1.0 / mse)))

    assert psnr(2 * b["I"].double().numpy().mean(1)) == pytest.approx(stored["psnr_T_tfp"], abs=REPRODUCE_TOL_DB)
    assert psnr(out.T.double().numpy()) == pytest.approx(stored["psnr_T"], abs=REPRODUCE_TOL_DB)

def test_model_card_quotes_the_stored_scores():
    doc = _scores()
    card = CARD.read_text()
    assert DEFAULT_WEIGHTS.name in card.splitlines()[0], "the model card's title must name the default checkpoint"
    assert doc["command"] in card, "the model card must show the command that regenerates its numbers"
    line = summary_line(doc["model_card"]["metrics"])  # the line `polspike checkpoint-scores` prints
    assert line in card, f"docs/MODEL_CARD.md must quote the stored scores verbatim: {line!r}"
    # and the score table's final-network row carries the same numbers
    m = doc["model_card"]["metrics"]
    row = next((ln for ln in card.splitlines() if ln.startswith("| **final**")), "")
    cells = [c.strip(" *") for c in row.strip("|").split("|")]
    assert cells[1:5] == [f"{m['psnr_T']:.2f}", f"{m['ssim_T']:.3f}", f"{m['psnr_R']:.2f}", f"{m['ssim_R']:.3f}"], row


@pytest.mark.parametrize("arch", sorted(EXPECTED_PARAMS))
def test_exact_parameter_count(arch):
    assert count_parameters(PolSpikeNet(NetConfig(arch=arch))) == EXPECTED_PARAMS[arch]


def test_default_architecture_and_shipped_checkpoint_parameter_counts():
    assert NetConfig().arch in EXPECTED_PARAMS
    assert DEFAULT_WEIGHTS.name in EXPECTED_SHIPPED, f"pin the parameter count of the new default {DEFAULT_WEIGHTS.name} in EXPECTED_SHIPPED"
    model, data = load_model(DEFAULT_WEIGHTS)
    n = count_parameters(model)
    assert n == EXPECTED_SHIPPED[DEFAULT_WEIGHTS.name] == data["param_count"]
    assert sum(t.numel() for k, t in data["state_dict"].items() if t.dtype.is_floating_point and "running_" not in k) >= n
    assert f"{n:,}" in CARD.read_text(), f"the model card must state the exact count {n:,}"


@pytest.mark.slow
def test_checkpoint_scores_check_exit_code(polspike_cli, tmp_path):
    """`polspike checkpoint-scores --check`: exit 0 for the shipped pair, 1 when the stored numbers are off."""
    import shutil

    ok = polspike_cli("checkpoint-scores", DEFAULT_WEIGHTS, "--check", timeout=600)
    assert ok.returncode == 0 and "reproduced" in " ".join(ok.stdout.split()), ok.stdout[-600:] + ok.stderr[-600:]
    w = shutil.copy(DEFAULT_WEIGHTS, tmp_path / DEFAULT_WEIGHTS.name)
    doc = _scores()
    doc["reduced"]["metrics"]["psnr_T"] += 0.1
    doc["reduced"]["setting"]["manifest"] = str(REPO / doc["reduced"]["setting"]["manifest"])
    scores_path(w).write_text(json.dumps(doc))
    bad = polspike_cli("checkpoint-scores", w, "--check", timeout=600)
    assert bad.returncode == 1 and "psnr_T: stored" in bad.stdout, bad.stdout[-600:] + bad.stderr[-600:]
