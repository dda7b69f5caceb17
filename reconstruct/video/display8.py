"""8-bit display frames of the live path in one numba pass: T, R and the side-by-side preview (input | T | R).

:func:`to8_frames` gives what the table lookup ``reconstruct.video.live._to8_fast`` gives for each of its five
images (the same float32 index arithmetic, the same 65536-entry gamma table; tested equal), written straight into
the preview's columns: no temporaries, no concatenation, and the GIL released (it runs on the encoding thread).
Without the preview only T and R are converted.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to8_frames"]


def _kernel(I2, T, R, gT, gR, gP, table, t8, r8, prev, with_prev):  # pragma: no cover - compiled
    H, W = T.shape
    top = np.float32(table.shape[0] - 1)
    half = np.float32(0.5)
    zero = np.float32(0.0)
    for y in range(H):
        for x in range(W):
            for src, g, dst, col in ((T[y, x], gT, t8, x), (R[y, x], gR, r8, x)):
                v = min(max(src * g + half, zero), top)
                dst[y, col] = table[np.uint16(v)]
            if not with_prev:
                continue
            for j, src in ((0, I2[y, x]), (1, T[y, x]), (2, R[y, x])):
                v = min(max(src * gP + half, zero), top)
                prev[y, j * W + x] = table[np.uint16(v)]


_compiled = None


def to8_frames(I2: np.ndarray, T: np.ndarray, R: np.ndarray, gains: dict[str, float], table: np.ndarray, preview: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(T8, R8, preview8) uint8 of float32 (H, W) images; ``gains`` has T, R, preview; ``table`` the gamma table;
    without ``preview`` the third is None (not converted).
    """
    global _compiled
    if _compiled is None:
        import numba

        _compiled = numba.njit(cache=True, nogil=True)(_kernel)
    H, W = T.shape
    n = np.float32(table.shape[0] - 1)
    t8 = np.empty((H, W), np.uint8)
    r8 = np.empty((H, W), np.uint8)
    prev = np.empty((H, 3 * W) if preview else (1, 1), np.uint8)
    f = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    _compiled(f(I2), f(T), f(R), np.float32(gains["T"] * n), np.float32(gains["R"] * n), np.float32(gains["preview"] * n), table, t8, r8, prev, bool(preview))
    return t8, r8, (prev if preview else None)
