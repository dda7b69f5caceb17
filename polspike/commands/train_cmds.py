"""``polspike train`` and ``polspike reconstruct``: the learned reconstructor's CLI (issue 9).

The CLI is the one place that wires the generator's layer content into
``reconstruct``'s on-the-fly window source (``reconstruct`` never imports
``generator``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from polspike.cli import app_typer
from polspike.errors import ConfigError

HELDOUT_IMAGES = ("chelsea", "coins", "grass", "text")
"""Bundled images kept out of on-the-fly training (validation / test content)."""


def generator_images(names: tuple[str, ...] | None = None, heldout: bool = False, size: int = 320):
    """Linear grey layer images from the generator's bundled offline content.

    Args:
        names: skimage names (default: all bundled names minus / only :data:`HELDOUT_IMAGES`).
        heldout: with ``names`` None, return the held-out set instead of the training set.
        size: images are fitted to size x size pixels.
    """
    from generator.layers import SKIMAGE_NAMES, load_source

    if names is None:
        names = tuple(n for n in SKIMAGE_NAMES if (n in HELDOUT_IMAGES) == heldout)
    return [load_source(f"skimage:{n}", (size, size))[0] for n in names]


def on_the_fly_sets(cfg, seed_val: int = 10_000):
    """(train set, validation set) of on-the-fly windows on disjoint image content."""
    from reconstruct.onthefly import ImageLayerProvider, OnTheFlyWindows

    train_set = OnTheFlyWindows(ImageLayerProvider(generator_images()), cfg.window, length=cfg.train_items, seed=cfg.seed)
    val_set = OnTheFlyWindows(ImageLayerProvider(generator_images(heldout=True)), cfg.window, length=cfg.val_items, seed=cfg.seed + seed_val)
    return train_set, val_set


@app_typer.command("train")
def train_cmd(
    config: Optional[Path] = typer.Argument(None, help="training TOML ([net], [loss], [solver], [window] tables; TrainConfig keys) [default: built-in defaults]"),
    out: Path = typer.Option(..., "--out", help="run directory (last.pt, log.csv, curves.png); an existing run is resumed"),
    data: Optional[Path] = typer.Option(None, "--data", help="built dataset directory (stored windows); omit to generate windows on the fly"),
    minutes: Optional[float] = typer.Option(None, "--minutes", help="stop after this many minutes (checkpointed; rerun to continue)"),
    device: Optional[str] = typer.Option(None, "--device", help="auto | cpu | cuda [default: config device]"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Train the reconstructor (paper Sec. 3.4 curriculum); resumable, deterministic for a seed on CPU."""
    import dataclasses

    from rich.console import Console

    from polspike.config import from_dict, load_toml
    from polspike.progress import rich_progress
    from reconstruct.train import TrainConfig, train

    cfg = from_dict(TrainConfig, load_toml(config), where=str(config)) if config else TrainConfig()
    if device:
        cfg = dataclasses.replace(cfg, device=device)
    if data is None:
        train_set, val_set = on_the_fly_sets(cfg)
        src = "on-the-fly windows (generator content, closed-form spike model)"
    else:
        try:
            from reconstruct.data import open_window_datasets  # dataset issue's stored-window loader
        except ImportError:
            raise ConfigError("stored-dataset training needs reconstruct.data (not available in this checkout); omit --data to train on the fly") from None
        train_set, val_set = open_window_datasets(data, cfg)
        src = f"stored windows in {data}"
    with rich_progress("train", enabled=not quiet) as cb:
        res = train(cfg, train_set, val_set, out, progress=cb, max_seconds=None if minutes is None else 60.0 * minutes)
    c = Console()
    c.print(f"data: {src}")
    c.print(f"PolSpikeNet: {res['param_count']:,} trainable parameters; step {res['step']}/{res['total_steps']}")
    m = res["metrics"]
    if m:
        c.print(f"validation PSNR of T: full {m['psnr_T']:.2f} dB, RWPS (learned zeta) {m['psnr_T_base']:.2f} dB, RWPS (GT zeta) {m['psnr_T_oracle']:.2f} dB")
    c.print(f"run directory: {out}")
