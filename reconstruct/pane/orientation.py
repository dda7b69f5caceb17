"""The orientation field: the AoLP of the modulated light per block, modulo 90 deg, and its scatter."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import torch

from polinfra.errors import ShapeError
from reconstruct.physics.harmonic_fit import half_turn_frames, harmonic_fit
from reconstruct.stream.sources import StreamTooShortError

log = logging.getLogger(__name__)


def block_sum(x: np.ndarray, s: int) -> np.ndarray:
    """Sums over s x s blocks of the last two axes (..., H, W) -> (..., H // s, W // s); a ragged edge is dropped."""
    H, W = x.shape[-2:]
    h, w = H // s, W // s
    return x[..., : h * s, : w * s].reshape(*x.shape[:-2], h, s, w, s).sum(axis=(-3, -1))


@dataclasses.dataclass(frozen=True)
class OrientationField:
    """The orientation field of a span (:func:`orientation_field`): block sums of z4 and what the fits read from them.

    Attributes:
        s4: (h, w) complex block sums of z4 (angle 4 AoLP).
        q: (h, w) block sums of |z4|^2, the noise scale: Var Re(s4 e^{-i t}) = q / 2 under pure noise.
        psi: (h, w) block orientation arg(s4) / 4 in [0, pi/2).
        s4_px, q_px: (H, W) the per-pixel sums before blocking.
        energy: (h, w) block sums of |z4|; coherence: |s4| / energy in [0, 1].
        dop: (H, W) mean per-window DoP; a0: (H, W) mean intensity.
        samples: chunks x block^2; chunks: half-turn chunks in the span; windows: sliding windows summed;
            chunk_frames: frames per chunk.
    The descriptive fields (energy onwards) are None / 0 for a field built from given sums.
    """

    s4: np.ndarray
    q: np.ndarray
    psi: np.ndarray
    s4_px: np.ndarray
    q_px: np.ndarray
    energy: np.ndarray | None = None
    coherence: np.ndarray | None = None
    dop: np.ndarray | None = None
    a0: np.ndarray | None = None
    samples: int = 0
    chunks: int = 0
    windows: int = 0
    chunk_frames: int = 0

    @property
    def blocks(self) -> tuple[int, int]:
        """(h, w): the block grid's shape."""
        return self.psi.shape


def orientation_field(I: np.ndarray, phi: np.ndarray, block: int) -> OrientationField:
    """Modulation orientation (mod 90 deg) and coherence on a block grid (module docstring, step 1).

    Each chunk's harmonic coefficients are normalised by the chunk mean (a0, with a small floor):
    z = (ac + i as) / a0, and z4 = z^2 carries angle 4 AoLP.  Spike noise on z grows as 1/sqrt(a0),
    so this roughly whitens bright and dark pixels alike.  Pure noise gives z4 of random phase:
    sum z4 grows as sqrt(samples) there and as samples where the pane modulates.

    Args:
        I: (M, H, W) Eq. (3) frames, radiance units, consecutive in time.
        phi: (M,) polarizer angles (window centres, unwrapped), radians.
        block: block size s in pixels.

    Returns:
        :class:`OrientationField`.
    """
    I = np.asarray(I, np.float64)
    phi = np.asarray(phi, np.float64)
    if I.ndim != 3 or phi.shape != I.shape[:1]:
        raise ShapeError(f"orientation_field needs I (M, H, W) and phi (M,); got {I.shape} and {phi.shape}", actual_shape=I.shape, expected_shape="(M, H, W)")
    # chunks of about half a polarizer turn (one cycle of 2 phi), at least 3 frames
    L = half_turn_frames(phi)
    n_chunks = I.shape[0] // L
    if n_chunks < 1:
        raise StreamTooShortError(f"self-calibration needs at least {L} frames (half a polarizer turn); got {I.shape[0]}: use a longer span")
    H, W = I.shape[1:]
    s4 = np.zeros((H, W), np.complex128)
    q = np.zeros((H, W))
    en = np.zeros((H, W))
    dop = np.zeros((H, W))
    a0s = np.zeros((H, W))
    floor = 0.05 * max(float(I.mean()), 1e-12)
    # sliding windows (every start frame): the design's anisotropy (angles not uniform over a cycle)
    # biases z4 of noise and of content drift along 4 x the window's start angle; over all starts
    # (the start advances by one stride) that angle turns round and the bias averages out
    starts = range(0, I.shape[0] - L + 1)
    for j in starts:
        sl = slice(j, j + L)
        a0, ac, as_ = (t.numpy() for t in harmonic_fit(torch.from_numpy(I[sl]), torch.from_numpy(phi[sl])))  # supp. Eq. (1)
        z = (ac + 1j * as_) / (np.abs(a0) + floor)
        z4 = z * z  # angle 4 AoLP: the sign of R - T (the 90 deg flip) drops out
        s4 += z4
        a = np.abs(z4)
        en += a
        q += a * a
        dop += np.abs(ac + 1j * as_) / np.maximum(np.abs(a0), 1e-12)
        a0s += a0
    n_win = len(starts)
    q *= L  # overlapping windows: each sample is correlated with about L neighbours (conservative noise scale)
    bs4 = block_sum(s4.real, block) + 1j * block_sum(s4.imag, block)
    ben, bq = block_sum(en, block), block_sum(q, block)
    coh = np.where(ben > 0, np.abs(bs4) / np.maximum(ben, 1e-300), 0.0)
    psi = np.mod(0.25 * np.angle(bs4), 0.5 * math.pi)
    return OrientationField(s4=bs4, q=bq, psi=psi, s4_px=s4, q_px=q, energy=ben, coherence=coh, dop=dop / n_win, a0=a0s / n_win,
                            samples=n_chunks * block * block, chunks=n_chunks, windows=n_win, chunk_frames=L)


def block_orientation_variance(s4: np.ndarray, s4_px: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Noise variance (rad^2) of each block's orientation psi_b = arg(s4_b) / 4 (``s4``: (h, w) block sums), measured from
    the scatter of its pixels' sums ``s4_px`` (H, W) perpendicular to the block's direction: Var Im(s4_b e^{-i 4 psi_b}) = (pixels) x their
    variance, and 4 |s4_b| dpsi = Im(...).  Unlike q / (32 |s4|^2) (the pure-noise scale, which holds the signal's
    power too), this is the orientation's actual spread, spike noise and content alike.  Also returns the block's
    effective number of contributing pixels (sum |s4_px|)^2 / sum |s4_px|^2.
    """
    sp = s4_px
    h, w = s4.shape
    b = int(block)
    sp = sp[: h * b, : w * b].reshape(h, b, w, b)
    u = np.exp(-1j * np.angle(s4))[:, None, :, None]
    perp = np.imag(sp * u)
    npx = b * b
    with np.errstate(divide="ignore", invalid="ignore"):  # a block with no modulation at all: nan (0 / 0), which the callers' v > 0 leaves out
        v = (perp ** 2).sum(axis=(1, 3)) * npx / max(npx - 1, 1) / (16.0 * np.maximum(np.abs(s4), 1e-300) ** 2)
    a = np.abs(sp)
    n_eff = a.sum(axis=(1, 3)) ** 2 / np.maximum((a * a).sum(axis=(1, 3)), 1e-300)
    return v, n_eff
