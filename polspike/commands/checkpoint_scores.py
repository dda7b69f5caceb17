"""``polspike checkpoint-scores``: the stored test scores beside a shipped checkpoint (model card source)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer


@app_typer.command("checkpoint-scores")
def checkpoint_scores_cmd(
    weights: Optional[Path] = typer.Argument(None, help="checkpoint [default: the shipped default, reconstruct.net.checkpoint.DEFAULT_WEIGHTS]"),
    manifest: str = typer.Option("datasets/manifests/paper_v1.toml", "--manifest", help="test windows from this manifest's test groups (the model card's test split)"),
    threads: int = typer.Option(1, "--threads", help="torch CPU threads (1 = the setting the stored scores are reproduced with)"),
    reduced_only: bool = typer.Option(False, "--reduced-only", help="recompute only the reduced evaluation (seconds); keep the stored model-card block if it belongs to these weights"),
    light: str = typer.Option("range", "--light", help="range: exposures from the default range (the v1/v2 scores); group: each manifest group's own sensor and light level (paper.toml-trained checkpoints)"),
    check: bool = typer.Option(False, "--check", help="do not write: re-run the reduced evaluation and compare with the stored file (exit 1 beyond 0.05 dB)"),
) -> None:
    """Evaluate a checkpoint on the held-out test set of `polspike evaluate-checkpoint` and write NAME.scores.json beside it.

    Two settings on the test groups of --manifest: "model_card" (96 windows of 64x64, seed 20000:
    the numbers the model card quotes; 1-2 minutes on one core) and "reduced" (8 windows of 32x32:
    the test suite re-runs it and requires every PSNR within 0.05 dB). The file records the
    weights' sha256, the manifest and this command.
    Exit code: 0, or 1 when --check finds a difference, 2 for bad input.
    """
    import json

    from rich.console import Console

    from polinfra.errors import CheckpointError, ConfigError
    from polspike.pipeline.checkpoint_scores import compare_reduced, evaluate_setting, scores_path, sha256_file, summary_line, write_scores
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS

    if threads < 1:
        raise ConfigError(f"--threads {threads} must be >= 1")
    w = Path(weights or DEFAULT_WEIGHTS)
    if not w.is_file():
        raise CheckpointError(f"checkpoint not found: {w}")
    con = Console()
    if check:
        sp = scores_path(w)
        if not sp.is_file():
            raise CheckpointError(f"{sp} missing: run `polspike checkpoint-scores {w} --threads 1`")
        doc = json.loads(sp.read_text())
        if doc.get("weights_sha256") != sha256_file(w):
            con.print(f"{sp} belongs to other weights (sha256 differs): rerun `{doc.get('command', 'polspike checkpoint-scores')}`")
            raise typer.Exit(1)
        bad = compare_reduced(doc["reduced"]["metrics"], evaluate_setting(w, doc["reduced"]["setting"], threads))
        for b in bad:
            con.print(b)
        con.print(f"{sp}: reduced evaluation {'reproduced' if not bad else 'NOT reproduced'} within 0.05 dB")
        if bad:
            raise typer.Exit(1)
        return
    if not Path(manifest).is_file():
        raise ConfigError(f"--manifest {manifest}: file not found")
    if light not in ("range", "group"):
        raise ConfigError(f"--light {light!r}: choose range or group")
    out = write_scores(w, manifest=manifest, threads=threads, model_card=not reduced_only, progress=lambda s: con.print(f"evaluating {w.name}: {s} setting ..."), light=light)
    doc = json.loads(out.read_text())
    for block in ("reduced", "model_card"):
        if block in doc:
            con.print(f"{block}: {summary_line(doc[block]['metrics'])}", soft_wrap=True)
    con.print(f"wrote {out}")
