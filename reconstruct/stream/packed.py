"""Packed spike streams and Eq. (3) window counts without unpacking to bytes.

A .dat holds a frame as H W bits, eight pixels a byte (LSB first).  The count of a pixel over a window
of n <= 255 steps is summed on the packed bytes directly: every byte is mapped to a 64-bit word that
holds its eight bits in eight byte lanes (a 256-entry table), and the words of the window's steps are
added; no lane can carry into the next (at most n <= 255 per lane), so the sum's bytes are the eight
pixels' counts, in pixel order on a little-endian machine.  One table look-up and one 64-bit add per
eight pixel-steps, and only the steps inside windows are read at all (13 of every ~58 at 31.5 deg).

:class:`PackedDat` reads a .dat by offset, also while a camera is still writing it (:meth:`PackedDat.refresh`
sees the frames that have arrived; a partly written last frame waits).  :class:`PackedArray` wraps packed
frames already in memory or made on the fly (:func:`reconstruct.stream.pane_stream.pane_stream_packed`).
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from polinfra.errors import DataFormatError, ShapeError

__all__ = ["LANES", "window_counts", "window_radiance", "PackedDat", "PackedArray", "PackedChunks"]

log = logging.getLogger(__name__)


def _lanes() -> np.ndarray:
    b = np.arange(256, dtype=np.uint64)
    out = np.zeros(256, np.uint64)
    for i in range(8):
        out |= ((b >> np.uint64(i)) & np.uint64(1)) << np.uint64(8 * i)
    return out


LANES = _lanes()
"""Byte -> 64-bit word with bit i of the byte in byte lane i."""

if sys.byteorder != "little":  # pragma: no cover - every supported platform is little-endian
    LANES = LANES.byteswap()


def window_counts(packed: np.ndarray, height: int, stored_w: int, width: int, flip: bool) -> np.ndarray:
    """Per-pixel spike counts over the steps of ``packed`` (n, H stored_w / 8) uint8, n <= 255.

    Returns:
        (height, width) uint8 counts, upright when ``flip`` (a .dat stores frames upside down), the
        header columns of a camera file dropped (``stored_w`` > ``width``).
    """
    n = packed.shape[0]
    if n > 255:
        raise ShapeError(f"a packed window sums at most 255 steps per byte lane; got {n}", packed.shape, "(<= 255, bytes)")
    if packed.shape[1] * 8 != height * stored_w:
        raise ShapeError(f"packed frames of {packed.shape[1]} bytes are not {height} x {stored_w} bits", packed.shape, f"(n, {height * stored_w // 8})")
    words = LANES[packed[0]]
    for k in range(1, n):
        words += LANES[packed[k]]
    c = words.view(np.uint8).reshape(height, stored_w)
    if flip:
        c = c[::-1]
    return c[:, :width]


def _radiance_py(packed, lanes, words, height, stored_w, width, flip, scale, out):  # pragma: no cover - compiled by numba
    n, nb = packed.shape
    for j in range(nb):
        words[j] = lanes[packed[0, j]]
    for k in range(1, n):
        for j in range(nb):
            words[j] += lanes[packed[k, j]]
    c = words.view(np.uint8)  # the pixels' counts in pixel order (little-endian byte lanes)
    for y in range(height):
        row = (height - 1 - y if flip else y) * stored_w
        for x in range(width):
            out[y, x] = np.float32(c[row + x]) / scale


_radiance = None


def window_radiance(packed: np.ndarray, height: int, stored_w: int, width: int, flip: bool, scale: np.float32, out: np.ndarray) -> np.ndarray:
    """``window_counts(...).astype(np.float32) / scale`` written into ``out`` (height, width) float32 in one numba pass
    (the same float32 values, bit for bit; no byte-lane words or counts kept), the GIL released.
    """
    global _radiance
    n = packed.shape[0]
    if n > 255:
        raise ShapeError(f"a packed window sums at most 255 steps per byte lane; got {n}", packed.shape, "(<= 255, bytes)")
    if packed.shape[1] * 8 != height * stored_w:
        raise ShapeError(f"packed frames of {packed.shape[1]} bytes are not {height} x {stored_w} bits", packed.shape, f"(n, {height * stored_w // 8})")
    if out.shape != (height, width) or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ShapeError(f"out must be a contiguous ({height}, {width}) float32 array; got {out.shape} {out.dtype}", out.shape, f"({height}, {width})")
    if _radiance is None:
        import numba

        _radiance = numba.njit(cache=True, nogil=True)(_radiance_py)
    _radiance(np.ascontiguousarray(packed), LANES, np.empty(packed.shape[1], np.uint64), int(height), int(stored_w), int(width), bool(flip), np.float32(scale), out)
    return out


class _WindowReads:
    """Eq. (3) windows of a packed reader (``read(a, b)``, ``height``, ``stored_w``, ``width``, ``flip``)."""

    def counts(self, a: int, b: int) -> np.ndarray:
        """Upright (H, W) spike counts over steps a..b-1."""
        return window_counts(self.read(a, b), self.height, self.stored_w, self.width, self.flip)

    def radiance(self, a: int, b: int, scale: np.float32, out: np.ndarray) -> np.ndarray:
        """``counts(a, b).astype(np.float32) / scale`` into ``out`` (:func:`window_radiance`)."""
        return window_radiance(self.read(a, b), self.height, self.stored_w, self.width, self.flip, scale, out)


class PackedArray(_WindowReads):
    """Packed upright frames (T, H W / 8) in memory, with the reading interface of :class:`PackedDat`."""

    flip = False

    def __init__(self, packed: np.ndarray, height: int, width: int):
        if packed.ndim != 2 or packed.shape[1] * 8 != height * width:
            raise ShapeError(f"packed frames must be (T, {height * width // 8}); got {packed.shape}", packed.shape, f"(T, {height * width // 8})")
        self.packed, self.height, self.width, self.stored_w = packed, height, width, width
        self.frames = packed.shape[0]

    def refresh(self) -> int:
        return self.frames

    def read(self, a: int, b: int) -> np.ndarray:
        return self.packed[a:b]

    def close(self) -> None:
        pass


class PackedChunks(PackedArray):
    """A packed stream made chunk by chunk (an iterator of (t, H W / 8) arrays), read forward only in bounded
    memory: steps before the last ``keep`` read are dropped.  ``frames`` grows as chunks are pulled.
    """

    def __init__(self, chunks: Iterator[np.ndarray], height: int, width: int, total: int):
        self._it = iter(chunks)
        self.height, self.width, self.stored_w = height, width, width
        self.total = int(total)
        self._buf = np.zeros((0, height * width // 8), np.uint8)
        self._start = 0  # step index of _buf[0]
        self.frames = 0

    def refresh(self) -> int:
        return self.total

    def read(self, a: int, b: int) -> np.ndarray:
        if a < self._start:
            raise ShapeError(f"steps {a}..{b} were already dropped (stream read forward from {self._start})", (a, b), f">= {self._start}")
        while self._start + self._buf.shape[0] < b:
            nxt = next(self._it, None)
            if nxt is None:
                raise ShapeError(f"steps {a}..{b} past the end of the stream ({self._start + self._buf.shape[0]} steps)", (a, b), "inside the stream")
            drop = max(0, a - self._start)
            self._buf = np.concatenate([self._buf[drop:], nxt])
            self._start += drop
        return self._buf[a - self._start : b - self._start]


class PackedDat(_WindowReads):
    """A raw Vidar .dat read by offset (``spike_sim.vidar_dat``'s layout: upside down, LSB first, optional 16 header
    columns), also while it grows.

    Args:
        path: the file.
        height, width: image size; ``stored_w``: columns per stored frame (``width`` or ``width + 16``), None =
            from the file size as :func:`spike_sim.vidar_dat.dat_frame_count` (a growing file: ``width``).
    """

    flip = True

    def __init__(self, path: str | os.PathLike, height: int, width: int, stored_w: int | None = None):
        self.path = Path(path)
        self.height, self.width = int(height), int(width)
        if stored_w is None:
            from spike_sim.vidar_dat import _layout

            stored_w = _layout(self.path, height, width)[0] if self.path.is_file() and self.path.stat().st_size > 0 else width
        if (height * stored_w) % 8:
            raise DataFormatError(f"{self.path}: a {height} x {stored_w} frame is not a whole number of bytes (H W divisible by 8)")
        self.stored_w = int(stored_w)
        self.frame_bytes = self.height * self.stored_w // 8
        self._fd: int | None = None
        self.frames = 0

    def refresh(self) -> int:
        """Whole frames in the file now (a partly written last frame is not counted)."""
        try:
            size = os.stat(self.path).st_size
        except FileNotFoundError:
            size = 0
        self.frames = size // self.frame_bytes
        return self.frames

    def read(self, a: int, b: int) -> np.ndarray:
        """Packed frames a..b-1, (b - a, frame_bytes) uint8, as stored (upside down)."""
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDONLY)
        nb = (b - a) * self.frame_bytes
        raw = os.pread(self._fd, nb, a * self.frame_bytes)
        if len(raw) != nb:
            raise DataFormatError(f"{self.path}: frames {a}..{b} asked, the file holds {self.refresh()}")
        return np.frombuffer(raw, np.uint8).reshape(b - a, self.frame_bytes)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def packed_source(reader, steps: int, phi0_rad: float, rev_per_s: float, rate_hz: float, name: str, chunk_steps: int = 500):
    """A :class:`reconstruct.stream.sources.SpikeSource` over the first ``steps`` steps of a packed reader (unpacked
    chunk by chunk): what the self-calibration and the exposure estimate read of a file that may still grow.
    """
    import math

    from reconstruct.stream.sources import SpikeSource

    t = (np.arange(steps) + 0.5) / rate_hz
    phi = phi0_rad + 2 * math.pi * rev_per_s * t
    H, W = reader.height, reader.width

    def chunks():
        for s in range(0, steps, chunk_steps):
            raw = reader.read(s, min(steps, s + chunk_steps))
            bits = np.unpackbits(raw, axis=1, bitorder="little").reshape(raw.shape[0], H, reader.stored_w)
            if reader.flip:
                bits = bits[:, ::-1]
            yield s, np.ascontiguousarray(bits[:, :, :W])

    return SpikeSource(chunks, phi, H, W, rate_hz, rev_per_s, name)
