"""Plot helpers shared by every stage: atomic PNG saving and labelled image panels."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polinfra.atomic import atomic_path

__all__ = ["save_figure", "image_grid"]


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically (PNG by the suffix) and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def image_grid(panels: list[tuple[str, np.ndarray, dict]], ncols: int = 3, title: str | None = None, panel_w: float = 3.6):
    """A figure of image panels, each with a title and a colour bar.

    Args:
        panels: (title, (H, W) array, imshow kwargs such as cmap, vmin, vmax, and
            optionally ``label`` for the colour bar's unit).
        ncols: panels per row.
        title: figure title.

    Returns:
        The matplotlib Figure.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = len(panels)
    nrows = int(np.ceil(n / ncols))
    h, w = panels[0][1].shape
    fig, axes = plt.subplots(nrows, ncols, figsize=(panel_w * ncols, panel_w * ncols * 0 + panel_w * h / w * nrows + 0.6 * nrows), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, (name, img, kw) in zip(axes.ravel(), panels):
        kw = dict(kw)
        label = kw.pop("label", None)
        im = ax.imshow(img, **({"cmap": "gray"} | kw))
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
        if label:
            cb.set_label(label, fontsize=8)
        cb.ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig
