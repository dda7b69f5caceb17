"""The code conventions, checked by ruff with the project's configuration (pyproject.toml [tool.ruff]): imports
sorted and used, no unused or undefined names, docstrings in one (Google) convention.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PATHS = ("polinfra", "polphysics", "generator", "spike_sim", "reconstruct", "polspike", "tests", "docs")


def _ruff() -> list[str]:
    exe = Path(sys.executable).with_name("ruff")
    if exe.exists():
        return [str(exe)]
    if shutil.which("ruff"):
        return ["ruff"]
    pytest.skip("ruff is not installed (pip install -e '.[test]' installs it)")


def test_the_tree_passes_ruff():
    out = subprocess.run([*_ruff(), "check", "--no-cache", *PATHS], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, "ruff check finds:\n" + out.stdout[-4000:]


def test_ruff_catches_an_unused_import_and_a_bad_docstring(tmp_path):
    """The configuration is live: a file with an unused import and a docstring without its closing line break fails."""
    bad = tmp_path / "bad.py"
    bad.write_text('"""Module."""\n\nimport os\n\n\ndef f(x):\n    """Return x.\n\n    More text."""\n    return x\n')
    out = subprocess.run([*_ruff(), "check", "--no-cache", "--config", str(REPO / "pyproject.toml"), str(bad)], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 1 and "F401" in out.stdout and "D209" in out.stdout, out.stdout
