"""Long-span helpers: the span's harmonic and zbar, the long-span separation, span blending and the anchor to the spike mean."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


def harmonic_of(zeta, phi, ridge: float = 1e-6):
    """The first harmonic (a, b, c) of zeta(phi) = a + b cos 2 phi + c sin 2 phi from its values at a window's angles,
    (..., N, H, W), (..., N) -> three (..., H, W) maps (least squares over the N observations).

    Paper Eq. (2) makes zeta a first harmonic of the polarizer angle (window averaging scales b and c, never a).  A
    tiny ridge on (b, c) keeps a degenerate angle set (a still polarizer) at the plain mean with b = c = 0.  A zeta
    that is not a first harmonic (the network's sigmoid, supp. Eq. (19)) gets its best first-harmonic fit.  numpy or
    torch (returned like ``zeta``).
    """
    is_t = torch.is_tensor(zeta)
    z = zeta.double() if is_t else torch.as_tensor(np.asarray(zeta, np.float64))
    p = (phi.double() if torch.is_tensor(phi) else torch.as_tensor(np.asarray(phi, np.float64))).to(z.device)
    A = torch.stack([torch.ones_like(p), torch.cos(2 * p), torch.sin(2 * p)], -1)  # (..., N, 3)
    G = A.transpose(-1, -2) @ A + ridge * A.shape[-2] * torch.diag(torch.tensor([0.0, 1.0, 1.0], dtype=A.dtype, device=A.device))
    rows = torch.linalg.solve(G, A.transpose(-1, -2))  # (..., 3, N): weights giving (a, b, c)
    out = [(rows[..., j, :, None, None] * z).sum(-3) for j in range(3)]
    return tuple(o.to(zeta.dtype) for o in out) if is_t else tuple(o.numpy().astype(np.asarray(zeta).dtype) for o in out)


def zbar_of(zeta, phi, ridge: float = 1e-6):
    """The polarizer-cycle mean of zeta from its values at a window's angles, (..., N, H, W), (..., N) -> (..., H, W).

    The level a of :func:`harmonic_of`, the zbar of :func:`anchor_to_mean`.  The plain mean over the N windows is
    not it: the N = 7, 0.65 ms windows cover ~84 deg of 2 phi, so their mean is a + ~0.8 b' (b' the amplitude at
    the window's angle), off by up to the whole modulation depth (at Brewster's angle that is zbar itself).
    """
    return harmonic_of(zeta, phi, ridge)[0]


HARMONIC_FLOOR = 1e-5
"""Floor added to zeta's squared first-harmonic amplitude b^2 + c^2 in :func:`long_span_separation`: where the pane
barely modulates (|zeta's modulation| below ~0.003, near-normal incidence) the long span's difference shrinks toward
0 instead of dividing noise by nothing."""


def long_span_separation(I_mean, I_harm, zeta, phi, floor: float = HARMONIC_FLOOR):
    """Separate the layers from the first harmonic of the whole long span of spikes (torch tensors).

    Over the span of the long spike mean (17.5 ms, about half a polarizer turn; the N windows sit inside it and use
    about a quarter of its spikes) paper Eq. (1)-(2) give per pixel I(t) = 1/2 [T + zeta(phi_t) D], D = R - T, so
    the spikes' first harmonic (b_I, c_I) (``I_harm``, radiance units: :class:`reconstruct.stream.groups.SpikeMeanSums`)
    equals D / 2 times zeta's (b, c) (:func:`harmonic_of` of ``zeta`` at the windows' angles ``phi``).  Projected on
    zeta's, D = 2 (b_I b + c_I c) / (b^2 + c^2 + floor), and T = 2 I_mean - a D as in :func:`anchor_to_mean`.  For a
    static scene every spike of the span counts (about 4x those of the N windows); motion blurs it as it blurs
    I_mean.

    Args:
        I_mean: (B, H, W) the long spike mean.
        I_harm: (B, 2, H, W) the spikes' first-harmonic coefficients over the same span (cos 2 phi, sin 2 phi).
        zeta: (B, N, H, W) zeta at the windows' angles; phi: (B, N).
        floor: :data:`HARMONIC_FLOOR`.

    Returns:
        (T, R) each (B, H, W).
    """
    a, b, c = harmonic_of(zeta, phi)
    D = span_difference(I_harm, b, c, floor)
    T = 2.0 * I_mean - a * D
    return T, T + D


def span_difference(I_harm, b, c, floor: float = HARMONIC_FLOOR):
    """D = R - T from the span's first harmonic ``I_harm`` (B, 2, H, W) projected on zeta's first harmonic (b, c):
    2 (b_I b + c_I c) / (b^2 + c^2 + floor) (:func:`long_span_separation`; finite where the modulation vanishes).
    """
    return 2.0 * (I_harm[:, 0] * b + I_harm[:, 1] * c) / (b * b + c * c + floor)


SPAN_SATURATION = 0.97
"""Spikes per step at or above which a pixel counts as saturated in :func:`span_weights`: a spike-camera pixel fires
at most once per step, so a window or span near that rate clips the light and its harmonic (the modulation is flattened
where the light is brightest); such pixels get no weight."""


def gaussian_kernel(sigma: float, dtype=torch.float64, device=None) -> torch.Tensor:
    """Normalised 1-D Gaussian of ``sigma`` pixels on a radius of 3 sigma (at least 1 pixel)."""
    r = max(1, int(math.ceil(3.0 * sigma)))
    t = torch.arange(-r, r + 1, dtype=dtype, device=device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    return k / k.sum()


def separable_blur(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """(B, H, W) maps convolved with the separable kernel k (x) k (odd length), reflected borders (replicated where
    the map is narrower than the kernel's radius).
    """
    r = k.numel() // 2
    H, W = x.shape[-2:]
    mode = "reflect" if (H > r and W > r) else "replicate"
    y = x.unsqueeze(1)
    k = k.to(x.dtype)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode=mode), k.view(1, 1, 1, -1))
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode=mode), k.view(1, 1, -1, 1))
    return y.squeeze(1)


def span_weights(I_mean, zeta, phi, exposure, span_steps, I_peak=None):
    """Inverse variance of the long span's difference D = R - T (:func:`long_span_separation`) per pixel, (B, H, W).

    Over ``span_steps`` steps a pixel firing with probability p = I exposure per step has a per-step variance
    p (1 - p) (spikes); the least-squares first harmonic of a span that covers about one turn of 2 phi has
    var(b_I) = var(c_I) = 2 p (1 - p) / (n exposure^2) in radiance units, so var(D) = 8 p (1 - p) / (n exposure^2
    (b^2 + c^2)) with (b, c) zeta's first harmonic.  The weight is its inverse; 0 where the pixel is saturated
    (:data:`SPAN_SATURATION`, on I_mean or on ``I_peak``, e.g. the largest of the windows' observations): the clipped
    spikes there say nothing of the modulation.  The integrate-and-fire pixel is more regular than this Bernoulli
    count, so the weights are conservative; :func:`span_blend`'s tolerance absorbs the scale.  ``exposure`` and
    ``span_steps``: numbers, or (B,) tensors (one per image, e.g. a training batch).
    """
    def per_image(v):  # a number, or one per image of the batch: (B,) -> (B, 1, 1)
        t = torch.as_tensor(v, dtype=I_mean.dtype, device=I_mean.device)
        return t.reshape(-1, 1, 1) if t.dim() == 1 else t

    n = per_image(span_steps).clamp_min(1.0)
    e = per_image(exposure)
    _, b, c = harmonic_of(zeta, phi)
    p = (I_mean * e).clamp(0.5 / n, 1.0 - 0.5 / n)
    w = n * e * e * (b * b + c * c) / (8.0 * p * (1.0 - p))
    sat = I_mean * e >= SPAN_SATURATION
    if I_peak is not None:
        sat = sat | (I_peak * e >= SPAN_SATURATION)
    return torch.where(sat, torch.zeros_like(w), w)


def span_blend(T, R, I_mean, I_harm, zeta, phi, w, sigma: float, tol, tol_t=None):
    """Move a separation's difference D = R - T toward the long span's where the span identifies it (torch, (B, H, W)).

    The span's D (:func:`long_span_separation`, every spike of 17.5 ms, unbiased) and the given separation's are two
    estimates of one map.  Their difference is smoothed by normalised convolution with the span's weights ``w``
    (:func:`span_weights`), c = G * (w (D_span - D)) / G * w, whose variance is var = (G^2 * w) / (G * w)^2; it is
    added with the gain lam = tol^2 / (tol^2 + var): the inverse-variance combination of the two when the given D errs
    by ``tol`` (a number or a (B, H, W) map; at the scale ``sigma``), so the span takes over where its noise is below
    tol and leaves D where the pane barely modulates, the pixel saturates or the light is dim.  ``tol_t`` (optional):
    the gain is at most tol_t^2 / (tol_t^2 + a^2 var), so T, which moves by a dD, gets no more of the span's noise than
    that.  ``sigma`` = 0: per pixel.  The change keeps the long mean: T -= a dD, R += (1 - a) dD with a = zeta's
    half-turn mean (as :func:`anchor_to_mean`).

    Returns:
        (T, R) each (B, H, W), float like ``T``.
    """
    a, b, c = harmonic_of(zeta.double(), phi.double())
    w = w.double()
    wx = w * (span_difference(I_harm.double(), b, c) - (R - T).double())  # w (D_span - D)
    if sigma > 0:
        k = gaussian_kernel(sigma, torch.float64, T.device)
        Gw, Gwx, G2w = separable_blur(w, k), separable_blur(wx, k), separable_blur(w, k * k)
    else:  # per pixel: the same formulas with G the identity
        Gw, Gwx, G2w = w, wx, w
    corr = Gwx / Gw.clamp_min(1e-300)

    def gain(tol_, scale=1.0):  # tol^2 / (tol^2 + scale^2 var), var = G^2 * w / (G * w)^2; tol a number or a (B, H, W) map
        t2 = torch.as_tensor(tol_, dtype=torch.float64, device=T.device) ** 2
        return t2 * Gw * Gw / (t2 * Gw * Gw + scale * scale * G2w + 1e-300)

    lam = gain(tol)
    if tol_t is not None:  # and T, which moves by a dD, no noisier than tol_t
        lam = torch.minimum(lam, gain(tol_t, a))
    dD = lam * corr
    return (T - (a * dD).to(T.dtype)), (R + ((1.0 - a) * dD).to(R.dtype))


def anchor_to_mean(T, R, I_mean, zbar):
    """Anchor a separation to the long spike mean: keep its difference D = R^ - T^, take the level from I_mean.

    Averaged over a half polarizer turn, paper Eq. (1) gives 2 I_mean = T + zbar (R - T) exactly for a static
    scene (zbar = the turn's mean zeta), so T = 2 I_mean - zbar D: the short windows supply only D, whose noise
    enters scaled by zbar (small for glass), and the level comes from ~27x more spikes than the 7 windows.
    Motion over the span blurs I_mean (the cost of the anchor).  numpy arrays or torch tensors (broadcasting);
    returns (T, R = T + D).
    """
    D = R - T
    Ta = 2.0 * I_mean - zbar * D
    return Ta, Ta + D


def gaussian_radius(sigma: float) -> int:
    """Kernel radius (pixels) of :func:`gaussian_blur`: 3 sigma, at least 1 (0 for sigma 0: no blur)."""
    return max(1, int(math.ceil(3.0 * sigma))) if sigma > 0 else 0


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (B, H, W) maps (kernel radius :func:`gaussian_radius`, reflected borders; replicated
    where the map is narrower than the radius): :func:`separable_blur` with :func:`gaussian_kernel`.
    """
    return separable_blur(x, gaussian_kernel(sigma, x.dtype, x.device))
