"""What a reconstructor reads: the N windows and the long-span inputs beside them, as one record.

A network (:class:`reconstruct.net.network.PolSpikeNet`) reads the N = 2K + 1 observations of a window and their
polarizer angles; some configurations also read the long spike mean around the centre frame (``I_mean``), the first
harmonic of that span (``I_harm``), the observations over the wide window (``I_wide``), and the stream's exposure and
span length (``exposure``, ``span_steps``).  :class:`WindowInputs` carries them together through the layers between
the data and the model (training batches, tiles, the stream's pending windows, evaluation groups); a model's
configuration names the inputs it reads (``cfg.inputs``, e.g. :attr:`reconstruct.net.network.NetConfig.inputs`) and
:meth:`WindowInputs.check` says, in one line, what is missing, extra or of the wrong shape.

Arrays are numpy arrays or torch tensors alike (only ``shape`` is read here).  Shapes, batched:
``I`` (B, N, H, W), ``phi`` (B, N), ``I_mean`` (B, H, W), ``I_harm`` (B, 2, H, W), ``I_wide`` (B, N, H, W);
``exposure`` and ``span_steps`` numbers or (B,) arrays.  Units: radiance (paper Eq. (1)), radians, steps.

``shifts`` (B, N, 2), optional, is not an input a configuration names: the windows' RIR shifts (dy, dx in pixels,
:func:`reconstruct.physics.rir.estimate_shifts` convention), estimated once by whoever builds the windows (the
stream) and used by a model that aligns its windows (``accepts_shifts``) instead of estimating them again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from polinfra.errors import ShapeError

__all__ = ["EXTRA_INPUTS", "MAP_INPUTS", "ReadsInputs", "WindowInputs", "inputs_of"]

EXTRA_INPUTS = ("I_mean", "I_harm", "I_wide", "exposure", "span_steps")
"""The inputs a model may read beside its windows, in the order of :class:`WindowInputs`."""

MAP_INPUTS = ("I_mean", "I_harm", "I_wide")
"""Of :data:`EXTRA_INPUTS`, the per-pixel maps (moved, padded and tiled with the windows)."""

_WHAT = {
    "I_mean": "the long spike mean around the centre frame",
    "I_harm": "the long span's first harmonic",
    "I_wide": "the observations over the wide window",
    "exposure": "the stream's exposure",
    "span_steps": "the long span's length in steps",
}


class ReadsInputs(Protocol):
    """A model configuration: observations per window and the inputs read beside them (names of :data:`EXTRA_INPUTS`)."""

    n_obs: int

    @property
    def inputs(self) -> frozenset[str]: ...


def inputs_of(model) -> frozenset[str]:
    """The inputs ``model`` reads beside its windows: its configuration's ``inputs``."""
    return frozenset(model.cfg.inputs)


def _shape(x) -> tuple[int, ...]:
    return tuple(int(s) for s in x.shape)


@dataclasses.dataclass(frozen=True)
class WindowInputs:
    """The windows of a batch and what a model reads beside them (module docstring: shapes and units)."""

    I: Any
    """(B, N, H, W) observations, radiance units."""
    phi: Any
    """(B, N) polarizer angles at the windows' centres, radians."""
    I_mean: Any = None
    """(B, H, W) the long spike mean around each centre frame (a ``use_mean`` network)."""
    I_harm: Any = None
    """(B, 2, H, W) the first harmonic (cos 2 phi, sin 2 phi) of the spikes over I_mean's span (``use_harm`` or ``span_level``)."""
    I_wide: Any = None
    """(B, N, H, W) the observations over the wide window, same centres and angles as ``I`` (``wide_input``)."""
    exposure: Any = None
    """spikes per step per unit radiance, a number or (B,) (``span_level``)."""
    span_steps: Any = None
    """steps of I_mean's span, a number or (B,) (``span_level``)."""
    shifts: Any = None
    """(B, N, 2) RIR shifts (dy, dx) registering each window onto its centre frame, estimated once (module docstring)."""

    @property
    def given(self) -> frozenset[str]:
        """The names of :data:`EXTRA_INPUTS` this record carries."""
        return frozenset(k for k in EXTRA_INPUTS if getattr(self, k) is not None)

    def extras(self) -> dict[str, Any]:
        """The inputs beside the windows this record carries, as keyword arguments of a model call."""
        return {k: getattr(self, k) for k in EXTRA_INPUTS if getattr(self, k) is not None}

    def only(self, names: frozenset[str]) -> WindowInputs:
        """This record without the inputs beside the windows that are not in ``names`` (what a model does not read)."""
        return dataclasses.replace(self, **{k: None for k in EXTRA_INPUTS if k not in names})

    def map_arrays(self, fn: Callable[[Any], Any], fn_scalar: Callable[[Any], Any] | None = None) -> WindowInputs:
        """``fn`` applied to ``I``, ``phi``, the maps and the shifts given; ``fn_scalar`` (default: unchanged) to exposure and span_steps."""
        kw = {k: fn(getattr(self, k)) for k in ("I", "phi", *MAP_INPUTS, "shifts") if getattr(self, k) is not None}
        if fn_scalar is not None:
            kw.update({k: fn_scalar(getattr(self, k)) for k in ("exposure", "span_steps") if getattr(self, k) is not None})
        return dataclasses.replace(self, **kw)

    def rows(self, i: int, j: int) -> WindowInputs:
        """Windows ``i:j`` of the batch (exposure and span_steps sliced where they are per window)."""

        def cut(v):
            return v[i:j] if getattr(v, "ndim", 0) > 0 else v

        return self.map_arrays(lambda a: a[i:j], cut)

    @classmethod
    def batch(cls, windows: Sequence[WindowInputs], exposure: Any = None, span_steps: Any = None) -> WindowInputs:
        """One batch of single windows (each ``I`` (N, H, W), ``phi`` (N,), maps without the batch axis; all carrying the
        same inputs), with the stream's ``exposure`` and ``span_steps``.
        """
        first = windows[0]
        kw = {k: np.stack([getattr(w, k) for w in windows]) for k in ("I", "phi", *MAP_INPUTS, "shifts") if getattr(first, k) is not None}
        return cls(**kw, exposure=exposure, span_steps=span_steps)

    def check(self, cfg: ReadsInputs) -> WindowInputs:
        """This record if it is what a model of configuration ``cfg`` reads, else a one-line :class:`ShapeError` naming the
        input that is missing, extra or of the wrong shape.
        """
        need = frozenset(cfg.inputs)
        missing = [k for k in EXTRA_INPUTS if k in need and getattr(self, k) is None]
        if missing:
            raise ShapeError(f"this network reads {', '.join(f'{k} ({_WHAT[k]})' for k in missing)} beside its windows; missing: {', '.join(missing)}",
                             actual_shape=None, expected_shape=", ".join(missing))
        extra = sorted(self.given - need, key=EXTRA_INPUTS.index)
        if extra:
            raise ShapeError(f"this network does not read {', '.join(extra)} (it reads {', '.join(k for k in EXTRA_INPUTS if k in need) or 'only its windows'})",
                             actual_shape=None, expected_shape="none of " + ", ".join(extra))
        si = _shape(self.I)
        if len(si) != 4 or si[1] != cfg.n_obs:
            raise ShapeError(f"I must be (B, {cfg.n_obs}, H, W); got {si}", actual_shape=si, expected_shape=f"(B, {cfg.n_obs}, H, W)")
        B, N, H, W = si
        want = {"phi": (B, N), "I_mean": (B, H, W), "I_harm": (B, 2, H, W), "I_wide": si, "shifts": (B, N, 2)}
        for k, shape in want.items():
            v = getattr(self, k)
            if v is not None and _shape(v) != shape:
                raise ShapeError(f"{k} must be {shape} for windows I {si}; got {_shape(v)}", actual_shape=_shape(v), expected_shape=shape)
        for k in ("exposure", "span_steps"):
            v = getattr(self, k)
            if v is not None and getattr(v, "ndim", 0) > 0 and _shape(v) != (B,):
                raise ShapeError(f"{k} must be a number or ({B},), one per window; got {_shape(v)}", actual_shape=_shape(v), expected_shape=(B,))
        return self
