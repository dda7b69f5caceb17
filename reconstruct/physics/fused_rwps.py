"""The physics RWPS solver as fused numba passes, for the real-time stream; registration shifts applied on the fly.

:func:`rwps_fused` gives what ``solve("rwps", zeta, I, config=cfg)`` of :mod:`reconstruct.physics.solvers` gives
for the adaptive, pooled-prior configuration without Huber passes (:data:`reconstruct.physics.solvers.
PHYSICS_SOLVER_CONFIG`: ``lambda_map = "adaptive"``, ``rwps_prior = "pooled"``, no IRLS), clamped at 0 as the
stream clamps, in three passes instead of some sixty (N, H, W) tensor operations:

1. per pixel, one image row at a time with the observation loop outside the pixel loop (the pixel loops vectorise;
   numba's ``error_model="numpy"`` keeps Python's zero-division branch out of them): the first ridge solve (``lambda_high``), the Poisson
   reliability weights (:func:`reconstruct.physics.solvers.poisson_reliability`), the weighted moments, the
   weighted least-squares solve and its residual variance (``_ls_noise``);
2. on (H, W) maps: the box means of the noise and of the pooled prior
   (:func:`reconstruct.physics.solvers.pooled_difference_prior`; edge-aware like ``avg_pool2d`` with
   ``count_include_pad=False``, by running sums down the columns and prefix sums along the rows), Conf and lambda
   (supp. Eq. (8));
3. per pixel: the final weighted ridge solve with the prior lambda (R - T - D0)^2 (supp. Eq. (9)).

:class:`RwpsWindow` is the same solve (one band) with pass 1 on chunks of rows two threads can take in turn (the
live path's stream thread takes the rows its solve thread has not reached), bit for bit the same.

With ``shifts`` (N, 2) the observations are read through the bilinear, border-replicated translation of
:func:`reconstruct.physics.rir.warp` (frames and zeta alike), so the warped window is never materialised: one shift
per frame, so a row is two source rows blended and read at one integer offset plus one fraction.

Sums and solves run in float64 with the float32 constants of the torch solver (eps 1e-7, its tiny floors; the pooled
statistics of pass 2 and their box means are stored in float32, their running and prefix sums in float64); the
torch path computes in float32, so the two agree to float32 rounding amplified by the conditioning of the pixel
(tested against the torch solver as the oracle: docs/realtime.md gives the tolerance).
"""

from __future__ import annotations

import contextlib
import threading
import types

import numpy as np

from reconstruct.physics.solvers import SolverConfig

__all__ = ["rwps_fused", "rwps_fused_supports", "box_mean", "RwpsWindow"]

_F32_TINY = float(np.finfo(np.float32).tiny)
_TINY2 = _F32_TINY**0.5  # the torch solver's tiny in moments / Conf / priors (float32)
_TINY4 = _F32_TINY**0.25  # its floor constant of the 2 x 2 solve (float32)
_EPS = 1e-7  # its relative diagonal floor (float32)
_POISSON_FLOOR = 0.05  # poisson_reliability's relative offset c


def rwps_fused_supports(config: SolverConfig) -> bool:
    """Whether :func:`rwps_fused` computes ``solve("rwps", ..., config=config)`` (else use the torch solver)."""
    iters = config.rwps_irls_iters if config.rwps_irls_iters >= 0 else config.irls_iters
    return config.lambda_map == "adaptive" and config.rwps_prior == "pooled" and iters == 0


def _load_row(img, k, y, oy, ox, fy, fx, warp, scale, v, dst):  # pragma: no cover - compiled
    """Row y of img[k] times scale into dst (W,), read at (y - dy, x - dx) when ``warp``: bilinear, border-replicated (the
    sample position y + oy + fy, 0 <= fy < 1, clamped to the image, as grid_sample's border padding).  The shift is
    one per frame: the rows y0, y1 are blended into v (W,) (contiguous, vectorises), then v is read at x + ox and
    x + ox + 1 through a slice on the columns where both lie inside the image (no clamp, no negative index: the loop
    vectorises), clamped only on the few border columns.
    """
    _, H, W = img.shape
    if not warp:
        for x in range(W):
            dst[x] = scale * np.float64(img[k, y, x])
        return
    y0 = min(max(y + oy, 0), H - 1)
    y1 = min(max(y + oy + 1, 0), H - 1)
    r0 = img[k, y0]
    r1 = img[k, y1]
    gy = scale * fy
    hy = scale - gy
    for x in range(W):  # vertical blend, times scale
        v[x] = hy * np.float64(r0[x]) + gy * np.float64(r1[x])
    hx = 1.0 - fx
    # x + ox and x + ox + 1 both inside [0, W - 1] for x in [xa, xb)
    xa = min(max(-ox, 0), W)
    xb = max(min(W - 1 - ox, W), xa)
    for x in range(xa):
        x0 = min(max(x + ox, 0), W - 1)
        x1 = min(max(x + ox + 1, 0), W - 1)
        dst[x] = hx * v[x0] + fx * v[x1]
    n = xb - xa
    if n > 0:
        vs = v[xa + ox : xb + ox + 1]
        ds = dst[xa:xb]
        for i in range(n):
            ds[i] = hx * vs[i] + fx * vs[i + 1]
    for x in range(xb, W):
        x0 = min(max(x + ox, 0), W - 1)
        x1 = min(max(x + ox + 1, 0), W - 1)
        dst[x] = hx * v[x0] + fx * v[x1]


def _pass_pixels(z, I, oy, ox, fy, fx, warp, lam1, out, chunks):  # pragma: no cover - compiled
    """Pass 1 (module docstring) on ``chunks`` bands of rows (``prange``: in parallel when compiled so), each with its
    own scratch rows: out (9, H, W) = S_rr, S_rt, S_tt, sum w, A^T W b (R, T), det M, sigma^2, D.
    """
    N, H, W = z.shape
    for c in prange(chunks):
        a = np.empty((N, W))
        b = np.empty((N, W))
        w = np.empty((N, W))
        acc = np.empty((16, W))
        _pixel_rows_c(z, I, oy, ox, fy, fx, warp, lam1, out, a, b, w, acc, c * H // chunks, (c + 1) * H // chunks)


def _pixel_rows(z, I, oy, ox, fy, fx, warp, lam1, out, a, b, w, acc, y_lo, y_hi):  # pragma: no cover - compiled
    """Pass 1 on rows y_lo..y_hi - 1, one image row at a time, the observation loop outside the pixel loop (so the
    pixel loops vectorise).  Scratch: a, b, w (N, W); acc (16, W).
    """
    N, H, W = z.shape
    srr, srt, stt, rr, rt, sw, sww = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6]
    R1, T1, pmin, psum, v = acc[7], acc[8], acc[9], acc[10], acc[11]
    for y in range(y_lo, y_hi):
        for k in range(N):
            _load_row_c(z, k, y, oy[k], ox[k], fy[k], fx[k], warp, 1.0, v, a[k])
            _load_row_c(I, k, y, oy[k], ox[k], fy[k], fx[k], warp, 2.0, v, b[k])
        acc[:5] = 0.0
        for k in range(N):
            ak, bk = a[k], b[k]
            for x in range(W):
                bt = 1.0 - ak[x]
                srr[x] += ak[x] * ak[x]
                srt[x] += ak[x] * bt
                stt[x] += bt * bt
                rr[x] += ak[x] * bk[x]
                rt[x] += bt * bk[x]
        for x in range(W):
            diag = lam1 * N + _EPS * (srr[x] + stt[x]) + _TINY4
            m11 = srr[x] + diag
            m22 = stt[x] + diag
            inv = 1.0 / (m11 * m22 - srt[x] * srt[x])
            R1[x] = (m22 * rr[x] - srt[x] * rt[x]) * inv
            T1[x] = (m11 * rt[x] - srt[x] * rr[x]) * inv
        a0, w0 = a[0], w[0]
        for x in range(W):
            p = a0[x] * R1[x] + (1.0 - a0[x]) * T1[x]
            p = p if p > 0.0 else 0.0
            w0[x] = p
            psum[x] = p
            pmin[x] = p
        for k in range(1, N):
            ak, wk = a[k], w[k]
            for x in range(W):
                p = ak[x] * R1[x] + (1.0 - ak[x]) * T1[x]
                p = p if p > 0.0 else 0.0
                wk[x] = p
                psum[x] += p
                pmin[x] = p if p < pmin[x] else pmin[x]
        for x in range(W):
            c = _POISSON_FLOOR * psum[x] / N + _TINY2
            psum[x] = c
            pmin[x] += c
        acc[:7] = 0.0
        for k in range(N):  # the weights (kept in w for the residual), their sums and the weighted moments in one pass
            ak, bk, wk = a[k], b[k], w[k]
            for x in range(W):
                wx = pmin[x] / (wk[x] + psum[x])
                wk[x] = wx
                bt = 1.0 - ak[x]
                wa = wx * ak[x]
                wb = wx * bt
                srr[x] += wa * ak[x]
                srt[x] += wa * bt
                stt[x] += wb * bt
                rr[x] += wa * bk[x]
                rt[x] += wb * bk[x]
                sw[x] += wx
                sww[x] += wx * wx
        for x in range(W):
            fl = _EPS * (srr[x] + stt[x]) + _TINY4
            m11 = srr[x] + fl
            m22 = stt[x] + fl
            inv = 1.0 / (m11 * m22 - srt[x] * srt[x])
            R1[x] = (m22 * rr[x] - srt[x] * rt[x]) * inv
            T1[x] = (m11 * rt[x] - srt[x] * rr[x]) * inv
            psum[x] = 0.0
        for k in range(N):
            ak, bk, wk = a[k], b[k], w[k]
            for x in range(W):
                r = bk[x] - (ak[x] * R1[x] + (1.0 - ak[x]) * T1[x])
                psum[x] += wk[x] * r * r
        o0, o1, o2, o3, o4, o5, o6, o7, o8 = out[0, y], out[1, y], out[2, y], out[3, y], out[4, y], out[5, y], out[6, y], out[7, y], out[8, y]
        for x in range(W):
            n_eff = sw[x] * sw[x] / (sww[x] + _TINY2)
            dof = n_eff - 2.0
            dof = dof if dof > 0.5 else 0.5
            o0[x] = srr[x]
            o1[x] = srt[x]
            o2[x] = stt[x]
            o3[x] = sw[x]
            o4[x] = rr[x]
            o5[x] = rt[x]
            dm = srr[x] * stt[x] - srt[x] * srt[x]
            o6[x] = dm if dm > 0.0 else 0.0
            o7[x] = psum[x] / (sw[x] + _TINY2) * n_eff / dof
            o8[x] = R1[x] - T1[x]


def _box_mean(x, k, out, cs, chunks):  # pragma: no cover - compiled
    """Edge-aware k x k box mean of each (H, W) map of x (M, H, W) into out: columns (running sums down the
    columns), then rows (prefix sums along them), each on ``chunks`` bands (``prange``); cs scratch (>= 1, W).
    The box of output i covers i - k // 2 .. i - k // 2 + k - 1 (avg_pool2d, padding k // 2, count_include_pad=False,
    cropped).  Per element the same sums in the same order whatever ``chunks``.
    """
    M, H, W = x.shape
    h = k // 2
    for m in range(M):
        for c in prange(chunks):  # vertical running sums (a row in, a row out: vectorised), a band of columns each
            j_lo, j_hi = c * W // chunks, (c + 1) * W // chunks
            n = j_hi - j_lo
            acc = cs[0, j_lo:j_hi]  # the bands hold disjoint columns of one row
            acc[:] = 0.0
            for i in range(min(k - h, H)):
                xi = x[m, i, j_lo:j_hi]
                for j in range(n):
                    acc[j] += xi[j]
            for i in range(H):
                inv = 1.0 / (min(i - h + k, H) - max(i - h, 0))
                o = out[m, i, j_lo:j_hi]
                for j in range(n):
                    o[j] = acc[j] * inv
                if i - h + k < H:  # the row entering the box of i + 1
                    xi = x[m, i - h + k, j_lo:j_hi]
                    for j in range(n):
                        acc[j] += xi[j]
                if i - h >= 0:  # the row leaving it
                    xi = x[m, i - h, j_lo:j_hi]
                    for j in range(n):
                        acc[j] -= xi[j]
        for c in prange(chunks):  # horizontal, a band of rows each, four rows at a time (independent prefix chains)
            pre = np.empty((4, W + 1))
            i_lo, i_hi = c * H // chunks, (c + 1) * H // chunks
            for i in range(i_lo, i_hi, 4):
                n = min(4, i_hi - i)
                if n == 4:
                    p0, p1, p2, p3 = pre[0], pre[1], pre[2], pre[3]
                    x0, x1, x2, x3 = out[m, i], out[m, i + 1], out[m, i + 2], out[m, i + 3]
                    p0[0] = p1[0] = p2[0] = p3[0] = 0.0
                    for j in range(W):
                        p0[j + 1] = p0[j] + x0[j]
                        p1[j + 1] = p1[j] + x1[j]
                        p2[j + 1] = p2[j] + x2[j]
                        p3[j + 1] = p3[j] + x3[j]
                else:
                    for r in range(n):
                        pr, xr = pre[r], out[m, i + r]
                        pr[0] = 0.0
                        for j in range(W):
                            pr[j + 1] = pr[j] + xr[j]
                for r in range(n):
                    _box_row_c(pre[r], out[m, i + r], k, h)


def _box_row(p, o, k, h):  # pragma: no cover - compiled
    """o[j] = mean of the row over its box j - h .. j - h + k - 1 cut to the row, from the row's prefix sums p (W + 1,);
    the interior columns through slices (the loop vectorises), the border ones with their counts.
    """
    W = o.shape[0]
    ja = min(h, W)
    jb = max(W - k + h + 1, ja)
    for j in range(ja):
        hi = min(j - h + k, W)
        o[j] = p[hi] / hi
    n = jb - ja
    if n > 0:
        inv = 1.0 / k
        ph = p[k : k + n]
        pl = p[0:n]
        oi = o[ja:jb]
        for j in range(n):
            oi[j] = (ph[j] - pl[j]) * inv
    for j in range(jb, W):
        lo = max(j - h, 0)
        hi = min(j - h + k, W)
        o[j] = (p[hi] - p[lo]) / (hi - lo)


def _pass_maps(s, noise_pool, pool, kappa0, snr_kappa, lam_lo, lam_hi, T, R, work, box, cs, chunks):  # pragma: no cover - compiled
    """Passes 2 and 3 (module docstring) on the pixel sums s (9, H, W); T, R (H, W) float32 out, clamped at 0; rows in
    parallel (``prange``) when compiled so.  The pixel loops run on rows (1-D views: they vectorise).
    """
    _, H, W = s.shape
    _box_mean_c(s[7:8], noise_pool, box[0:1], cs, chunks)  # sigma^2 pooled over noise_pool
    for y in prange(H):
        sw_, dt_, d_, b0 = s[3, y], s[6, y], s[8, y], box[0, y]
        w0, w1, w2, w3, w4 = work[0, y], work[1, y], work[2, y], work[3, y], work[4, y]
        for x in range(W):
            sw = sw_[x]
            detm = dt_[x]
            v = b0[x] * sw / (detm + _EPS * sw * sw + _TINY2)
            v = v if v < 1e12 else 1e12
            u = detm / (sw + _TINY2)
            w0[x] = v  # v_D (kept: box holds the pooled ones below)
            w1[x] = u
            w2[x] = u * d_[x]
            w3[x] = u * v
            w4[x] = 4.0 * detm / (sw * sw + _TINY2)
    _box_mean_c(work[1:5], pool, box[1:5], cs, chunks)
    for y in prange(H):
        d_, b1, b2, w1, w2, w3 = s[8, y], box[1, y], box[2, y], work[1, y], work[2, y], work[3, y]
        for x in range(W):
            d0 = b2[x] / (b1[x] + _TINY2)
            e = d_[x] - d0
            w2[x] = d0
            w3[x] = w1[x] * e * e
    _box_mean_c(work[3:4], pool, box[0:1], cs, chunks)  # box[0] <- <u (D - D0)^2>
    for y in prange(H):
        b0, b1, b3, b4, w0, w2 = box[0, y], box[1, y], box[3, y], box[4, y], work[0, y], work[2, y]
        s0, s1, s2_, s3, s4, s5 = s[0, y], s[1, y], s[2, y], s[3, y], s[4, y], s[5, y]
        Ty, Ry = T[y], R[y]
        for x in range(W):
            bu = b1[x] + _TINY2
            s2 = (b0[x] - b3[x]) / bu
            s2 = s2 if s2 > 0.0 else 0.0
            bd = b4[x]
            d0 = w2[x] * bd / (bd + kappa0 + _TINY2)
            q = s2 / (w0[x] + _TINY2)
            conf = q / (q + snr_kappa)
            lam = lam_lo * conf + lam_hi * (1.0 - conf)  # supp. Eq. (8)
            srr, srt, stt, sw = s0[x], s1[x], s2_[x], s3[x]
            ls = lam * sw
            rR = s4[x] + ls * d0
            rT = s5[x] - ls * d0
            fl = _EPS * (srr + stt) + _TINY4
            m11 = srr + ls + fl
            m22 = stt + ls + fl
            m12 = srt - ls
            det = m11 * m22 - m12 * m12
            r = (m22 * rR - m12 * rT) / det  # supp. Eq. (9), 2x2 adjugate
            t = (m11 * rT - m12 * rR) / det
            Ry[x] = r if r > 0.0 else 0.0
            Ty[x] = t if t > 0.0 else 0.0


prange = range  # numba.prange once the kernels compile (numba is imported only then)
_load_row_c = None
_pixel_rows_c = None
_box_mean_c = None
_box_row_c = None
_k: dict = {}


def _get():
    """The compiled kernels (``parallel=True``: the ``prange`` loops on numba's threads; with one band the plain builds)."""
    global _load_row_c, _pixel_rows_c, _box_mean_c, _box_row_c, prange
    if not _k:
        import numba

        prange = numba.prange
        # error_model="numpy": IEEE division, no zero-division branch (which stops the pixel loops vectorising)
        jit = numba.njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
        par = numba.njit(cache=True, nogil=True, fastmath=True, parallel=True, error_model="numpy")
        _load_row_c = jit(_load_row)
        _pixel_rows_c = jit(_pixel_rows)
        _box_row_c = jit(_box_row)
        _box_mean_c = par(_box_mean)
        _k["pixels"] = par(_pass_pixels)
        _k["maps"] = par(_pass_maps)
        # one band: the loops compiled plainly (the parallel form's outlined loop bodies vectorise less: the maps pass
        # 4.0 -> 2.8 ms at 400 x 250), the box means too (no parallel region to enter: 2.5 -> 2.35 ms)
        _k["pixels1"] = jit(_pass_pixels)
        _k["maps1"] = jit(_one_band(_pass_maps, _box_mean_c=jit(_one_band(_box_mean))))
        _k["box"] = _box_mean_c
    return _k


def _one_band(fn, **over):
    """``fn`` with ``prange`` as ``range`` (and the other globals ``over`` gives), named apart for numba's cache."""
    f = types.FunctionType(fn.__code__, {**fn.__globals__, "prange": range, **over}, fn.__name__ + "_one_band")
    f.__qualname__ = fn.__qualname__ + "_one_band"
    return f


class _Scratch:
    """Work arrays of one frame size, made once."""

    def __init__(self, N: int, H: int, W: int):
        self.s = np.empty((9, H, W))
        self.work = np.empty((5, H, W), np.float32)  # pooled statistics: float32 halves their memory traffic
        self.box = np.empty((5, H, W), np.float32)
        self.cs = np.empty((1, W))  # the box means' running column sums


_scratch: dict[tuple[int, int, int], _Scratch] = {}


def _shift_parts(shifts: np.ndarray | None, N: int):
    """Integer offsets and fractions of the sample positions y - dy, x - dx (floor decomposition)."""
    if shifts is None:
        z = np.zeros(N, np.int64)
        f = np.zeros(N)
        return z, z, f, f, False
    s = np.asarray(shifts, np.float64).reshape(N, 2)
    py, px = -s[:, 0], -s[:, 1]
    oy, ox = np.floor(py), np.floor(px)
    return oy.astype(np.int64), ox.astype(np.int64), py - oy, px - ox, bool(np.any(s != 0.0))


def rwps_fused(zeta: np.ndarray, I: np.ndarray, config: SolverConfig, shifts: np.ndarray | None = None, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """RWPS T, R (H, W) float32, clamped at 0, of one window (module docstring).

    Args:
        zeta, I: (N, H, W) mixing coefficients and observations (radiance units, paper Eq. (1)).
        config: solver parameters; :func:`rwps_fused_supports` must hold.
        shifts: optional (N, 2) (dy, dx) registration shifts (:func:`reconstruct.physics.rir.warp`'s convention),
            applied to zeta and I alike.
        threads: numba threads of the passes (bands of rows in parallel; 0 = numba's setting, all cores by default);
            the result does not depend on it (every pixel sums in the same order).

    Returns:
        (T, R), each (H, W) float32.
    """
    from polinfra.errors import ConfigError, ShapeError

    if not rwps_fused_supports(config):
        raise ConfigError("the fused RWPS takes the adaptive, pooled-prior solver without Huber passes (PHYSICS_SOLVER_CONFIG)")
    if I.ndim != 3 or zeta.shape != I.shape:
        raise ShapeError(f"zeta and I must both be (N, H, W); got {zeta.shape} and {I.shape}", actual_shape=tuple(I.shape), expected_shape="(N, H, W)")
    N, H, W = I.shape
    k = _get()
    sc = _scratch.get((N, H, W))
    if sc is None:
        sc = _scratch[(N, H, W)] = _Scratch(N, H, W)
    oy, ox, fy, fx, warp = _shift_parts(shifts, N)
    z = np.ascontiguousarray(zeta, np.float32)
    i = np.ascontiguousarray(I, np.float32)
    T = np.empty((H, W), np.float32)
    R = np.empty((H, W), np.float32)
    with _threads(threads) as n:
        one = "1" if n == 1 else ""
        k["pixels" + one](z, i, oy, ox, fy, fx, warp, float(config.lambda_high), sc.s, n)
        k["maps" + one](sc.s, int(config.noise_pool), int(config.prior_pool), float(config.prior_kappa), float(config.snr_kappa), float(config.lambda_low),
                  float(config.lambda_high), T, R, sc.work, sc.box, sc.cs, n)
    return T, R


class RwpsWindow:
    """One window's :func:`rwps_fused` (one band) in parts two threads can share: the pixel pass on chunks of rows that
    any thread takes in turn (:meth:`pixels`), then the maps passes (:meth:`finish`).  Each row's sums are made by the
    same compiled code whoever takes it, so T and R are those of :func:`rwps_fused`, bit for bit.  ``zeta`` and ``I``
    are read until :meth:`wait_pixels` returns; ``sums`` (9, H, W) float64 holds the pixel sums until :meth:`finish`
    returns (two windows in flight need two).
    """

    def __init__(self, zeta: np.ndarray, I: np.ndarray, config: SolverConfig, shifts: np.ndarray | None = None, sums: np.ndarray | None = None, chunks: int = 8):
        from polinfra.errors import ConfigError, ShapeError

        if not rwps_fused_supports(config):
            raise ConfigError("the fused RWPS takes the adaptive, pooled-prior solver without Huber passes (PHYSICS_SOLVER_CONFIG)")
        if I.ndim != 3 or zeta.shape != I.shape:
            raise ShapeError(f"zeta and I must both be (N, H, W); got {zeta.shape} and {I.shape}", actual_shape=tuple(I.shape), expected_shape="(N, H, W)")
        N, H, W = I.shape
        self.k = _get()
        self.sc = _scratch.get((N, H, W))
        if self.sc is None:
            self.sc = _scratch[(N, H, W)] = _Scratch(N, H, W)
        self.s = self.sc.s if sums is None else sums
        self.cfg = config
        self.oy, self.ox, self.fy, self.fx, self.warp = _shift_parts(shifts, N)
        self.z = np.ascontiguousarray(zeta, np.float32)
        self.i = np.ascontiguousarray(I, np.float32)
        self.n = max(1, min(int(chunks), H))
        self.next = 0
        self.left = self.n
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.err: BaseException | None = None

    def pixels(self) -> int:
        """Pass 1 on the chunks of rows no thread has taken yet (returns when none is left; others may still run);
        returns the number of chunks this call made.
        """
        N, H, W = self.i.shape
        a, b, w, acc = np.empty((N, W)), np.empty((N, W)), np.empty((N, W)), np.empty((16, W))
        lam1 = float(self.cfg.lambda_high)
        made = 0
        while True:
            with self.lock:
                c = self.next
                self.next += 1
            if c >= self.n:
                return made
            try:
                made += 1
                if self.err is None:
                    _pixel_rows_c(self.z, self.i, self.oy, self.ox, self.fy, self.fx, self.warp, lam1, self.s, a, b, w, acc, c * H // self.n, (c + 1) * H // self.n)
            except BaseException as e:  # noqa: BLE001 - raised by wait_pixels on the waiting thread
                self.err = e
            finally:
                with self.lock:
                    self.left -= 1
                    if self.left == 0:
                        self.done.set()

    def cancel(self) -> None:
        """Give the window up (its caller failed): waiting threads return at once, :meth:`finish` raises."""
        if self.err is None:
            self.err = RuntimeError("the window was given up")
        self.done.set()

    def wait_pixels(self) -> None:
        """Until every chunk of the pixel pass is made (zeta and I are free then); raises what a chunk raised."""
        self.done.wait()
        if self.err is not None:
            raise self.err

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """The rest of the pixel pass, then passes 2 and 3: (T, R), each (H, W) float32."""
        self.pixels()
        self.wait_pixels()
        c = self.cfg
        _, H, W = self.i.shape
        T = np.empty((H, W), np.float32)
        R = np.empty((H, W), np.float32)
        with _threads(1):  # the box means' prange loops on one thread (numba's threads are per calling thread)
            self.k["maps1"](self.s, int(c.noise_pool), int(c.prior_pool), float(c.prior_kappa), float(c.snr_kappa), float(c.lambda_low), float(c.lambda_high),
                            T, R, self.sc.work, self.sc.box, self.sc.cs, 1)
        return T, R


@contextlib.contextmanager
def _threads(threads: int):
    """The numba threads of the kernels' parallel loops: ``threads`` bands of rows (0 = one per thread of numba's
    setting) on at most as many threads as numba's pool holds; yields the number of bands.
    """
    import numba

    before = numba.get_num_threads()
    bands = before if threads <= 0 else int(threads)
    numba.set_num_threads(min(bands, numba.config.NUMBA_NUM_THREADS))
    try:
        yield bands
    finally:
        numba.set_num_threads(before)


def box_mean(x: np.ndarray, k: int, threads: int = 1) -> np.ndarray:
    """Edge-aware k x k box mean of (H, W) or (M, H, W) maps (the kernel's; float64)."""
    x = np.asarray(x, np.float64)
    x3 = np.ascontiguousarray(x.reshape((-1,) + x.shape[-2:]))
    out = np.empty_like(x3)
    with _threads(threads) as n:
        _get()["box"](x3, int(k), out, np.empty((1, x3.shape[-1])), n)
    return out.reshape(x.shape)
