"""The Mitsuba tests' skip policy: skip only when mitsuba is not installed; under CI an
unavailable backend fails instead of skipping; no test module skips Mitsuba on its own.
"""

from __future__ import annotations

import importlib.util

import pytest
from _mitsuba_common import require_mitsuba


def _outcome() -> tuple[str, str]:
    """Call require_mitsuba and return ('skip' | 'fail' | 'ok', message); a skip must not skip this test."""
    try:
        require_mitsuba()
    except pytest.skip.Exception as exc:
        return "skip", str(exc)
    except pytest.fail.Exception as exc:
        return "fail", str(exc)
    return "ok", ""


def _unavailable(monkeypatch):
    """Make the llvm backend unavailable the way a missing libLLVM 19 does."""
    import generator.mitsuba_backend as mb
    from polinfra.errors import BackendUnavailableError

    def broken(request="auto", spectral=False):
        raise BackendUnavailableError("--variant llvm needs libLLVM 19 (simulated)")

    monkeypatch.setattr(mb, "resolve_backend", broken)


def test_missing_backend_fails_under_ci(monkeypatch):
    _unavailable(monkeypatch)
    monkeypatch.setenv("CI", "true")
    kind, msg = _outcome()
    assert kind == "fail" and "libLLVM 19" in msg, (kind, msg)


def test_missing_backend_skips_outside_ci(monkeypatch):
    _unavailable(monkeypatch)
    monkeypatch.delenv("CI", raising=False)
    kind, msg = _outcome()
    assert kind == "skip" and "libLLVM 19" in msg, (kind, msg)


def test_not_installed_skips_even_under_ci(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mitsuba" else real(name, *a))
    monkeypatch.setenv("CI", "true")
    kind, msg = _outcome()
    assert kind == "skip" and "not installed" in msg, (kind, msg)


def test_a_broken_import_is_not_a_skip_under_ci(monkeypatch):
    """Installed but failing to import (e.g. a broken native library): under CI a failure."""
    import generator.mitsuba_backend as mb
    from polinfra.errors import BackendUnavailableError

    def broken_import():
        raise BackendUnavailableError("cannot import mitsuba (libdrjit-core.so: undefined symbol)")

    monkeypatch.setattr(mb, "load_mitsuba", broken_import)
    monkeypatch.setattr(mb, "resolve_backend", lambda *a, **k: broken_import())
    monkeypatch.setenv("CI", "1")
    kind, msg = _outcome()
    assert kind == "fail" and "undefined symbol" in msg, (kind, msg)


def test_no_test_module_skips_mitsuba_on_its_own():
    """Every Mitsuba test goes through require_mitsuba: no ``importorskip`` of mitsuba or drjit anywhere in the
    suite (at module level it would skip a whole file on a broken install even under CI).
    """
    import re
    from pathlib import Path

    tests = Path(__file__).resolve().parents[1]
    pat = re.compile(r"""importorskip\(\s*['"](mitsuba|drjit)""")
    offenders = [f"{p.relative_to(tests)}:{n}" for p in sorted(tests.rglob("*.py")) for n, line in enumerate(p.read_text().splitlines(), 1) if pat.search(line)]
    assert not offenders, f"importorskip of mitsuba / drjit (use _mitsuba_common.require_mitsuba): {offenders}"
