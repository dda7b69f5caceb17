"""The plain least-squares solver as one fused pass per pixel (numba), for the real-time stream.

:func:`ls_fused` gives what ``solve("ls", zeta, I)`` of :mod:`reconstruct.physics.solvers` gives (supp. Eq. (9)
with lambda = 0 and unit weights: the 2 x 2 normal equations per pixel, the same diagonal floor), clamped at 0
as the stream clamps, but reads each observation once and keeps the moments of a block of pixels in a small
scratch: no (N, H, W) temporaries.  Sums run in float64 (the torch path sums float32), so the two agree to float32 rounding of the
moments (tested: relative 1e-4 of the frame's peak).  :func:`ls_fused_harmonic` solves the same equations when zeta is
paper Eq. (2) in angle-sum form: the zeta moments in closed form, no zeta frames (the live path's pass).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ls_fused", "ls_fused_harmonic"]

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


def _harmonic_py(I, c, s, m, ac, as_, T, R, acc):  # pragma: no cover - compiled by numba below; kept plain for reading
    """The same normal equations when zeta_k = m + ac c_k + as s_k (paper Eq. (2) by the angle-sum identity): the zeta
    moments are closed forms in six window sums of c_k, s_k; the data moments need three sums of I per pixel.
    """
    N, P = I.shape
    B = acc.shape[1]
    C1 = S1 = C2 = S2 = CS = 0.0
    for k in range(N):
        C1 += c[k]
        S1 += s[k]
        C2 += c[k] * c[k]
        S2 += s[k] * s[k]
        CS += c[k] * s[k]
    n_obs = np.float64(N)
    s0, sc, ss = acc[0], acc[1], acc[2]
    for p0 in range(0, P, B):
        n = min(B, P - p0)
        acc[:3, :n] = 0.0
        k = 0
        while k < N:  # four, two or one observations a pass: fewer loads and stores of the block's sums
            if k + 4 <= N:
                i0, i1, i2, i3 = I[k, p0 : p0 + n], I[k + 1, p0 : p0 + n], I[k + 2, p0 : p0 + n], I[k + 3, p0 : p0 + n]
                c0, c1, c2, c3, e0, e1, e2, e3 = c[k], c[k + 1], c[k + 2], c[k + 3], s[k], s[k + 1], s[k + 2], s[k + 3]
                for q in range(n):
                    v0, v1, v2, v3 = np.float64(i0[q]), np.float64(i1[q]), np.float64(i2[q]), np.float64(i3[q])
                    s0[q] += (v0 + v1) + (v2 + v3)
                    sc[q] += (c0 * v0 + c1 * v1) + (c2 * v2 + c3 * v3)
                    ss[q] += (e0 * v0 + e1 * v1) + (e2 * v2 + e3 * v3)
                k += 4
            elif k + 2 <= N:
                i0, i1 = I[k, p0 : p0 + n], I[k + 1, p0 : p0 + n]
                c0, c1, e0, e1 = c[k], c[k + 1], s[k], s[k + 1]
                for q in range(n):
                    v0, v1 = np.float64(i0[q]), np.float64(i1[q])
                    s0[q] += v0 + v1
                    sc[q] += c0 * v0 + c1 * v1
                    ss[q] += e0 * v0 + e1 * v1
                k += 2
            else:
                i0 = I[k, p0 : p0 + n]
                c0, e0 = c[k], s[k]
                for q in range(n):
                    v0 = np.float64(i0[q])
                    s0[q] += v0
                    sc[q] += c0 * v0
                    ss[q] += e0 * v0
                k += 1
        mq, aq, bq = m[p0 : p0 + n], ac[p0 : p0 + n], as_[p0 : p0 + n]
        Tq = T[p0 : p0 + n]
        Rq = R[p0 : p0 + n]
        for q in range(n):
            mm, a, b = np.float64(mq[q]), np.float64(aq[q]), np.float64(bq[q])
            lin = a * C1 + b * S1
            sz = n_obs * mm + lin  # sum zeta
            srr = mm * (sz + lin) + a * a * C2 + 2.0 * a * b * CS + b * b * S2  # sum zeta^2
            srt = sz - srr
            stt = n_obs - 2.0 * sz + srr
            rr = 2.0 * (mm * s0[q] + a * sc[q] + b * ss[q])  # sum zeta 2 I
            rt = 2.0 * s0[q] - rr
            floor = _EPS * (srr + stt) + _TINY4
            m11 = srr + floor
            m22 = stt + floor
            inv = 1.0 / (m11 * m22 - srt * srt)
            r = (m22 * rr - srt * rt) * inv
            t = (m11 * rt - srt * rr) * inv
            Rq[q] = r if r > 0.0 else 0.0
            Tq[q] = t if t > 0.0 else 0.0


_BLOCK = 4096
_BLOCK_HARMONIC = 1024  # three float64 sums of 1024 pixels stay in the L1 cache


_compiled: dict = {}


def _get(kernel=_kernel_py):
    f = _compiled.get(kernel)
    if f is None:
        import numba

        f = _compiled[kernel] = numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")(kernel)
    return f


def ls_fused(zeta: np.ndarray, I: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares T, R (H, W) float32 (clamped at 0) of one window: zeta, I (N, H, W) float32."""
    N, H, W = I.shape
    z = np.ascontiguousarray(zeta, np.float32).reshape(N, H * W)
    i = np.ascontiguousarray(I, np.float32).reshape(N, H * W)
    T = np.empty(H * W, np.float32)
    R = np.empty(H * W, np.float32)
    _get()(z, i, T, R, np.empty((5, min(_BLOCK, H * W))))
    return T.reshape(H, W), R.reshape(H, W)


def ls_fused_harmonic(I: np.ndarray, cos2: np.ndarray, sin2: np.ndarray, mean: np.ndarray, ac: np.ndarray, as_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`ls_fused` of the window whose zeta is paper Eq. (2) in angle-sum form, zeta_k = mean + ac cos2_k + as_ sin2_k,
    without making zeta: I (N, H, W) float32; cos2, sin2 (N,) the cos and sin of 2 phi_k (with the span factor in ac, as_);
    mean, ac, as_ (H, W) maps, float32 (half the memory traffic of float64; read as float64) or float64.  The zeta moments
    are closed forms in float64 (no float32 rounding of zeta), so the result agrees with :func:`ls_fused` on the float32
    zeta to float32 rounding, not bit for bit (tested).
    """
    N, H, W = I.shape
    i = np.ascontiguousarray(I, np.float32).reshape(N, H * W)
    dt = np.float32 if all(a.dtype == np.float32 for a in (mean, ac, as_)) else np.float64
    f = lambda a, t: np.ascontiguousarray(a, t).reshape(-1)  # noqa: E731
    T = np.empty(H * W, np.float32)
    R = np.empty(H * W, np.float32)
    _get(_harmonic_py)(i, f(cos2, np.float64), f(sin2, np.float64), f(mean, dt), f(ac, dt), f(as_, dt), T, R, np.empty((3, min(_BLOCK_HARMONIC, H * W))))
    return T.reshape(H, W), R.reshape(H, W)
