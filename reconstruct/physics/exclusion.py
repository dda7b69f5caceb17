"""Gradient exclusion of the solved layers: a content criterion for the pane's zeta.

Paper Eq. (1): I_k = 1/2 [T + zeta_k (R - T)], zeta_k = A + B cos 2(phi_k - phi_perp) (Eq. (2); A, B the mean and
half difference of R_perp, R_par).  Over a half polarizer turn the harmonic fit (supp. Eq. (1)) gives the mean
a0 = [T + A (R - T)] / 2 and the modulation along phi_perp m = g B (R - T) / 2 (g: the window's sinc), so under a
hypothesis (A', B') the layers solve in closed form: D' = 2 m / (g B'), T' = 2 a0 - A' D', R' = T' + D'.  With the
truth (A, B) and a hypothesis off in scale and shape,

    T' = T + alpha (R - T),  R' = T + beta (R - T),  alpha = A - A' B / B',  beta = alpha + B / B',

so a wrong zeta mixes the layers: R' carries T's texture (beta != 1) and T' carries R's (alpha != 0).  Under the
right zeta R' and T' are the two independent layers and their gradients are uncorrelated (the gradient-exclusion
idea of reflection separation; the paper's Eq. (11) uses it as a loss).  A pane model or index that scales zeta by k
(A' = k A, B' = k B) gives alpha = 0, beta = 1 / k and a correlation of the sign of k - 1; one with a different
theta dependence (single vs slab, Brewster angle) leaves correlations of opposite signs at different incidences.

The spike noise of one solve is shared by its R' and T' (T' = 2 a0 - A' D' and R' = T' + D' both carry D''s noise,
with opposite-signed weights), which would bias the correlation; so the stream is split in time into parts and R'
of one part is correlated with T' of another (:func:`cross_gradient_sums`): disjoint spikes, independent noise.

Used by ``polspike calibrate-pane`` (pane model and index where the modulation depths do not reach the DoP cone's
edges) and by the self zeta's 90 deg twin and pane-model test (``reconstruct.pane.content.layer_gradient_correlation``).
"""

from __future__ import annotations

import numpy as np

from polinfra.errors import ConfigError

__all__ = ["part_harmonics", "rotate_parts", "solve_layers", "cross_gradient_sums", "label_correlations", "SIGMA_PX"]

SIGMA_PX = 1.5
"""Gaussian smoothing (pixels) of the solved layers before their gradients are taken: keeps the texture, damps the
per-pixel spike noise (which only widens the score's spread: it is independent across parts)."""


def part_harmonics(I: np.ndarray, phi: np.ndarray, parts: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """The stream split in time into ``parts`` consecutive parts, each as the mean over its back-to-back chunks of
    about half a polarizer turn of the harmonic fit (supp. Eq. (1)): a list of (a0, c) with c = ac + i as, (H, W).

    Eq. (1) is linear in the layers, so the chunk mean of a0 and c is that of the time-averaged layers (moving
    content is averaged, not mis-fitted).
    """
    import torch

    from reconstruct.physics.harmonic_fit import half_turn_frames, harmonic_fit

    I = np.asarray(I, np.float64)
    phi = np.asarray(phi, np.float64)
    L = half_turn_frames(phi)
    C = I.shape[0] // L
    if C < parts:
        raise ConfigError(f"the gradient-exclusion test needs {parts} half turns of the polarizer ({parts * L} frames); got {I.shape[0]} frames")
    out = []
    bounds = np.linspace(0, C, parts + 1).round().astype(int)
    for p in range(parts):
        sl = slice(bounds[p] * L, bounds[p + 1] * L)
        c0 = bounds[p + 1] - bounds[p]
        Ic = torch.from_numpy(I[sl].reshape(c0, L, *I.shape[1:]))
        Pc = torch.from_numpy(phi[sl].reshape(c0, L))
        a0, ac, as_ = (t.numpy() for t in harmonic_fit(Ic, Pc))
        out.append((a0.mean(0), (ac + 1j * as_).mean(0)))
    return out


def rotate_parts(parts, phi_perp: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The parts' modulation turned to the plane of incidence, (a0, Re(c e^{-2i phi_perp})): what every hypothesis of
    :func:`solve_layers` takes (give the result with ``phi_perp = None`` to solve many hypotheses without redoing it).
    """
    rot = np.exp(-2j * phi_perp)
    return [(a0, (c * rot).real) for a0, c in parts]


def solve_layers(a0: np.ndarray, c: np.ndarray, phi_perp: np.ndarray | None, A: np.ndarray, B: np.ndarray, gain: float = 1.0, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(R', T') of paper Eq. (1)-(2) from one part's harmonic mean a0 and modulation c under zeta's (A, B) (module docstring);
    ``phi_perp`` None: c is already turned to the plane of incidence (:func:`rotate_parts`); ``mask``: D and T set to 0
    where it is False.
    """
    m = c if phi_perp is None else (c * np.exp(-2j * phi_perp)).real
    D = 2.0 * m / (gain * np.where(np.abs(B) > 1e-6, B, 1e-6))
    T = 2.0 * a0 - A * D
    if mask is not None:
        D, T = np.where(mask, D, 0.0), np.where(mask, T, 0.0)
    return T + D, T


def _grad(x: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    from scipy.ndimage import gaussian_filter

    y = gaussian_filter(x, sigma) if sigma > 0 else x
    return np.diff(y, axis=1)[:-1, :], np.diff(y, axis=0)[:, :-1]


def _checkerboard(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The two disjoint pixel sets of a checkerboard (each pixel's four neighbours lie in the other set)."""
    yy, xx = np.indices(shape)
    even = (yy + xx) % 2 == 0
    return even, ~even


def _set_sigma(sigma: float) -> float:
    return max(sigma, 0.7)  # every pixel needs kept neighbours


def _set_weight(keep: np.ndarray, sigma: float) -> np.ndarray:
    """The Gaussian weight of the kept pixels around each pixel (the normalisation of :func:`_set_grad`)."""
    from scipy.ndimage import gaussian_filter

    return np.maximum(gaussian_filter(keep.astype(np.float64), _set_sigma(sigma)), 1e-12)


def _set_grad(x: np.ndarray, keep: np.ndarray, sigma: float, weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gradient of x seen through the pixels ``keep`` only: normalised convolution (the Gaussian mean of the kept
    pixels; ``weight``: :func:`_set_weight` of ``keep``, computed here when None), then the forward differences of
    :func:`_grad`.
    """
    from scipy.ndimage import gaussian_filter

    y = gaussian_filter(np.where(keep, x, 0.0), _set_sigma(sigma)) / (_set_weight(keep, sigma) if weight is None else weight)
    return np.diff(y, axis=1)[:-1, :], np.diff(y, axis=0)[:, :-1]


def cross_gradient_sums(parts, phi_perp: np.ndarray | None, A: np.ndarray, B: np.ndarray, gain: float = 1.0, sigma: float = SIGMA_PX,
                        mask: np.ndarray | None = None, pairs: str = "all", pixels: str = "same") -> dict:
    """Per-pixel products of the layers' gradients solved under zeta (A, B), crossed between time parts (``parts``:
    (a0, c) per part; with ``phi_perp`` None, as turned by :func:`rotate_parts`).

    Returns (H - 1, W - 1) maps ``cross`` (gR_p . gT_q with p != q, x and y gradients summed; ``pairs`` = "all": the
    mean over the ordered pairs of distinct parts, "adjacent": the mean over j of (gR_j . gT_j+1 + gR_j+1 . gT_j) / 2,
    which keeps the layers' motion between the two parts small), ``pr`` and ``pt`` (mean of |gR_p|^2 and |gT_p|^2
    over parts).  ``mask`` (H, W): pixels left out (the layers set to 0 there, gradient pairs touching them 0).  Sum
    the maps over any pixel set and form cross / sqrt(pr pt) for its normalised correlation (:func:`label_correlations`).
    Shared by ``polspike calibrate-pane`` (pane model and index) and the self zeta's 90 deg twin test
    (``reconstruct.pane.content.layer_gradient_correlation``).

    ``pixels``: ``same`` takes both layers' gradients from every pixel; ``split`` takes R' from one set of a
    checkerboard and T' from the other (both ways, averaged; normalised convolution at ``sigma``), so that what a
    pixel carries into both layers drops out of their correlation.  That is the sensor's fixed pattern: a static
    per-pixel gain (threshold and gain mismatch, ~7 % in the default sensor) multiplies R' and T' alike and, being
    static, survives the crossing of time parts; it correlates their gradients positively at the right zeta, which
    a wrong zeta's leak of the opposite sign cancels (docs/calibrate_pane.md: the index was read low).
    """
    from scipy.ndimage import gaussian_filter

    if pairs not in ("all", "adjacent"):
        raise ConfigError(f"pairs = {pairs!r}: choose all or adjacent")
    if pixels not in ("same", "split"):
        raise ConfigError(f"pixels = {pixels!r}: choose same or split")
    okx = oky = None
    if mask is not None:
        okx, oky = mask[:-1, :-1] & mask[:-1, 1:], mask[:-1, :-1] & mask[1:, :-1]
    sets = _checkerboard(np.shape(parts[0][0])) if pixels == "split" else None
    if sets is not None and mask is not None:
        sets = tuple(S & mask for S in sets)
    weights = None if sets is None else tuple(_set_weight(S, sigma) for S in sets)
    gs = []  # per part: {"R": (gradient from set 0, from set 1), "T": ...}; the same gradient twice for pixels = same
    for a0, c in parts:
        R, T = solve_layers(a0, c, phi_perp, A, B, gain, None if sets is not None else mask)
        g = {}
        for k, x in (("R", R), ("T", T)):
            if sets is not None:  # each set's normalised convolution; gradient pairs touching the mask 0
                both = tuple(_set_grad(x, S, sigma, wt) for S, wt in zip(sets, weights))
                if mask is not None:
                    both = tuple((np.where(okx, u[0], 0.0), np.where(oky, u[1], 0.0)) for u in both)
            elif mask is None:
                both = (_grad(x, sigma),) * 2
            else:  # R = T + D with D and T zero outside the mask
                y = gaussian_filter(x, sigma)
                both = ((np.where(okx, np.diff(y, axis=1)[:-1, :], 0.0), np.where(oky, np.diff(y, axis=0)[:, :-1], 0.0)),) * 2
            g[k] = both
        gs.append(g)
    P = len(gs)
    if P < 2:
        raise ConfigError("cross_gradient_sums needs at least two time parts")
    prod = lambda u, v: u[0] * v[0] + u[1] * v[1]  # noqa: E731

    def mix(u, v):  # one layer's gradient from set 0 with the other's from set 1, both ways (pixels = same: u . v)
        return prod(u[0], v[1]) if (u[0] is u[1] and v[0] is v[1]) else 0.5 * (prod(u[0], v[1]) + prod(u[1], v[0]))

    def own(u):  # a gradient's own power, over both sets
        return prod(u[0], u[0]) if u[0] is u[1] else 0.5 * (prod(u[0], u[0]) + prod(u[1], u[1]))

    def total(k):  # a layer's gradients summed over the parts, per set (pixels = same: one sum, twice)
        per_set = [tuple(sum(g[k][s][a] for g in gs) for a in (0, 1)) for s in ((0, 1) if sets is not None else (0,))]
        return (per_set[0], per_set[-1])

    tot = {k: total(k) for k in ("R", "T")}

    def off_diagonal(k, m):  # sum over ordered pairs of distinct parts p != q of mix(k_p, m_q), in O(P): all pairs less p = q
        return mix(tot[k], tot[m]) - sum(mix(g[k], g[m]) for g in gs)

    if pairs == "adjacent":
        cross = sum(0.5 * (mix(gs[j]["R"], gs[j + 1]["T"]) + mix(gs[j + 1]["R"], gs[j]["T"])) for j in range(P - 1)) / (P - 1)
    else:
        cross = off_diagonal("R", "T") / (P * (P - 1))
    pr = sum(own(g["R"]) for g in gs) / P
    pt = sum(own(g["T"]) for g in gs) / P
    # the layers' gradient power crossed between parts as well: the spike noise is independent across parts, so these
    # hold the content's power without the noise's (pr, pt hold both; a hypothesis that amplifies the noise, small B',
    # would otherwise have its correlation shrunk by its own noise and look less mixed)
    prx = off_diagonal("R", "R") / (P * (P - 1))
    ptx = off_diagonal("T", "T") / (P * (P - 1))
    return {"cross": cross, "pr": pr, "pt": pt, "pr_x": prx, "pt_x": ptx}


def label_correlations(sums: dict, labels: np.ndarray, n_labels: int, power: str = "same") -> np.ndarray:
    """Normalised gradient correlation cross / sqrt(pr pt) per label (an int map of shape (H - 1, W - 1) or (H, W),
    -1 = left out); NaN for empty labels.  ``power``: ``same`` normalises by each part's own gradient power (content
    plus spike noise), ``cross`` by the power crossed between parts (content only, noise-free in expectation; NaN where
    it is not positive: a label where the noise swamps the content).
    """
    if power not in ("same", "cross"):
        raise ConfigError(f"power = {power!r}: choose same or cross")
    kr, kt = ("pr", "pt") if power == "same" else ("pr_x", "pt_x")
    lab = labels[: sums["cross"].shape[0], : sums["cross"].shape[1]]
    ok = lab >= 0
    li = lab[ok]
    cr = np.bincount(li, sums["cross"][ok], n_labels)
    pr = np.bincount(li, sums[kr][ok], n_labels)
    pt = np.bincount(li, sums[kt][ok], n_labels)
    good = (pr > 0) & (pt > 0)
    den = np.sqrt(np.where(good, pr * pt, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(good, cr / den, np.nan)

