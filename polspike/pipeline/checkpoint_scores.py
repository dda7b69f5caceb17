"""Stored test scores of a shipped checkpoint, so the model card cannot drift from the weights.

``polspike checkpoint-scores WEIGHTS`` evaluates a checkpoint twice on the held-out synthetic
test set of ``polspike evaluate-checkpoint`` (on-the-fly windows of the test groups of
``datasets/manifests/paper_v1.toml`` by default, the split the shipped checkpoints were scored on):

* ``model_card``: the model card's setting (96 windows of 64x64, seed 20000); the card quotes
  these numbers;
* ``reduced``: a small deterministic setting (8 windows of 32x32, same seed, one torch thread)
  that the test suite re-runs in seconds and compares within 0.05 dB
  (``tests/recon/test_shipped_checkpoint.py``).

Both go to ``<weights stem>.scores.json`` beside the weights, with the weights' sha256 (a
scores file of other weights is detected), the manifest whose test groups were used, and the
exact command that regenerates it.  The test set is generated from the manifest by the generator
and spike_sim, so a change there that moves the numbers also calls for regenerating the file.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

SCORES_FORMAT = "polspike-scores/1"
DEFAULT_MANIFEST = "datasets/manifests/paper_v1.toml"  # the split the shipped checkpoints were trained and scored on
MODEL_CARD_SETTING = {"items": 96, "crop": 64, "seed": 20_000}
REDUCED_SETTING = {"items": 8, "crop": 32, "seed": 20_000}
REPRODUCE_TOL_DB = 0.05
"""Allowed |PSNR difference| (dB) between a re-run of the reduced evaluation and the stored one."""

__all__ = ["SCORES_FORMAT", "DEFAULT_MANIFEST", "MODEL_CARD_SETTING", "REDUCED_SETTING", "REPRODUCE_TOL_DB", "scores_path", "sha256_file", "summary_line", "evaluate_setting", "write_scores", "compare_reduced"]


def scores_path(weights: str | os.PathLike) -> Path:
    """``reconstruct/weights/NAME.pt`` -> ``reconstruct/weights/NAME.scores.json``."""
    p = Path(weights)
    return p.with_name(p.stem + ".scores.json")


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def evaluate_setting(weights: str | os.PathLike, setting: dict[str, Any], threads: int = 1) -> dict[str, float]:
    """PSNR / SSIM of ``weights`` on the held-out test set of ``setting`` (CPU, ``threads`` torch threads, as trained: the
    data-consistency floor only where the setting says ``floor = true``; the stored scores predate it).
    """
    import torch

    from polspike.commands.train_cmds import heldout_inputs, heldout_test_set
    from reconstruct.net.checkpoint import load_model
    from reconstruct.net.train import evaluate_model

    old = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        model, _ = load_model(weights, "cpu", floor=bool(setting.get("floor", False)))
        ds = heldout_test_set(setting["crop"], setting["items"], setting["seed"], setting["manifest"], light=setting.get("light", "range"), **heldout_inputs(model))
        with torch.no_grad():
            return evaluate_model(model, ds, batch_size=8, device="cpu", ssim=True)
    finally:
        torch.set_num_threads(old)


def _command(weights: Path, manifest: str, light: str = "range") -> str:
    try:
        shown = weights.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        shown = weights
    return f"polspike checkpoint-scores {shown} --manifest {manifest} --threads 1" + ("" if light == "range" else f" --light {light}")


def write_scores(weights: str | os.PathLike, manifest: str = DEFAULT_MANIFEST, threads: int = 1, model_card: bool = True, progress=None, light: str = "range") -> Path:
    """Evaluate ``weights`` in both settings and write ``scores_path(weights)`` atomically.

    ``model_card=False`` keeps the stored model-card block (when its sha256 matches) and
    recomputes only the reduced one.
    """
    import json

    import torch

    from polinfra.atomic import write_json
    from reconstruct.net.checkpoint import read_checkpoint

    w = Path(weights)
    data = read_checkpoint(w)
    sha = sha256_file(w)
    out = scores_path(w)
    prev = json.loads(out.read_text()) if out.is_file() else {}
    doc: dict[str, Any] = {
        "format": SCORES_FORMAT,
        "weights": w.name,
        "weights_sha256": sha,
        "arch": (data.get("net") or {}).get("arch", "v1"),  # checkpoints without the key are v1
        "step": data.get("step"),
        "manifest": manifest,
        "command": _command(w, manifest, light),
        "torch": torch.__version__,
        "threads": threads,
        "reproduce_tol_db": REPRODUCE_TOL_DB,
    }
    if progress:
        progress("reduced")
    extra = {} if light == "range" else {"light": light}  # range: the settings of the first scores files, unchanged
    reduced = {**REDUCED_SETTING, "manifest": manifest, **extra}
    doc["reduced"] = {"setting": reduced, "metrics": evaluate_setting(w, reduced, threads)}
    if model_card:
        if progress:
            progress("model_card")
        card = {**MODEL_CARD_SETTING, "manifest": manifest, **extra}
        doc["model_card"] = {"setting": card, "metrics": evaluate_setting(w, card, threads)}
    elif prev.get("weights_sha256") == sha and prev.get("manifest") == manifest and "model_card" in prev:
        doc["model_card"] = prev["model_card"]
    write_json(out, doc)
    return out


def summary_line(metrics: dict[str, float]) -> str:
    """One line of the headline scores; the model card quotes the model-card setting's line verbatim."""
    m = metrics
    return (f"T {m['psnr_T']:.2f} dB / SSIM {m['ssim_T']:.3f}; RWPS-only {m['psnr_T_base']:.2f}; oracle {m['psnr_T_oracle']:.2f};"
            f" TFP {m['psnr_T_tfp']:.2f}; R {m['psnr_R']:.2f} / {m['ssim_R']:.3f}")


def compare_reduced(stored: dict[str, Any], fresh: dict[str, float], tol_db: float = REPRODUCE_TOL_DB) -> list[str]:
    """Differences beyond ``tol_db`` (PSNR keys) or ``tol_db / 25`` (SSIM keys) between stored and fresh metrics."""
    bad = []
    for k, v in stored.items():
        if not (k.startswith("psnr") or k.startswith("ssim")):
            continue
        tol = tol_db if k.startswith("psnr") else tol_db / 25.0
        if k not in fresh or abs(float(fresh[k]) - float(v)) > tol:
            bad.append(f"{k}: stored {v:.4f}, now {fresh.get(k, float('nan')):.4f} (tolerance {tol:g})")
    return bad
