"""The plain least-squares solver as one fused pass per pixel (numba), for the real-time stream.

:func:`ls_fused` gives what ``solve("ls", zeta, I)`` of :mod:`reconstruct.physics.solvers` gives (supp. Eq. (9)
with lambda = 0 and unit weights: the 2 x 2 normal equations per pixel, the same diagonal floor), clamped at 0
as the stream clamps, but reads each observation once and keeps the moments of a block of pixels in a small
scratch: no (N, H, W) temporaries.  Sums run in float64 (the torch path sums float32), so the two agree to float32 rounding of the
moments (tested: relative 1e-4 of the frame's peak).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ls_fused"]

_TINY4 = float(np.finfo(np.float32).tiny) ** 0.25  # the torch solver's floor constant for float32
_EPS = 1e-7


def _kernel_py(z, I, T, R, acc):  # pragma: no cover - compiled by numba below; kept plain for reading
    """Blocks of B = acc.shape[1] pixels: the observation loop outside the pixel loop (which vectorises), the moments of
    a block in acc (5, B); per pixel the same sums in the same order as one pixel at a time.
    """
    N, P = z.shape
    B = acc.shape[1]
    srr, srt, stt, rr, rt = acc[0], acc[1], acc[2], acc[3], acc[4]
    for p0 in range(0, P, B):
        n = min(B, P - p0)
        acc[:5, :n] = 0.0  # the five moments of this block
        for k in range(N):
            zk = z[k, p0 : p0 + n]
            ik = I[k, p0 : p0 + n]
            for q in range(n):
                a = np.float64(zk[q])
                bt = 1.0 - a
                b = 2.0 * np.float64(ik[q])
                srr[q] += a * a
                srt[q] += a * bt
                stt[q] += bt * bt
                rr[q] += a * b
                rt[q] += bt * b
        Tq = T[p0 : p0 + n]
        Rq = R[p0 : p0 + n]
        for q in range(n):
            floor = _EPS * (srr[q] + stt[q]) + _TINY4
            m11 = srr[q] + floor
            m22 = stt[q] + floor
            det = m11 * m22 - srt[q] * srt[q]
            r = (m22 * rr[q] - srt[q] * rt[q]) / det
            t = (m11 * rt[q] - srt[q] * rr[q]) / det
            Rq[q] = r if r > 0.0 else 0.0
            Tq[q] = t if t > 0.0 else 0.0


_BLOCK = 4096


_compiled = None


def _get():
    global _compiled
    if _compiled is None:
        import numba

        _compiled = numba.njit(cache=True, nogil=True, fastmath=False)(_kernel_py)
    return _compiled


def ls_fused(zeta: np.ndarray, I: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares T, R (H, W) float32 (clamped at 0) of one window: zeta, I (N, H, W) float32."""
    N, H, W = I.shape
    z = np.ascontiguousarray(zeta, np.float32).reshape(N, H * W)
    i = np.ascontiguousarray(I, np.float32).reshape(N, H * W)
    T = np.empty(H * W, np.float32)
    R = np.empty(H * W, np.float32)
    _get()(z, i, T, R, np.empty((5, min(_BLOCK, H * W))))
    return T.reshape(H, W), R.reshape(H, W)
