"""The masked Gauss-Newton translation fit of RIR as one numba loop, for the real-time stream.

:func:`gauss_newton_fused` computes what ``reconstruct.physics.rir._gauss_newton`` computes (the sub-pixel
refinement of :func:`reconstruct.physics.rir.estimate_shifts` and the per-level fit of
:class:`reconstruct.physics.rir.ChainedRir`): per iteration, the moving image and its gradient sampled at the mask
points minus the shift (bilinear, border-replicated, as ``grid_sample``), photometric normalisation on the mask
(zero mean, unit sample standard deviation), the 2 x 2 normal equations with the same relative floor, the step
clamped to +-0.5 px, a stop once the step is below 1e-4 px.  In float64 like the torch version; a few
microseconds per iteration instead of a dozen small torch calls (tested equal to 1e-9 px).

:func:`pyramid_fused` builds the per-frame levels of the chained fit (the frame smoothed as scipy's
``gaussian_filter`` smooths it, reflect mode, block means as ``rir._block_sum_mean``, central-difference gradients as
``np.gradient``) in one compiled call, float64; tested equal to the numpy / scipy levels to 1e-12.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gauss_newton_fused", "pyramid_fused", "erode_fused", "block_mean_fused", "smooth_fused"]


def _gn(r_ref, stack, pts, s, iters, J):  # pragma: no cover - compiled
    P = pts.shape[0]
    _, H, W = stack.shape
    m = 0.0
    for p in range(P):
        m += r_ref[p]
    m /= P
    v = 0.0
    for p in range(P):
        v += (r_ref[p] - m) ** 2
    sd = max(np.sqrt(v / (P - 1)), 1e-30)
    rn = np.empty(P)
    for p in range(P):
        rn[p] = (r_ref[p] - m) / sd
    st = stack.reshape(3, H * W)
    for _ in range(iters):
        # one shift for all points: the sample position pts - s splits into an integer offset and one fraction;
        # a point whose 2 x 2 neighbourhood lies inside the image reads it directly, the others clamp (border)
        oy = int(np.floor(-s[0]))
        ox = int(np.floor(-s[1]))
        gy = -s[0] - oy
        gx = -s[1] - ox
        for p in range(P):
            y0 = int(pts[p, 0]) + oy
            x0 = int(pts[p, 1]) + ox
            if y0 >= 0 and x0 >= 0 and y0 < H - 1 and x0 < W - 1:
                q = y0 * W + x0
                for c in range(3):
                    sc = st[c]
                    top = (1.0 - gx) * sc[q] + gx * sc[q + 1]
                    bot = (1.0 - gx) * sc[q + W] + gx * sc[q + W + 1]
                    J[c, p] = (1.0 - gy) * top + gy * bot
                continue
            yy = min(max(pts[p, 0] - s[0], 0.0), H - 1.0)
            xx = min(max(pts[p, 1] - s[1], 0.0), W - 1.0)
            y0 = int(np.floor(yy))
            x0 = int(np.floor(xx))
            fy = yy - y0
            fx = xx - x0
            y1 = min(y0 + 1, H - 1)
            x1 = min(x0 + 1, W - 1)
            for c in range(3):
                top = (1.0 - fx) * stack[c, y0, x0] + fx * stack[c, y0, x1]
                bot = (1.0 - fx) * stack[c, y1, x0] + fx * stack[c, y1, x1]
                J[c, p] = (1.0 - fy) * top + fy * bot
        m = 0.0
        for p in range(P):
            m += J[0, p]
        m /= P
        v = 0.0
        for p in range(P):
            v += (J[0, p] - m) ** 2
        sd = max(np.sqrt(v / (P - 1)), 1e-30)
        h11 = h12 = h22 = g1 = g2 = 0.0
        for p in range(P):
            r = rn[p] - (J[0, p] - m) / sd
            a1 = -J[1, p] / sd
            a2 = -J[2, p] / sd
            h11 += a1 * a1
            h12 += a1 * a2
            h22 += a2 * a2
            g1 += a1 * r
            g2 += a2 * r
        fl = 1e-9 * (h11 + h22) + 1e-30
        h11 += fl
        h22 += fl
        det = h11 * h22 - h12 * h12
        d0 = (h22 * g1 - h12 * g2) / det
        d1 = (h11 * g2 - h12 * g1) / det
        d0 = min(max(d0, -0.5), 0.5)
        d1 = min(max(d1, -0.5), 0.5)
        s[0] += d0
        s[1] += d1
        if max(abs(d0), abs(d1)) < 1e-4:
            break


def _reflect(i, n):  # pragma: no cover - compiled
    """scipy.ndimage's ``reflect`` boundary (d c b a | a b c d), any distance out."""
    while i < 0 or i >= n:
        i = -i - 1 if i < 0 else 2 * n - 1 - i
    return i


def _smooth(img, w, out, tmp):  # pragma: no cover - compiled
    """Separable correlation with the symmetric kernel w (2 r + 1,) along rows, then columns (scipy's order), reflect
    mode; img (H, W) float32 or float64, out and tmp (H, W) float64.
    """
    H, W = img.shape
    r = w.shape[0] // 2
    for i in range(H):  # taps t and 2 r - t share a weight: one multiply per pair
        o = tmp[i]
        c = img[i]
        wr = w[r]
        for j in range(W):
            o[j] = wr * np.float64(c[j])
        for t in range(r):
            s0 = img[_reflect_c(i + t - r, H)]
            s1 = img[_reflect_c(i + r - t, H)]
            wt = w[t]
            for j in range(W):
                o[j] += wt * (np.float64(s0[j]) + np.float64(s1[j]))
    for i in range(H):
        src = tmp[i]
        o = out[i]
        for j in range(min(r, W)):
            acc = 0.0
            for t in range(2 * r + 1):
                acc += w[t] * src[_reflect_c(j + t - r, W)]
            o[j] = acc
        n = W - 2 * r
        if n > 0:
            oo = out[i, r : r + n]
            sc = src[r : r + n]
            wr = w[r]
            for j in range(n):
                oo[j] = wr * sc[j]
            for t in range(r):
                sa = src[t : t + n]
                sb = src[2 * r - t : 2 * r - t + n]
                wt = w[t]
                for j in range(n):
                    oo[j] += wt * (sa[j] + sb[j])
        for j in range(max(W - r, r), W):
            acc = 0.0
            for t in range(2 * r + 1):
                acc += w[t] * src[_reflect_c(j + t - r, W)]
            o[j] = acc


def _block(img, f, out):  # pragma: no cover - compiled
    """Means of f x f blocks (the rows of a block summed first, then its columns, as ``rir._block_sum_mean``)."""
    h, w = out.shape
    ff = f * f
    row = np.empty(f * w)
    for i in range(h):
        for j in range(f * w):
            row[j] = img[f * i, j]
        for k in range(1, f):
            src = img[f * i + k]
            for j in range(f * w):
                row[j] += src[j]
        o = out[i]
        for j in range(w):
            acc = row[f * j]
            for k in range(1, f):
                acc += row[f * j + k]
            o[j] = acc / ff


def _gradient(img, st):  # pragma: no cover - compiled
    """The image and its gradients into st (3, h, w) (img, d/dy, d/dx): central differences, one-sided at the borders (``np.gradient``)."""
    h, w = img.shape
    for i in range(h):
        for j in range(w):
            st[0, i, j] = img[i, j]
    for i in range(h):
        if h < 2:
            for j in range(w):
                st[1, i, j] = 0.0
        elif i == 0:
            for j in range(w):
                st[1, i, j] = img[1, j] - img[0, j]
        elif i == h - 1:
            for j in range(w):
                st[1, i, j] = img[h - 1, j] - img[h - 2, j]
        else:
            for j in range(w):
                st[1, i, j] = (img[i + 1, j] - img[i - 1, j]) / 2.0
        if w < 2:
            for j in range(w):
                st[2, i, j] = 0.0
            continue
        st[2, i, 0] = img[i, 1] - img[i, 0]
        st[2, i, w - 1] = img[i, w - 1] - img[i, w - 2]
        for j in range(1, w - 1):
            st[2, i, j] = (img[i, j + 1] - img[i, j - 1]) / 2.0


def _kernel1d(sigma: float) -> np.ndarray:
    """scipy.ndimage's Gaussian weights (truncate 4)."""
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    p = np.exp(-0.5 / (sigma * sigma) * x * x)
    return p / p.sum()


def pyramid_fused(frame: np.ndarray, sigma: float, base: int, levels: tuple[int, ...]) -> dict[int, np.ndarray]:
    """The chained fit's levels of one frame: {level: (3, h, w) float64 image and its gradients (y, x)}.

    The frame is block-averaged by ``base`` first (1 = not), smoothed by a Gaussian of ``sigma`` px there (0 = not),
    then each level ``lv`` (a multiple of ``base``) is its block mean by ``lv // base`` with its gradients.
    """
    k = _get()
    img = np.ascontiguousarray(frame)
    if base > 1:
        b = np.empty((img.shape[0] // base, img.shape[1] // base))
        k["block"](img, base, b)
        img = b
    if sigma > 0:
        sm = np.empty(img.shape)
        k["smooth"](img, _kernel1d(sigma), sm, np.empty(img.shape))
    else:
        sm = np.asarray(img, np.float64)
    out = {}
    for lv in levels:
        f = lv // base
        src = sm
        if f > 1:
            src = np.empty((sm.shape[0] // f, sm.shape[1] // f))
            k["block"](sm, f, src)
        st = np.empty((3,) + src.shape)
        k["gradient"](src, st)
        out[lv] = st
    return out


def _erode(m, iters, out):  # pragma: no cover - compiled
    """``iters`` binary erosions by the 4-neighbour cross, outside the image 0 (scipy's ``binary_erosion`` with
    ``border_value=0``); m, out (H, W) uint8 0 / 1, m overwritten.
    """
    H, W = m.shape
    for _ in range(iters):
        for j in range(W):
            out[0, j] = 0
            out[H - 1, j] = 0
        for i in range(1, H - 1):
            o, up, mid, dn = out[i], m[i - 1], m[i], m[i + 1]
            o[0] = 0
            o[W - 1] = 0
            for j in range(1, W - 1):
                o[j] = mid[j] & up[j] & dn[j] & mid[j - 1] & mid[j + 1]
        m[:, :] = out


def erode_fused(mask: np.ndarray, px: int) -> np.ndarray:
    """``scipy.ndimage.binary_erosion(mask, iterations=px, border_value=0)`` (the cross structure; tested equal)."""
    m = np.array(mask, dtype=np.uint8)
    if px <= 0 or m.size == 0:
        return m.astype(bool)
    out = np.empty_like(m)
    _get()["erode"](m, int(px), out)
    return out.astype(bool)


def block_mean_fused(img: np.ndarray, f: int) -> np.ndarray:
    """Means of f x f blocks of (..., H, W) images, float64 (``rir._block_sum_mean``'s order of additions)."""
    x = np.ascontiguousarray(img)
    lead = x.shape[:-2]
    x3 = x.reshape((-1,) + x.shape[-2:])
    out = np.empty((x3.shape[0], x3.shape[1] // f, x3.shape[2] // f))
    for i in range(x3.shape[0]):
        _get()["block"](x3[i], int(f), out[i])
    return out.reshape(lead + out.shape[-2:])


def smooth_fused(img: np.ndarray, sigma: float) -> np.ndarray:
    """The Gaussian smoothing of scipy's ``gaussian_filter(img, sigma)`` (reflect mode, truncate 4) of (..., H, W) images, float64."""
    x = np.ascontiguousarray(img)
    x3 = x.reshape((-1,) + x.shape[-2:])
    out = np.empty(x3.shape)
    if sigma <= 0:
        out[:] = x3
        return out.reshape(x.shape)
    w, tmp = _kernel1d(sigma), np.empty(x3.shape[-2:])
    for i in range(x3.shape[0]):
        _get()["smooth"](x3[i], w, out[i], tmp)
    return out.reshape(x.shape)


_reflect_c = None
_kernels: dict = {}


def _get() -> dict:
    global _reflect_c
    if not _kernels:
        import numba

        jit = numba.njit(cache=True, nogil=True, error_model="numpy")  # IEEE division: no zero-division branch in the loops
        _reflect_c = jit(_reflect)
        _kernels["smooth"] = jit(_smooth)
        _kernels["block"] = jit(_block)
        _kernels["gradient"] = jit(_gradient)
        _kernels["erode"] = jit(_erode)
    return _kernels


_compiled = None


def gauss_newton_fused(r_ref: np.ndarray, stack: np.ndarray, pts: np.ndarray, s0: np.ndarray, iters: int) -> np.ndarray:
    """Shift (dy, dx) float64 of the moving image onto the reference at the mask points (module docstring).

    Args:
        r_ref: (P,) reference values at ``pts``.
        stack: (3, H, W) the moving image and its gradients (y, x).
        pts: (P, 2) (y, x) pixel positions, P >= 2.
        s0: (2,) starting shift.
        iters: at most this many iterations.
    """
    global _compiled
    if _compiled is None:
        import numba

        _compiled = numba.njit(cache=True, nogil=True, fastmath=True)(_gn)
    s = np.array(s0, np.float64).reshape(2).copy()
    st = np.ascontiguousarray(stack, np.float64)
    _compiled(np.ascontiguousarray(r_ref, np.float64), st, np.ascontiguousarray(pts, np.float64), s, int(iters), np.empty((3, pts.shape[0])))
    return s
