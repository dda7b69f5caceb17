"""Mitsuba backend selection (generator/mitsuba_backend.py)."""

from __future__ import annotations

import pytest
from _mitsuba_common import require_mitsuba

from polinfra.errors import BackendUnavailableError

pytestmark = pytest.mark.mitsuba


@pytest.fixture(autouse=True)
def _mitsuba_works():
    """The one skip policy (_mitsuba_common.require_mitsuba): skip only when mitsuba is not installed; under CI
    an installed Mitsuba whose import or backend fails is a failure, not a skip.
    """
    require_mitsuba()


def test_auto_picks_a_working_polarized_variant():
    """auto: cuda > llvm > scalar; whatever it returns is set and polarized."""
    import mitsuba

    from generator.mitsuba_backend import resolve_backend

    be = resolve_backend("auto")
    assert be.backend in ("cuda", "llvm", "scalar")
    assert "polarized" in be.variant
    assert mitsuba.variant() == be.variant
    # every skipped backend is explained
    assert all(":" in line for line in be.fallbacks)


def test_variant_table():
    """Mono vs spectral names; the wheel has no scalar mono polarized variant."""
    from generator.mitsuba_backend import variant_name

    assert variant_name("llvm", False) == "llvm_ad_mono_polarized"
    assert variant_name("llvm", True) == "llvm_ad_spectral_polarized"
    assert variant_name("cuda", False) == "cuda_ad_mono_polarized"
    assert variant_name("scalar", False) == "scalar_spectral_polarized"


def test_unknown_variant_is_one_line_error():
    from generator.mitsuba_backend import resolve_backend

    with pytest.raises(BackendUnavailableError, match="unknown variant 'metal'") as ei:
        resolve_backend("metal")
    assert "\n" not in str(ei.value)


def test_missing_libllvm_is_one_line_error(monkeypatch):
    """Forcing llvm without libLLVM 19 anywhere: a clear error, not a crash."""
    import generator.mitsuba_backend as mb

    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(mb, "DEFAULT_LIBLLVM", "/nonexistent/libLLVM.so.19.1")
    with pytest.raises(BackendUnavailableError, match="libLLVM 19") as ei:
        mb.resolve_backend("llvm")
    assert "\n" not in str(ei.value)


def test_forced_unavailable_backend_raises_and_auto_falls_back(monkeypatch, caplog):
    """A backend whose JIT fails: forced -> error; auto -> logged fallback to the next one."""
    import generator.mitsuba_backend as mb

    mb.resolve_backend("auto")  # make sure some variant works first
    monkeypatch.setitem(mb._PROBED, "llvm_ad_mono_polarized", "RuntimeError: Cannot select fminimum (simulated)")
    monkeypatch.setitem(mb._PROBED, "cuda_ad_mono_polarized", "no CUDA (simulated)")
    with pytest.raises(BackendUnavailableError, match="fminimum"):
        mb.resolve_backend("llvm")
    with caplog.at_level("WARNING"):
        be = mb.resolve_backend("auto")
    assert be.backend == "scalar"
    assert any("falling back" in r.message for r in caplog.records)
