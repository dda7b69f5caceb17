"""Opt-in CPU speed-ups of a trained network at inference: the same weights, the outputs within float32 rounding.

* ``fast``: the network's convolutions in channels-last (NHWC) memory format.  oneDNN's NHWC kernels vectorise over
  the channels, where the default NCHW layout of these narrow layers (1-80 channels at 400 x 252) leaves AVX2 lanes
  idle: measured 1.9x on the refinement and 1.8x on the per-observation encoders on one thread (docs/realtime.md,
  "The network path").  The convolutions then sum in another order, so T and R move by float32 rounding (a few 1e-7
  of a layer value; tests/recon/test_net_inference.py states the tolerance).
* ``compile``: ``torch.compile`` (inductor) of the network's whole forward pass: the convolutions, and the solves, the
  floor and the levels' many pointwise operations fused into generated C++ loops (graph breaks where Python decides,
  e.g. RIR's warp).  Needs a C++ compiler (``$CXX``, g++, c++ or clang++ on the PATH): without one, or when the
  compiled call fails, the network runs eagerly (a warning says so).  The first call compiles (minutes on two cores;
  :class:`CompileStats` records it); only that first input shape is compiled: another (a stream's last, smaller batch)
  runs eagerly rather than compiling again.

* ``bf16``: the learned convolutions and the attention in bfloat16 (``torch.autocast``), on CPUs that compute it natively
  (AMX or AVX-512 BF16; elsewhere bfloat16 is emulated and slower, so the network stays in float32 and a warning says
  so).  Only the network's own layers: the encoders, the attention, the weight and zeta heads and the refinement.  The
  physics around them (the RWPS solves, the floor, the levels, the anchor) stays in float32 and float64, and each
  layer's output returns to float32.  bfloat16 keeps 8 significant bits, so T and R move by about 1e-3 of their level:
  a quality change, measured on the test split and stated in docs/realtime.md, not a rounding.

All change the module in place and keep :meth:`PolSpikeNet.forward`'s contract, so wrappers (the external-zeta models
of :mod:`reconstruct.net.net_zeta`, :class:`reconstruct.net.network.SymmetryEnsemble`) run the faster network as they
are.  Training never uses them.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from typing import Any

import torch

from reconstruct.net.network import PolSpikeNet

__all__ = ["CompileStats", "accelerate", "find_network", "cxx_compiler", "native_bf16"]

log = logging.getLogger(__name__)


@dataclasses.dataclass
class CompileStats:
    """What ``compile`` did: ``status`` (off | on | eager: why), the compiled calls' first-call seconds (compile time included)."""

    status: str = "off"
    bf16: str = "off"
    """bfloat16 layers: off | on | off: why (no native bfloat16 on this CPU)."""
    first_calls: int = 0
    first_call_wall_s: float = 0.0
    first_call_cpu_s: float = 0.0

    def summary(self) -> dict[str, Any]:
        """The fields as a dict that follows later changes (the instance's own ``__dict__``): a run summary written at the
        end of the stream shows the compile calls made during it.
        """
        return vars(self)


def find_network(model) -> PolSpikeNet | None:
    """The :class:`PolSpikeNet` inside ``model`` (itself, or behind ``.net`` wrappers), or None (a physics model)."""
    for _ in range(8):
        if isinstance(model, PolSpikeNet):
            return model
        model = getattr(model, "net", None)
        if model is None:
            return None
    return None


def cxx_compiler() -> str | None:
    """Path of the C++ compiler inductor would use (``$CXX``, else g++, c++ or clang++ on the PATH), or None."""
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def native_bf16(device: torch.device | str = "cpu") -> bool:
    """True where ``device`` computes bfloat16 convolutions natively: a CUDA device with bfloat16, a CPU with AMX tiles or
    AVX-512 BF16 (oneDNN's bfloat16 kernels; without them it emulates bfloat16, slower than float32).
    """
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    probes = ("_is_amx_tile_supported", "_is_avx512_bf16_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in probes)


def _as_float32(out):
    """The layers' outputs back in float32 (tensors, or tuples of them) for the physics after them."""
    if torch.is_tensor(out):
        return out.float() if out.dtype == torch.bfloat16 else out
    if isinstance(out, tuple):
        return tuple(_as_float32(o) for o in out)
    return out


def _in_bf16(obj, method: str, device_type: str) -> None:
    """Run ``obj.method`` under bfloat16 autocast, its outputs back in float32 (in place, an instance attribute)."""
    inner = getattr(obj, method)

    def run(*args, **kw):
        with torch.autocast(device_type, dtype=torch.bfloat16):
            out = inner(*args, **kw)
        return _as_float32(out)

    setattr(obj, method, run)


def _guarded(module: torch.nn.Module, stats: CompileStats, what: str) -> None:
    """Replace ``module.forward`` by its compiled form for the first input shape it sees, falling back to the eager
    forward for good on the first failure (and for other shapes).
    """
    eager = module.forward
    compiled = torch.compile(eager, dynamic=False)
    seen: set[tuple] = set()

    def forward(*args, **kw):
        key = tuple(tuple(a.shape) for a in args if torch.is_tensor(a))
        if stats.status == "on" and (not seen or key in seen):
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                out = compiled(*args, **kw)
            except Exception as exc:  # inductor's C++ build or a graph it cannot lower: the eager module computes the same
                stats.status = f"eager: {what} failed to compile ({type(exc).__name__}: {str(exc).splitlines()[0][:120] if str(exc) else ''})"
                log.warning("torch.compile: %s; running the network eagerly", stats.status)
                return eager(*args, **kw)
            if key not in seen:
                seen.add(key)
                stats.first_calls += 1
                stats.first_call_wall_s += time.perf_counter() - w0
                stats.first_call_cpu_s += time.process_time() - c0
            return out
        return eager(*args, **kw)

    module.forward = forward


def accelerate(model, *, fast: bool = False, compile_: bool = False, bf16: bool = False) -> CompileStats:
    """Apply the speed-ups to the network inside ``model`` (in place; eval mode expected) -> the compile status.

    ``fast``: channels-last convolutions; ``compile_``: ``torch.compile`` of the network's forward pass; ``bf16``: the
    learned layers in bfloat16 where the hardware computes it natively (module docstring).  A model without a network
    (a physics model) is left as it is.
    """
    stats = CompileStats()
    net = find_network(model)
    if net is None:
        if compile_:
            stats.status = "eager: no network to compile"
        return stats
    if fast:
        net.to(memory_format=torch.channels_last)
    if bf16:
        device = next(net.parameters()).device
        if native_bf16(device):
            for obj, method in ((net.param, "forward"), (net.param, "encode_obs"), (net.refine, "forward")):
                if hasattr(obj, method):
                    _in_bf16(obj, method, device.type)
            stats.bf16 = "on"
        else:
            stats.bf16 = f"off: no native bfloat16 on this {device.type} (AMX or AVX-512 BF16); the network runs in float32"
            log.warning("--bf16: %s", stats.bf16)
    if compile_:
        cxx = cxx_compiler()
        if cxx is None:
            stats.status = "eager: no C++ compiler (set CXX or install g++)"
            log.warning("--compile: %s; running the network eagerly", stats.status)
            return stats
        stats.status = "on"
        _guarded(net, stats, "the network")
    return stats
