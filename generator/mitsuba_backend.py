r"""Mitsuba 3 backend selection: CUDA > LLVM > scalar, with logged fallbacks.

Mitsuba is imported lazily, inside :func:`load_mitsuba`, so nothing else in
polspike needs it.  A *backend* is one of ``"cuda"``, ``"llvm"``, ``"scalar"``;
together with the spectral flag it names a polarized Mitsuba variant:

==========  ================================  ==================================
backend     mono (``spectral=False``)         spectral (``spectral=True``)
==========  ================================  ==================================
cuda        ``cuda_ad_mono_polarized``        ``cuda_ad_spectral_polarized``
llvm        ``llvm_ad_mono_polarized``        ``llvm_ad_spectral_polarized``
scalar      ``scalar_spectral_polarized`` *   ``scalar_spectral_polarized``
==========  ================================  ==================================

\\* The PyPI wheel ships no ``scalar_mono_polarized``; a mono request on the
scalar backend runs the spectral variant with a white (wavelength-constant)
scene, which gives the same numbers as mono.

``auto`` tries cuda, then llvm, then scalar.  A backend that imports but fails
its first JIT kernel (e.g. LLVM 15's "Cannot select fminimum") is skipped with
a logged warning.  A *forced* backend that is unavailable raises
:class:`~polinfra.errors.BackendUnavailableError` with a one-line message.

The LLVM backend needs ``libLLVM`` 19: if ``DRJIT_LIBLLVM_PATH`` is unset and
:data:`DEFAULT_LIBLLVM` exists, it is set before Dr.Jit is imported.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any

from polinfra.errors import BackendUnavailableError

__all__ = [
    "BACKENDS",
    "DEFAULT_LIBLLVM",
    "Backend",
    "load_mitsuba",
    "resolve_backend",
    "variant_name",
]

log = logging.getLogger(__name__)

BACKENDS = ("cuda", "llvm", "scalar")
"""Backends in order of preference for ``auto``."""

DEFAULT_LIBLLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
"""libLLVM used by Dr.Jit's LLVM backend when ``DRJIT_LIBLLVM_PATH`` is unset."""

_PROBED: dict[str, str | None] = {}  # variant -> None if it works, else the failure text


@dataclasses.dataclass(frozen=True)
class Backend:
    """A usable Mitsuba variant.

    Attributes:
        backend: ``"cuda"``, ``"llvm"`` or ``"scalar"``.
        variant: the Mitsuba variant name that was set.
        spectral: True when the variant samples wavelengths.
        requested: what the caller asked for (``"auto"`` or a backend name).
        fallbacks: one line per backend tried and skipped, with the reason.
    """

    backend: str
    variant: str
    spectral: bool
    requested: str
    fallbacks: tuple[str, ...] = ()

    @property
    def vectorized(self) -> bool:
        """True for JIT (wavefront) variants, False for scalar."""
        return self.backend != "scalar"

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for render.json."""
        return dataclasses.asdict(self)


def _set_llvm_path() -> None:
    if not os.environ.get("DRJIT_LIBLLVM_PATH") and Path(DEFAULT_LIBLLVM).is_file():
        os.environ["DRJIT_LIBLLVM_PATH"] = DEFAULT_LIBLLVM


def load_mitsuba():
    """Import and return the ``mitsuba`` module (lazy; sets the LLVM path default).

    Raises:
        BackendUnavailableError: mitsuba is not installed or fails to import.
    """
    _set_llvm_path()
    try:
        import mitsuba as mi
    except Exception as exc:  # ImportError or a broken native library
        raise BackendUnavailableError(f"cannot import mitsuba ({exc}); install mitsuba>=3.7 (pip install mitsuba)") from None
    return mi


def variant_name(backend: str, spectral: bool) -> str:
    """Mitsuba variant for ``backend`` and the spectral flag (see module table)."""
    if backend not in BACKENDS:
        raise BackendUnavailableError(f"unknown backend {backend!r}; use one of auto, {', '.join(BACKENDS)}")
    if backend == "scalar":
        return "scalar_spectral_polarized"
    return f"{backend}_ad_{'spectral' if spectral else 'mono'}_polarized"


def _probe(mi, variant: str) -> str | None:
    """Set ``variant`` and run a tiny JIT kernel; None if it works, else why not."""
    if variant in _PROBED:
        if _PROBED[variant] is None:
            mi.set_variant(variant)
        return _PROBED[variant]
    reason: str | None = None
    if variant not in mi.variants():
        reason = f"variant {variant} is not compiled into this mitsuba build"
    else:
        try:
            mi.set_variant(variant)
            if not variant.startswith("scalar"):
                import drjit as dr

                x = dr.arange(mi.Float, 8) * 0.5
                val = float(dr.sum(dr.minimum(dr.sqrt(x), 1.0))[0] if dr.width(dr.sum(x)) else 0.0)
                if not val == val:  # NaN
                    reason = "JIT test kernel returned NaN"
        except Exception as exc:
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            reason = f"{type(exc).__name__}: {msg}"
            if variant.startswith("llvm"):
                reason += f" (LLVM backend needs libLLVM 19; set DRJIT_LIBLLVM_PATH, now {os.environ.get('DRJIT_LIBLLVM_PATH')!r})"
    _PROBED[variant] = reason
    return reason


def resolve_backend(request: str = "auto", spectral: bool = False) -> Backend:
    """Choose, set and return a working polarized Mitsuba variant.

    Args:
        request: ``"auto"`` (cuda > llvm > scalar, skipping any that fail with
            a logged warning) or one backend name to force.
        spectral: choose a spectral variant (else mono; scalar is always spectral).

    Returns:
        The :class:`Backend` that is now Mitsuba's current variant.

    Raises:
        BackendUnavailableError: unknown request, or a forced backend that
            cannot run (e.g. missing libLLVM), or no backend works at all.
    """
    req = str(request).lower()
    if req not in ("auto", *BACKENDS):
        raise BackendUnavailableError(f"unknown variant {request!r}; use one of auto, {', '.join(BACKENDS)}")
    mi = load_mitsuba()
    if req != "auto":
        if req == "llvm" and not os.environ.get("DRJIT_LIBLLVM_PATH") and not Path(DEFAULT_LIBLLVM).is_file():
            raise BackendUnavailableError(
                f"--variant llvm needs libLLVM 19: install libllvm19 or set DRJIT_LIBLLVM_PATH (default {DEFAULT_LIBLLVM} is missing)"
            )
        var = variant_name(req, spectral)
        reason = _probe(mi, var)
        if reason is not None:
            raise BackendUnavailableError(f"--variant {req} ({var}) is unavailable: {reason}; use --variant auto")
        return Backend(req, var, "spectral" in var, req)
    fallbacks: list[str] = []
    for be in BACKENDS:
        var = variant_name(be, spectral)
        reason = _probe(mi, var)
        if reason is None:
            for line in fallbacks:
                log.info("mitsuba backend skipped: %s", line)
            if be != BACKENDS[0] and be == "scalar":
                log.warning("mitsuba: no JIT backend works, falling back to the slow scalar variant (%s)", "; ".join(fallbacks))
            return Backend(be, var, "spectral" in var, req, tuple(fallbacks))
        if be == "llvm":
            log.warning("mitsuba: LLVM variant %s failed, falling back: %s", var, reason)
        fallbacks.append(f"{var}: {reason}")
    raise BackendUnavailableError(f"no Mitsuba polarized variant works: {'; '.join(fallbacks)}")
