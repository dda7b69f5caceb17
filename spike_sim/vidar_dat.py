"""Raw Vidar ``.dat`` spike files, read and written exactly as SpikeCV and spikezoo do.

Layout (see ../shared/data/real_spikes/README.md):

* no header; frames of H x W bits are concatenated (H W / 8 bytes per frame);
  a file whose size is not a whole number of frames is malformed;
* inside a frame, row-major, pixel 8k + i is bit i of byte k (LSB first), i.e.
  ``np.packbits(frame, bitorder="little")``;
* the file stores the image UPSIDE DOWN: readers flip rows after unpacking,
  writers flip before packing;
* camera files may be 416 columns wide: 16 extra header columns, dropped on
  read (spikezoo's ``remove_head``: the last 16 columns after the flip).

Streams in memory are (T, H, W) uint8 0/1, upright (row 0 at the top).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from polinfra.atomic import atomic_path, finish_atomic
from polinfra.errors import DataFormatError, OutputError, ShapeError

__all__ = ["read_dat", "iter_dat", "write_dat", "DatWriter", "dat_frame_count", "CAMERA_WIDTH", "HEAD_COLUMNS"]

log = logging.getLogger(__name__)

CAMERA_WIDTH = 416
"""Width of raw camera files that carry 16 header columns."""
HEAD_COLUMNS = 16


def _layout(path: Path, height: int, width: int, head_columns: int | None = None) -> tuple[int, int]:
    """(stored width, frame count) of a .dat file; DataFormatError when malformed.

    ``head_columns``: None = auto (the plain width if the size fits it, else
    ``width + 16`` camera frames), 0 = plain frames only, 16 = camera frames only.
    A size that fits both (a camera file of 25 k frames of 416 columns is also 26 k
    frames of 400) is read as plain frames with a logged warning: pass
    ``head_columns=16`` for camera files.
    """
    if not path.is_file():
        raise DataFormatError(f"spike file not found: {path}")
    if head_columns not in (None, 0, HEAD_COLUMNS):
        raise DataFormatError(f"head_columns must be None (auto), 0 or {HEAD_COLUMNS}, got {head_columns!r}")
    size = path.stat().st_size
    if size == 0:
        raise DataFormatError(f"{path} is empty: a .dat holds at least one {height}x{width} frame ({height * width // 8} bytes)")
    cands = (width, width + HEAD_COLUMNS) if head_columns is None else (width + head_columns,)
    fits = [w for w in cands if (height * w) % 8 == 0 and height * w // 8 > 0 and size % (height * w // 8) == 0]
    if fits:
        if len(fits) > 1:
            log.warning("%s: %d bytes is a whole number of both %dx%d and %dx%d frames; reading %d columns (pass head_columns=%d for a camera file)",
                        path, size, height, fits[0], height, fits[1], fits[0], HEAD_COLUMNS)
        w = fits[0]
        return w, size // (height * w // 8)
    raise DataFormatError(
        f"{path}: {size} bytes is not a whole number of {height}x{width} frames ({height * width // 8} bytes each)"
        f" nor of {height}x{width + HEAD_COLUMNS} camera frames; check --height/--width"
    )


def dat_frame_count(path: str | os.PathLike, height: int = 250, width: int = 400, head_columns: int | None = None) -> int:
    """Number of frames in a .dat file (``head_columns`` as in :func:`read_dat`)."""
    return _layout(Path(path), height, width, head_columns)[1]


def _decode(raw: np.ndarray, n: int, height: int, stored_w: int, width: int, flip: bool) -> np.ndarray:
    bits = np.unpackbits(raw.reshape(n, height * stored_w // 8), axis=1, bitorder="little")
    frames = bits.reshape(n, height, stored_w)
    if flip:
        frames = frames[:, ::-1, :]
    if stored_w != width:
        frames = frames[:, :, :width]
    return np.ascontiguousarray(frames)


def iter_dat(
    path: str | os.PathLike, height: int = 250, width: int = 400, chunk_frames: int = 1000, flip: bool = True, head_columns: int | None = None
) -> Iterator[np.ndarray]:
    """Yield (t, H, W) uint8 chunks of a .dat file, memory bounded by ``chunk_frames``."""
    p = Path(path)
    stored_w, n = _layout(p, height, width, head_columns)
    fb = height * stored_w // 8
    with open(p, "rb") as fh:
        for start in range(0, n, chunk_frames):
            m = min(chunk_frames, n - start)
            raw = np.frombuffer(fh.read(m * fb), dtype=np.uint8)
            yield _decode(raw, m, height, stored_w, width, flip)


def read_dat(
    path: str | os.PathLike,
    height: int = 250,
    width: int = 400,
    frames: slice | None = None,
    flip: bool = True,
    head_columns: int | None = None,
) -> np.ndarray:
    """Read a raw Vidar .dat file.

    Args:
        path: the file.
        height, width: frame size of the image (a 416-wide camera file is
            recognised and its 16 header columns dropped).
        frames: optional slice of frame indices (read lazily via memory map).
        flip: undo the upside-down storage (True = what SpikeCV / spikezoo do).
            ``flip=False`` exists to show what a reader that forgets it sees.
        head_columns: None = auto-detect 16 camera header columns from the file
            size (plain frames win when both fit, with a logged warning); 0 or 16
            to say which (spikezoo's ``remove_head``).

    Returns:
        (T, H, W) uint8 spikes, upright when ``flip``.

    Raises:
        DataFormatError: missing file or size not a whole number of frames.
    """
    p = Path(path)
    stored_w, n = _layout(p, height, width, head_columns)
    fb = height * stored_w // 8
    if frames is not None and not isinstance(frames, slice):
        raise DataFormatError(f"frames must be a slice of frame indices, got {type(frames).__name__}")
    sel = range(n)[frames] if frames is not None else range(n)
    if len(sel) == 0:
        return np.zeros((0, height, width), np.uint8)
    mm = np.memmap(p, dtype=np.uint8, mode="r", shape=(n, fb))
    raw = np.asarray(mm[frames]) if frames is not None else np.asarray(mm)
    return _decode(raw, raw.shape[0], height, stored_w, width, flip)


def _encode(spikes: np.ndarray, flip: bool) -> bytes:
    if spikes.ndim != 3:
        raise ShapeError(f"spikes must be (T, H, W), got shape {spikes.shape}", spikes.shape, "(T, H, W)")
    T, H, W = spikes.shape
    if (H * W) % 8:
        raise ShapeError(f"a .dat frame needs H*W divisible by 8, got {H}x{W}", spikes.shape, "(T, H, W) with H*W % 8 == 0")
    f = spikes[:, ::-1, :] if flip else spikes
    return np.packbits(np.ascontiguousarray(f, dtype=np.uint8).reshape(T, H * W) != 0, axis=1, bitorder="little").tobytes()


def write_dat(path: str | os.PathLike, spikes: np.ndarray, flip: bool = True) -> Path:
    """Write (T, H, W) 0/1 spikes as a raw .dat file (atomically), upside down like SpikeCV."""
    with DatWriter(path, flip=flip) as w:
        w.write(spikes)
    return Path(path)


class DatWriter:
    """Streaming .dat writer: append (t, H, W) chunks; the file appears only on close.

    Use as a context manager; on an exception the temporary file is removed.
    Also accepts packed upright frames (t, H*W/8) via :meth:`write_packed`.
    """

    def __init__(self, path: str | os.PathLike, flip: bool = True):
        self.path = Path(path)
        self.flip = flip
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        self._fh = open(self._tmp, "wb")
        self.frames = 0
        self.shape: tuple[int, int] | None = None

    def write(self, spikes: np.ndarray) -> None:
        """Append upright (t, H, W) 0/1 frames."""
        spikes = np.asarray(spikes)
        if self.shape is None:
            self.shape = spikes.shape[1:]
        elif spikes.shape[1:] != self.shape:
            raise ShapeError(f"chunk frames are {spikes.shape[1:]}, earlier ones were {self.shape}", spikes.shape, f"(t, {self.shape[0]}, {self.shape[1]})")
        self._fh.write(_encode(spikes, self.flip))
        self.frames += spikes.shape[0]

    def write_packed(self, packed: np.ndarray, height: int, width: int) -> None:
        """Append upright frames packed LSB-first per frame, (t, ceil(H W / 8)) uint8."""
        if self.flip and width % 8 == 0:
            rows = packed.reshape(packed.shape[0], height, width // 8)[:, ::-1, :]
            self._fh.write(np.ascontiguousarray(rows).tobytes())
            self.frames += packed.shape[0]
            self.shape = (height, width)
        else:
            bits = np.unpackbits(packed, axis=1, bitorder="little", count=height * width).reshape(-1, height, width)
            self.write(bits)

    def close(self, ok: bool = True) -> None:
        """Finish the file (rename into place) or discard it."""
        if self._fh.closed:
            return
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        try:
            finish_atomic(self._ctx, ok)
        except OSError as exc:  # pragma: no cover - disk errors
            raise OutputError(f"cannot write {self.path}: {exc}") from None

    def __enter__(self) -> DatWriter:
        return self

    def __exit__(self, et, ev, tb) -> None:
        self.close(ok=et is None)
