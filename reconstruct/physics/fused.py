"""The plain least-squares solver as one fused pass per pixel (numba), for the real-time stream.

:func:`ls_fused` gives what ``solve("ls", zeta, I)`` of :mod:`reconstruct.physics.solvers` gives (supp. Eq. (9)
with lambda = 0 and unit weights: the 2 x 2 normal equations per pixel, the same diagonal floor), clamped at 0
as the stream clamps, but reads each observation once and keeps the moments in registers: no (N, H, W)
temporaries.  Sums run in float64 (the torch path sums float32), so the two agree to float32 rounding of the
moments (tested: relative 1e-4 of the frame's peak).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ls_fused"]

_TINY4 = float(np.finfo(np.float32).tiny) ** 0.25  # the torch solver's floor constant for float32
_EPS = 1e-7


def _kernel_py(z, I, T, R):  # pragma: no cover - compiled by numba below; kept plain for reading
    N, P = z.shape
    for p in range(P):
        srr = srt = stt = rr = rt = 0.0
        for k in range(N):
            a = np.float64(z[k, p])
            bt = 1.0 - a
            b = 2.0 * np.float64(I[k, p])
            srr += a * a
            srt += a * bt
            stt += bt * bt
            rr += a * b
            rt += bt * b
        floor = _EPS * (srr + stt) + _TINY4
        m11 = srr + floor
        m22 = stt + floor
        det = m11 * m22 - srt * srt
        r = (m22 * rr - srt * rt) / det
        t = (m11 * rt - srt * rr) / det
        R[p] = r if r > 0.0 else 0.0
        T[p] = t if t > 0.0 else 0.0


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
    _get()(z, i, T, R)
    return T.reshape(H, W), R.reshape(H, W)
