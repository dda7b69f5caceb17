"""CLI wiring: exit code 2 and one line for bad input, no traceback."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-c", "from polspike.cli import app; app()"]


def run(*args, check=False):
    return subprocess.run(CLI + list(args), capture_output=True, text=True, cwd=REPO, timeout=300)


def test_zeta_calculator_json():
    r = run("zeta", "--n", "1.5", "--theta-deg", "45", "--phi-deg", "30", "--phi-perp-deg", "0", "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert round(d["R_perp"], 4) == 0.0920 and round(d["R_par"], 4) == 0.0085
    assert d["zeta"] == pytest.approx(0.0920 * 0.75 + 0.0085 * 0.25, abs=1e-4)


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["zeta", "--n", "0"], "--n"),
        (["zeta", "--theta-deg", "95"], "--theta-deg"),
        (["zeta", "--pane", "slab"], "--pane"),
        (["render", "no_such_scene", "--out", "/tmp/polspike-x"], "scene file not found"),
        (["render", "brewster", "--out", "/tmp/polspike-x", "--tier", "magic"], "unknown tier"),
        (["render", "brewster", "--out", "/tmp/polspike-x", "--frames", "abc"], "--frames"),
    ],
)
def test_bad_input_exit_2_one_line(args, fragment):
    r = run(*args)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert fragment in r.stderr
    assert "Traceback" not in r.stderr
    assert len([ln for ln in r.stderr.strip().splitlines() if ln.strip()]) == 1


def test_bad_scene_file_exit_2(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[pane]\nn = -2\n')
    r = run("render", str(p), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "pane.n" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o" / "render.json").exists()
