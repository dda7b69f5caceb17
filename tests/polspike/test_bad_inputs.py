"""Hardening: one test per bad input of the spike/reconstruct half of the CLI.

Each case must give exit code 2, one line on stderr that names what to fix, no
traceback, and nothing half-written under a final name.  The scene-file cases
live in test_hardening.py.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polinfra.errors import DataFormatError

REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-c", "from polspike.cli import app; app()"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True, cwd=REPO, timeout=300)


def one_line_exit_2(r: subprocess.CompletedProcess, *fragments: str) -> None:
    assert r.returncode == 2, (r.returncode, r.stdout[-400:], r.stderr[-1500:])
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])


def no_final_outputs(out: Path) -> None:
    """Nothing was published: the folder is absent or holds no finished file."""
    if out.exists():
        finished = [p for p in out.rglob("*") if p.is_file() and ".tmp" not in p.name]
        assert not finished, finished


@pytest.fixture(scope="module")
def render_dir(tmp_path_factory) -> Path:
    import dataclasses

    from generator.render import RenderOptions, render
    from generator.scene import load_scene

    s = load_scene("brewster")
    s = dataclasses.replace(s, camera=dataclasses.replace(s.camera, width=32, height=20))
    out = tmp_path_factory.mktemp("r") / "render"
    render(s, out, RenderOptions(tier="analytic", duration_s=0.02))
    return out


def test_dat_not_whole_frames(tmp_path):
    f = tmp_path / "odd.dat"
    f.write_bytes(bytes(1000 * 3 + 7))  # 40x200 frames are 1000 bytes
    out = tmp_path / "o"
    r = run("reconstruct", f, "--height", 40, "--width", 200, "--phi0-deg", 0, "--rev-per-s", 30, "--out", out)
    one_line_exit_2(r, "not a whole number", "--height/--width")
    no_final_outputs(out)


def test_dat_without_resolution(tmp_path):
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(1000))
    r = run("reconstruct", f, "--out", tmp_path / "o")
    one_line_exit_2(r, "--height", "--width")
    no_final_outputs(tmp_path / "o")


def test_missing_checkpoint(tmp_path):
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(1000 * 400))
    r = run("reconstruct", f, "--height", 40, "--width", 200, "--phi0-deg", 0, "--rev-per-s", 30, "--weights", tmp_path / "nope.pt", "--out", tmp_path / "o")
    one_line_exit_2(r, "nope.pt")
    no_final_outputs(tmp_path / "o")


def test_corrupt_checkpoint(tmp_path):
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(1000 * 400))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    r = run("reconstruct", f, "--height", 40, "--width", 200, "--phi0-deg", 0, "--rev-per-s", 30, "--weights", bad, "--out", tmp_path / "o")
    one_line_exit_2(r, "bad.pt")
    no_final_outputs(tmp_path / "o")


@pytest.mark.parametrize("duration", ["0", "-0.5"])
def test_simulate_duration_must_be_positive(render_dir, tmp_path, duration):
    out = tmp_path / "g"
    r = run("simulate", render_dir, "--duration", duration, "--out", out, "--quiet")
    one_line_exit_2(r, "duration")
    no_final_outputs(out)


def test_simulate_unwritable_output(render_dir, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    r = run("simulate", render_dir, "--duration", "0.005", "--out", blocker / "g", "--quiet")
    one_line_exit_2(r)
    assert blocker.read_text() == "x"


def test_simulate_missing_render(tmp_path):
    r = run("simulate", tmp_path / "no_render", "--duration", "0.005", "--out", tmp_path / "g", "--quiet")
    one_line_exit_2(r, "no_render")


@settings(max_examples=200, deadline=None)
@given(size=st.integers(0, 4096), h=st.integers(1, 64), w=st.integers(1, 64), seed=st.integers(0, 2**16))
def test_fuzz_dat_reader(tmp_path_factory, size, h, w, seed):
    """Random files and frame sizes: the reader returns whole upright frames or raises DataFormatError, nothing else."""
    from spike_sim.vidar_dat import read_dat

    p = tmp_path_factory.mktemp("dat") / "f.dat"
    p.write_bytes(np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes())
    try:
        x = read_dat(p, height=h, width=w)
    except DataFormatError as exc:
        assert "\n" not in str(exc)
        return
    assert x.dtype == np.uint8 and x.shape[1:] == (h, w) and set(np.unique(x)) <= {0, 1}
    assert x.shape[0] * h * w <= size * 8

