"""8-bit display frames of the live path in one numba pass: T, R and the side-by-side preview (input | T | R).

:func:`to8_frames` gives what the table lookup ``reconstruct.video.live._to8_fast`` gives for each of its five
images (the same float32 index arithmetic, the same 65536-entry gamma table; tested equal), written straight into
the preview's columns: no temporaries, no concatenation, and the GIL released (it runs on the encoding thread).
Without the preview only T and R are converted.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to8_frames"]


def _row(src, g, table, dst, col0, idx, top):  # pragma: no cover - compiled (inlined into _kernel)
    """One row: the float32 index arithmetic first (it vectorises), then the table gathers."""
    half = np.float32(0.5)
    zero = np.float32(0.0)
    W = src.shape[0]
    for x in range(W):
        idx[x] = np.uint16(min(max(src[x] * g + half, zero), top))
    for x in range(W):
        dst[col0 + x] = table[idx[x]]


def _kernel(I2, T, R, gT, gR, gP, table, t8, r8, prev, with_prev, idx):  # pragma: no cover - compiled
    H, W = T.shape
    top = np.float32(table.shape[0] - 1)
    for y in range(H):
        _row_c(T[y], gT, table, t8[y], 0, idx, top)
        _row_c(R[y], gR, table, r8[y], 0, idx, top)
        if with_prev:
            _row_c(I2[y], gP, table, prev[y], 0, idx, top)
            _row_c(T[y], gP, table, prev[y], W, idx, top)
            _row_c(R[y], gP, table, prev[y], 2 * W, idx, top)


_compiled = None
_row_c = None


def to8_frames(I2: np.ndarray, T: np.ndarray, R: np.ndarray, gains: dict[str, float], table: np.ndarray, preview: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(T8, R8, preview8) uint8 of float32 (H, W) images; ``gains`` has T, R, preview; ``table`` the gamma table;
    without ``preview`` the third is None (not converted).
    """
    global _compiled
    if _compiled is None:
        import numba

        global _row_c
        _row_c = numba.njit(cache=True, nogil=True, inline="always")(_row)
        _compiled = numba.njit(cache=True, nogil=True)(_kernel)
    H, W = T.shape
    n = np.float32(table.shape[0] - 1)
    t8 = np.empty((H, W), np.uint8)
    r8 = np.empty((H, W), np.uint8)
    prev = np.empty((H, 3 * W) if preview else (1, 1), np.uint8)
    f = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    _compiled(f(I2), f(T), f(R), np.float32(gains["T"] * n), np.float32(gains["R"] * n), np.float32(gains["preview"] * n), table, t8, r8, prev, bool(preview),
              np.empty(W, np.uint16))
    return t8, r8, (prev if preview else None)
