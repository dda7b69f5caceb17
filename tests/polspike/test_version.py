"""``polspike --version``: the package version (as pyproject.toml declares it) and the default checkpoint's name."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_version_prints_package_version_and_default_checkpoint(polspike_cli):
    # the library's default, read in a clean interpreter (tests/ on sys.path here shadows the package name)
    src = "from reconstruct.net.checkpoint import DEFAULT_WEIGHTS; print(DEFAULT_WEIGHTS)"
    DEFAULT_WEIGHTS = Path(subprocess.run([sys.executable, "-c", src], capture_output=True, text=True, check=True, cwd=REPO).stdout.strip())
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    r = polspike_cli("--version", timeout=120)
    assert r.returncode == 0, (r.stdout, r.stderr[-1500:])
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stdout
    assert declared in re.split(r"[\s,]+", lines[0]), (declared, lines[0])
    assert DEFAULT_WEIGHTS.name in lines[0], (DEFAULT_WEIGHTS.name, lines[0])
    assert DEFAULT_WEIGHTS.is_file(), f"the default checkpoint {DEFAULT_WEIGHTS} is not shipped"


def test_version_wins_over_a_subcommand(polspike_cli):
    """Eager: ``--version`` prints and exits before any subcommand or its missing arguments."""
    r = polspike_cli("--version", "render", timeout=120)
    assert r.returncode == 0, (r.stdout, r.stderr[-1500:])
    assert r.stdout.startswith("polspike "), r.stdout
