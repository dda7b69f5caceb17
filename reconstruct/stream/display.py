"""Display gains for 8-bit output: a running histogram of radiance and the gain that clips a set fraction."""

from __future__ import annotations

import logging
import math

import numpy as np

log = logging.getLogger(__name__)

_HIST_LO, _HIST_HI, _HIST_BINS = -6.0, 6.0, 12 * 1024  # log10 range and bins of the display histograms (0.23 % per bin)


def _to8(x: np.ndarray, gain: float) -> np.ndarray:
    return (np.clip(x * gain, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


DISPLAY_CLIP_FRACTION = 1e-3
"""At most this fraction of a video's pixels (all its frames together) reach white (module docstring)."""


DISPLAY_WHITE = 0.99
"""The clip quantile is mapped to this linear value (below 0.9957, the lowest that rounds to 255 after the 1/2.2 gamma)."""


class DisplayHistogram:
    """Streaming histogram of a video's pixel values on a log scale, for :func:`display_gain`.

    Values <= 10^-6 (also zero and negative ones, which display black) fall into the first bin;
    the upper edge of the bin holding the quantile bounds the exact quantile from above, so the
    gain chosen from it never clips more than the requested fraction.
    """

    def __init__(self):
        self.counts = np.zeros(_HIST_BINS + 1, np.int64)
        self.n = 0

    def add(self, x: np.ndarray) -> None:
        v = np.asarray(x, np.float64).ravel()
        v = v[np.isfinite(v)]
        lg = np.log10(np.maximum(v, 10.0**_HIST_LO))
        idx = np.clip(np.ceil((lg - _HIST_LO) / (_HIST_HI - _HIST_LO) * _HIST_BINS).astype(np.int64), 0, _HIST_BINS)
        self.counts += np.bincount(idx, minlength=_HIST_BINS + 1)
        self.n += v.size

    def upper_quantile(self, fraction_above: float) -> float:
        """A value q with at most ``fraction_above`` of the values above it (the bin's upper edge)."""
        if self.n == 0:
            return 1.0
        allowed = math.floor(fraction_above * self.n)
        above = self.n - np.cumsum(self.counts)  # values in bins after bin i
        i = int(np.argmax(above <= allowed))
        return float(10.0 ** (_HIST_LO + (_HIST_HI - _HIST_LO) * i / _HIST_BINS))


def display_gain(hist: DisplayHistogram, clip_fraction: float = DISPLAY_CLIP_FRACTION) -> float:
    """Display gain of one video: at most ``clip_fraction`` of its pixels map to white (8-bit 255)."""
    return DISPLAY_WHITE / max(hist.upper_quantile(clip_fraction), 1e-6)
