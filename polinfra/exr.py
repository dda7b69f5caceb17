"""Multichannel float32 OpenEXR read/write (atomic), used by every generator tier.

Channels are named 2-D float32 arrays of shape ``(H, W)``; row 0 is the top of
the image.  Non-finite values are refused on write (no NaN or Inf ever reaches
an output file).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polinfra.atomic import atomic_path
from polinfra.errors import DataFormatError, ShapeError

__all__ = ["write_exr", "read_exr"]


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray], attrs: dict[str, str] | None = None) -> Path:
    """Atomically write float32 channels ``{name: (H, W)}`` to an EXR file.

    Raises:
        ShapeError: channels differ in shape or are not 2-D.
        ValueError: a channel holds NaN or Inf.
    """
    import OpenEXR

    if not channels:
        raise ShapeError("write_exr needs at least one channel")
    shapes = {k: np.shape(v) for k, v in channels.items()}
    first = next(iter(shapes.values()))
    if len(first) != 2 or any(s != first for s in shapes.values()):
        raise ShapeError(f"EXR channels must share one (H, W) shape; got {shapes}", actual_shape=first, expected_shape="(H, W)")
    data = {}
    for k, v in channels.items():
        a = np.ascontiguousarray(v, dtype=np.float32)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"channel {k!r} holds NaN or Inf; refusing to write {path}")
        data[k] = a
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attrs or {}).items():
        header[k] = str(v)
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, data) as f:
            f.write(str(tmp))
    return Path(path)


def read_exr(path: str | os.PathLike, names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Read float32 channels from an EXR file as ``{name: (H, W) float32}``.

    Args:
        path: the file.
        names: channels to return (all when None).

    Raises:
        DataFormatError: file missing, unreadable, or a requested channel absent.
    """
    import OpenEXR

    p = Path(path)
    if not p.is_file():
        raise DataFormatError(f"EXR file not found: {p}")
    try:
        with OpenEXR.File(str(p), separate_channels=True) as f:
            chans = {k: np.asarray(c.pixels, dtype=np.float32) for k, c in f.channels().items()}
    except Exception as exc:  # OpenEXR raises plain exceptions on corrupt files
        raise DataFormatError(f"cannot read EXR {p}: {exc}") from None
    if names is None:
        return chans
    missing = [n for n in names if n not in chans]
    if missing:
        raise DataFormatError(f"EXR {p} lacks channels {missing}; it has {sorted(chans)}")
    return {n: chans[n] for n in names}
